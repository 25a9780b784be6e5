"""The stage runner: the pipeline (fingerprints, manifest, atomic stage folders) and which folders recon may write
into. The typed options it fingerprints are `recon.config`'s, read by every layer."""

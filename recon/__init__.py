"""recon: photos → camera poses → neural radiance field → colored mesh."""

__version__ = "0.1.0"

"""The pipeline's stages, in order. Each one plans (`recon.plans`), prints its reasons, calls the libraries and writes
its own folder."""
from __future__ import annotations

from recon.runner.pipeline import RECON_NAMES, Pipeline, Stage
from recon.stages import mesh, normalize, poses, train

STAGES: list[Stage] = [poses.STAGE, normalize.STAGE, train.STAGE, mesh.STAGE]


def default_pipeline() -> Pipeline:
    return Pipeline(STAGES)


def scene_parts() -> frozenset[str]:
    """What recon makes at the top of a scene folder (stage folders, manifest, lock, logs, scratch): no other
    output of recon may be written inside them (`recon.runner.ownership`)."""
    return RECON_NAMES | {s.folder for s in STAGES}

"""The pipeline's stages, in order. Each module is thin: it wires config and artifacts to the libraries."""
from __future__ import annotations

from recon.pipeline import Pipeline, Stage
from recon.stages import mesh, normalize, poses, train

STAGES: list[Stage] = [poses.STAGE, normalize.STAGE, train.STAGE, mesh.STAGE]


def default_pipeline() -> Pipeline:
    return Pipeline(STAGES)

"""recon: photos → camera poses → neural radiance field → colored mesh.

The Python API (see recon/app/api.py): `recon.run(photos, out=..., preset=...)` → `RunResult`;
`recon.load_field(scene)` → a `Field` that renders cameras. Errors are `recon.errors` classes.
Importing recon is light: torch and the pipeline load on first use.
"""
from __future__ import annotations

from typing import Any

from recon.errors import ConfigError, InputError, ReconError

__version__ = "0.1.0"
__all__ = ["ConfigError", "Field", "InputError", "ReconError", "Render", "RunResult", "StageResult", "load_field", "run"]

_API = {"run", "load_field", "RunResult", "StageResult", "Field", "Render"}


def __getattr__(name: str) -> Any:
    if name in _API:
        from recon.app import api

        return getattr(api, name)
    raise AttributeError(f"module 'recon' has no attribute '{name}'")

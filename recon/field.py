"""A trained radiance field on disk: which model, how it was built, its weights — and loading it back.

`field.pt` holds the model kind, its constructor arguments and its state dict, so render, eval and
mesh rebuild exactly the model train fitted without knowing the training config.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from recon.atomic import atomic_open, interrupts_deferred
from recon.errors import ReconError

FIELD_FILE = "field.pt"
FIELD_FORMAT = 1


def build_model(kind: str, kwargs: dict[str, Any]) -> torch.nn.Module:
    """Construct a RadianceModel from its kind and constructor arguments (tensors given as lists)."""
    args = {k: (torch.tensor(v, dtype=torch.float32) if k == "aabb" else v) for k, v in kwargs.items()}
    if kind == "classic":
        from recon.nerf.classic import ClassicModel

        return ClassicModel(**args)
    if kind == "fast":
        from recon.nerf.fast import FastConfig, FastModel

        cfg = dict(args.pop("config", {}))
        cfg["aabb"] = tuple(tuple(row) for row in cfg.get("aabb", FastConfig.aabb))
        return FastModel(FastConfig(**cfg), **args)
    if kind == "surface":
        from recon.nerf.surface import SurfaceConfig, SurfaceModel

        cfg = dict(args.pop("config", {}))
        cfg["aabb"] = tuple(tuple(row) for row in cfg.get("aabb", SurfaceConfig.aabb))
        return SurfaceModel(SurfaceConfig(**cfg), **args)
    raise ReconError(f"Unknown model kind '{kind}' in a field file; it was written by a newer recon?")


def save_field(path: Path, kind: str, kwargs: dict[str, Any], model: torch.nn.Module, meta: dict[str, Any]) -> None:
    """Atomically write the model (weights on CPU) with what is needed to rebuild it."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    # a Python file object: a full disk raises OSError(ENOSPC), not torch's RuntimeError
    with interrupts_deferred(), atomic_open(path, "wb") as f:
        torch.save({"format": FIELD_FORMAT, "kind": kind, "kwargs": kwargs, "state_dict": state, "meta": meta}, f)


def load_field(folder: Path, device: torch.device | str = "cpu") -> tuple[torch.nn.Module, dict[str, Any]]:
    """The trained model (eval mode, on `device`) and its metadata (aabb, background, image size...)."""
    path = folder / FIELD_FILE
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ReconError(f"No trained field at {path}. Run the train stage first (recon run ... or recon train SCENE).") from None
    except Exception as exc:  # truncated/corrupt pickle: torch raises several types
        raise ReconError(f"The trained field {path} is unreadable ({exc}). Re-run training: recon train SCENE.") from None
    model = build_model(data["kind"], data["kwargs"])
    model.load_state_dict(data["state_dict"])
    model.to(device).eval()
    return model, {"kind": data["kind"], **data.get("meta", {})}

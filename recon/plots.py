"""PNG outputs people look at: training curves, render-vs-photo panels, depth maps, the speed/accuracy plot."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from recon.atomic import atomic_open

os.environ.setdefault("MPLBACKEND", "Agg")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110, bbox_inches="tight")


def depth_to_color(depth: np.ndarray, opacity: np.ndarray | None = None, near: float | None = None, far: float | None = None) -> np.ndarray:
    """Depth (H, W) → turbo-colored (H, W, 3) in [0, 1]; transparent pixels (opacity < 0.5) black."""
    from matplotlib import colormaps

    d = np.asarray(depth, dtype=np.float64)
    mask = np.isfinite(d) if opacity is None else (np.asarray(opacity) > 0.5) & np.isfinite(d)
    if mask.any():
        lo = np.percentile(d[mask], 1) if near is None else near
        hi = np.percentile(d[mask], 99) if far is None else far
    else:
        lo, hi = 0.0, 1.0
    x = np.clip((d - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = colormaps["turbo"](x)[..., :3]
    rgb[~mask] = 0.0
    return rgb.astype(np.float32)


def training_curves(history: Sequence[dict], evals: Sequence[dict], path: Path, title: str = "",
                    resumes: Sequence[dict] = ()) -> None:
    """PSNR vs step and vs wall time (train batches and held-out evaluations), loss on a log axis; a dashed line where
    training went on from a checkpoint or a finished field (`resumes`: step, time_s, from, budget_before, budget)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    if history:
        steps = [h["step"] for h in history]
        axes[0].plot(steps, [h["psnr"] for h in history], lw=0.8, alpha=0.7, label="train batch")
        axes[1].plot([h["time_s"] for h in history], [h["psnr"] for h in history], lw=0.8, alpha=0.7, label="train batch")
        axes[2].semilogy(steps, [max(h["loss"], 1e-12) for h in history], lw=0.8)
    if evals:
        axes[0].plot([e["step"] for e in evals], [e["psnr"] for e in evals], "o-", label="held-out views")
        axes[1].plot([e["time_s"] for e in evals], [e["psnr"] for e in evals], "o-", label="held-out views")
    for r in resumes:
        label = f"went on from the {r['from']}" + (f" ({r['budget_before'] or 'no budget'} → {r['budget'] or 'none'})"
                                                   if r["budget_before"] != r["budget"] else "")
        for ax, x in zip(axes, (r["step"], r["time_s"], r["step"]), strict=True):
            ax.axvline(x, color="grey", ls="--", lw=0.8, label=label)
    axes[0].set(xlabel="step", ylabel="PSNR (dB)", title="PSNR vs step")
    axes[1].set(xlabel="training wall time (s)", ylabel="PSNR (dB)", title="PSNR vs time")
    axes[2].set(xlabel="step", ylabel="loss (MSE)", title="loss")
    for ax in axes[:2]:
        ax.grid(alpha=0.3)
        if history or evals or resumes:  # a run of under 10 steps without evaluations has no curve to name
            ax.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    _save(fig, path)
    plt.close(fig)


def comparison_panel(render: np.ndarray, photo: np.ndarray | None, depth_rgb: np.ndarray | None, path: Path, caption: str = "") -> None:
    """Side by side: photo | render | depth, saved as one PNG (no axes, pixel-exact)."""
    from recon.capture.images import save_image

    tiles = [t for t in (photo, render, depth_rgb) if t is not None]
    h = max(t.shape[0] for t in tiles)
    gap = np.ones((h, 4, 3), dtype=np.float32)
    row = []
    for t in tiles:
        t = t[..., :3]
        if t.shape[0] != h:
            t = np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0)), constant_values=1.0)
        row += [t, gap]
    save_image(path, np.concatenate(row[:-1], axis=1))
    if caption:
        path.with_suffix(".txt").write_text(caption + "\n")


def tradeoff_plot(runs: Sequence[dict], path: Path, title: str = "PSNR vs wall time") -> None:
    """One curve per preset: held-out PSNR against training wall time."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    for run in runs:
        evals = run.get("evals", [])
        if evals:
            ax.plot([e["time_s"] for e in evals], [e["psnr"] for e in evals], "o-", label=run["name"])
    ax.set(xlabel="training wall time (s)", ylabel="held-out PSNR (dB)", title=title)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    else:  # runs too short for an evaluation (train.eval_every): say so rather than leave the axes blank
        ax.text(0.5, 0.5, "no held-out evaluation during training\n(fewer steps than train.eval_every)",
                ha="center", va="center", transform=ax.transAxes)
    _save(fig, path)
    plt.close(fig)


def accuracy_plot(runs: Sequence[dict], path: Path, title: str = "mesh accuracy vs training time") -> None:
    """One point per preset: mesh F-score (at 1 % and 0.5 % of the diagonal) against training time, so a
    preset that trains longer for a better mesh (the surface model) sits beside the density presets."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    for marker, key, label in (("o", "fscore_1pct", "F@1%"), ("s", "fscore_05pct", "F@0.5%")):
        pts = [(r["train_time_s"], r[key], r["name"]) for r in runs if r.get(key) is not None]
        if pts:
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], marker=marker, label=label)
            for x, y, name in pts:
                ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, 3), fontsize=8)
    ax.set(xlabel="training wall time (s)", ylabel="F-score against the true surface", title=title)
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, path)
    plt.close(fig)


def mesh_sheet(tiles: Sequence[tuple[str, Path]], path: Path, tile_inches: float = 3.5) -> None:
    """Meshes side by side, each preview (a PNG) under its caption: which preset's mesh looks how, at a glance."""
    from PIL import Image

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(tiles), figsize=(tile_inches * len(tiles), tile_inches + 0.5), squeeze=False)
    for ax, (caption, preview) in zip(axes[0], tiles, strict=True):
        with Image.open(preview) as img:
            ax.imshow(np.asarray(img.convert("RGB")))
        ax.set_title(caption, fontsize=10)
        ax.axis("off")
    _save(fig, path)
    plt.close(fig)


def mask_overview(photos: Sequence[np.ndarray], masks: Sequence[np.ndarray], path: Path, columns: int = 4,
                  tile: int = 240) -> None:
    """A contact sheet of photos (float (H, W, 3) in [0, 1]) with what their masks ((H', W') bool or [0, 1], any size)
    call background dimmed to a quarter: one glance shows whether a segmentation holds the object and nothing else."""
    from PIL import Image

    tiles = []
    for photo, mask in zip(photos, masks, strict=True):
        img = Image.fromarray(np.round(np.clip(photo[..., :3], 0, 1) * 255).astype(np.uint8))
        img.thumbnail((tile, tile))
        cut = Image.fromarray((np.asarray(mask) >= 0.5).astype(np.uint8) * 255)
        keep = np.asarray(cut.resize(img.size, Image.Resampling.NEAREST)) > 127
        arr = np.asarray(img).astype(np.float32) * np.where(keep[..., None], 1.0, 0.25)
        canvas = np.full((tile, tile, 3), 255, np.uint8)
        canvas[: arr.shape[0], : arr.shape[1]] = arr.astype(np.uint8)
        tiles.append(canvas)
    rows = [tiles[i:i + columns] for i in range(0, len(tiles), columns)]
    rows[-1] = rows[-1] + [np.full((tile, tile, 3), 255, np.uint8)] * (columns - len(rows[-1]))
    Image.fromarray(np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)).save(path)

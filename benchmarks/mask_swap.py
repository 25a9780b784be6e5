"""What better masks would buy: one normalized scene trained and meshed twice, one after the other, on its own masks
and on masks given instead (a generated capture's true ones), with the same SfM, box and settings.

    python benchmarks/mask_swap.py --scene ~/.cache/recon/bench/painted_view/tabletop_painted-fast \
        --masks ~/.cache/recon/datasets/tabletop_painted/capture/masks \
        --gt ~/.cache/recon/datasets/tabletop_painted/capture/gt_mesh.ply \
        --set train.budget= --set train.steps=3000 --name painted_true_masks

The scene is copied twice under the work folder (its poses and normalize stages as they are); in the second copy every
photo's mask is replaced by the file of the same name in --masks. Each copy's train and mesh stages run from
scratch; rows hold steps, rays/s, held-out PSNR (each on its own masks) and the mesh against the true surface.
Writes benchmarks/results/<name>.json after each run. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))


def swap_masks(scene: Path, masks: Path) -> int:
    """Point every masked frame of the scene copy at a copy of the given mask of the same name; how many."""
    info_path = scene / "02_scene" / "scene.json"
    info = json.loads(info_path.read_text())
    folder = scene / "02_scene" / "given_masks"
    folder.mkdir(exist_ok=True)
    swapped = 0
    for frame in info["frames"]:
        if not frame.get("mask_path"):
            continue
        name = Path(frame["mask_path"]).name
        if not (masks / name).is_file():
            sys.exit(f"--masks {masks} has no {name} (the scene's mask of {frame.get('file_path')})")
        shutil.copy2(masks / name, folder / name)
        frame["mask_path"] = str(folder / name)
        swapped += 1
    if not swapped:
        sys.exit(f"{scene} has no masked photos: nothing to swap")
    info_path.write_text(json.dumps(info, indent=2))
    return swapped


def main() -> None:
    from mesh_options import add_retrain_options, fresh_copy, mesh_row, retrain_setup, run_stages

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--masks", type=Path, required=True, help="masks to train on instead, named as the scene's")
    add_retrain_options(parser)
    args = parser.parse_args()

    from recon.atomic import write_json_atomic

    source, result, work, preset, overrides = retrain_setup(args)
    rows: list[dict[str, Any]] = []
    for masks in ("own", "given"):
        scene = work / masks
        fresh_copy(source, scene, "03_field", "04_mesh")
        swapped = swap_masks(scene, args.masks.expanduser()) if masks == "given" else None
        ran = run_stages(scene, preset, overrides, "train")
        metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
        row = {"masks": masks, "given_masks": str(args.masks) if swapped else None, "photos_swapped": swapped,
               "source_scene": str(source), "preset": preset, "overrides": args.set, **ran,
               "steps": metrics["steps"], "rays_per_s": metrics["rays_per_s"],
               "psnr": metrics["test"]["psnr"], **mesh_row(scene, args.gt.expanduser() if args.gt else None)}
        rows.append(row)
        f = f", F@1% {row['fscore_1pct']:.3f}, F@0.5% {row['fscore_05pct']:.3f}" if "fscore_1pct" in row else ""
        print(f"{masks} masks: {row['steps']} steps, test PSNR {row['psnr']:.2f} dB{f}")
        write_json_atomic(result, rows)
    print(f"wrote {result}")


if __name__ == "__main__":
    main()

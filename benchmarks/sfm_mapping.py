"""What COLMAP's mapping options cost and buy on a capture's own matches: the poses stage's database mapped again with
each variant, one after the other, timed, and the cameras scored against reference poses.

    python benchmarks/sfm_mapping.py \
        --scene video=SCENE_A --truth video=~/.cache/recon/datasets/tabletop_video@1/transforms.json \
        --scene fox=SCENE_B --truth fox=../shared/data/fox/transforms.json \
        --variant colmap=ba_global_frames_ratio=1.1,ba_global_points_ratio=1.1,\
mapper.ba_global_ignore_redundant_points3D=false \
        --variant recon= --refine --name sfm_mapping_refined

A SCENE is a recon scene folder whose poses stage ran (`01_poses/colmap/` keeps its database and photos). Each variant
maps a copy of that database (`recon.capture.sfm._map` with the variant's options set after recon's, its first pass:
no relaxed retry; with --refine then the stage's final robust adjustment, `refine_robust`); --global-mapping adds
COLMAP's global mapping (GLOMAP) in its defaults as one more row. The rows hold the seconds, the photos registered,
points, mean reprojection error and, with --truth, the cameras against the reference poses after a robust similarity
fit: median and worst centre error over the rig's radius, median rotation error. Writes
benchmarks/results/<name>.json after each run. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def parse_value(text: str) -> Any:
    """'1.4' -> 1.4, '3' -> 3, 'true' -> True: COLMAP's options are typed."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    name, _, rest = text.partition("=")
    options = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        options[key] = parse_value(value)
    return name, options


def pose_scores(frames: dict[str, dict], truth: dict[str, np.ndarray]) -> dict[str, float]:
    """Cameras against the reference poses (matched by file stem) after `fit_sim3_robust` on their centres."""
    from recon.geometry.compare import fit_sim3_robust

    names = [n for n in frames if Path(n).stem in truth]
    est = np.stack([np.asarray(frames[n]["c2w"], float) for n in names])
    ref = np.stack([truth[Path(n).stem] for n in names])
    s, rot, t, _ = fit_sim3_robust(est[:, :3, 3], ref[:, :3, 3])
    centres = s * est[:, :3, 3] @ rot.T + t
    radius = float(np.sqrt(((ref[:, :3, 3] - ref[:, :3, 3].mean(0)) ** 2).sum(1).mean()))
    err = np.linalg.norm(centres - ref[:, :3, 3], axis=1) / radius
    rel = np.einsum("nji,jk,nkl->nil", ref[:, :3, :3], rot, est[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return {"cameras_scored": len(names), "centre_error_median": float(np.median(err)),
            "centre_error_max": float(err.max()), "rotation_error_median_deg": float(np.median(ang))}


def map_global(database: Path, image_dir: Path, models_dir: Path, seed: int) -> Any:
    """COLMAP's global mapping (GLOMAP: rotation averaging, then all positions at once), its defaults; the model
    with the most registered photos, or None."""
    import pycolmap

    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = seed
    models_dir.mkdir(parents=True)
    models = pycolmap.global_mapping(database, image_dir, models_dir, options=options)
    return max(models.values(), key=lambda r: r.num_reg_images(), default=None)


def map_once(scene: Path, tuning: dict[str, Any], refine: bool, mapper: str = "incremental") -> dict[str, Any]:
    from recon.capture.colmap import reconstruction_frames
    from recon.capture.sfm import SfmOptions, _map, refine_robust

    colmap = scene / "01_poses" / "colmap"
    names = sorted(p.relative_to(colmap / "images").as_posix() for p in (colmap / "images").rglob("*") if p.is_file())
    with tempfile.TemporaryDirectory() as work:
        database = Path(work) / "database.db"
        shutil.copyfile(colmap / "database.db", database)
        start = time.perf_counter()
        if mapper == "global":
            rec = map_global(database, colmap / "images", Path(work) / "models", SfmOptions().seed)
        else:
            rec, _ = _map(database, colmap / "images", Path(work) / "models", SfmOptions(), needed=2, relaxed=False,
                       tuning=tuning)
        if refine and rec is not None:
            rec, _ = refine_robust(rec)
        seconds = time.perf_counter() - start
    if rec is None:
        return {"seconds": round(seconds, 2), "registered": 0, "photos": len(names)}
    frames, xyz, *_ = reconstruction_frames(rec, names)
    return {"seconds": round(seconds, 2), "registered": rec.num_reg_images(), "photos": len(names),
            "points": int(len(xyz)), "reprojection_error_px": float(rec.compute_mean_reprojection_error()),
            "frames": frames}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", action="append", required=True, help="NAME=SCENE folder (its poses stage ran)")
    parser.add_argument("--truth", action="append", default=[], help="NAME=transforms.json of reference poses")
    parser.add_argument("--variant", action="append", default=[], help="NAME=key=value,key=value ('' = defaults)")
    parser.add_argument("--refine", action="store_true", help="then the poses stage's final robust adjustment")
    parser.add_argument("--global-mapping", action="store_true",
                        help="one more row a scene: COLMAP's global mapping (GLOMAP) with its defaults")
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    scenes = dict(item.split("=", 1) for item in args.scene)
    truths = {}
    for item in args.truth:
        key, path = item.split("=", 1)
        doc = json.loads(Path(path).expanduser().read_text())
        truths[key] = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], float) for f in doc["frames"]}
    variants = [("incremental", *parse_variant(v)) for v in args.variant]
    if args.global_mapping:
        variants.append(("global", "glomap", {}))
    out = REPO / "benchmarks" / "results" / f"{args.name}.json"
    import pycolmap

    from recon.app.bench import provenance

    where, rows = provenance(), []
    for scene_name, folder in scenes.items():
        for mapper, variant, tuning in variants:
            load = [round(x, 2) for x in os.getloadavg()]
            date = datetime.now(timezone.utc).isoformat(timespec="seconds")
            row = map_once(Path(folder).expanduser(), tuning, args.refine, mapper)
            frames = row.pop("frames", None)
            if frames and scene_name in truths:
                row.update(pose_scores(frames, truths[scene_name]))
            row = {"scene": scene_name, "mapper": mapper, "variant": variant, "options": tuning,
                   "refined": args.refine, **row, "pycolmap": pycolmap.__version__, **where, "date": date,
                   "load_average_start": load}
            rows.append(row)
            print(json.dumps(row), flush=True)
            out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()

"""What close-ups do to the mesh: the generated close-up capture trained on its orbit photos alone, then on all of them.

    python benchmarks/closeups_share.py --name closeups_share [--preset fast] [--data tabletop_closeups]

The capture (`recon bench --data tabletop_closeups`, or `wall_mounted`: fixtures/gen_tabletop.py `--closeups`) has
12 photos around the object and 12 close-ups of one part of it between them. Both runs train on every photo they
get (`normalize.test_every=0`), so the only difference is the close-ups: each is `recon run` from the photos alone
(its own SfM and automatic masks), then scored against the true surface as `recon eval --gt-mesh` does. Rows: photos,
steps, rays/s, PSNR (on training photos: none is held out), the mesh's F-score at 1% and 0.5% of the diagonal, Chamfer, normal agreement. Writes
benchmarks/results/NAME.json with the commit, machine and load after each run. It measures; it asserts nothing.
`--figure PATH` also draws an orbit photo, a close-up and the two meshes (their `preview_front.png`) side by side;
with `--figure-only` from the scenes an earlier run left in `--work`.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def link_photos(photos: list[Path], folder: Path) -> Path:
    """A photos folder holding exactly these photos (hard links, or copies on another file system)."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for photo in photos:
        try:
            os.link(photo, folder / photo.name)
        except OSError:
            shutil.copyfile(photo, folder / photo.name)
    return folder


def figure(work: Path, photos: list[Path], out: Path) -> None:
    """An orbit photo, a close-up, and the mesh from the orbit photos alone and with the close-ups, in a row."""
    tiles_row([*photos, work / "orbit" / "scene" / "04_mesh" / "preview_front.png",
               work / "all" / "scene" / "04_mesh" / "preview_front.png"], out)


def tiles_row(paths: list[Path], out: Path, side: int = 400) -> None:
    """The images at `paths`, each fitted into a white square of `side` px, in a row, as a PNG at `out`."""
    import cv2
    import numpy as np

    tiles = []
    for path in paths:
        img = cv2.imread(str(path))
        if img is None:
            raise SystemExit(f"cannot read {path}: run without --figure-only first")
        scale = side / max(img.shape[:2])
        img = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        tile = np.full((side, side, 3), 255, np.uint8)
        y, x = (side - img.shape[0]) // 2, (side - img.shape[1]) // 2
        tile[y:y + img.shape[0], x:x + img.shape[1]] = img
        tiles.append(tile)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.hstack(tiles))
    print(f"figure: {out}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--name", required=True, help="the record's name: benchmarks/results/NAME.json")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--data", default="tabletop_closeups", help="a generated capture with close-ups")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: ~/.cache/recon/bench/NAME)")
    ap.add_argument("--figure", type=Path, default=None, help="also draw the photos and meshes into this PNG")
    ap.add_argument("--figure-only", action="store_true", help="only draw --figure from an earlier run's scenes")
    a = ap.parse_args(argv)

    from recon.app.bench import provenance, resolve_dataset
    from recon.atomic import write_json_atomic
    from recon.evaluation.mesh_eval import compare_to_gt

    photos, gt_mesh = resolve_dataset(a.data)
    info = json.loads((gt_mesh.parent / "scene_info.json").read_text())
    closeups = {Path(info["frames"][i]["file_path"]).name for i in info.get("closeups", [])}
    if not closeups:
        raise SystemExit(f"{a.data} has no close-ups (scene_info.json lists none)")
    every = sorted(photos.glob("*.jpg"))
    work = a.work or Path.home() / ".cache" / "recon" / "bench" / a.name
    shown = [next(p for p in every if p.name not in closeups), next(p for p in every if p.name in closeups)]
    if a.figure_only:
        if a.figure is None:
            raise SystemExit("--figure-only needs --figure PATH")
        figure(work, shown, a.figure)
        return
    where = provenance()
    rows = []
    for variant, chosen in (("orbit photos alone", [p for p in every if p.name not in closeups]),
                            ("orbit photos and close-ups", every)):
        slug = "orbit" if len(chosen) < len(every) else "all"
        folder = link_photos(chosen, work / slug / "photos")
        scene = work / slug / "scene"
        load_start = [round(x, 2) for x in os.getloadavg()]
        subprocess.run([sys.executable, "-c", "from recon.app.cli import main; main()", "run", str(folder), "--out",
                        str(scene), "--preset", a.preset, "--set", "normalize.test_every=0", "--quiet"],
                       check=True, cwd=REPO)
        metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
        result = compare_to_gt(scene, gt_mesh)
        row = {"variant": variant, "data": a.data, "preset": a.preset, "photos": len(chosen),
               "closeups": len([p for p in chosen if p.name in closeups]), **where,
               "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "load_average_start": load_start, "load_average_end": [round(x, 2) for x in os.getloadavg()],
               "steps": metrics["steps"], "rays_per_s": round(metrics["rays_per_s"], 1),
               "psnr": round(metrics["test"]["psnr"], 2), "psnr_on": "training photos (none held out)",
               "fscore_1pct": round(result["fscore@0.01"], 4), "fscore_05pct": round(result["fscore@0.005"], 4),
               "chamfer_rel": round(result["chamfer_l1_rel"], 5),
               "normal_consistency": round(result.get("normal_consistency", float("nan")), 4)}
        rows.append(row)
        print(f"{variant}: {row['photos']} photos, {row['steps']} steps, {row['rays_per_s']:,.0f} rays/s, "
              f"F@1% {row['fscore_1pct']:.3f}, F@0.5% {row['fscore_05pct']:.3f}, Chamfer {row['chamfer_rel']:.2%}",
              flush=True)
        write_json_atomic(REPO / "benchmarks" / "results" / f"{a.name}.json", rows)  # a record is a list of rows
    print(f"record: benchmarks/results/{a.name}.json")
    if a.figure is not None:
        figure(work, shown, a.figure)


if __name__ == "__main__":
    main()

"""`recon bench` reports the surface preset beside the density ones: mesh columns and the accuracy plot."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.app.bench import write_results
from recon.capture.images import read_image


def _row(name: str, model: str, t: float, f1: float, f05: float, nc: float) -> dict:
    return {"name": name, "model": model, "steps": 100, "train_time_s": t, "wall_s": t + 5, "psnr": 30.0,
            "ssim": 0.95, "test_views": 5, "rays_per_s": 1000.0, "evals": [{"time_s": t, "psnr": 30.0}],
            "fscore_1pct": f1, "chamfer_rel": 0.004, "fscore_05pct": f05, "normal_consistency": nc}


def test_bench_table_lists_mesh_accuracy_and_plots_one_point_per_preset(tmp_path: Path) -> None:
    rows = [_row("fast", "fast", 240.0, 0.891, 0.812, 0.873), _row("surface", "surface", 600.0, 0.962, 0.917, 0.991)]
    write_results(rows, tmp_path, "sample")
    table = (tmp_path / "bench.md").read_text().splitlines()
    surface = next(line for line in table if line.startswith("| surface |"))
    cells = [c.strip() for c in surface.strip("|").split("|")]
    header = [c.strip() for c in next(line for line in table if line.startswith("| preset")).strip("|").split("|")]
    assert cells[header.index("F-score@0.5%")] == "0.917"
    assert cells[header.index("normal agreement")] == "0.991"
    assert cells[header.index("F-score@1%")] == "0.962"
    plot = read_image(tmp_path / "bench_accuracy.png")
    assert plot.ndim == 3 and plot.shape[0] > 100 and float(np.std(plot)) > 0.01  # a drawn figure, not blank
    assert "bench_accuracy.png" in "\n".join(table)


def test_bench_without_ground_truth_has_no_accuracy_plot(tmp_path: Path) -> None:
    row = _row("surface", "surface", 600.0, 0.9, 0.9, 0.9)
    for key in ("fscore_1pct", "chamfer_rel", "fscore_05pct", "normal_consistency"):
        row.pop(key)
    write_results([row], tmp_path, "lego-half")
    assert not (tmp_path / "bench_accuracy.png").exists()
    assert "F-score" not in (tmp_path / "bench.md").read_text()


def test_bench_table_says_how_many_pieces_the_mesh_is_in_when_the_rows_know(tmp_path: Path) -> None:
    whole = {**_row("fast", "fast", 240.0, 0.9, 0.8, 0.9), "mesh_pieces": 3, "mesh_largest_piece_area": 0.981}
    unmeshed = _row("balanced", "fast", 600.0, 0.9, 0.8, 0.9)
    write_results([whole, unmeshed], tmp_path, "fox")
    table = (tmp_path / "bench.md").read_text().splitlines()
    header = [c.strip() for c in next(line for line in table if line.startswith("| preset")).strip("|").split("|")]
    fast = [c.strip() for c in next(line for line in table if line.startswith("| fast |")).strip("|").split("|")]
    balanced = [c.strip() for c in next(line for line in table if line.startswith("| balanced |")).strip("|").split("|")]
    assert len(fast) == len(header) == len(balanced)
    assert fast[header.index("mesh pieces")] == "3" and fast[header.index("largest piece's area")] == "98.1%"
    assert balanced[header.index("mesh pieces")] == "—"
    write_results([unmeshed], tmp_path, "fox")
    assert "mesh pieces" not in (tmp_path / "bench.md").read_text()


def test_bench_shows_each_meshed_presets_preview_side_by_side(tmp_path: Path) -> None:
    """bench_meshes.png holds a tile per preset whose mesh stage left a preview, and bench.md shows it; without any
    preview (`--until train`) there is no sheet."""
    from PIL import Image

    rows = [_row("fast", "fast", 240.0, 0.9, 0.8, 0.9), _row("surface", "surface", 600.0, 0.95, 0.9, 0.99)]
    write_results(rows, tmp_path, "sample")
    assert not (tmp_path / "bench_meshes.png").exists()
    assert "bench_meshes.png" not in (tmp_path / "bench.md").read_text()
    for name, colour in (("fast", (255, 0, 0)), ("surface", (0, 0, 255))):
        (tmp_path / f"sample-{name}" / "04_mesh").mkdir(parents=True)
        Image.new("RGB", (64, 64), colour).save(tmp_path / f"sample-{name}" / "04_mesh" / "preview_front.png")
    write_results(rows, tmp_path, "sample")
    sheet = read_image(tmp_path / "bench_meshes.png")
    assert "bench_meshes.png" in (tmp_path / "bench.md").read_text()
    red = (sheet[..., 0] > 0.9) & (sheet[..., 1] < 0.1) & (sheet[..., 2] < 0.1)
    blue = (sheet[..., 2] > 0.9) & (sheet[..., 0] < 0.1) & (sheet[..., 1] < 0.1)
    assert red.any() and blue.any()
    assert np.nonzero(red)[1].mean() < np.nonzero(blue)[1].mean()  # in the rows' order, left to right

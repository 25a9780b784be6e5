"""A photo beside the meshes of scenes made from it: a PNG, one panel each, labelled.

    python benchmarks/mesh_figure.py --photo DATA/photos/view_000.jpg \
        --scene "empty start=/tmp/p0/tabletop_painted-fast" --scene "hull start=/tmp/p1/tabletop_painted-fast" \
        --out docs/painted_hull_start.png

Each scene's panel is its mesh stage's preview (`04_mesh/preview_front.png`, or `--view side`), as the stage drew
it, or with `--view below` its mesh.ply drawn from under the table, or with `--view section --gt-mesh GT.ply` a slice
through its mesh (red) and the true one (green) in the truth's frame (`--at AXIS=FRACTION` of the true box, e.g. x=0.35):
what hides inside a mesh, which no rendered view shows. The photo is cropped to a square around its middle (`--crop`:
its side, a fraction of the shorter side). It measures nothing: the numbers are in the records.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from PIL import Image, ImageDraw

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))  # this checkout's recon, not an installed one
from figures import side_by_side, write_png  # noqa: E402

PANEL = 360
"""Each panel's side in pixels."""


def _square(image: Image.Image, fraction: float = 1.0) -> Image.Image:
    side = round(min(image.size) * fraction)
    left, top = (image.width - side) // 2, (image.height - side) // 2
    return image.crop((left, top, left + side, top + side)).resize((PANEL, PANEL), Image.BILINEAR)


def _from_below(ply: Path) -> Image.Image:
    """The mesh (+Z up, vertex colours) drawn as the stage's previews are, from 35° under it."""
    import numpy as np
    import trimesh

    from recon.geometry.preview import render_preview

    mesh = trimesh.load(ply, process=False)
    colors = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0
    return Image.fromarray(render_preview(mesh.vertices, mesh.faces, colors, azimuth_deg=30.0, elevation_deg=-35.0,
                                          size=PANEL))


SLAB = 0.0015
"""A section draws the surface samples within this fraction of the true box's diagonal of the slicing plane."""


def _section(scene: Path, gt_mesh: Path, at: str) -> Image.Image:
    """Our mesh (red) over the true mesh (green), sampled within SLAB of a plane across the true box (`--at`), drawn
    at the same scale for every scene."""
    import numpy as np
    import trimesh

    from recon.evaluation.mesh_eval import in_truth_frame

    name, _, fraction = at.partition("=")
    axis = "xyz".index(name)
    ours, gt, *_ = in_truth_frame(scene, gt_mesh)
    low, high = np.asarray(gt.bounds)
    plane = low[axis] + float(fraction) * (high[axis] - low[axis])
    slab = SLAB * float(np.linalg.norm(high - low))
    across = [a for a in range(3) if a != axis]
    span = float((high - low)[across].max()) * 1.1
    centre = (low + high)[across] / 2
    image = Image.new("RGB", (PANEL, PANEL), (255, 255, 255))
    pixels = image.load()
    for mesh, colour in ((gt, (40, 170, 60)), (ours, (210, 30, 30))):
        points = trimesh.sample.sample_surface(mesh, 2_000_000, seed=0)[0]
        near = points[np.abs(points[:, axis] - plane) < slab][:, across]
        uv = ((near - centre) / span + 0.5) * (PANEL - 1)
        for u, v in np.round(uv).astype(int):
            for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):  # two pixels wide
                if 0 <= u + du < PANEL and 0 <= v + dv < PANEL:
                    pixels[u + du, PANEL - 1 - v - dv] = colour
    return image


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photo", type=Path, required=True)
    parser.add_argument("--scene", action="append", required=True, help="LABEL=SCENE_DIR (repeatable, in order)")
    parser.add_argument("--view", choices=["front", "side", "below", "section"], default="front",
                        help="front, side: the stage's previews; below: mesh.ply drawn from under the table; section: "
                             "a slice through the mesh and the true one (--gt-mesh, --at)")
    parser.add_argument("--gt-mesh", type=Path, help="--view section: the true mesh")
    parser.add_argument("--at", default="z=0.5", help="--view section: the slicing plane, AXIS=FRACTION of the true box")
    parser.add_argument("--crop", type=float, default=1.0, help="the photo's square, a fraction of its shorter side")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    a = parser.parse_args()
    if a.view == "section" and (a.gt_mesh is None or not a.gt_mesh.is_file()):
        raise SystemExit("--view section needs --gt-mesh, the true mesh file")
    if a.view == "section" and not re.fullmatch(r"[xyz]=(0(\.\d+)?|1(\.0+)?)", a.at):
        raise SystemExit(f"--at {a.at!r}: give AXIS=FRACTION, e.g. z=0.35 (axis x, y or z; fraction 0 to 1)")

    panels = [("photo", _square(Image.open(a.photo).convert("RGB"), a.crop))]
    for spec in a.scene:
        label, sep, folder = spec.rpartition("=")
        preview = Path(folder) / "04_mesh" / ("mesh.ply" if a.view in ("below", "section") else f"preview_{a.view}.png")
        if not sep or not preview.is_file():
            raise SystemExit(f"--scene {spec!r}: give LABEL=SCENE_DIR of a scene whose mesh stage wrote {preview.name}")
        if a.view == "section":
            panels.append((label, _section(Path(folder), a.gt_mesh, a.at)))
            continue
        panels.append((label, _from_below(preview) if a.view == "below" else
                       _square(Image.open(preview).convert("RGB"))))
    figure = side_by_side([panel for _, panel in panels])
    draw = ImageDraw.Draw(figure)
    for i, (label, _) in enumerate(panels):
        draw.text((i * PANEL + 8, 8), label, fill=(200, 30, 30))
    write_png(figure, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the figure scripts share: panels side by side, and the PNG written through recon.atomic.

Imported by the scripts next to it (benchmarks/ is on their path as the folder they run from).
"""
from __future__ import annotations

import sys
from pathlib import Path

from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's recon, not an installed one

from recon.atomic import atomic_open  # noqa: E402


def side_by_side(panels: list[Image.Image], background: tuple[int, int, int] = (0, 0, 0)) -> Image.Image:
    """The panels in one row, left to right, top-aligned."""
    row = Image.new("RGB", (sum(p.width for p in panels), max(p.height for p in panels)), background)
    x = 0
    for panel in panels:
        row.paste(panel, (x, 0))
        x += panel.width
    return row


def write_png(figure: Image.Image, out: Path) -> None:
    """Write the figure to out (its folder made), atomically, and say where."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(out) as f:
        figure.save(f, format="PNG")
    print(f"figure: {out}")

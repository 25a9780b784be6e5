"""xatlas in a process of its own: xatlas segfaults on some meshes, and a crash there must end only the optional
textured copy (a RuntimeError the mesh stage reports), never the run. This module imports only numpy and xatlas,
so the child starts in a fraction of a second; a plain subprocess, not multiprocessing (spawn would re-run the
caller's main script)."""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np


def xatlas_unwrap(scaled: np.ndarray, tris: np.ndarray, max_chart_area: float, size: int, padding: int) -> tuple:
    """xatlas itself: (atlas count, chart count, source, faces, uv of the first atlas, or None when not one atlas)."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(scaled, tris)
    charts = xatlas.ChartOptions()
    charts.max_chart_area = max_chart_area
    charts.max_iterations = 0
    pack = xatlas.PackOptions()
    pack.resolution = size  # xatlas picks its texel density to about fit: its atlas may be larger; uv are fractions
    pack.padding = padding
    pack.bilinear = True
    atlas.generate(chart_options=charts, pack_options=pack)
    if atlas.atlas_count != 1:
        return atlas.atlas_count, atlas.chart_count, None, None, None
    return (atlas.atlas_count, atlas.chart_count, *(np.asarray(a) for a in atlas[0]))


def crash() -> None:
    """Dereference NULL: what a segfaulting xatlas does to its process (for the tests)."""
    import ctypes

    ctypes.string_at(0)


CHILD_FUNCTIONS = {"xatlas_unwrap": xatlas_unwrap, "crash": crash}


def in_child(name: str, *args: Any) -> Any:
    """CHILD_FUNCTIONS[name](*args) in a fresh Python process (pickled through its stdin/stdout); RuntimeError,
    with the child's last error line, when it fails or dies."""
    call = "from recon.geometry.atlas_child import _child_main; _child_main()"
    root = str(Path(__file__).resolve().parents[2])  # this recon, installed or not
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, "-c", call], input=pickle.dumps((name, args)), capture_output=True, env=env)
    if done.returncode != 0:
        last = done.stderr.decode(errors="replace").strip().splitlines()[-1:]
        why = last[0] if last else f"killed by signal {-done.returncode}" if done.returncode < 0 else f"exit {done.returncode}"
        raise RuntimeError(f"{name} failed in its own process ({why}): the textured copy is skipped; a smaller "
                           f"mesh.texture_faces may avoid it")
    return pickle.loads(done.stdout)


def _child_main() -> None:
    name, args = pickle.loads(sys.stdin.buffer.read())
    sys.stdout.buffer.write(pickle.dumps(CHILD_FUNCTIONS[name](*args)))

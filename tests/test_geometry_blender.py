"""The exported glb opens in Blender upright, with its vertex colors (skipped when `blender` is absent).

Blender runs headless (`blender -b`) with a small import script passed by --python-expr; it prints one
JSON line that the test checks. Debian's Blender 3.4 glTF importer still calls `numpy.bool` (removed
in numpy 1.24), so the script restores it before importing.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from recon.geometry.export import export_mesh, srgb_to_linear

BLENDER = shutil.which("blender")
pytestmark = pytest.mark.skipif(BLENDER is None, reason="blender is not installed")

IMPORT_SCRIPT = """
import json, sys
import numpy
numpy.bool = bool  # Debian Blender 3.4's glTF importer uses the alias numpy 1.24 removed
import bpy
path = sys.argv[sys.argv.index("--") + 1]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=path)
(obj,) = [o for o in bpy.context.scene.objects if o.type == "MESH"]
me = obj.data
world = [list(obj.matrix_world @ v.co) for v in me.vertices]
attrs = [a.name for a in me.color_attributes]
col = me.color_attributes[0] if attrs else None
loops = [[lp.vertex_index, *col.data[i if col.domain == "CORNER" else lp.vertex_index].color[:3]]
         for i, lp in enumerate(me.loops)] if col else []
print("RESULT " + json.dumps({"vertices": world, "faces": len(me.polygons), "colors": attrs, "loops": loops}))
"""


def blender_env() -> dict[str, str]:
    """Our environment minus PATH entries of this interpreter: a system Blender's embedded Python
    locates its standard library from the `python3` found on PATH (a pyenv/venv one breaks numpy)."""
    ours = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix)}
    keep = [p for p in os.environ.get("PATH", "").split(os.pathsep)
            if not any(os.path.realpath(p).startswith(o + os.sep) for o in ours)]
    return {**os.environ, "PATH": os.pathsep.join(keep)}


def test_glb_imports_upright_with_colors(tmp_path):
    tower = trimesh.creation.box(extents=(0.2, 0.4, 1.6))  # tall along scene +Z
    tower.apply_translation((0.0, 0.0, 0.8))
    v, f = np.asarray(tower.vertices), np.asarray(tower.faces)
    colors = np.stack([v[:, 2] / 1.6, np.full(len(v), 0.25), 0.5 + v[:, 1]], axis=1)
    glb = export_mesh(v, f, colors, tmp_path)["glb"]
    run = subprocess.run(
        [BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", IMPORT_SCRIPT, "--", str(glb)],
        capture_output=True, text=True, timeout=120, env=blender_env(),
    )
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-2000:] + run.stderr[-2000:]
    got = json.loads(lines[-1][len("RESULT "):])
    world = np.array(got["vertices"])
    assert len(world) == len(v) and got["faces"] == len(f)
    extent = world.max(axis=0) - world.min(axis=0)
    assert np.argmax(extent) == 2  # Blender is +Z up: the tower stands upright
    np.testing.assert_allclose(np.sort(world, axis=0), np.sort(v, axis=0), atol=1e-5)  # scene frame restored
    assert got["colors"], "no color attribute on the imported mesh"
    loops = np.array(got["loops"])
    # Blender's .color reads linear values; they must match the linear COLOR_0 at each loop's vertex.
    nearest = np.argmin(np.linalg.norm(world[loops[:, 0].astype(int), None] - v[None], axis=-1), axis=1)
    np.testing.assert_allclose(loops[:, 1:], srgb_to_linear(colors[nearest]), atol=0.01)

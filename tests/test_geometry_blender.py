"""The exported glbs open in Blender: the vertex-colored one upright with its colors, the textured one with
an Image Texture in its material that a Cycles render shows (skipped when `blender` is absent).

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
from PIL import Image

from recon.geometry.export import export_mesh, export_textured_mesh, srgb_to_linear
from recon.geometry.texture import make_textured_mesh

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


@pytest.fixture(scope="module", autouse=True)
def blender_has_numpy() -> None:
    """Skip unless Blender's Python imports numpy: its glTF importer needs it, and Debian's blender package does
    not depend on python3-numpy, so a plain `apt-get install blender` cannot import a glb at all."""
    run = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", "import numpy"],
                         capture_output=True, text=True, timeout=120, env=blender_env())
    if run.returncode != 0:
        pytest.skip("Blender's Python cannot import numpy, which its glTF importer needs (apt-get install python3-numpy)")


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


TEXTURED_SCRIPT = """
import json, sys
import numpy
numpy.bool = bool  # Debian Blender 3.4's glTF importer uses the alias numpy 1.24 removed
import bpy
path, render_path = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=path)
(obj,) = [o for o in bpy.context.scene.objects if o.type == "MESH"]
mat = obj.active_material
nodes = [n for n in mat.node_tree.nodes if n.type == "TEX_IMAGE" and n.image is not None]
linked = [l.to_socket.name for n in nodes for o in n.outputs for l in o.links]
scene = bpy.context.scene
cam = bpy.data.cameras.new("cam")  # orthographic, looking down -Z at the XY plane, image up = +Y
cam.type = "ORTHO"
cam.ortho_scale = 2.2
cam_obj = bpy.data.objects.new("cam", cam)
cam_obj.location = (0.0, 0.0, 3.0)
scene.collection.objects.link(cam_obj)
scene.camera = cam_obj
world = bpy.data.worlds.new("w")  # uniform white sky: a flat diffuse surface shows its albedo
world.use_nodes = True
world.node_tree.nodes["Background"].inputs[0].default_value = (1, 1, 1, 1)
scene.world = world
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 16
scene.cycles.use_denoising = False  # Debian builds Cycles without OpenImageDenoise
scene.render.resolution_x = scene.render.resolution_y = 64
scene.render.resolution_percentage = 100
scene.view_settings.view_transform = "Standard"
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = render_path
bpy.ops.render.render(write_still=True)
print("RESULT " + json.dumps({"material": mat.name, "images": [list(n.image.size) for n in nodes], "linked": linked}))
"""


def checker(points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """A 4×4 checker over [-1, 1]² in scene x, y: dark red and light blue squares (sRGB)."""
    odd = (np.floor((points[:, 0] + 1) * 2) + np.floor((points[:, 1] + 1) * 2)) % 2
    return np.where(odd[:, None] > 0, [[0.15, 0.35, 0.85]], [[0.8, 0.15, 0.1]])


def test_textured_glb_shows_its_texture_in_blender(tmp_path):
    grid = trimesh.creation.box(extents=(2.0, 2.0, 0.02)).subdivide().subdivide()  # a thin slab, top face at z = 0.01
    textured = make_textured_mesh(grid.vertices, grid.faces, 400, 128, checker)
    paths = export_textured_mesh(textured.vertices, textured.faces, textured.uv, textured.texture, tmp_path,
                                 normals=textured.normals)
    render_path = tmp_path / "render.png"
    run = subprocess.run(
        [BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", TEXTURED_SCRIPT, "--",
         str(paths["glb"]), str(render_path)],
        capture_output=True, text=True, timeout=300, env=blender_env(),
    )
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-2000:] + run.stderr[-2000:]
    got = json.loads(lines[-1][len("RESULT "):])
    assert got["images"] == [[128, 128]]  # one Image Texture node with our image, made by the importer
    assert "Base Color" in got["linked"]  # wired to the shader's base color: no node work needed
    render = np.asarray(Image.open(render_path).convert("RGB"), np.float64) / 255
    # not one flat color: the texture's own spread (std over its island texels), mostly kept
    tex = textured.texture[textured.mask].astype(np.float64) / 255
    assert render.std(axis=(0, 1)).mean() > 0.5 * tex.std(axis=0).mean()
    # and the checker where it belongs: each square's centre pixel has that square's color (uv not flipped)
    for row in range(64):
        for col in range(64):
            x, y = -1.1 + (col + 0.5) * 2.2 / 64, 1.1 - (row + 0.5) * 2.2 / 64
            fx, fy = (x + 1) * 2 % 1, (y + 1) * 2 % 1
            if max(abs(x), abs(y)) < 0.95 and 0.3 < fx < 0.7 and 0.3 < fy < 0.7:
                np.testing.assert_allclose(render[row, col], checker(np.array([[x, y, 0.0]]))[0], atol=0.12)

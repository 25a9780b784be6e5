"""export_mesh: glb/obj/ply round trips through trimesh — counts, colors, up axis, transform, atomicity."""
from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest
import trimesh

from recon.geometry.export import Z_UP_TO_Y_UP, export_mesh, srgb_to_linear


@pytest.fixture
def tower():
    """A tall box in the scene frame (+Z up): 0.2 × 0.4 × 1.6, base at z = 0, colored by height."""
    mesh = trimesh.creation.box(extents=(0.2, 0.4, 1.6))
    mesh.apply_translation((0.0, 0.0, 0.8))
    v = np.asarray(mesh.vertices)
    colors = np.stack([v[:, 2] / 1.6, 0.25 + 0 * v[:, 0], 0.5 + v[:, 1]], axis=1)  # r = height, g = 0.25
    return v, np.asarray(mesh.faces), colors


def load(path, ext) -> trimesh.Trimesh:
    if ext == "glb":  # one mesh, one node without transform; its geometry keeps COLOR_0
        (mesh,) = trimesh.load(path, file_type=ext, process=False).geometry.values()
        return mesh
    return trimesh.load(path, file_type=ext, force="mesh", process=False)


def test_writes_three_files_with_counts_and_colors(tower, tmp_path):
    v, f, c = tower
    paths = export_mesh(v, f, c, tmp_path)
    assert set(paths) == {"glb", "obj", "ply"} and all(p.is_file() for p in paths.values())
    assert [p.name for p in sorted(tmp_path.iterdir())] == ["mesh.glb", "mesh.obj", "mesh.ply"]  # no temp files
    for ext in ("glb", "obj", "ply"):
        mesh = load(paths[ext], ext)
        assert len(mesh.vertices) == len(v) and len(mesh.faces) == len(f), ext
    glb = load(paths["glb"], "glb").visual.vertex_attributes["color"]
    np.testing.assert_allclose(glb, srgb_to_linear(c), atol=1e-6)  # glTF COLOR_0 is linear, float32
    for ext in ("obj", "ply"):
        got = load(paths[ext], ext).visual.vertex_colors[:, :3] / 255.0
        np.testing.assert_allclose(got, c, atol=1 / 255, err_msg=ext)  # sRGB kept


def test_up_axis_glb_obj_y_up_ply_z_up(tower, tmp_path):
    v, f, c = tower
    paths = export_mesh(v, f, c, tmp_path)
    for ext, up in (("glb", 1), ("obj", 1), ("ply", 2)):
        mesh = load(paths[ext], ext)
        assert np.argmax(mesh.extents) == up, ext
        assert mesh.bounds[0, up] == pytest.approx(0.0, abs=1e-6)  # base at 0, tower grows up
        assert mesh.volume > 0, ext  # still wound outward
    glb = load(paths["glb"], "glb")
    np.testing.assert_allclose(glb.extents, [0.2, 1.6, 0.4], atol=1e-6)  # scene y (0.4) → glTF -z
    flat = export_mesh(v, f, c, tmp_path / "z", y_up=False)
    assert np.argmax(load(flat["glb"], "glb").extents) == 2


def test_transform_is_applied_before_up_axis_and_mirrors_keep_winding(tower, tmp_path):
    v, f, c = tower
    t = np.diag([2.0, 2.0, 2.0, 1.0])
    t[:3, 3] = [1.0, 2.0, 3.0]
    paths = export_mesh(v, f, c, tmp_path, stem="scaled", transform=t)
    ply = load(paths["ply"], "ply")
    np.testing.assert_allclose(ply.bounds, [[0.8, 1.6, 3.0], [1.2, 2.4, 6.2]], atol=1e-6)
    glb = load(paths["glb"], "glb")
    expected = trimesh.transform_points(ply.vertices, Z_UP_TO_Y_UP)
    np.testing.assert_allclose(glb.vertices, expected, atol=1e-5)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirrored = load(export_mesh(v, f, c, tmp_path / "m", transform=mirror)["ply"], "ply")
    assert mirrored.volume > 0
    with pytest.raises(ValueError, match="4x4 affine"):
        export_mesh(v, f, c, tmp_path, transform=np.ones((4, 4)))


def test_glb_container_is_valid_gltf2(tower, tmp_path):
    v, f, c = tower
    data = export_mesh(v, f, c, tmp_path)["glb"].read_bytes()
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert (magic, version, length) == (b"glTF", 2, len(data))
    js_len, js_type = struct.unpack("<I4s", data[12:20])
    doc = json.loads(data[20 : 20 + js_len])
    assert js_type == b"JSON" and js_len % 4 == 0
    prim = doc["meshes"][0]["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION", "NORMAL", "COLOR_0"}
    assert doc["materials"][prim["material"]]["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    bin_len, bin_type = struct.unpack("<I4s", data[20 + js_len : 28 + js_len])
    assert bin_type == b"BIN\0" and bin_len == doc["buffers"][0]["byteLength"] + (-bin_len % 4)


def test_srgb_to_linear_reference_points():
    np.testing.assert_allclose(srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])),
                               [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-6)


def test_bad_inputs_are_rejected(tower, tmp_path):
    v, f, c = tower
    with pytest.raises(ValueError, match="colors"):
        export_mesh(v, f, c[:-1], tmp_path)
    with pytest.raises(ValueError, match="faces"):
        export_mesh(v, f + len(v), c, tmp_path)


def test_files_get_normal_permissions_and_overwrite(tower, tmp_path):
    v, f, c = tower
    export_mesh(v, f, c, tmp_path)
    paths = export_mesh(v, f, c * 0.5, tmp_path)  # rewrite in place, atomically
    np.testing.assert_allclose(load(paths["ply"], "ply").visual.vertex_colors[:, :3] / 255, c * 0.5, atol=1 / 255)
    umask = os.umask(0)
    os.umask(umask)
    assert all(p.stat().st_mode & 0o777 == 0o666 & ~umask for p in paths.values())  # like open(), not 0600
    assert len(list(tmp_path.iterdir())) == 3

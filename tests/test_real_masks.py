"""Masks beside the photos (white = object): found by stem, trained as alpha, and the mesh keeps only what
they call object. Also the tabletop fixture: its masks are the object's true silhouette."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from recon.camera import look_at
from recon.capture.images import save_image
from recon.capture.scene import find_masks, import_transforms
from recon.config import MeshConfig
from recon.errors import InputError
from recon.evaluation.views import View, load_view
from recon.meshing.photos import inside_masks

REPO = Path(__file__).resolve().parents[1]


def test_masks_beside_the_photos_are_found_by_stem_and_missing_ones_named(tmp_path: Path) -> None:
    photos = tmp_path / "images"
    photos.mkdir()
    (tmp_path / "masks").mkdir()
    paths = []
    for name in ("a.jpg", "b.jpg"):
        save_image(photos / name, np.zeros((40, 40, 3)))
        paths.append(photos / name)
    assert find_masks(paths) == (None, {})
    save_image(tmp_path / "masks" / "a.png", np.ones((40, 40)))
    with pytest.raises(InputError, match=r"no mask for 1 photo\(s\): b\.jpg"):
        find_masks(paths)
    save_image(tmp_path / "masks" / "b.png", np.ones((40, 40)))
    folder, masks = find_masks(paths)
    assert folder == tmp_path / "masks" and masks == {"a.jpg": tmp_path / "masks" / "a.png", "b.jpg": tmp_path / "masks" / "b.png"}


def test_mask_becomes_the_alpha_the_photo_trains_with(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    rng = np.random.default_rng(0)
    save_image(tmp_path / "images" / "a.png", rng.random((60, 80, 3)))
    mask = np.zeros((60, 80))
    mask[10:50, 20:60] = 1.0
    save_image(tmp_path / "masks" / "a.png", mask)
    doc = {"fl_x": 80, "w": 80, "h": 60, "frames": [
        {"file_path": "images/a.png", "mask_path": "masks/a.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    scene = import_transforms(tmp_path)
    assert scene.has_alpha and scene.frames[0].mask_path.endswith("masks/a.png")
    view = load_view(scene, scene.frames[0], max_side=40, keep_alpha=scene.has_alpha)
    assert view.image.shape == (30, 40, 4)
    alpha = view.image[..., 3] >= 128
    expected = np.zeros((30, 40), bool)
    expected[5:25, 10:30] = True
    assert (alpha == expected).mean() > 0.98


def test_mesh_keeps_only_what_the_masks_call_object() -> None:
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    table = trimesh.creation.box(extents=(3, 3, 0.02))
    table.apply_translation((0, 0, -0.31))
    w, h, fl = 96, 72, 90.0
    views = []
    for i in range(8):
        az = 2 * np.pi * i / 8
        c2w = look_at(2.0 * np.array([np.cos(az), np.sin(az), 0.6]), np.zeros(3))
        # the ball's silhouette, drawn from its own projected surface samples
        pts = ball.sample(20000, seed=i) if hasattr(ball, "sample") else ball.vertices
        local = (pts - c2w[:3, 3]) @ c2w[:3, :3]
        u = np.floor(w / 2 + fl * local[:, 0] / -local[:, 2]).astype(int)
        r = np.floor(h / 2 - fl * local[:, 1] / -local[:, 2]).astype(int)
        img = np.zeros((h, w, 4), np.uint8)
        ok = (u >= 0) & (u < w) & (r >= 0) & (r < h)
        img[r[ok], u[ok], 3] = 255
        views.append(View(f"v{i}", img, c2w, (fl, fl, w / 2, h / 2), 0.1, 5.0))
    keep = inside_masks(views, MeshConfig().mask_keep_fraction)
    assert keep(ball.vertices).mean() > 0.99
    framed_table = table.vertices  # the table's corners are seen outside the silhouette
    assert not keep(framed_table).any()


def test_tabletop_fixture_masks_are_the_object_silhouette_and_cached(tmp_path: Path) -> None:
    sys.path.insert(0, str(REPO / "fixtures"))
    import gen_tabletop

    out = gen_tabletop.generate(tmp_path / "tt", views=3, size="64x48", supersample=1, mesh_res=64)
    info = json.loads((out / "scene_info.json").read_text())
    mesh = trimesh.load(out / "gt_mesh.ply")
    cell = np.ptp(np.asarray(info["object_bounds"]), axis=0).max() / 64
    assert mesh.vertices[:, 2].min() >= info["table_z"] - cell  # object only: nothing under the table top
    doc = json.loads((out / "transforms.json").read_text())
    fl, cx, cy = doc["fl_x"], doc["cx"], doc["cy"]
    for frame in doc["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        mask = np.asarray(Image.open(out / "masks" / (Path(frame["file_path"]).stem + ".png"))) > 127
        local = (mesh.vertices - c2w[:3, 3]) @ c2w[:3, :3]
        u = np.floor(cx + fl * local[:, 0] / -local[:, 2]).astype(int)
        r = np.floor(cy - fl * local[:, 1] / -local[:, 2]).astype(int)
        ok = (u >= 0) & (u < 64) & (r >= 0) & (r < 48)
        assert ok.mean() > 0.99 and mask[r[ok], u[ok]].mean() > 0.95  # every object point lands in the mask
        assert 0.05 < mask.mean() < 0.6  # and the mask is not the whole picture
    assert len({tuple(g) for g in info["gains"]}) > 1  # some photos have another exposure
    stamp = os.stat(out / "images" / "view_000.jpg").st_mtime_ns
    gen_tabletop.generate(out, views=3, size="64x48", supersample=1, mesh_res=64)
    assert os.stat(out / "images" / "view_000.jpg").st_mtime_ns == stamp  # cached: not rendered again


def test_unsure_masks_crop_a_mesh_by_majority_in_the_photos_pixels(tmp_path: Path) -> None:
    """normalize's unsure masks are at the photos' own (distorted) pixels: a ball off the middle of strongly distorted
    photos stays whole and the table around it goes; a vertex stays while at least half of the photos with a mask
    call it object, and a photo without a mask file casts no vote."""
    from recon.camera import project
    from recon.capture.scene import Frame
    from recon.meshing.photos import inside_photo_masks

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    table = trimesh.creation.box(extents=(3, 3, 0.02))
    table.apply_translation((0, 0, -0.31))
    w, h, fl, k1 = 160, 120, 110.0, -0.3
    frames, masks = [], {}
    for i in range(8):
        az = 2 * np.pi * i / 8
        # aimed beside the ball, so it sits off the image centre, where the lens moves it most
        c2w = look_at(2.0 * np.array([np.cos(az), np.sin(az), 0.6]), np.array([-np.sin(az), np.cos(az), 0.0]) * 0.45)
        frame = Frame(f"photos/v{i}.jpg", c2w, fl, fl, w / 2, h / 2, w, h, k1=k1)
        uv, z = project(ball.sample(40000, seed=i), c2w, frame.intrinsics_at(w, h), frame.distortion)
        u, r = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        mask = np.zeros((h, w), np.float32)
        ok = (z > 0) & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        mask[r[ok], u[ok]] = 1.0
        frames.append(frame)
        masks[frame.stem] = mask
    folder = tmp_path / "masks_unsure"
    folder.mkdir()

    def write(empty: int = 0, missing: int = 0) -> None:
        for path in folder.iterdir():
            path.unlink()
        for k, (stem, mask) in enumerate(masks.items()):
            if k >= missing:
                save_image(folder / f"{stem}.png", (np.zeros_like(mask) if k < missing + empty else mask)[..., None])

    write()
    keep = inside_photo_masks(frames, folder, 0.5)
    assert keep(ball.vertices).mean() > 0.99  # the mask is read at the photo's pixels and undistorted
    around = np.stack([np.cos(np.linspace(0, 2 * np.pi, 64)), np.sin(np.linspace(0, 2 * np.pi, 64)), np.zeros(64)], -1)
    assert not keep(0.48 * around).any()  # a ring around the ball's equator, inside under half of its silhouettes
    assert not keep(table.vertices).any()
    write(empty=3)  # 5 of 8 call the ball object: kept
    assert keep(ball.vertices).mean() > 0.99
    write(empty=5)  # 3 of 8: dropped
    assert not keep(ball.vertices).any()
    write(missing=5)  # 3 masks, all calling it object: kept
    assert keep(ball.vertices).mean() > 0.99

"""Phone EXIF reaches COLMAP: focal-length priors, and one camera per device (issue 11, defect 1).

Synthetic JPEGs carry EXIF written with PIL; the copies the poses stage writes for COLMAP must keep
make, model and focal length (with Orientation 1: their pixels are already upright), and feature
extraction must give two phones of one resolution two cameras, each with the EXIF focal prior.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from recon.capture.sfm import SfmOptions, _image_info, camera_groups, choose_camera, extract
from recon.stages.poses import prepare_photo

EXIF_IFD = 0x8769


def phone_photo(path: Path, make: str, model: str, fl35: int, size=(320, 240), orientation: int = 1, seed: int = 0,
                focal_mm: float = 4.2) -> None:
    rng = np.random.default_rng(seed)
    img = Image.fromarray((rng.random((size[1], size[0], 3)) * 255).astype(np.uint8))
    exif = Image.Exif()
    exif[0x010F], exif[0x0110], exif[0x0112] = make, model, orientation
    exif.get_ifd(EXIF_IFD).update({0x920A: focal_mm, 0xA405: fl35})
    img.save(path, exif=exif, quality=95)


def test_copy_for_colmap_keeps_device_and_focal_exif_upright(tmp_path: Path) -> None:
    src = tmp_path / "IMG_1.jpg"
    phone_photo(src, "Apple", "iPhone 12", 26, size=(320, 240), orientation=6)  # stored sideways
    out = tmp_path / "sfm"
    out.mkdir()
    name, original, small = prepare_photo(src, out, max_side=200)
    assert original == (240, 320) and small == (150, 200)  # turned upright, then downscaled
    with Image.open(out / name) as im:
        assert im.size == (150, 200)
        exif = im.getexif()
        assert exif.get(0x0112) == 1  # pixels are upright already: a reader must not turn them again
        assert (exif.get(0x010F), exif.get(0x0110)) == ("Apple", "iPhone 12")
        sub = exif.get_ifd(EXIF_IFD)
        assert sub.get(0xA405) == 26 and abs(float(sub.get(0x920A)) - 4.2) < 1e-6


def test_two_phones_or_two_lenses_of_one_resolution_get_a_camera_each_with_focal_priors(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    # two photos of an iPhone's main lens, one of its ultra-wide (same make, model and size), one of a Samsung
    specs = [("Apple", "iPhone 12", 26, 4.2), ("Apple", "iPhone 12", 26, 4.2), ("Samsung", "SM-G991B", 24, 5.4),
             ("Apple", "iPhone 12", 13, 1.54)]
    for i, (make, model, fl35, focal) in enumerate(specs):
        phone_photo(photos / f"p{i}.jpg", make, model, fl35, seed=i, focal_mm=focal)
    image_dir = tmp_path / "sfm"
    image_dir.mkdir()
    names = [prepare_photo(photos / f"p{i}.jpg", image_dir, max_side=320)[0] for i in range(4)]
    sizes, devices = _image_info(image_dir, names)
    assert devices == ["Apple iPhone 12 at 4.2 mm (26 mm equiv.)", "Apple iPhone 12 at 4.2 mm (26 mm equiv.)",
                       "Samsung SM-G991B at 5.4 mm (24 mm equiv.)", "Apple iPhone 12 at 1.54 mm (13 mm equiv.)"]
    model, shared, reason = choose_camera(sizes, devices)
    assert not shared and "3 cameras" in reason
    groups = camera_groups(sizes, devices, shared)
    assert groups == [[0, 1], [2], [3]]
    database = tmp_path / "db.db"
    extract(database, image_dir, names, groups, model, SfmOptions(num_threads=1))
    with pycolmap.Database.open(database) as db:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        camera_of = {im.name: im.camera_id for im in db.read_all_images()}
    assert len(cameras) == 3
    assert camera_of["p0.jpg"] == camera_of["p1.jpg"] != camera_of["p2.jpg"] != camera_of["p3.jpg"] != camera_of["p0.jpg"]
    diag = math.hypot(320, 240)
    for name, fl35 in (("p0.jpg", 26), ("p2.jpg", 24), ("p3.jpg", 13)):
        cam = cameras[camera_of[name]]
        assert cam.has_prior_focal_length
        # COLMAP's 35 mm rule: focal over the 43.27 mm film diagonal, times the image diagonal in pixels
        assert abs(cam.params[0] - fl35 / math.hypot(36, 24) * diag) < 0.5


def test_photos_without_exif_keep_the_old_grouping() -> None:
    sizes = [(320, 240)] * 3 + [(640, 480)]
    assert camera_groups(sizes, [None] * 4, shared=False) == [[0], [1], [2], [3]]
    assert camera_groups(sizes, ["A"] * 4, shared=False) == [[0, 1, 2], [3]]
    assert camera_groups(sizes, ["A"] * 4, shared=False, shared_intrinsics="no") == [[0], [1], [2], [3]]
    assert camera_groups(sizes, [None] * 4, shared=True) == [[0, 1, 2, 3]]


# ---------------------------------------------------------------------------------------------- few photos
class FakeModel:
    def __init__(self, n: int) -> None:
        self.n = n

    def num_reg_images(self) -> int:
        return self.n


def test_dropped_photos_trigger_the_retry_and_the_better_model_wins() -> None:
    from recon.capture.sfm import ATTEMPTS, register_best

    tried = []

    def run(attempt):
        tried.append(attempt.name)
        return FakeModel({"default": 10, "more features": 14}[attempt.name])

    best, log = register_best(run, total=14, options=SfmOptions())
    assert tried == ["default", "more features"] and best.n == 14
    assert [e["registered"] for e in log] == [10, 14]
    assert "16384 features" in log[1]["settings"] and "guided matching" in log[1]["settings"]
    assert "2× resolution" in log[1]["settings"]
    # all registered at once: no retry; a worse retry never replaces the better model
    tried.clear()
    best, log = register_best(lambda a: (tried.append(a.name), FakeModel(14))[1], total=14, options=SfmOptions())
    assert tried == ["default"] and len(log) == 1
    best, log = register_best(lambda a: FakeModel(12 if a is ATTEMPTS[0] else 9), total=14, options=SfmOptions())
    assert best.n == 12 and len(log) == 2


def test_few_photos_all_train_and_say_how_psnr_is_measured() -> None:
    from recon.capture.normalization import FEW_PHOTOS, assign_split
    from recon.capture.scene import Frame

    def frames(n: int) -> list:
        return [Frame(f"/p/{i:02d}.jpg", np.eye(4), 100.0, 100.0, 50.0, 50.0, 100, 100) for i in range(n)]

    few = frames(15)
    why = assign_split(few, test_every=8, val_every=8)
    assert all(f.split == "train" for f in few) and "training photos" in why and "15" in why
    many = frames(FEW_PHOTOS + 4)
    assign_split(many, test_every=8, val_every=0)
    assert sum(f.split == "test" for f in many) == 3 and sum(f.split == "train" for f in many) == FEW_PHOTOS + 1


def test_one_more_photo_never_trains_on_fewer() -> None:
    """Above FEW_PHOTOS the held-out photos are capped so that FEW_PHOTOS still train: the number of training photos
    never falls as photos are added (with or without validation photos), and the held-out ones stay spread."""
    from recon.capture.normalization import FEW_PHOTOS, assign_split
    from recon.capture.scene import Frame

    for val_every in (0, 8):
        trained = []
        for n in range(1, 90):
            frames = [Frame(f"/p/{i:02d}.jpg", np.eye(4), 100.0, 100.0, 50.0, 50.0, 100, 100) for i in range(n)]
            assign_split(frames, test_every=8, val_every=val_every)
            held = [i for i, f in enumerate(frames) if f.split != "train"]
            trained.append(n - len(held))
            assert trained[-1] >= min(n, FEW_PHOTOS)
            if len(held) > 1:
                assert max(np.diff(held + [held[0] + n])) <= 2 * n / len(held) + 1  # spread over the capture
            if n > FEW_PHOTOS + 8:
                assert sum(f.split == "test" for f in frames) == -(-n // 8)  # uncapped: every 8th, as before
        assert all(b >= a for a, b in zip(trained, trained[1:])), trained


def test_iphone_heic_photos_are_read_upright_posed_and_exported_as_jpeg(tmp_path: Path) -> None:
    """An iPhone's default format: pixels stored sideways, the file's rotation (irot, which pillow-heif writes from
    EXIF Orientation 6 given as bytes) turning them upright; libheif applies it and the EXIF then reads Orientation 1."""
    import recon
    from typer.testing import CliRunner

    from recon.app.cli import app
    from recon.capture.images import oriented_size, read_image
    from recon.capture.scene import import_transforms, load_scene

    sample = sorted((Path(__file__).resolve().parents[1] / "fixtures" / "sample" / "images").glob("*.jpg"))[:12]
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, path in enumerate(sample):
        exif = Image.Exif()
        exif[0x010F], exif[0x0110], exif[0x0112] = "Apple", "iPhone 15", 6
        exif.get_ifd(EXIF_IFD).update({0x920A: 6.1, 0xA405: 26})
        with Image.open(path) as upright:
            upright.crop((0, 0, 400, 300)).transpose(Image.Transpose.ROTATE_90).save(photos / f"IMG_{i:04d}.HEIC", exif=exif.tobytes())
    first = photos / "IMG_0000.HEIC"
    assert oriented_size(first) == (400, 300)
    truth = np.asarray(Image.open(sample[0]).convert("RGB").crop((0, 0, 400, 300)), dtype=np.float32) / 255
    assert np.abs(read_image(first) - truth).mean() < 0.02  # upright: turned sideways it would not even fit

    scene = tmp_path / "scene"
    recon.run(photos, out=scene, preset="fast", until_stage="normalize")
    frames = load_scene(scene / "01_poses").frames
    assert len(frames) == 12 and {(f.w, f.h) for f in frames} == {(400, 300)}
    copies = sorted((scene / "01_poses" / "colmap" / "images").iterdir())
    assert [p.suffix for p in copies] == [".jpg"] * 12  # COLMAP reads no HEIC
    with Image.open(copies[0]) as copy:
        assert (copy.getexif().get(0x0110), copy.getexif().get(0x0112)) == ("iPhone 15", 1)

    out = tmp_path / "ns"
    result = CliRunner().invoke(app, ["export", str(scene), "--format", "nerfstudio", "--out", str(out)])
    assert result.exit_code == 0, result.output
    exported = import_transforms(out).frames
    assert [Path(f.file_path).name for f in exported] == [f"IMG_{i:04d}.jpg" for i in range(12)]
    with Image.open(exported[0].file_path) as img:
        assert img.format == "JPEG" and img.size == (400, 300)

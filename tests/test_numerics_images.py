"""read_image at the extremes of real photos: bit depths, alpha, gray, EXIF rotation, tiny and huge images."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from recon.capture.images import MIN_SIDE, oriented_size, read_image
from recon.errors import InputError


def test_8bit_rgb_png_is_exact(tmp_path: Path) -> None:
    arr = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    Image.fromarray(arr).save(tmp_path / "a.png")
    out = read_image(tmp_path / "a.png")
    assert out.dtype == np.float32 and out.shape == (40, 50, 3)
    np.testing.assert_array_equal(out, arr / np.float32(255.0))


@pytest.mark.parametrize("peak", [200, 4000, 65535])
def test_16bit_gray_png_keeps_its_range(tmp_path: Path, peak: int) -> None:
    # regression: a dark 16-bit photo (all values <= 255) was divided by 255 instead of 65535, i.e. 257x too bright
    arr = (np.linspace(0, peak, 40 * 48).reshape(40, 48)).astype(np.uint16)
    Image.fromarray(arr).save(tmp_path / "g16.png")
    assert Image.open(tmp_path / "g16.png").mode.startswith("I;16")
    out = read_image(tmp_path / "g16.png")
    assert out.shape == (40, 48, 3)
    np.testing.assert_allclose(out[..., 1], arr / 65535.0, rtol=0, atol=1e-7)


def test_16bit_rgb_png_reads_to_within_8_bit_precision(tmp_path: Path) -> None:
    import cv2

    arr = np.random.default_rng(1).integers(0, 65536, (40, 50, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), arr[..., ::-1])
    out = read_image(tmp_path / "c16.png")
    assert out.shape == (40, 50, 3) and out.dtype == np.float32
    # Pillow decodes 16-bit color PNG as 8-bit: correct values, 8-bit precision
    np.testing.assert_allclose(out, arr / 65535.0, rtol=0, atol=1.0 / 255)


def test_rgba_and_gray_alpha_keep_alpha_gray_becomes_rgb(tmp_path: Path) -> None:
    rgba = np.random.default_rng(2).integers(0, 256, (36, 40, 4), dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    np.testing.assert_array_equal(read_image(tmp_path / "rgba.png"), rgba / np.float32(255.0))
    la = rgba[..., [0, 3]]
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    out = read_image(tmp_path / "la.png")
    assert out.shape == (36, 40, 4)
    np.testing.assert_array_equal(out[..., 3], la[..., 1] / np.float32(255.0))
    gray = rgba[..., 0]
    Image.fromarray(gray, "L").save(tmp_path / "l.png")
    out = read_image(tmp_path / "l.png")
    assert out.shape == (36, 40, 3)
    np.testing.assert_array_equal(out[..., 2], gray / np.float32(255.0))
    Image.new("1", (40, 36), 1).save(tmp_path / "bw.png")
    assert read_image(tmp_path / "bw.png").min() == 1.0
    Image.new("CMYK", (40, 36), (0, 255, 0, 0)).save(tmp_path / "cmyk.jpg")
    np.testing.assert_allclose(read_image(tmp_path / "cmyk.jpg")[18, 20], [1.0, 0.0, 1.0], atol=0.02)


@pytest.mark.parametrize("max_side", [None, 40])
def test_exif_rotated_jpeg_is_returned_upright(tmp_path: Path, max_side: int | None) -> None:
    # stored 80 wide x 60 high, left half dark; Orientation 6 = "rotate 90° clockwise to display"
    arr = np.full((60, 80, 3), 230, np.uint8)
    arr[:, :40] = 20
    img = Image.fromarray(arr)
    exif = img.getexif()
    exif[0x0112] = 6
    img.save(tmp_path / "rot.jpg", exif=exif, quality=95)
    assert oriented_size(tmp_path / "rot.jpg") == (60, 80)
    out = read_image(tmp_path / "rot.jpg", max_side=max_side)
    h, w = (80, 60) if max_side is None else (40, 30)
    assert out.shape == (h, w, 3)
    # displayed upright, the stored left (dark) half is now the top half
    assert out[: h // 2 - 2].mean() < 0.15 and out[h // 2 + 2 :].mean() > 0.85


def test_tiny_images_32_ok_31_rejected_by_name(tmp_path: Path) -> None:
    Image.new("RGB", (MIN_SIDE, 500), (1, 2, 3)).save(tmp_path / "ok.png")
    assert read_image(tmp_path / "ok.png").shape == (500, MIN_SIDE, 3)
    Image.new("RGB", (500, MIN_SIDE - 1), (1, 2, 3)).save(tmp_path / "small.png")
    with pytest.raises(InputError, match=r"small\.png is only 500×31 px.*at least 32"):
        read_image(tmp_path / "small.png")


def test_huge_image_is_downscaled_on_read(tmp_path: Path) -> None:
    path = tmp_path / "huge.png"
    Image.new("RGB", (8000, 6000), (10, 200, 30)).save(path)  # compresses to a few hundred kB
    assert path.stat().st_size < 2_000_000
    out = read_image(path, max_side=1600)
    assert out.shape == (1200, 1600, 3) and out.dtype == np.float32
    assert out.nbytes < 25_000_000  # what stays in memory is the downscaled image
    np.testing.assert_allclose(out[600, 800], np.array([10, 200, 30]) / 255.0, atol=1e-6)


def test_corrupt_and_non_images_are_rejected_by_name(tmp_path: Path) -> None:
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    with pytest.raises(InputError, match=r"bad\.jpg.*corrupt or not an image"):
        read_image(tmp_path / "bad.jpg")
    good = tmp_path / "trunc.png"
    Image.fromarray(np.random.default_rng(3).integers(0, 256, (200, 200, 3), dtype=np.uint8)).save(good)
    good.write_bytes(good.read_bytes()[:2000])
    with pytest.raises(InputError, match=r"trunc\.png"):
        read_image(good)

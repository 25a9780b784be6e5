"""Blurred photos left out of training: each photo's sharpness against the photos that share its view."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from recon.capture.blur import MIN_TRAINING_PHOTOS, blurred_photos, sharpness, sharpness_shares
from recon.capture.images import save_image
from recon.capture.scene import Frame, Scene


def _texture(seed: int, side: int = 96) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(cv2.GaussianBlur(rng.random((side, side, 3)).astype(np.float32), (0, 0), 1.0) * 1.5 - 0.25, 0, 1)


def _capture(tmp_path: Path, n: int, blurred: dict[int, float], dark: tuple[int, ...] = ()) -> Scene:
    """n photos of one texture in a ring, each sharing sparse points with its neighbours; `blurred`: index → the
    blur's sigma in pixels; `dark`: photos a third as bright (a shorter exposure), sharp."""
    frames, visibility = [], {}
    for i in range(n):
        image = np.roll(_texture(0), 3 * i, axis=1)
        if i in blurred:
            image = cv2.GaussianBlur(image, (0, 0), blurred[i])
        if i in dark:
            image = image / 3
        save_image(tmp_path / f"p{i:02d}.png", image)
        frames.append(Frame(str(tmp_path / f"p{i:02d}.png"), np.eye(4), 80.0, 80.0, 48.0, 48.0, 96, 96,
                            split="test" if i == 0 else "train"))
        visibility[f"p{i:02d}.png"] = np.arange(10 * i, 10 * i + 40) % (10 * n)  # overlaps the next three
    return Scene(frames=frames, point_visibility=visibility)


def test_sharpness_falls_with_blur_and_not_with_exposure() -> None:
    gray = _texture(1).mean(axis=-1)
    assert abs(sharpness(gray * 0.3) / sharpness(gray) - 1) < 1e-3  # a shorter exposure is as sharp
    assert sharpness(cv2.GaussianBlur(gray, (0, 0), 1.5)) < 0.3 * sharpness(gray)
    assert sharpness(np.full((8, 8), 0.5)) == 0.0


def test_the_blurred_photos_are_found_among_their_neighbours_and_few_are_left_out(tmp_path: Path) -> None:
    scene = _capture(tmp_path, 30, {5: 2.0, 17: 3.0, 0: 3.0}, dark=(9, 10))
    shares = sharpness_shares(scene, 640)
    assert shares["p05.png"] < 0.35 and shares["p17.png"] < 0.35
    assert min(v for n, v in shares.items() if n not in ("p00.png", "p05.png", "p17.png")) > 0.7  # darker ones too
    assert blurred_photos(scene, 640).keys() == {"p05.png", "p17.png"}  # p00 is held out: scored, never dropped
    (tmp_path / "many").mkdir()
    (tmp_path / "few").mkdir()
    many = _capture(tmp_path / "many", 30, {i: 2.5 for i in range(2, 30, 5)})  # 6 blurred of 29 training photos
    left_out = blurred_photos(many, 640)
    assert len(left_out) == int(29 / 8) and set(left_out) <= {f"p{i:02d}.png" for i in range(2, 30, 5)}
    few = _capture(tmp_path / "few", MIN_TRAINING_PHOTOS, {3: 3.0})  # 19 training photos: every one counts
    assert blurred_photos(few, 640) == {}


def test_normalize_leaves_the_blurred_photos_out_and_says_which(tmp_path: Path) -> None:
    """The stage drops them from the scene it writes (training and meshing never read them), names each with its
    share and how to keep them; `normalize.blurred=keep` and a video's frames (chosen for sharpness already) keep all."""
    import io
    from types import SimpleNamespace

    from rich.console import Console

    from recon.app.progress import Reporter
    from recon.config import NormalizeConfig
    from recon.stages.normalize import _leave_out_blurred

    said = io.StringIO()
    ctx = SimpleNamespace(config=NormalizeConfig(), report=Reporter(Console(file=said, width=300, color_system=None)))
    scene = _capture(tmp_path, 30, {5: 2.0, 17: 3.0})
    assert _leave_out_blurred(ctx, scene).keys() == {"p05.png", "p17.png"}
    assert len(scene.frames) == 28 and scene.notes["blurred"].keys() == {"p05.png", "p17.png"}
    assert "2 of 29 training photos are blurred" in said.getvalue() and "normalize.blurred=keep" in said.getvalue()
    kept = _capture(tmp_path, 30, {5: 2.0})
    assert _leave_out_blurred(SimpleNamespace(config=NormalizeConfig(blurred="keep"), report=ctx.report), kept) == {}
    kept.source_kind = "video"
    assert _leave_out_blurred(ctx, kept) == {} and len(kept.frames) == 30


def test_a_close_up_among_wider_views_is_not_judged(tmp_path: Path) -> None:
    """Magnified, an object's own texture is smoother than the table and room the wider views around it hold: a
    close-up (its view under 1/1.25 of its neighbours' span) measures low and is left alone."""
    scene = _capture(tmp_path, 30, {7: 3.0})  # photo 7: smooth, as a magnified plain part looks
    scene.aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    for i, frame in enumerate(scene.frames):
        frame.c2w = np.eye(4)
        frame.c2w[2, 3] = 1.5 if i == 7 else 4.0  # the close-up stands nearer the box
    assert "p07.png" not in sharpness_shares(scene, 640) and blurred_photos(scene, 640) == {}
    scene.frames[7].c2w[2, 3] = 4.0  # from as far as the others, the same photo is blurred
    assert blurred_photos(scene, 640).keys() == {"p07.png"}

"""Views coarser than the training photos are rendered with k×k rays a pixel (recon.evaluation.views.rays_a_side):
a coarser photo's pixel is the mean of its area, so one ray through its centre would score aliasing as error."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.camera import look_at
from recon.capture.scene import Frame
from recon.evaluation.views import (
    MAX_RAYS_A_SIDE,
    View,
    evaluate,
    rays_a_side,
    render_view,
    supersampling_note,
    training_focal,
)
from tests.analytic_sphere import AABB, BACKGROUND, SoftSphere

POSE = look_at(np.array([0.4, -2.6, 1.2]), np.zeros(3))
BOX = torch.tensor(AABB, dtype=torch.float32)


def _view(name: str, side: int, focal: float, image: np.ndarray | None = None) -> View:
    img = np.zeros((side, side, 3), np.uint8) if image is None else image
    return View(name, img, POSE, (focal, focal, side / 2, side / 2), 0.0, 0.0)


@pytest.fixture(scope="module")
def sharp_sphere() -> SoftSphere:
    return SoftSphere(amplitude=400.0, width=0.002, samples=192)  # its silhouette is a step: pixels there alias


def test_k_by_k_rays_are_the_area_mean_of_the_fine_render(sharp_sphere: SoftSphere) -> None:
    fine = render_view(sharp_sphere, _view("fine", 64, 96.0), BOX, BACKGROUND)
    coarse = render_view(sharp_sphere, _view("coarse", 32, 48.0), BOX, BACKGROUND, rays_side=2)
    area = {k: v.reshape(32, 2, 32, 2, *v.shape[2:]).mean(axis=(1, 3)) for k, v in fine.items()}
    for key in ("rgb", "opacity", "depth"):
        assert coarse[key].shape == area[key].shape
        np.testing.assert_allclose(coarse[key], area[key], atol=2e-5)
    one_ray = render_view(sharp_sphere, _view("coarse", 32, 48.0), BOX, BACKGROUND)
    partial = (area["opacity"] > 0.1) & (area["opacity"] < 0.9)  # the silhouette's pixels
    assert partial.sum() > 20
    assert np.abs(one_ray["opacity"] - area["opacity"])[partial].mean() > 0.1


def test_evaluate_supersamples_coarse_views_and_scores_them_against_their_area_mean(sharp_sphere: SoftSphere) -> None:
    fine = render_view(sharp_sphere, _view("fine", 64, 96.0), BOX, BACKGROUND)["rgb"]
    photo = np.round(fine.reshape(32, 2, 32, 2, 3).mean(axis=(1, 3)) * 255).astype(np.uint8)  # read_image's BOX downscale
    view = _view("half", 32, 48.0, photo)
    plain = evaluate(sharp_sphere, [view], BOX, BACKGROUND)
    sampled = evaluate(sharp_sphere, [view], BOX, BACKGROUND, focal=96.0)
    assert "rays_a_side" not in plain["views"][0] and sampled["views"][0]["rays_a_side"] == 2
    assert sampled["psnr"] > 45.0  # the photo's own rounding to 8 bits is what is left
    assert sampled["psnr"] > plain["psnr"] + 10.0
    same = evaluate(sharp_sphere, [view], BOX, BACKGROUND, focal=48.0)
    assert same["psnr"] == pytest.approx(plain["psnr"]) and "rays_a_side" not in same["views"][0]


def test_evaluate_reports_each_view_once_it_is_scored(sharp_sphere: SoftSphere) -> None:
    """`on_view` (the stage's progress bar) advances once a view, so the bar's count is the views scored."""
    views = [_view(f"v{i}", 16, 24.0) for i in range(3)]
    calls: list[None] = []
    result = evaluate(sharp_sphere, views, BOX, BACKGROUND, fitted=False, on_view=lambda: calls.append(None))
    assert len(calls) == len(result["views"]) == 3


@pytest.mark.parametrize(("focal", "expected"), [(100.0, 1), (130.0, 1), (160.0, 2), (200.0, 2), (290.0, 3),
                                                 (1000.0, MAX_RAYS_A_SIDE), (50.0, 1)])
def test_rays_a_side_is_the_nearest_whole_ratio_of_pixel_sizes(focal: float, expected: int) -> None:
    assert rays_a_side(_view("v", 40, 100.0), focal) == expected


def test_training_focal_is_the_focal_at_the_size_training_reads_the_photos() -> None:
    frames = [Frame(file_path=f"p{i}.png", c2w=np.eye(4), fl_x=f, fl_y=f, cx=800, cy=600, w=1600, h=1200)
              for i, f in enumerate((1000.0, 1200.0, 1100.0))]
    assert training_focal(frames, 800) == pytest.approx(550.0)  # half size: the median 1100 px halves
    assert training_focal(frames, 4000) == pytest.approx(1100.0)  # never scaled up


def test_the_note_says_which_views_are_supersampled_and_is_silent_otherwise() -> None:
    views = [_view("a", 40, 100.0), _view("b", 20, 50.0)]
    assert supersampling_note(views, 50.0) is None
    note = supersampling_note(views, 100.0)
    assert note is not None and "1 of 2 views" in note and "b:" in note and "2×2" in note

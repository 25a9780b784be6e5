"""Per-photo appearance: the batcher's image indices, identity start, the automatic switch, recovering
known gains, and a held-out protocol whose scored pixels never shape the transform."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torch import Tensor, nn

from recon.nerf.appearance import (
    PhotoAppearance,
    apply_affine,
    decide,
    exposure_spread,
    fit_affine,
    to_neutral,
)
from recon.nerf.evaluate import held_out_right_half, left_right_split, render_image
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.fitting import RayBatcher
from recon.nerf.pieces import Appearance
from recon.nerf.render import RadianceModel, render_dense
from recon.nerf.sampling import stratified
from recon.nerf.trainer import train
from tests.ball_scene import ring_cameras

SAMPLE = Path(__file__).resolve().parents[1] / "fixtures" / "sample"
AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
COLOR = torch.tensor([0.6, 0.4, 0.3])


class FixedBall(RadianceModel):
    """A ball of known colour: the field is right, so only the photos' gains are left to learn."""

    def __init__(self) -> None:
        super().__init__()
        self.unused = nn.Parameter(torch.zeros(()))  # the optimizer needs one parameter; its gradient is 0

    def density(self, x: Tensor) -> Tensor:
        return 30.0 * (x.norm(dim=-1) < 0.6).to(x.dtype)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return COLOR.expand(x.shape[0], 3)

    def render_rays(self, rays_o, rays_d, near, far, *, training, background, colors=True):
        t = stratified(near, far, 96, jitter=False)
        sigma = self.density((rays_o[:, None] + t[..., None] * rays_d[:, None]).reshape(-1, 3)).view(t.shape)
        out = render_dense(sigma, (COLOR + 0.0 * self.unused).expand(*t.shape, 3), t, far, background)
        out["background"] = torch.as_tensor(background).expand(rays_o.shape[0], 3)
        return out


def _cameras(n: int, size: int) -> tuple[Tensor, Tensor]:
    c2w = ring_cameras(n)
    f = size * 1.2
    return c2w, torch.tensor([[f, f, size / 2, size / 2]]).expand(n, 4).contiguous()


# ----------------------------------------------------------------------------- batcher
def test_batcher_carries_each_rays_image_index() -> None:
    """Image k is filled with the value k / 10: every ray's target must match its reported image."""
    sizes = [(5, 7), (6, 4), (3, 3)]
    images = [torch.full((h, w, 3), k / 10.0) for k, (h, w) in enumerate(sizes)]
    c2w, intr = _cameras(3, 6)
    b = RayBatcher(images, c2w, intr, aabb=AABB, drop_missed=False, seed=1)
    seen = []
    for _ in range(4):  # 4 x 40 rays: crosses epochs (35 + 24 + 9 = 68 rays)
        batch = b.next_batch(40)
        assert batch["image"].dtype == torch.long
        torch.testing.assert_close(batch["rgb"][:, 0], batch["image"].float() / 10.0)
        seen.append(batch["image"])
    counts = torch.bincount(torch.cat(seen)[:68], minlength=3)  # the first epoch: each pixel once
    assert counts.tolist() == [35, 24, 9]
    dropped = RayBatcher(images, c2w, intr, aabb=AABB * 0.3, seed=1)  # kept pixels only: indices still right
    batch = dropped.next_batch(dropped.n_rays)
    torch.testing.assert_close(batch["rgb"][:, 0], batch["image"].float() / 10.0)


# ----------------------------------------------------------------------------- identity start
def test_identity_start_renders_exactly_as_without_appearance() -> None:
    torch.manual_seed(0)
    cfg = FastConfig(density_res=32, feature_res=16, occupancy_res=16, occupancy_warmup=0, aabb=((-1, -1, -1), (1, 1, 1)))
    model = FastModel(cfg).eval()
    with torch.no_grad():  # a field with colours and some opacity, not the flat start
        for param in model.parameters():
            param.normal_(0.0, 1.0)
    c2w, intr = _cameras(1, 16)
    from recon.nerf.rays import camera_rays, ray_aabb

    o, d = camera_rays(c2w[0], *intr[0].tolist(), 16, 16)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    near, far, _ = ray_aabb(o, d, AABB)
    bg = torch.tensor([0.2, 0.5, 0.9])
    out = model.render_rays(o, d, near, far, training=False, background=bg)
    assert float(out["opacity"].detach().max()) > 0.1 and float(out["rgb"].detach().std()) > 0.01
    image = torch.randint(0, 5, (o.shape[0],))
    assert torch.equal(PhotoAppearance(5)(out, image), out["rgb"])
    torch.testing.assert_close(PhotoAppearance(5, include_background=False)(out, image), out["rgb"], atol=1e-6, rtol=0)
    assert float(PhotoAppearance(5).regularizer()) == 0.0


def test_first_training_step_is_the_same_with_and_without_appearance() -> None:
    c2w, intr = _cameras(3, 10)
    images = torch.stack([render_image(FixedBall(), c, intr[0], 10, 10, aabb=AABB)["rgb"] for c in c2w]) * 0.8
    losses = []
    for app in (None, PhotoAppearance(3)):
        b = RayBatcher(images, c2w, intr, aabb=AABB, seed=0)
        pieces = [] if app is None else [Appearance(app)]
        losses.append(train(FixedBall(), b, steps=1, lr=1e-2, batch_rays=64, pieces=pieces)["loss"])
    assert losses[0] == losses[1] > 1e-4


def test_alpha_photos_transform_only_the_fields_part() -> None:
    """Where the field is empty (opacity 0) the composited background stays as it is, whatever the transform."""
    app = PhotoAppearance(2, include_background=False)
    with torch.no_grad():
        app.delta[1] = torch.tensor([[0.5, 0.1, 0.0], [0.0, -0.3, 0.0], [0.2, 0.0, 0.4]])
        app.bias[1] = torch.tensor([0.1, -0.1, 0.05])
    bg = torch.rand(4, 3)
    out = {"rgb": bg.clone(), "opacity": torch.zeros(4), "background": bg}
    torch.testing.assert_close(app(out, torch.ones(4, dtype=torch.long)), bg)
    c = torch.rand(4, 3)
    opaque = {"rgb": c, "opacity": torch.ones(4), "background": bg}
    torch.testing.assert_close(app(opaque, torch.ones(4, dtype=torch.long)), c @ app.matrices()[1].T + app.bias[1])


# ----------------------------------------------------------------------------- recovering gains
def test_training_recovers_known_per_photo_gains() -> None:
    """Photos = the true render × a per-photo, per-channel gain. The field is exact and each channel shows two
    values (ball, black backdrop), so gain g and bias 0 is the only exact fit (closed form); training must find it."""
    gains = torch.tensor([[1.0, 1.0, 1.0], [0.7, 0.75, 0.8], [1.2, 1.1, 0.9], [0.9, 1.0, 1.15]])
    c2w, intr = _cameras(4, 12)
    black = (0.0, 0.0, 0.0)  # the backdrop pins the bias at 0, the ball the gain: a well-conditioned fit
    clean = torch.stack([render_image(FixedBall(), c, intr[0], 12, 12, aabb=AABB, background=black)["rgb"] for c in c2w])
    photos = clean * gains[:, None, None, :]
    app = PhotoAppearance(4, kind="gain", reg_weight=0.0)  # the pull to the identity would shrink the gains a little
    b = RayBatcher(photos, c2w, intr, aabb=AABB, background=black, drop_missed=False, seed=0)
    train(FixedBall(), b, steps=120, lr=5e-2, lr_final=5e-3, batch_rays=256, pieces=[Appearance(app)])
    with torch.no_grad():
        got = torch.diagonal(app.matrices(), dim1=1, dim2=2)
    torch.testing.assert_close(got, gains, atol=0.01, rtol=0)
    assert float(app.bias.abs().max()) < 0.01


# ----------------------------------------------------------------------------- automatic switch
def _sample_photos(n: int) -> tuple[list[np.ndarray], np.ndarray]:
    meta = json.loads((SAMPLE / "transforms.json").read_text())
    frames = meta["frames"][:n]
    images = [np.asarray(Image.open(SAMPLE / f["file_path"]).convert("RGB")) for f in frames]
    return images, np.array([f["transform_matrix"] for f in frames], dtype=np.float64)


def test_auto_is_off_for_equal_exposures_and_on_for_known_gains() -> None:
    images, c2w = _sample_photos(12)
    equal = exposure_spread(images, c2w)
    on, why = decide("auto", equal)
    assert not on and "off" in why and equal.pairs >= 10
    assert equal.largest < 0.05
    gains = {2: (0.7, 0.75, 0.8), 5: (1.25, 1.15, 1.0), 9: (0.85, 0.9, 1.1)}
    scaled = [np.clip(np.round(im * np.array(gains.get(i, (1.0, 1.0, 1.0)))), 0, 255).astype(np.uint8)
              for i, im in enumerate(images)]
    spread = exposure_spread(scaled, c2w)
    on, why = decide("auto", spread)
    assert on and "on" in why
    assert spread.changed == 3 and set(np.flatnonzero(spread.per_photo > spread.threshold)) == set(gains)
    for i, g in gains.items():  # the estimated log gains are the known ones (clipping spares the matched colours)
        np.testing.assert_allclose(spread.log_gain[i], np.log(g), atol=0.06)
    assert decide("off", spread)[0] is False and decide("on", equal)[0] is True
    with pytest.raises(ValueError):
        decide("sometimes", equal)


def test_a_slow_drift_neighbours_read_as_constant_is_measured_by_far_partners() -> None:
    """A phone's exposure that follows the light round an object: the log gain drifts with the camera's azimuth
    (0.15 cos azimuth), so neighbouring photos differ by less than the threshold while photos further apart differ
    by more. Matched with their nearest cameras alone the photos look constant; with the far partners facing the same
    way the switch turns on and the fitted gains are the true ones."""
    meta = json.loads((SAMPLE / "transforms.json").read_text())
    images = [np.asarray(Image.open(SAMPLE / f["file_path"]).convert("RGB")) for f in meta["frames"]]
    c2w = np.array([f["transform_matrix"] for f in meta["frames"]], dtype=np.float64)
    log_gain = 0.15 * np.cos(np.arctan2(c2w[:, 1, 3], c2w[:, 0, 3]))
    drifted = [np.clip(np.round(im * np.exp(g)), 0, 255).astype(np.uint8) for im, g in zip(images, log_gain)]
    near_only = exposure_spread(drifted, c2w, far=0)
    on_near, why_near = decide("auto", near_only)
    assert not on_near and near_only.changed >= 10  # the gains are there, the pairs hide them
    assert "its 4 nearest and up to 0 further off" in why_near
    spread = exposure_spread(drifted, c2w)
    on, why = decide("auto", spread)
    assert on and spread.pairs > near_only.pairs and spread.pairs_changed > 3 * near_only.pairs_changed
    np.testing.assert_allclose(spread.log_gain, np.repeat((log_gain - np.median(log_gain))[:, None], 3, 1), atol=0.03)


# ----------------------------------------------------------------------------- held-out protocol
def test_held_out_transform_never_sees_the_scored_half() -> None:
    rng = np.random.default_rng(0)
    pred = rng.uniform(0.1, 0.9, (20, 30, 3)).astype(np.float32)
    gain = np.array([0.7, 0.8, 1.1], np.float32)
    photo = np.clip(pred * gain + 0.02, 0, 1)
    got, ref = held_out_right_half(pred, photo)
    left, right = left_right_split(30)
    assert got.shape == ref.shape == (20, 15, 3) and np.array_equal(ref, photo[:, right])
    np.testing.assert_allclose(got, photo[:, right], atol=0.01)  # the left half's transform fits the right half
    tampered = photo.copy()
    tampered[:, right] = rng.uniform(0, 1, tampered[:, right].shape)  # scored pixels changed: render unchanged
    got2, ref2 = held_out_right_half(pred, tampered)
    assert np.array_equal(got2, got) and not np.array_equal(ref2, ref)
    shifted = photo.copy()
    shifted[:, left] *= 0.5  # the fitted half changed: the transform follows
    assert not np.allclose(held_out_right_half(pred, shifted)[0], got, atol=0.05)


def test_closed_form_fit_with_alpha_leaves_the_background_alone() -> None:
    rng = np.random.default_rng(1)
    c = rng.uniform(0.1, 0.9, (500, 3))
    op = rng.uniform(0, 1, 500)
    bg = np.array([1.0, 1.0, 1.0])
    a_true = np.array([[0.8, 0.05, 0.0], [0.0, 0.9, 0.0], [0.02, 0.0, 1.1]])
    b_true = np.array([0.03, -0.02, 0.0])
    pred = c * op[:, None] + (1 - op[:, None]) * bg
    target = (c @ a_true.T + b_true) * op[:, None] + (1 - op[:, None]) * bg
    a, b = fit_affine(pred, target, opacity=op, background=bg, ridge=0.0)
    np.testing.assert_allclose(a, a_true, atol=1e-6)
    np.testing.assert_allclose(b, b_true, atol=1e-6)
    np.testing.assert_allclose(apply_affine(pred, a, b, opacity=op, background=bg), np.clip(target, 0, 1), atol=1e-5)


def test_photos_baked_onto_the_mesh_are_brought_to_the_neutral_appearance() -> None:
    app = PhotoAppearance(1)
    with torch.no_grad():
        app.delta[0] = torch.tensor([[-0.3, 0.05, 0.0], [0.0, -0.25, 0.0], [0.0, 0.02, -0.2]])
        app.bias[0] = torch.tensor([0.02, 0.0, -0.01])
    rng = np.random.default_rng(2)
    neutral = rng.uniform(0.1, 0.9, (6, 5, 3))
    photo_f = neutral @ app.matrices()[0].detach().double().numpy().T + app.bias[0].detach().double().numpy()
    photo = np.concatenate([np.round(photo_f * 255).astype(np.uint8), np.full((6, 5, 1), 200, np.uint8)], axis=-1)
    back = to_neutral(photo, app.summary(["p"])["p"])
    assert np.abs(back[..., :3].astype(float) - neutral * 255).max() <= 1.5  # 8-bit rounding, twice
    assert np.array_equal(back[..., 3], photo[..., 3]) and to_neutral(photo, None) is photo


def test_auto_needs_the_pairs_to_differ_not_only_the_least_squares_gains() -> None:
    """A few inconsistent pairs (specular highlights, glossy parts seen from two sides, mismatches) that least squares
    spreads over many photos do not switch the model on; an exposure change that shows in many pairs does (counts
    measured with and without the far partners: benchmarks/results/exposure_pairs.json)."""
    from recon.nerf.appearance import ExposureSpread, decide

    gains = np.zeros((60, 3))
    per_photo = np.r_[np.full(16, 0.2), np.zeros(44)]
    for pairs, changed_pairs in ((234, 9), (328, 27)):  # the Lego: constant exposure, glossy parts
        lego_like = ExposureSpread(gains, per_photo, 0.08, changed=16, pairs=pairs, pairs_changed=changed_pairs)
        on, why = decide("auto", lego_like)
        assert not on and f"{changed_pairs} of those pairs" in why
    tabletop_like = ExposureSpread(gains, per_photo, 0.08, changed=16, pairs=79, pairs_changed=59)
    assert decide("auto", tabletop_like)[0]
    fox_near_only = ExposureSpread(gains, per_photo, 0.08, changed=27, pairs=161, pairs_changed=19)
    assert not decide("auto", fox_near_only)[0]  # a drift: neighbours alone see too few changed pairs
    fox = ExposureSpread(gains, per_photo, 0.08, changed=27, pairs=368, pairs_changed=143)
    assert decide("auto", fox)[0]


def test_photos_cut_out_by_masks_are_measured_whole_and_no_measurement_is_not_called_constant() -> None:
    """A plain object alone gives SIFT no matches: its photos' exposure, when their alpha is only their masks, is
    measured on the whole photo (the camera's gain is the whole photo's); a render's own alpha hides colours that
    are not the photo's, and with nothing to match the switch says it could not measure, not that all is constant."""
    from recon.capture.scene import Frame
    from recon.config import TrainConfig
    from recon.evaluation.views import View
    from recon.plans.training import choose_appearance

    images, c2w = _sample_photos(12)
    gains = {2: (0.7, 0.75, 0.8), 5: (1.25, 1.15, 1.0), 9: (0.85, 0.9, 1.1)}
    h, w = images[0].shape[:2]
    alpha = np.zeros((h, w, 1), np.uint8)
    alpha[h // 2 - 3 : h // 2 + 3, w // 2 - 3 : w // 2 + 3] = 255  # the "object": a few pixels, nothing to match
    views, frames = [], []
    for i, im in enumerate(images):
        scaled = np.clip(np.round(im * np.array(gains.get(i, (1.0, 1.0, 1.0)))), 0, 255).astype(np.uint8)
        views.append(View(f"{i:02d}", np.concatenate([scaled, alpha], axis=-1), c2w[i], (w, w, w / 2, h / 2), 0.1, 9.0))
        frames.append(Frame(f"/p/{i:02d}.png", c2w[i], w, w, w / 2, h / 2, w, h, split="train", mask_path=f"/m/{i:02d}.png"))
    on, why = choose_appearance(TrainConfig(), "fast", views, frames)
    assert on and "measured on the colours of SIFT matches" in why
    own_alpha = [replace(f, mask_path=None) for f in frames]
    on, why = choose_appearance(TrainConfig(), "fast", views, own_alpha)
    assert not on and "could not be measured" in why and "constant" not in why


def test_a_field_without_appearance_is_also_scored_with_each_photos_colours_fitted_on_its_left_half() -> None:
    """`psnr_fitted`: a photo taken at another exposure scores low against the neutral render and high once its
    colour transform is fitted on the left half; an appearance field's score is that already, so it has none. The
    printed note concludes an exposure cost only from the gain over the same pixels unfitted."""
    from recon.camera import look_at
    from recon.evaluation.views import EXPOSURE_COST_DB, View, evaluate, fitted_note, render_view
    from tests.analytic_sphere import AABB, BACKGROUND, SoftSphere

    sphere, box = SoftSphere(amplitude=400.0, width=0.02, samples=96), torch.tensor(AABB, dtype=torch.float32)
    pose = look_at(np.array([0.4, -2.6, 1.2]), np.zeros(3))
    render = render_view(sphere, View("r", np.zeros((48, 48, 3), np.uint8), pose, (60.0, 60.0, 24.0, 24.0), 0, 0),
                         box, BACKGROUND)["rgb"]
    darker = np.clip(np.round(render * np.array([0.6, 0.7, 0.8]) * 255), 0, 255).astype(np.uint8)
    view = View("d", darker, pose, (60.0, 60.0, 24.0, 24.0), 0.0, 0.0)
    scored = evaluate(sphere, [view], box, BACKGROUND)
    assert scored["psnr"] < 25.0 and scored["psnr_fitted"] > scored["psnr"] + 15.0
    assert scored["views"][0]["psnr_fitted"] == pytest.approx(scored["psnr_fitted"])
    assert "psnr_fitted" not in evaluate(sphere, [view], box, BACKGROUND, appearance=True)
    # the note compares the fit with the same right halves unfitted, and says the exposure cost only when it is one
    assert scored["psnr_right_half"] < 25.0
    assert "cost the plain score" in fitted_note(scored) and "little" not in fitted_note(scored)
    same = View("s", np.clip(np.round(render * 255), 0, 255).astype(np.uint8), pose, (60.0, 60.0, 24.0, 24.0), 0.0, 0.0)
    unchanged = evaluate(sphere, [same], box, BACKGROUND)
    assert abs(unchanged["psnr_fitted"] - unchanged["psnr_right_half"]) < EXPOSURE_COST_DB
    assert fitted_note(unchanged).endswith("cost the plain score little")
    assert fitted_note(evaluate(sphere, [view], box, BACKGROUND, appearance=True)) is None

"""The backdrop key (issue 13): photos on a plain backdrop train the backdrop's pixels as empty space for the surface
model, so its closed zero set cannot close over what only the backdrop shows (a hole seen through, an unseen base)."""
from __future__ import annotations

import numpy as np
import pytest

from recon.capture.scene import Scene
from recon.config import TrainConfig
from recon.evaluation.views import BACKDROP_TOLERANCE, View, key_backdrop, plain_backdrop
from recon.plans.training import choose_background, key_backdrop_for

RNG = np.random.default_rng(0)


def _photo(backdrop: tuple[float, float, float], noise: float = 0.0, size: int = 40) -> np.ndarray:
    """A square of object texture (channels 0.1-0.7) in the middle of a backdrop with JPEG-like noise."""
    img = np.ones((size, size, 3)) * np.asarray(backdrop) + RNG.normal(0.0, noise, (size, size, 3))
    q = size // 4
    img[q:-q, q:-q] = RNG.uniform(0.1, 0.7, (size - 2 * q, size - 2 * q, 3))
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def _view(image: np.ndarray) -> View:
    return View("v", image, np.eye(4), (30.0, 30.0, 20.0, 20.0), 0.0, 0.0)


def test_key_makes_the_backdrop_transparent_the_object_opaque_and_composites_back_to_the_photo() -> None:
    white = (1.0, 1.0, 1.0)
    photo = _photo(white, noise=0.006)
    photo[10, 5] = np.round(255 * (0.5 * 1.0 + 0.5 * np.array([0.2, 0.4, 0.6])))  # an edge pixel, half object
    rgba = key_backdrop(photo, np.ones(3))
    alpha = rgba[..., 3] / 255.0
    q = photo.shape[0] // 4
    assert alpha[q:-q, q:-q].min() == 1.0  # every object pixel stays object
    backdrop = np.ones(alpha.shape, bool)
    backdrop[q:-q, q:-q] = False
    backdrop[10, 5] = False
    assert alpha[backdrop].max() == 0.0  # noise within the tolerance is backdrop
    assert alpha[10, 5] == 1.0  # half an object pixel differs by 0.2-0.4: object
    over_backdrop = rgba[..., :3] / 255.0 * alpha[..., None] + (1.0 - alpha[..., None])
    # the object's pixels come back as they were; the backdrop's as its colour, which the noise was within tolerance of
    np.testing.assert_allclose(over_backdrop[~backdrop], photo[~backdrop] / 255.0, atol=1.5 / 255)
    np.testing.assert_allclose(over_backdrop[backdrop], 1.0)
    assert np.abs(photo[backdrop] / 255.0 - 1.0).max() <= BACKDROP_TOLERANCE


def test_key_ramps_alpha_between_one_and_three_tolerances_and_unmixes_the_colour() -> None:
    grey = np.array([0.5, 0.5, 0.5])
    d = np.array([0.0, BACKDROP_TOLERANCE, 2 * BACKDROP_TOLERANCE, 3 * BACKDROP_TOLERANCE, 0.3])
    photo = np.round((grey[None] - d[:, None]) * 255).astype(np.uint8)[None]  # darker than the backdrop by d
    rgba = key_backdrop(photo, grey)
    np.testing.assert_allclose(rgba[0, :, 3] / 255.0, [0.0, 0.0, 0.5, 1.0, 1.0], atol=0.06)
    a = rgba[0, 2, 3] / 255.0
    recomposed = rgba[0, 2, :3] / 255.0 * a + grey * (1 - a)
    np.testing.assert_allclose(recomposed, photo[0, 2] / 255.0, atol=2 / 255)


def test_plain_backdrop_tells_a_light_box_from_a_room() -> None:
    color, plain = plain_backdrop([_view(_photo((0.9, 0.9, 0.95), noise=0.006)) for _ in range(3)])
    np.testing.assert_allclose(color, [0.9, 0.9, 0.95], atol=0.01)
    assert plain == 1.0
    room = [_view(np.round(RNG.uniform(0, 1, (40, 40, 3)) * 255).astype(np.uint8)) for _ in range(3)]
    assert plain_backdrop(room)[1] < 0.2


def _scene(has_alpha: bool = False, capture: str = "object") -> Scene:
    return Scene(frames=[], aabb=((-1, -1, -1), (1, 1, 1)), capture=capture, has_alpha=has_alpha)


@pytest.mark.parametrize("mode, kind, capture, plain, alpha, keyed, says", [
    ("auto", "surface", "object", True, False, True, "backdrop key: on (100% of the photos' border pixels"),
    ("auto", "fast", "object", True, False, False, "surface model's photos only"),
    ("auto", "surface", "object", False, False, False, "no plain backdrop"),
    ("auto", "surface", "object", True, True, False, "not needed"),
    ("off", "surface", "object", True, False, False, "train.backdrop_key=off"),
    ("on", "fast", "object", True, False, True, "train.backdrop_key=on"),
])
def test_the_key_is_chosen_by_model_and_backdrop_and_says_why(mode: str, kind: str, capture: str, plain: bool, alpha: bool,
                                                              keyed: bool, says: str) -> None:
    if plain:
        views = [_view(_photo((1.0, 1.0, 1.0), noise=0.006)) for _ in range(3)]
    else:
        views = [_view(np.round(RNG.uniform(0, 1, (40, 40, 3)) * 255).astype(np.uint8)) for _ in range(3)]
    cfg = TrainConfig(backdrop_key=mode)
    out, backdrop, why = key_backdrop_for(cfg, kind, _scene(alpha, capture), views)
    assert says in why
    assert (backdrop is not None) == keyed
    assert all(v.image.shape[-1] == (4 if keyed else 3) for v in out)
    background, random_bg, bg_why = choose_background(cfg, _scene(alpha, capture), out, backdrop)
    if keyed:
        assert random_bg and "keyed" in bg_why
        np.testing.assert_allclose(background, backdrop)
    else:
        assert random_bg == alpha  # masks: random backgrounds as before; no key, no alpha: the border colour


@pytest.mark.parametrize("keyed", [False, True])
def test_a_white_ball_on_a_white_backdrop_survives_without_the_key_and_vanishes_with_it(keyed: bool) -> None:
    """Photos of nothing but a white backdrop and a surface model whose initial sphere is painted white: the photos'
    colours are matched already, so without the key nothing moves it; keyed, the backdrop's pixels carve it away."""
    import math

    import torch

    from recon.camera import look_at
    from recon.nerf.fitting import RayBatcher
    from recon.nerf.surface import SurfaceConfig, SurfaceModel
    from recon.nerf.trainer import train

    torch.manual_seed(0)
    n, size, fl = 6, 16, 20.0
    c2w = np.stack([look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 1.0]), np.zeros(3))
                    for a in np.linspace(0, 2 * math.pi, n, endpoint=False)])
    photos = [np.full((size, size, 3), 255, np.uint8) for _ in range(n)]  # the backdrop alone
    images = [torch.from_numpy(key_backdrop(p, np.ones(3)) if keyed else p) for p in photos]
    cfg = SurfaceConfig(aabb=((-1.0,) * 3, (1.0,) * 3), sdf_res=17, sdf_levels=1, feature_res=8, feature_dim=4, level_every=0,
                        eikonal_samples=256, eikonal_points=256, boundary_points=120)
    model = SurfaceModel(cfg)
    with torch.no_grad():
        model.color_mlp[-1].bias.fill_(8.0)  # white
    batcher = RayBatcher(images, torch.tensor(c2w, dtype=torch.float32), torch.tensor([[fl, fl, size / 2, size / 2]] * n),
                         aabb=model.aabb, background=torch.ones(3), random_background=keyed, seed=0)
    train(model, batcher, steps=60, lr=1e-2, batch_rays=256)
    model.eval()
    with torch.no_grad():
        o = torch.tensor(c2w[:, :3, 3], dtype=torch.float32)
        d = -o / o.norm(dim=-1, keepdim=True)  # the centre rays, straight through where the sphere began
        out = model.render_rays(o, d, torch.zeros(n), torch.full((n,), 6.0), training=False)
    opacity = float(out["opacity"].mean())
    if keyed:
        assert opacity < 0.1
    else:
        assert opacity > 0.9

"""FastModel: interface shapes, initial opacity, regularizers against brute force, a few training steps."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from recon.nerf.fast import FastConfig, FastModel, distortion_loss_packed, sh_encode, sh_product, sh_terms
from recon.nerf.grid import DenseGrid
from recon.nerf.occupancy import density_threshold

TINY = dict(density_res=24, feature_res=16, feature_dim=4, occupancy_res=8, occupancy_warmup=4,
            occupancy_every=2, mlp_width=16, mlp_layers=1)


def _rays(n: int, seed: int = 0, radius: float = 4.0):
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * radius
    d = torch.nn.functional.normalize(-o + torch.randn(n, 3, generator=g) * 0.8, dim=-1)
    return o, d, torch.full((n,), 2.0), torch.full((n,), 6.0)


@pytest.mark.parametrize("grid", ["dense", "vm", "hash"])
@pytest.mark.parametrize("unbounded", [False, True])
def test_render_rays_shapes_and_finite(grid: str, unbounded: bool) -> None:
    torch.manual_seed(0)
    cfg = FastConfig(grid=grid, unbounded=unbounded, cone_angle=0.01 if unbounded else 0.0,
                     distortion_weight=0.01, entropy_weight=0.01, tv_weight=0.1, **TINY)
    model = FastModel(cfg)
    o, d, near, far = _rays(64)
    o[:4] = torch.tensor([10.0, 10.0, 10.0])  # rays that miss the box entirely
    d[:4] = torch.tensor([1.0, 0.0, 0.0])
    for training in (True, False):
        out = model.render_rays(o, d, near, far, training=training, background=torch.ones(3))
        assert out["rgb"].shape == (64, 3) and out["depth"].shape == (64,) and out["opacity"].shape == (64,)
        for key in ("rgb", "depth", "opacity", "reg"):
            assert torch.isfinite(out[key]).all(), key
        assert bool((out["opacity"] >= 0).all() and (out["opacity"] <= 1 + 1e-5).all())
    if not unbounded:
        torch.testing.assert_close(out["rgb"][:4], torch.ones(4, 3))  # misses show the background
    x = torch.randn(100, 3)
    assert model.density(x).shape == (100,) and model.radiance(x, d[:1].expand(100, 3)).shape == (100, 3)


@pytest.mark.parametrize("native", [True, False])
def test_a_depth_only_render_gives_the_same_depth_without_the_colour_work(native: bool, monkeypatch) -> None:
    """colors=False (the mesh stage's depth maps, the depth prior): the same depth and opacity, no colour evaluated,
    the background as rgb; through the C marcher (rendering) and the torch one (training, and CUDA)."""
    import recon.nerf.fast as fast

    if not native:
        monkeypatch.setattr(fast, "march_render_native", lambda *a, **k: None)
        monkeypatch.setattr(fast, "march_dense_native", lambda *a, **k: None)
    torch.manual_seed(0)
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1}))
    with torch.no_grad():
        model.density_grid.table.add_(torch.randn_like(model.density_grid.table) * 3.0)
    o, d, near, far = _rays(96)
    bg = torch.tensor([0.2, 0.4, 0.6])
    colored = []
    monkeypatch.setattr(FastModel, "_rgb_unit", lambda self, u, dirs: colored.append(len(u)) or torch.zeros(len(u), 3))
    with torch.no_grad():
        full = model.render_rays(o, d, near, far, training=False, background=bg)
        assert colored and sum(colored) > 0
        colored.clear()
        depth_only = model.render_rays(o, d, near, far, training=False, background=bg, colors=False)
    assert not colored
    torch.testing.assert_close(depth_only["depth"], full["depth"])
    torch.testing.assert_close(depth_only["opacity"], full["opacity"])
    assert 0 < float(full["opacity"].mean()) < 1
    torch.testing.assert_close(depth_only["rgb"], bg.expand(96, 3))


def test_initial_opacity_per_step_and_zero_outside_box() -> None:
    cfg = FastConfig(init_alpha=0.01, **TINY)
    model = FastModel(cfg)
    sigma = model.density(torch.zeros(5, 3))
    alpha = 1 - torch.exp(-sigma * model.step_size)
    torch.testing.assert_close(alpha, torch.full_like(alpha, 0.01), rtol=1e-4, atol=1e-6)
    assert float(model.density(torch.tensor([[3.0, 0.0, 0.0]])).detach()[0]) == 0.0


@pytest.mark.parametrize("activation", ["softplus", "trunc_exp"])
@pytest.mark.parametrize("levels", [1, 3])
def test_a_start_shape_holds_its_opacity_inside_and_the_initial_one_outside(activation: str, levels: int) -> None:
    """start_inside: opacity hull_start_alpha a step at the vertices inside the shape (the coarsest level's grid over
    the box), init_alpha far from it; the wrong shape, no alpha or a shrunk grid are refused."""
    cfg = FastConfig(init_alpha=0.01, hull_start_alpha=0.2, density_activation=activation, density_levels=levels,
                     **TINY)
    model = FastModel(cfg)
    r = model.start_resolution
    assert r == (TINY["density_res"] if levels == 1 else min(model.density_grid.resolutions))
    axis = torch.linspace(0.0, 1.0, r)
    u = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1)  # [ix, iy, iz] -> unit point
    inside = ((u - torch.tensor([0.5, 0.5, 0.3])).norm(dim=-1) < 0.25) & (u[..., 0] > 0.4)  # not symmetric in x, z
    model.start_inside(inside)
    box = model.grid_box
    world = box[0] + u * (box[1] - box[0])

    def alpha(x: torch.Tensor) -> torch.Tensor:
        return 1 - torch.exp(-model.density(x).detach() * model.step_size)

    deep = inside.clone()  # vertices whose whole neighbourhood is inside: trilinear reads there see the shape alone
    for axis_ in range(3):
        for shift in (1, -1):
            deep &= torch.roll(inside, shift, axis_)
    far = ~inside
    for axis_ in range(3):
        for shift in (1, -1):
            far &= ~torch.roll(inside, shift, axis_)
    assert deep.any() and far.any()
    torch.testing.assert_close(alpha(world[deep]), torch.full((int(deep.sum()),), 0.2), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(alpha(world[far]), torch.full((int(far.sum()),), 0.01), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="start shape must be"):
        model.start_inside(inside[:-1])
    with pytest.raises(ValueError, match="hull_start_alpha"):
        FastModel(FastConfig(hull_start_alpha=0.0, **TINY)).start_inside(inside)
    model.shrunk.fill_(True)
    with pytest.raises(ValueError, match="shrunk"):
        model.start_inside(inside)


def test_trunc_exp_density_never_overflows() -> None:
    model = FastModel(FastConfig(density_activation="trunc_exp", **TINY))
    with torch.no_grad():
        for p in model.density_grid.parameters():
            p.fill_(1e6)
    assert torch.isfinite(model.density(torch.zeros(3, 3))).all()


def test_distortion_loss_matches_brute_force() -> None:
    g = torch.Generator().manual_seed(0)
    counts = [3, 0, 5, 1]
    ri = torch.repeat_interleave(torch.arange(4), torch.tensor(counts))
    m = ri.shape[0]
    w = torch.rand(m, generator=g, dtype=torch.float64)
    delta = torch.rand(m, generator=g, dtype=torch.float64) * 0.1
    t = torch.cat([torch.sort(torch.rand(c, generator=g, dtype=torch.float64))[0] for c in counts])
    expected = 0.0
    for r in range(4):
        sel = ri == r
        wr, tr, dr = w[sel], t[sel], delta[sel]
        expected += float((wr[:, None] * wr[None, :] * (tr[:, None] - tr[None, :]).abs()).sum() + (wr**2 * dr).sum() / 3)
    assert float(distortion_loss_packed(w, t, delta, ri, 4)) == pytest.approx(expected / 4, rel=1e-10)


def test_sh_encoding_is_orthonormal_on_the_sphere() -> None:
    """Real SH of degree <= 3: Gram matrix over a Fibonacci sphere = identity / (4 pi)."""
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = (1 - z**2).sqrt()
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    y = sh_encode(d, 3)
    gram = y.t() @ y * (4 * math.pi / n)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_as_one_matrix_product_equals_the_terms(degree: int) -> None:
    """The GPU's harmonics (powers of d times a matrix read off the terms) are the terms' to rounding, on unit
    directions, the axes themselves and directions that are not unit length (both are polynomials); a CPU runs the
    terms."""
    g = torch.Generator().manual_seed(degree)
    d = torch.cat([F.normalize(torch.randn(5000, 3, generator=g, dtype=torch.float64), dim=-1),
                   torch.eye(3, dtype=torch.float64), -torch.eye(3, dtype=torch.float64),
                   3 * torch.rand(50, 3, generator=g, dtype=torch.float64) - 1.5])
    torch.testing.assert_close(sh_product(d, degree), sh_terms(d, degree), atol=1e-12, rtol=0)
    torch.testing.assert_close(sh_product(d.float(), degree), sh_terms(d.float(), degree), atol=2e-6, rtol=0)
    assert sh_product(d.float(), degree).dtype == torch.float32
    assert torch.equal(sh_encode(d.float(), degree), sh_terms(d.float(), degree))
    with pytest.raises(ValueError, match="sh_degree"):
        sh_product(d, 4)


def test_occupancy_refresh_culls_empty_space_after_warmup() -> None:
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1}))
    with torch.no_grad():
        model.density_grid.table.fill_(-30.0)  # empty everywhere...
        model.density_grid.volume()[10:14, 10:14, 10:14] = 30.0  # ...but a small block at the centre
    for step in range(0, 12, 2):
        model.step_update(step)
    assert 0.0 < model.occupancy.occupied_fraction() < 0.2
    box = model.march_box
    assert bool((box[0] > model.aabb[0]).all() and (box[1] < model.aabb[1]).all())


def test_param_groups_cover_all_parameters_once() -> None:
    model = FastModel(FastConfig(background="learned", **TINY))
    groups = model.param_groups(1e-2)
    ids = [id(p) for g in groups for p in g["params"]]
    assert sorted(ids) == sorted(id(p) for p in model.parameters())
    assert groups[0]["lr"] == pytest.approx(1e-2 * model.config.grid_lr_scale)


def test_the_distortion_loss_starts_once_its_share_of_training_is_done() -> None:
    model = FastModel(FastConfig(distortion_weight=0.03, distortion_from=0.25, entropy_weight=0.0, tv_weight=0.0,
                                 **TINY))
    weights = []
    for progress in (0.0, 0.24, 0.25, 1.0):
        model.set_progress(progress)
        weights.append(model.distortion_weight_now())
    assert weights == [0.0, 0.0, 0.03, 0.03]
    held = FastModel(FastConfig(distortion_weight=0.03, **TINY))
    held.set_progress(0.0)
    assert held.distortion_weight_now() == 0.03
    o, d, near, far = _rays(64)
    model.set_progress(0.1)  # not yet: no distortion term in the training loss
    assert "reg" not in model.render_rays(o, d, near, far, training=True, background=torch.ones(3))
    model.set_progress(0.5)
    assert float(model.render_rays(o, d, near, far, training=True, background=torch.ones(3))["reg"]) > 0


def test_the_distortion_loss_stops_once_its_window_is_over() -> None:
    model = FastModel(FastConfig(distortion_weight=0.03, distortion_from=0.1, distortion_until=0.6,
                                 entropy_weight=0.0, tv_weight=0.0, **TINY))
    weights = []
    for progress in (0.05, 0.1, 0.59, 0.6, 1.0):
        model.set_progress(progress)
        weights.append(model.distortion_weight_now())
    assert weights == [0.0, 0.03, 0.03, 0.0, 0.0]
    o, d, near, far = _rays(64)
    assert "reg" not in model.render_rays(o, d, near, far, training=True, background=torch.ones(3))


def test_a_few_steps_reduce_the_loss_on_a_synthetic_target() -> None:
    """Target: rays through a red ball of radius 0.5 are red, others white (over a white background)."""
    torch.manual_seed(0)
    model = FastModel(FastConfig(**TINY))
    opt = torch.optim.Adam(model.param_groups(1e-2))
    o, d, near, far = _rays(512, seed=1)
    # distance of closest approach to the origin decides the target color
    closest = (o - (o * d).sum(-1, keepdim=True) * d).norm(dim=-1)
    target = torch.where((closest < 0.5)[:, None], torch.tensor([1.0, 0.1, 0.1]), torch.ones(3))
    losses = []
    for step in range(40):
        model.step_update(step)
        out = model.render_rays(o, d, near, far, training=True, background=torch.ones(3))
        loss = (out["rgb"] - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert sum(losses[-5:]) / 5 < 0.3 * sum(losses[:5]) / 5


def _lego(root, split: str, res: int, limit: int | None = None):
    """Images (K, res, res, 3) composited on white, c2w (K, 4, 4) and focal (px) of the half-res Lego."""
    import json

    import numpy as np
    from PIL import Image

    meta = json.loads((root / f"transforms_{split}.json").read_text())
    frames = meta["frames"][:limit] if limit else meta["frames"]
    imgs, poses = [], []
    for f in frames:
        im = Image.open(root / f"{f['file_path']}.png").convert("RGBA").resize((res, res), Image.BOX)
        a = np.asarray(im, np.float32) / 255.0
        imgs.append(a[..., :3] * a[..., 3:] + (1 - a[..., 3:]))
        poses.append(np.array(f["transform_matrix"], np.float32))
    focal = 0.5 * res / math.tan(0.5 * meta["camera_angle_x"])
    return torch.tensor(np.stack(imgs)), torch.tensor(np.stack(poses)), focal


def _pixel_rays(c2w: torch.Tensor, focal: float, res: int, px: torch.Tensor, py: torch.Tensor):
    """OpenGL camera rays through pixel centres: c2w (N, 4, 4), px/py (N,) integer pixel coordinates."""
    d = torch.stack([(px + 0.5 - res / 2) / focal, -(py + 0.5 - res / 2) / focal, -torch.ones_like(px)], -1)
    d = torch.nn.functional.normalize((c2w[:, :3, :3] @ d[..., None])[..., 0], dim=-1)
    return c2w[:, :3, 3], d


@pytest.mark.slow
def test_lego_100px_reaches_20db_in_150_steps(shared_data) -> None:
    """End to end on real data: 150 steps x 4096 rays at 100x100 (~22 dB measured; ~1 min of CPU)."""
    root = shared_data / "nerf_synthetic_lego_half"
    res, batch = 100, 4096
    imgs, poses, focal = _lego(root, "train", res)
    timgs, tposes, _ = _lego(root, "test", res, limit=2)
    torch.manual_seed(0)
    model = FastModel(FastConfig())
    opt = torch.optim.Adam(model.param_groups(1e-2), fused=True)
    white = torch.ones(3)
    for step in range(150):
        model.step_update(step)
        i = torch.randint(0, imgs.shape[0], (batch,))
        px, py = torch.randint(0, res, (batch,)), torch.randint(0, res, (batch,))
        o, d = _pixel_rays(poses[i], focal, res, px.float(), py.float())
        out = model.render_rays(o, d, torch.full((batch,), 2.0), torch.full((batch,), 6.0), training=True, background=white)
        loss = (out["rgb"] - imgs[i, py, px]).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.eval()
    py, px = torch.meshgrid(torch.arange(res), torch.arange(res), indexing="ij")
    psnrs = []
    with torch.no_grad():
        for k in range(2):
            o, d = _pixel_rays(tposes[k].expand(res * res, 4, 4), focal, res, px.reshape(-1).float(), py.reshape(-1).float())
            n = o.shape[0]
            rgb = model.render_rays(o, d, torch.full((n,), 2.0), torch.full((n,), 6.0), training=False, background=white)["rgb"]
            psnrs.append(-10 * math.log10(float((rgb.view(res, res, 3) - timgs[k]).square().mean())))
    assert sum(psnrs) / 2 > 20.0, psnrs


def test_shrinking_the_grids_keeps_the_field_and_empties_the_outside() -> None:
    """After the re-sample onto the occupied box, σ inside it is what it was (to interpolation error)."""
    torch.manual_seed(0)
    model = FastModel(FastConfig(**{**TINY, "density_res": 33, "feature_res": 33, "shrink_margin": 0.0}))
    with torch.no_grad():
        x = model.aabb[0] + (model.aabb[1] - model.aabb[0]) * torch.rand(4000, 3)
        ball = lambda p: 8.0 * torch.exp(-(p.norm(dim=-1) / 0.5) ** 2)  # smooth field: small interpolation error
        for level in model.density_grid.modules():
            if isinstance(level, DenseGrid):
                level.table.zero_()
        first = model.density_grid.grids[-1]
        lin = torch.linspace(0, 1, first.res)
        u = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
        first.table.copy_(ball(model.aabb[0] + u * (model.aabb[1] - model.aabb[0]))[:, None])
        inner = torch.tensor([[-0.75] * 3, [0.75] * 3])
        rgb_before = model.radiance(x, torch.nn.functional.normalize(torch.ones_like(x), dim=-1))
        sigma_before = model.density(x)
        assert model.shrink_grids(inner)
        sigma_after = model.density(x)
    torch.testing.assert_close(model.grid_box, inner)
    inside = (x.abs() < 0.75).all(-1)
    rel = (sigma_after[inside] - sigma_before[inside]).abs() / sigma_before[inside]
    assert float(rel.max()) < 0.05
    assert bool((sigma_after[~inside] == 0).all())
    with torch.no_grad():
        rgb_after = model.radiance(x[inside], torch.nn.functional.normalize(torch.ones_like(x[inside]), dim=-1))
    assert float((rgb_after - rgb_before[inside]).abs().max()) < 0.05
    assert not model.shrink_grids(torch.tensor([[-0.74] * 3, [0.74] * 3]))  # < 10% smaller: not worth it


def test_a_hash_colour_grid_stays_on_the_scene_box_when_the_density_grid_shrinks() -> None:
    """The density grid is re-sampled onto the occupied box; the hash colour grid is not (it has no vertices to
    re-sample), and its reads follow the points: the colour at every world point inside the new box is the same."""
    torch.manual_seed(1)
    model = FastModel(FastConfig(**{**TINY, "grid": "hash", "feature_res": 40, "hash_table_log2": 10,
                                    "shrink_margin": 0.0, "aabb": ((-1.0, -1.2, -0.8), (1.1, 1.0, 1.0))}))
    with torch.no_grad():
        model.color_grid.table.normal_(0.0, 1.0)  # colours that vary at the finest levels
        x = torch.rand(3000, 3) * 1.2 - 0.6
        d = torch.nn.functional.normalize(torch.randn(3000, 3), dim=-1)
        before = model.radiance(x, d)
        table = model.color_grid.table.clone()
        assert model.shrink_grids(torch.tensor([[-0.6, -0.7, -0.65], [0.6, 0.62, 0.6]]))
        after = model.radiance(x, d)
        model._color_unit = lambda u: u  # read the hash grid in the shrunk box's coordinates: other colours
        unmapped = model.radiance(x, d)
    assert not torch.equal(model.grid_box, model.aabb) and torch.equal(model.color_grid.table, table)
    torch.testing.assert_close(after, before, rtol=0, atol=1e-5)
    assert float((unmapped - before).abs().max()) > 1e-2


def test_shrink_happens_once_and_asks_for_fresh_optimizer_moments() -> None:
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1, "shrink_step": 6}))
    with torch.no_grad():
        model.density_grid.table.fill_(-30.0)
        model.density_grid.volume()[10:14, 10:14, 10:14] = 30.0
    moved = [model.step_update(step) for step in range(0, 16, 2)]
    assert moved == [False, False, False, True, False, False, False, False]  # step 6: first refresh >= shrink_step
    assert bool(model.shrunk)
    assert float((model.grid_box[1] - model.grid_box[0]).max()) < 0.5 * float((model.aabb[1] - model.aabb[0]).max())
    box = model.march_box  # marching never leaves the grids
    assert bool((box[0] >= model.grid_box[0] - 1e-6).all() and (box[1] <= model.grid_box[1] + 1e-6).all())


def test_the_grids_shrink_onto_what_has_grown_not_onto_untouched_space_still_occupied() -> None:
    """Straight after the warm-up a slow occupancy ramp still keeps space at the initial opacity; the grids shrink
    onto the matter that has grown, so the field keeps its fine voxels."""
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1, "shrink_step": 6}))
    model.cull_slowly()
    with torch.no_grad():
        model.density_grid.volume()[10:14, 10:14, 10:14] = 30.0  # grown; the rest untouched, at the initial opacity
    moved = [model.step_update(step) for step in range(0, 16, 2)]
    assert model.occupancy.occupied_fraction() > 0.9  # untouched space is not culled yet
    assert any(moved) and bool(model.shrunk)
    assert float((model.grid_box[1] - model.grid_box[0]).max()) < 0.5 * float((model.aabb[1] - model.aabb[0]).max())


def test_a_faint_young_field_is_not_culled_nor_shrunk_onto() -> None:
    """A field below the occupancy threshold everywhere at the end of the warm-up keeps the whole box to march
    (and its grids) until part of it passes the threshold; then the grid culls and the grids shrink."""
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1, "shrink_step": 6, "occupancy_alpha": 0.5,
                                    "occupancy_alpha_start": 0.5}))
    with torch.no_grad():
        model.density_grid.table.fill_(-30.0)
        model.density_grid.volume()[10:14, 10:14, 10:14] = -2.0  # faint: well under 50% opacity a step
    moved = [model.step_update(step) for step in range(0, 12, 2)]
    assert not any(moved) and not bool(model.shrunk) and model.occupancy.faint
    assert bool(model.occupancy.occupied.all()) and torch.equal(model.march_box, model.aabb)
    with torch.no_grad():
        model.density_grid.volume()[10:14, 10:14, 10:14] = 30.0  # it has grown
    moved = [model.step_update(step) for step in range(12, 30, 2)]
    assert any(moved) and bool(model.shrunk) and not model.occupancy.faint
    assert model.occupancy.occupied_fraction() < 0.2


def test_culling_slowly_keeps_untouched_space_until_the_threshold_passes_the_initial_opacity() -> None:
    """A field that culls slowly keeps the samples of space still at the initial opacity (no ray has touched it, or
    the colours cannot yet place a surface in it) straight after the warm-up, and culls it once the rising threshold
    passes ``init_alpha``; space trained empty is culled at once, space trained dense never. At the usual pace
    untouched space is culled at once."""
    cfg = FastConfig(**{**TINY, "density_levels": 1, "shrink_step": 0})
    assert cfg.slow_occupancy_alpha_start < cfg.init_alpha < cfg.occupancy_alpha_start < cfg.occupancy_alpha
    usual, model = FastModel(cfg), FastModel(cfg)
    model.cull_slowly()
    for m in (usual, model):
        with torch.no_grad():
            volume = m.density_grid.volume()
            volume[:11, :11, :11] = -30.0  # trained empty
            volume[12:18, 12:18, 12:18] = 30.0  # trained dense
    for step in range(0, cfg.occupancy_warmup + 2 * cfg.occupancy_every, cfg.occupancy_every):
        usual.step_update(step)
    assert not bool(usual.occupancy.query(torch.full((1, 3), 1.2)).any())
    occ = model.occupancy
    empty, dense, untouched = (occ.query(torch.full((1, 3), v)) for v in (-0.9, 0.3, 1.2))
    assert bool(empty.all()) and bool(dense.all()) and bool(untouched.all())  # the warm-up keeps all
    for step in range(0, cfg.occupancy_warmup + 8 * cfg.occupancy_every, cfg.occupancy_every):
        model.step_update(step)
    assert occ.is_warm()
    empty, dense, untouched = (occ.query(torch.full((1, 3), v)) for v in (-0.9, 0.3, 1.2))
    assert not bool(empty.any()) and bool(dense.all()) and bool(untouched.all())
    crossing = cfg.occupancy_warmup + cfg.slow_occupancy_ramp
    for step in range(cfg.occupancy_warmup + 8 * cfg.occupancy_every, crossing + 8 * cfg.occupancy_every,
                      cfg.occupancy_every):
        model.step_update(step)
    untouched = occ.query(torch.full((1, 3), 1.2))
    assert not bool(untouched.any()) and bool(occ.query(torch.full((1, 3), 0.3)).all())


def test_an_unbounded_scene_culls_from_its_own_occupancy_opacity() -> None:
    """A room's fog is culled harder than an object's: the grid's final threshold is that of
    ``unbounded_occupancy_alpha`` in contracted space and of ``occupancy_alpha`` in a box; the warm-up start is shared."""
    cfg = {**TINY, "occupancy_alpha": 0.05, "unbounded_occupancy_alpha": 0.2, "occupancy_alpha_start": 0.02}
    for unbounded, alpha in ((False, 0.05), (True, 0.2)):
        model = FastModel(FastConfig(**{**cfg, "unbounded": unbounded}))
        occ = model.occupancy
        assert model.occupancy_alpha == alpha
        assert math.isclose(occ.sigma_threshold, density_threshold(alpha, model.step_size), rel_tol=1e-12)
        assert math.isclose(occ.start_threshold, density_threshold(0.02, model.step_size), rel_tol=1e-12)


def test_density_is_counted_per_voxel_so_a_few_steps_make_a_surface_opaque() -> None:
    """Adam moves a raw grid value by ~lr per step; per-voxel units make ~60 steps at lr 0.1 enough for an
    opaque voxel, where world units (σ in the hundreds at real resolutions) would take thousands."""
    model = FastModel(FastConfig(**{**TINY, "density_levels": 1}))
    raw = torch.full((1, 1), 60 * 0.1)  # 60 steps of lr 0.1 above the initial value
    with torch.no_grad():
        model.density_grid.table.fill_(float(raw))
    sigma = float(model.density(torch.zeros(1, 3)))
    opacity_per_voxel = 1 - math.exp(-sigma * (model.aabb[1, 0] - model.aabb[0, 0]) / (model.config.density_res - 1))
    assert opacity_per_voxel > 0.85

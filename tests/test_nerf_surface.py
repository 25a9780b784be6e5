"""The surface (SDF) field: NeuS opacity, finite differences, zero-set meshing and a tiny training run,
against closed forms (planes, spheres) and a sphere rendered here."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from recon.app.progress import Reporter
from recon.camera import look_at
from recon.config import MeshConfig
from recon.field import build_model
from recon.meshing.extraction import extract_zero_set
from recon.nerf.fitting import RayBatcher
from recon.nerf.rays import camera_rays
from recon.nerf.render import accumulate_packed, render_weights_packed
from recon.nerf.surface import SurfaceConfig, SurfaceModel, eikonal_loss, neus_tau, sdf_fd_terms
from recon.nerf.trainer import train

BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _plane_ray(angle_deg: float, s: float, step: float, t_star: float = 1.3):
    """One ray along +x through the plane whose normal makes angle_deg with -x, crossing the ray at t_star:
    SDF values at uniform interval boundaries t covering t_star ± 20 logistic widths (1 / (s cos))."""
    a = math.radians(angle_deg)
    normal = torch.tensor([-math.cos(a), math.sin(a), 0.0], dtype=torch.float64)
    point = torch.tensor([t_star, 0.0, 0.0], dtype=torch.float64)
    half = 20.0 / (s * math.cos(a))
    n = int(math.ceil(2 * half / step))
    t = t_star - half + torch.arange(n + 1, dtype=torch.float64) * step + 0.37 * step  # boundaries off the crossing
    x = torch.stack([t, torch.zeros_like(t), torch.zeros_like(t)], -1)
    f = (x - point) @ normal
    return f, t, s


@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0, 80.0])
@pytest.mark.parametrize("s", [5.0, 50.0, 2000.0])
def test_neus_weights_peak_at_the_plane_at_any_angle(angle: float, s: float) -> None:
    step = 0.01
    f, t, s = _plane_ray(angle, s, step)
    tau = neus_tau(f[:-1], f[1:], s)
    delta = t[1:] - t[:-1]
    ri = torch.zeros(len(delta), dtype=torch.long)
    w, _ = render_weights_packed(tau / delta, delta, ri, 1)
    mid = 0.5 * (t[1:] + t[:-1])
    depth = float(accumulate_packed(w, mid, ri, 1)[0] / w.sum())
    peak = int(w.argmax())
    # the weights are the logistic density of the crossing (symmetric about it): the mean depth is the
    # surface up to the midpoint rule, and the heaviest interval holds the surface
    assert abs(depth - 1.3) < (0.5 * step if s * step * math.cos(math.radians(angle)) > 1 else 1e-3)
    assert t[peak] - 1e-12 <= 1.3 <= t[peak + 1] + 1e-12
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-6)


def test_naive_logistic_density_is_biased_where_neus_is_not() -> None:
    """The reason for NeuS's form: sigma = s * sigmoid(-s f) (a density from the SDF alone) puts the weight
    peak in front of a tilted surface — where sigmoid = cos / (1 + cos), 2 ln 2 / s early at 60° — while
    NeuS's opacity puts it on the surface."""
    step, s = 0.002, 20.0
    f, t, _ = _plane_ray(60.0, s, step)
    delta = t[1:] - t[:-1]
    ri = torch.zeros(len(delta), dtype=torch.long)
    mid = 0.5 * (t[1:] + t[:-1])
    f_mid = 0.5 * (f[1:] + f[:-1])
    w_naive, _ = render_weights_packed(s * torch.sigmoid(-s * f_mid), delta, ri, 1)
    w_neus, _ = render_weights_packed(neus_tau(f[:-1], f[1:], s) / delta, delta, ri, 1)
    assert abs(float(mid[w_neus.argmax()]) - 1.3) <= step
    assert 1.3 - float(mid[w_naive.argmax()]) == pytest.approx(2 * math.log(2) / s, abs=2 * step)


def test_eikonal_term_is_zero_for_exact_sdfs_and_not_for_scaled_ones() -> None:
    x = torch.rand(500, 3, dtype=torch.float64) * 1.6 - 0.8
    x = x[x.norm(dim=-1) > 0.2]  # away from the sphere's centre, where its distance has a kink

    def sphere(p: torch.Tensor) -> torch.Tensor:
        return p.norm(dim=-1) - 0.5

    normal = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    normal = normal / normal.norm()

    def plane(p: torch.Tensor) -> torch.Tensor:
        return p @ normal - 0.1

    for fn in (sphere, plane):
        grad, lap = sdf_fd_terms(fn, x, 1e-3)
        assert float(eikonal_loss(grad)) < 1e-10
    grad, lap = sdf_fd_terms(plane, x, 1e-3)
    assert float(lap.abs().max()) < 1e-6  # a plane has no curvature
    grad, lap = sdf_fd_terms(sphere, x, 1e-3)
    assert torch.allclose(lap, 2.0 / x.norm(dim=-1), rtol=1e-4)  # Laplacian of |x| = 2 / |x|
    grad, _ = sdf_fd_terms(lambda p: 2.0 * plane(p), x, 1e-3)
    assert float(eikonal_loss(grad)) == pytest.approx(1.0, abs=1e-9)  # |∇(2f)| = 2


def test_initial_field_is_the_exact_sphere_sdf() -> None:
    model = SurfaceModel(SurfaceConfig(aabb=BOX, sdf_res=33, sdf_levels=2, feature_res=8, feature_dim=4, init_radius=0.5))
    x = torch.rand(2000, 3) * 2 - 1
    assert torch.allclose(model.sdf(x), x.norm(dim=-1) - 0.5, atol=1e-6)
    grad, _ = sdf_fd_terms(model.sdf, x[x.norm(dim=-1) > 0.4], model.fd_step)
    assert float(eikonal_loss(grad).detach()) < 1e-4  # central differences across a coarse cell (0.125): O(h²/r²) error


@pytest.mark.parametrize("log_s", [-14.0, 0.0, 18.0])
def test_gradients_stay_finite_at_tiny_and_huge_sharpness(log_s: float) -> None:
    torch.manual_seed(0)
    model = SurfaceModel(SurfaceConfig(aabb=BOX, sdf_res=33, sdf_levels=2, feature_res=8, feature_dim=4, occupancy_res=8))
    with torch.no_grad():
        model.log_s.fill_(log_s)
        for g in model.sdf_grid.grids:
            g.table.normal_(0.0, 0.05)
    o = torch.tensor([[0.0, -3.0, 0.0]]).repeat(64, 1) + torch.randn(64, 3) * 0.05
    d = torch.nn.functional.normalize(-o + torch.randn(64, 3) * 0.1, dim=-1)
    out = model.render_rays(o, d, torch.full((64,), 1.0), torch.full((64,), 5.0), training=True,
                            background=torch.ones(3))
    loss = ((out["rgb"] - 0.3) ** 2).mean() + out["reg"]
    loss.backward()
    assert torch.isfinite(loss)
    for p in model.parameters():
        if p.grad is not None:
            assert torch.isfinite(p.grad).all()
    assert model.log_s.grad is not None and torch.isfinite(model.log_s.grad)
    # and the opacity itself at the extremes, directly: no NaN, in [0, 1]
    f0 = torch.linspace(-1, 1, 101, requires_grad=True)
    for s in (1e-6, 1e8):
        tau = neus_tau(f0, f0 - 0.01, s)
        alpha = -torch.expm1(-tau.clamp(max=1e3))
        alpha.sum().backward()
        assert torch.isfinite(alpha).all() and float(alpha.min()) >= 0 and float(alpha.max()) <= 1
        assert torch.isfinite(f0.grad).all()


@pytest.mark.parametrize("log_s", [0.0, 6.0])
def test_the_surface_models_c_compositing_renders_and_trains_as_the_torch_one(log_s: float,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The surface model composites in one C pass a ray (recon.nerf.fast.composite_packed) where the library loads:
    the same colour, depth and opacity, and the same gradients in the SDF, the colour grid and the sharpness, as the
    torch weights and sums."""
    import recon.nerf.fast as fast
    from recon.nerf.native import native_marcher

    if native_marcher() is None:
        pytest.skip("the native library is not built here")
    torch.manual_seed(0)
    model = SurfaceModel(SurfaceConfig(aabb=BOX, sdf_res=33, sdf_levels=2, feature_res=8, feature_dim=4, occupancy_res=8))
    with torch.no_grad():
        model.log_s.fill_(log_s)
        for g in model.sdf_grid.grids:
            g.table.add_(torch.randn_like(g.table) * 0.02)
        model.color_grid.table.normal_()
    o = torch.tensor([[0.0, -3.0, 0.0]]).repeat(200, 1) + torch.randn(200, 3) * 0.05
    d = torch.nn.functional.normalize(-o + torch.randn(200, 3) * 0.3, dim=-1)
    runs = []
    for torch_path in (False, True):
        if torch_path:
            monkeypatch.setattr(fast, "composite_packed_native", lambda *args: None)
        model.zero_grad()
        torch.manual_seed(1)  # the march's jitter
        out = model.render_rays(o, d, torch.full((200,), 1.0), torch.full((200,), 5.0), training=True,
                                background=torch.ones(3))
        ((out["rgb"] - 0.3) ** 2).mean().add(out["depth"].mean()).backward()
        runs.append(({k: out[k].detach() for k in ("rgb", "depth", "opacity")},
                     [p.grad.clone() for p in model.parameters() if p.grad is not None]))
    (c_out, c_grads), (t_out, t_grads) = runs
    assert 0.2 < float(c_out["opacity"].mean()) < 1.0  # rays through the sphere and past it
    for key in c_out:
        torch.testing.assert_close(c_out[key], t_out[key], atol=2e-5, rtol=1e-4)
    assert len(c_grads) == len(t_grads) >= 3
    for a, b in zip(c_grads, t_grads):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-3)


class _Sphere(torch.nn.Module):
    """An analytic signed distance (a sphere) with the surface model's interface for meshing."""

    def __init__(self, centre: tuple[float, float, float], radius: float) -> None:
        super().__init__()
        self.register_buffer("c", torch.tensor(centre))
        self.radius = radius

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.c).norm(dim=-1) - self.radius


@pytest.mark.parametrize(("nodes", "mode"), [(65, "dense"), (161, "coarse-to-fine")])
def test_analytic_sphere_sdf_meshes_at_its_radius_closed(nodes: int, mode: str) -> None:
    centre, radius = (0.1, -0.05, 0.02), 0.55
    aabb = torch.tensor(BOX)
    v, f, info = extract_zero_set(_Sphere(centre, radius), aabb, (nodes,) * 3, MeshConfig(), Reporter(quiet=True))
    assert info["mode"] == mode and info["iso"] == 0.0
    cell = 2.0 / (nodes - 1)
    r = np.linalg.norm(v - np.asarray(centre), axis=1)
    assert abs(r.mean() - radius) < 0.02 * cell and np.abs(r - radius).max() < 0.1 * cell
    mesh = trimesh.Trimesh(v, f)
    assert mesh.is_watertight and mesh.volume > 0  # closed, outward faces
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * radius**3, rel=0.01)


def test_zero_set_is_closed_where_the_object_leaves_the_box() -> None:
    """A sphere cut by the box: the box faces close the mesh instead of leaving a hole."""
    v, f, _ = extract_zero_set(_Sphere((0.0, 0.0, -0.8), 0.6), torch.tensor(BOX), (49,) * 3, MeshConfig(), Reporter(quiet=True))
    mesh = trimesh.Trimesh(v, f)
    assert mesh.is_watertight and float(v[:, 2].min()) < -0.95


def test_a_closed_zero_set_is_capped_flat_on_its_support() -> None:
    """mesh.closed on a surface field: the ball cut at a table 0.3 under its centre, a flat base at the table."""
    base = np.array([0.0, 0.0, 1.0, -0.3])
    v, f, info = extract_zero_set(_Sphere((0.0, 0.0, 0.0), 0.6), torch.tensor(BOX), (65,) * 3, MeshConfig(),
                                  Reporter(quiet=True), closed=True, support=base)
    mesh = trimesh.Trimesh(v, f)
    cap = math.pi * 0.3**2 * (3 * 0.6 - 0.3) / 3  # the part of the ball below the table
    assert mesh.is_watertight and mesh.volume == pytest.approx(4 / 3 * math.pi * 0.6**3 - cap, rel=0.02)
    assert float(v[:, 2].min()) == pytest.approx(-0.3, abs=2 / 64) and info["fill"]["below_plane_nodes"] > 0


def _sphere_views(radius: float, n: int = 20, w: int = 32, f: float = 40.0):
    """n photos of a sphere (colour = its normal, on white) from cameras 3 units away, spread over the sphere."""
    golden = math.pi * (3 - math.sqrt(5))
    c2ws, images = [], []
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        eye = 3.0 * np.array([math.sqrt(1 - z * z) * math.cos(golden * i), math.sqrt(1 - z * z) * math.sin(golden * i), z])
        c2w = look_at(eye, np.zeros(3))
        o, d = camera_rays(torch.tensor(c2w, dtype=torch.float32), f, f, w / 2, w / 2, w, w)
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - radius**2)
        t = -b - disc.clamp_min(0).sqrt()
        col = 0.5 + 0.45 * (o + d * t[..., None]) / radius
        images.append(torch.where((disc > 0)[..., None], col, torch.ones_like(col)))
        c2ws.append(c2w)
    return torch.stack(images), torch.tensor(np.stack(c2ws), dtype=torch.float32), torch.tensor([[f, f, w / 2, w / 2]] * n)


def _zero_radius(model: SurfaceModel, n: int = 1000) -> np.ndarray:
    """Distance from the origin to the zero set along n directions (bisection)."""
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    lo, hi = torch.zeros(n), torch.ones(n)
    with torch.no_grad():
        for _ in range(25):
            mid = 0.5 * (lo + hi)
            inside = model.sdf(dirs * mid[:, None]) < 0
            lo, hi = torch.where(inside, mid, lo), torch.where(inside, hi, mid)
    return lo.numpy()


def test_tiny_training_run_moves_the_surface_to_the_rendered_sphere() -> None:
    torch.manual_seed(0)
    radius = 0.7
    images, c2w, intr = _sphere_views(radius)
    cfg = SurfaceConfig(aabb=BOX, sdf_res=33, sdf_levels=2, level_every=20, feature_res=16, feature_dim=8, init_radius=0.5,
                        occupancy_res=16, eikonal_samples=1024, eikonal_points=512)
    model = SurfaceModel(cfg)
    before = _zero_radius(model)
    assert abs(before.mean() - radius) > 0.19  # starts on its 0.5 sphere
    batcher = RayBatcher(images, c2w, intr, aabb=torch.tensor(BOX), seed=0)
    train(model, batcher, steps=60, lr=1e-2, batch_rays=512)
    after = _zero_radius(model)
    assert abs(after.mean() - radius) < 0.03 and after.std() < 0.03
    kind_kwargs = {"config": {**cfg.__dict__, "aabb": [list(r) for r in BOX]}}
    rebuilt = build_model("surface", kind_kwargs)  # the field file's round trip
    rebuilt.load_state_dict(model.state_dict())
    x = torch.rand(100, 3) * 2 - 1
    assert torch.allclose(rebuilt.sdf(x), model.sdf(x))


def test_normal_agreement_is_one_for_the_same_surface_and_lower_for_a_different_shape() -> None:
    from recon.geometry.compare import chamfer_fscore

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    same = chamfer_fscore(ball, ball, n_samples=20_000)["normal_consistency"]
    cube = chamfer_fscore(trimesh.creation.box(extents=(0.9, 0.9, 0.9)), ball, n_samples=20_000)["normal_consistency"]
    assert same > 0.99 and cube < 0.95
    assert "normal_consistency" not in chamfer_fscore(np.asarray(ball.vertices), ball, n_samples=2000)  # points: no normals


def test_model_choice_names_the_surface_model_and_refuses_it_for_unbounded_scenes() -> None:
    from recon.capture.scene import Scene
    from recon.config import TrainConfig
    from recon.errors import ReconError
    from recon.plans.training import model_spec

    box = np.array(BOX)
    kind, kwargs, _, reasons = model_spec(TrainConfig(model="surface"), Scene(frames=[], aabb=box, capture="object"), [])
    assert kind == "surface" and tuple(map(tuple, kwargs["config"]["aabb"])) == BOX and "zero level set" in reasons[0]
    with pytest.raises(ReconError, match="object capture"):
        model_spec(TrainConfig(model="surface"), Scene(frames=[], aabb=box, capture="unbounded"), [])
    assert build_model(kind, kwargs).config.aabb == BOX

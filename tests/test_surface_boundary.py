"""The box-boundary term: the SDF must close inside its box (closed forms on spheres and planes)."""
from __future__ import annotations

import pytest
import torch

from recon.nerf.surface import SurfaceConfig, SurfaceModel, boundary_loss, box_face_points

BOX = ((-1.0, -0.5, -2.0), (1.0, 0.5, 0.0))


def test_face_points_lie_on_all_six_faces() -> None:
    box = torch.tensor(BOX)
    x = box_face_points(box, 600)
    assert bool(((x >= box[0] - 1e-6) & (x <= box[1] + 1e-6)).all())
    on = (x[:, None, :] - box[None]).abs() < 1e-6  # (n, side, axis)
    assert bool((on.sum((1, 2)) >= 1).all())  # every point on a face
    assert all(int(on[:, s, a].sum()) >= 100 for s in range(2) for a in range(3))  # 100 per face


def test_boundary_loss_is_zero_when_closed_inside_and_linear_where_the_inside_reaches_a_face() -> None:
    f = torch.tensor([0.5, 0.3, 0.2])
    assert float(boundary_loss(f, 0.2)) == 0.0
    f = torch.tensor([0.5, -0.1, -0.3, 0.1], requires_grad=True)
    loss = boundary_loss(f, 0.2)
    assert float(loss.detach()) == pytest.approx((0.3 + 0.5 + 0.1) / 4)
    loss.backward()
    assert torch.allclose(f.grad, torch.tensor([0.0, -0.25, -0.25, -0.25]))  # pushes f up where it is too low


def test_initial_sphere_pays_nothing_and_a_sphere_through_the_floor_is_pushed_back_inside() -> None:
    cfg = SurfaceConfig(aabb=((-1.0,) * 3, (1.0,) * 3), sdf_res=33, sdf_levels=2, feature_res=8, feature_dim=4,
                        init_radius=0.8, boundary_points=3000)
    model = SurfaceModel(cfg)
    margin = cfg.boundary_margin_cells * model.voxel_size
    faces = box_face_points(model.aabb, 3000)
    assert float(boundary_loss(model.sdf(faces), margin)) == 0.0  # the sphere (r 0.8) is 0.2 > margin from every face
    with torch.no_grad():
        grid = model.sdf_grid.grids[0]  # the coarsest level, active from step 0
        grid.table.sub_(0.5)  # the whole inside grows by 0.5: the sphere now reaches every face
    before = float(boundary_loss(model.sdf(faces), margin))
    assert before > 0.1
    opt = torch.optim.Adam(model.sdf_grid.parameters(), lr=0.02)
    for _ in range(30):
        opt.zero_grad()
        loss = boundary_loss(model.sdf(box_face_points(model.aabb, 3000)), margin)
        loss.backward()
        opt.step()
    assert float(boundary_loss(model.sdf(faces), margin)) < 0.2 * before


def test_hull_planes_bound_the_points_and_start_the_sdf_flat_under_a_flat_base() -> None:
    """The initial surface from the sparse points' convex hull: a box of points gives its six faces, the SDF at step 0
    is the signed distance to them (flat under the base, where a sphere would leave a cave), |grad| = 1."""
    import numpy as np

    from recon.nerf.surface import hull_planes, planes_sdf

    rng = np.random.default_rng(0)
    lo, hi = np.array([-0.6, -0.4, -0.5]), np.array([0.6, 0.4, 0.9])  # a tall object
    pts = rng.uniform(lo, hi, (400, 3))
    for axis in range(3):  # points on every face, as SfM finds on a textured box
        for side, value in ((0, lo[axis]), (1, hi[axis])):
            face = rng.uniform(lo, hi, (50, 3))
            face[:, axis] = value
            pts = np.concatenate([pts, face])
    stray = np.array([[2.0, 0.0, 0.0]])  # outside the box: ignored
    planes = hull_planes(np.concatenate([pts, stray]), ((-1.0,) * 3, (1.0,) * 3))
    p = torch.tensor(planes, dtype=torch.float32)
    assert float(planes_sdf(torch.tensor(pts, dtype=torch.float32), p).max()) < 1e-5  # every point inside or on it
    assert (0.0, 0.0, -1.0, 0.5) in planes  # the bottom face, once (its coplanar triangles merged)
    x = torch.tensor([[0.0, 0.0, -0.5], [0.0, 0.0, -0.7], [0.0, 0.0, 0.0], [0.1, 0.2, -0.6]])
    assert torch.allclose(planes_sdf(x, p), torch.tensor([0.0, 0.2, -0.4, 0.1]), atol=1e-5)
    box = (tuple(lo - 0.05), tuple(hi + 0.05))  # the normalize stage's box: the points plus a margin
    model = SurfaceModel(SurfaceConfig(aabb=box, sdf_res=41, sdf_levels=2, init_planes=tuple(planes)))
    under = torch.tensor([[x, y, -0.5] for x in (-0.3, 0.0, 0.3) for y in (-0.2, 0.0, 0.2)])
    assert float(model.sdf(under).abs().max()) < 1e-4  # the whole underside at the base's bottom
    sphere = SurfaceModel(SurfaceConfig(aabb=box, sdf_res=41, sdf_levels=2))
    assert float(sphere.sdf(under).min()) > 0.1  # the sphere's bottom lies far above it: a cave to fill
    from recon.nerf.surface import sdf_fd_terms

    grad, _ = sdf_fd_terms(model.sdf, torch.tensor([[0.0, 0.0, -0.52], [0.3, 0.0, 0.0], [0.0, 0.1, 0.5]]), 0.01)
    assert torch.allclose(grad.norm(dim=-1), torch.ones(3), atol=1e-3)


def test_hull_planes_fall_back_to_nothing_for_too_few_or_flat_points() -> None:
    import numpy as np

    from recon.nerf.surface import hull_planes

    box = ((-1.0,) * 3, (1.0,) * 3)
    assert hull_planes(np.zeros((0, 3)), box) == []
    assert hull_planes(np.random.default_rng(0).uniform(-0.5, 0.5, (10, 3)), box) == []
    flat = np.random.default_rng(1).uniform(-0.5, 0.5, (100, 3))
    flat[:, 2] = 0.1
    assert hull_planes(flat, box) == []


@pytest.mark.parametrize("weight", [0.0, 0.1])
def test_the_init_prior_pulls_a_drifted_unseen_underside_back_to_the_hull(weight: float) -> None:
    """Nothing but the regularizers acts on a surface no photo sees: a drift of the coarse level (what the seen parts
    cause in training) stays without the prior, and is pulled back to the hull with it."""
    import numpy as np

    from recon.nerf.surface import hull_planes

    torch.manual_seed(0)
    lo, hi = np.array([-0.6, -0.4, -0.5]), np.array([0.6, 0.4, 0.2])
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)
    planes = hull_planes(np.concatenate([corners, (lo + hi)[None] / 2]), ((-1.0,) * 3, (1.0,) * 3), min_points=4)
    cfg = SurfaceConfig(aabb=((-1.0,) * 3, (1.0,) * 3), sdf_res=33, sdf_levels=2, level_every=0, init_planes=tuple(planes),
                        init_prior_weight=weight, curvature_weight=0.0, boundary_weight=0.0, eikonal_points=2048)
    model = SurfaceModel(cfg)
    with torch.no_grad():
        model.sdf_grid.grids[0].table.add_(0.05)  # the coarse level drifted: the underside moved 0.05 up
    under = torch.tensor([[x, y, -0.5] for x in (-0.3, 0.0, 0.3) for y in (-0.2, 0.0, 0.2)])
    before = float(model.sdf(under).detach().mean())
    opt = torch.optim.Adam(model.sdf_grid.parameters(), lr=3e-3)
    for _ in range(60):
        opt.zero_grad()
        model._regularizers(torch.zeros(0, 3)).backward()
        opt.step()
    after = float(model.sdf(under).detach().mean())
    assert before == pytest.approx(0.05, abs=1e-4)
    if weight > 0:
        assert abs(after) < 0.3 * before
    else:
        assert abs(after) > 0.5 * before

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

"""The classic NeRF MLP: the paper's architecture, and the coarse+fine model's interface."""
from __future__ import annotations

import torch

from recon.nerf.classic import ClassicModel, ClassicNeRF
from recon.nerf.render import RadianceModel


def test_architecture_matches_the_paper() -> None:
    net = ClassicNeRF()
    # 63 -> 256 x 8 with gamma(x) re-injected into layer index 5, density head, 256 feature,
    # 256 + 27 -> 128 -> 3: the official implementation's 595,844 parameters per network
    assert sum(p.numel() for p in net.parameters()) == 595_844
    in_features = [layer.in_features for layer in net.trunk]
    assert in_features == [63, 256, 256, 256, 256, 256 + 63, 256, 256]
    assert net.color[0].in_features == 256 + 27 and net.color[0].out_features == 128


def test_density_depends_on_position_only_and_rgb_in_unit_range() -> None:
    torch.manual_seed(0)
    net = ClassicNeRF(depth=3, width=32, skip=1)
    x = torch.randn(50, 3)
    d1 = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    s1, c1 = net(x, d1)
    s2, c2 = net(x, -d1)
    torch.testing.assert_close(s1, s2)
    torch.testing.assert_close(net.density(x), s1)
    assert not torch.allclose(c1, c2)
    assert torch.all(s1 >= 0) and torch.all((c1 > 0) & (c1 < 1))
    # softplus cannot overflow: huge raw outputs stay finite
    with torch.no_grad():
        net.sigma_head.bias.fill_(1e30)
    assert torch.isfinite(net.density(x)).all()


def test_model_interface_shapes_gradients_and_determinism() -> None:
    torch.manual_seed(0)
    aabb = torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    model = ClassicModel(aabb, n_coarse=8, n_fine=16, depth=2, width=32, skip=0)
    assert isinstance(model, RadianceModel)
    n = 10
    o = torch.tensor([0.0, 0.0, 4.0]).expand(n, 3)
    d = torch.nn.functional.normalize(torch.randn(n, 3) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    near, far = torch.full((n,), 2.0), torch.full((n,), 6.0)
    out = model.render_rays(o, d, near, far, training=True, background=torch.ones(3))
    assert out["rgb"].shape == (n, 3) and out["depth"].shape == (n,) and out["opacity"].shape == (n,)
    assert len(out["aux_rgb"]) == 1 and out["aux_rgb"][0].shape == (n, 3)
    assert out["weights"].shape == (n, 24)
    (out["rgb"].sum() + out["aux_rgb"][0].sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    assert model.coarse.trunk[0].weight.grad is not None and model.fine.trunk[0].weight.grad is not None
    with torch.no_grad():
        a = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
        b = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
    torch.testing.assert_close(a["rgb"], b["rgb"])
    assert torch.all((a["depth"] >= 2.0) & (a["depth"] <= 6.0))


def test_density_and_radiance_use_the_fine_net_in_world_coordinates() -> None:
    torch.manual_seed(1)
    aabb = torch.tensor([[0.0, 0.0, 0.0], [2.0, 4.0, 2.0]])
    model = ClassicModel(aabb, n_coarse=4, n_fine=4, depth=2, width=16, skip=0)
    x = torch.tensor([[1.0, 2.0, 1.0], [2.0, 4.0, 0.0]])
    x_norm = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, -1.0]])
    torch.testing.assert_close(model.density(x), model.fine.density(x_norm))
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    torch.testing.assert_close(model.radiance(x, d), model.fine(x_norm, d)[1])
    coarse_only = ClassicModel(aabb, n_coarse=4, n_fine=0, depth=2, width=16, skip=0)
    assert coarse_only.fine is None
    out = coarse_only.render_rays(x, d, torch.zeros(2), torch.ones(2), training=False, background=torch.zeros(3))
    assert "aux_rgb" not in out and out["rgb"].shape == (2, 3)

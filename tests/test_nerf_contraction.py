"""Scene contraction (L-inf, mip-NeRF 360 form): identity inside, continuous, invertible, monotone."""
from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from recon.nerf.contraction import contract, uncontract

coord = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)


def test_identity_inside_unit_box() -> None:
    x = torch.rand(100, 3, dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(contract(x), x)


def test_closed_form_on_an_axis() -> None:
    """(2 - 1/r) at distance r along +X: 2 -> 1.5, 4 -> 1.75."""
    x = torch.tensor([[2.0, 0.5, -1.0], [4.0, 0.0, 0.0]], dtype=torch.float64)
    expected = torch.tensor([[1.5, 0.375, -0.75], [1.75, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(contract(x), expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_continuous_at_the_box_face(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    face = torch.rand(200, 3, generator=g, dtype=dtype) * 2 - 1
    face[:, 0] = 1.0  # on the +X face
    eps = 1e-4
    inner, outer = face * (1 - eps), face * (1 + eps)
    assert (contract(outer) - contract(inner)).abs().max() < 4 * eps
    assert contract(face).dtype == dtype


@settings(max_examples=200, deadline=None)
@given(st.tuples(coord, coord, coord))
def test_invertible_and_bounded(p: tuple[float, float, float]) -> None:
    x = torch.tensor([p], dtype=torch.float64)
    y = contract(x)
    assert float(y.abs().max()) < 2.0
    torch.testing.assert_close(uncontract(y), x, rtol=1e-8, atol=1e-8)


@settings(max_examples=100, deadline=None)
@given(st.tuples(coord, coord, coord), st.floats(min_value=0.01, max_value=1e3))
def test_monotone_along_rays_from_the_origin(p: tuple[float, float, float], s: float) -> None:
    """Moving outwards along a ray from the box centre never moves the contracted point inwards."""
    x = torch.tensor([p], dtype=torch.float64)
    if float(x.abs().max()) < 1e-6:
        return
    ts = torch.linspace(0.0, s, 64, dtype=torch.float64)[:, None]
    n = torch.linalg.vector_norm(contract(ts * x / x.abs().max()), ord=float("inf"), dim=-1)
    assert bool((n[1:] >= n[:-1] - 1e-12).all())


def test_ordered_samples_stay_ordered_along_any_ray() -> None:
    """Samples ordered along a ray map to points ordered by distance travelled in contracted space."""
    g = torch.Generator().manual_seed(2)
    o = torch.randn(32, 3, generator=g, dtype=torch.float64) * 0.5
    d = torch.nn.functional.normalize(torch.randn(32, 3, generator=g, dtype=torch.float64), dim=-1)
    t = torch.linspace(0, 50, 400, dtype=torch.float64)
    y = contract(o[:, None] + d[:, None] * t[None, :, None])  # (32, 400, 3)
    seg = (y[:, 1:] - y[:, :-1]).norm(dim=-1)
    # the direction of travel never reverses: consecutive segments point the same way
    cos = ((y[:, 2:] - y[:, 1:-1]) * (y[:, 1:-1] - y[:, :-2])).sum(-1) / (seg[:, 1:] * seg[:, :-1]).clamp_min(1e-30)
    assert bool((cos > 0).all())


def test_keeps_device_and_gradients_finite_at_origin() -> None:
    x = torch.zeros(2, 3, requires_grad=True)
    contract(x).sum().backward()
    assert torch.isfinite(x.grad).all()

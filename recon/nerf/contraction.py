"""Scene contraction for unbounded scenes (mip-NeRF 360, Barron et al. 2022, eq. 10) with the L-inf norm.

    contract(x) = x                                   if ||x||_inf <= 1
                = (2 - 1 / ||x||_inf) * x / ||x||_inf  otherwise

maps R^3 onto the open cube (-2, 2)^3: the unit box (the bounded part, normalized scene frame) is kept
as is, everything outside is squeezed into the shell between the unit box and the box of half-width 2.
The L-inf norm (instead of mip-NeRF 360's L2) makes the image a cube, so a cubic grid wastes no cells
(as in Zip-NeRF / nerfstudio's ``SceneContraction(order=inf)``). Both maps keep the input's device and
dtype; the direction x / ||x||_inf is preserved, so a ray's contracted image stays on one side of the
origin and ||contract(x)||_inf is monotone in ||x||_inf.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["contract", "uncontract"]


def contract(x: Tensor) -> Tensor:
    """Contract points x (..., 3), world units, into [-2, 2]^3 (identity inside the unit box).

    +-inf coordinates (a ray to infinity) land on the outer face (inf / inf would be NaN); NaN stays NaN.
    """
    big = torch.finfo(x.dtype).max
    x = x.clamp(-big, big)
    n = torch.linalg.vector_norm(x, ord=float("inf"), dim=-1, keepdim=True)
    safe = n.clamp_min(1.0)  # also keeps the unused branch finite (no 1/0 at the origin)
    return torch.where(n <= 1.0, x, (2.0 - 1.0 / safe) * (x / safe))


def uncontract(y: Tensor) -> Tensor:
    """Inverse of :func:`contract`: y (..., 3) with ||y||_inf < 2 -> world points (..., 3).

    Outside the unit box ||y||_inf = 2 - 1/||x||_inf, so ||x||_inf = 1 / (2 - ||y||_inf) and
    x = y * ||x||_inf / ||y||_inf. Inputs on or beyond the outer face map to infinity (clamped to
    a finite large value to stay NaN-free).
    """
    m = torch.linalg.vector_norm(y, ord=float("inf"), dim=-1, keepdim=True)
    safe_m = m.clamp(1.0, 2.0 - torch.finfo(y.dtype).eps * 4)
    norm_x = 1.0 / (2.0 - safe_m)
    return torch.where(m <= 1.0, y, y * (norm_x / safe_m))

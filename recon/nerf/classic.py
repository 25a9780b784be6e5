"""The original NeRF (Mildenhall et al., ECCV 2020): an 8x256 MLP, coarse + fine hierarchical sampling.

Slow on a CPU (hundreds of rays/s) but the reference the fast model is measured against, and the
"vanilla" preset. Architecture as in the paper's Fig. 7 and the official code:

    gamma(x) (63) -> 8 x [Linear 256, ReLU], with gamma(x) concatenated to the activation of layer
    index ``skip`` (0-based; default 4, the fifth layer) and fed into the next layer
    -> density head Linear(256, 1)                         (position only)
    -> feature Linear(256, 256), concat gamma(d) (27) -> Linear 128, ReLU -> Linear 3, sigmoid

Density activation: ``softplus(raw - 1)`` (as in mip-NeRF) instead of the paper's ReLU: it cannot
overflow or die (ReLU units stuck below 0 get no gradient, which the paper's training noise fights),
and starts at sigma ~ 0.31, i.e. alpha ~ 1e-2 per sample for the default spacing in a [-1.5, 1.5]
box, which lets surfaces form early (see CPU_NERF_NOTES.md, lesson 2).
"""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .encoding import PositionalEncoding
from .render import RadianceModel, render_dense
from .sampling import sample_pdf, stratified

__all__ = ["ClassicModel", "ClassicNeRF"]


class ClassicNeRF(nn.Module):
    """One NeRF MLP: (position, direction) -> (density, RGB).

    Positions are encoded as given; :class:`ClassicModel` maps its scene box to [-1, 1]^3 first.

    Args:
        pos_freqs: frequency bands for positions (10 -> 63 inputs).
        dir_freqs: frequency bands for view directions (4 -> 27 inputs).
        depth: number of 256-wide trunk layers (8).
        width: trunk width (256); the color layer has ``width // 2``.
        skip: 0-based trunk layer after whose activation the encoded position is concatenated.
    """

    def __init__(self, pos_freqs: int = 10, dir_freqs: int = 4, depth: int = 8, width: int = 256, skip: int = 4) -> None:
        super().__init__()
        self.pos_enc = PositionalEncoding(pos_freqs)
        self.dir_enc = PositionalEncoding(dir_freqs)
        self.skip = skip
        p = self.pos_enc.out_dim
        layers = [nn.Linear(p, width)]
        for i in range(1, depth):
            layers.append(nn.Linear(width + (p if i == skip + 1 else 0), width))
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.color = nn.Sequential(nn.Linear(width + self.dir_enc.out_dim, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def _trunk(self, x: Tensor) -> Tensor:
        """Encoded positions -> final trunk activation (M, width)."""
        gx = self.pos_enc(x)
        h = gx
        for i, layer in enumerate(self.trunk):
            h = F.relu(layer(h))
            if i == self.skip:
                h = torch.cat([gx.to(h.dtype), h], dim=-1)
        return h

    @staticmethod
    def _activate(raw: Tensor) -> Tensor:
        return F.softplus(raw - 1.0)

    def density(self, x: Tensor) -> Tensor:
        """x: (M, 3) in the network's input frame -> sigma (M,) in float32 (even under autocast)."""
        return self._activate(self.sigma_head(self._trunk(x)).squeeze(-1).float())

    def forward(self, x: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
        """x: (M, 3) positions, d: (M, 3) unit directions -> sigma (M,), rgb (M, 3) in [0, 1].

        Outputs are float32 even under bf16 autocast, so that volume rendering stays in float32.
        """
        h = self._trunk(x)
        sigma = self._activate(self.sigma_head(h).squeeze(-1).float())
        feat = self.feature(h)
        rgb = torch.sigmoid(self.color(torch.cat([feat, self.dir_enc(d).to(feat.dtype)], dim=-1)).float())
        return sigma, rgb


class ClassicModel(RadianceModel):
    """Coarse + fine NeRF with hierarchical sampling, implementing :class:`RadianceModel`.

    The coarse net sees ``n_coarse`` stratified samples; the fine net sees those plus ``n_fine``
    drawn from the coarse weights (NeRF Sec. 5.2). Both are supervised: the coarse rendering is
    returned as ``aux_rgb``. ``n_fine = 0`` gives a single-network model (coarse only).

    Args:
        aabb: (2, 3) scene box in world units; positions are mapped from it to [-1, 1]^3 before
            encoding (the paper's normalization), so sigma stays per WORLD unit.
        n_coarse, n_fine: samples per ray. Remaining args: see :class:`ClassicNeRF`.
    """

    def __init__(
        self,
        aabb: Tensor | None = None,
        n_coarse: int = 64,
        n_fine: int = 128,
        pos_freqs: int = 10,
        dir_freqs: int = 4,
        depth: int = 8,
        width: int = 256,
        skip: int = 4,
    ) -> None:
        super().__init__()
        if aabb is None:
            aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
        aabb = torch.as_tensor(aabb, dtype=torch.float32)
        if aabb.shape != (2, 3):
            raise ValueError(f"aabb must have shape (2, 3), got {tuple(aabb.shape)}")
        self.register_buffer("aabb", aabb.clone())
        self.n_coarse, self.n_fine = n_coarse, n_fine
        kw = dict(pos_freqs=pos_freqs, dir_freqs=dir_freqs, depth=depth, width=width, skip=skip)
        self.coarse = ClassicNeRF(**kw)
        self.fine = ClassicNeRF(**kw) if n_fine > 0 else None

    def _normalize(self, x: Tensor) -> Tensor:
        """World points (..., 3) -> [-1, 1]^3 over the scene box."""
        lo, hi = self.aabb[0].to(x), self.aabb[1].to(x)
        return (x - lo) / (hi - lo) * 2.0 - 1.0

    @property
    def _final(self) -> ClassicNeRF:
        return self.fine if self.fine is not None else self.coarse

    def _render_net(self, net: ClassicNeRF, rays_o, rays_d, t, far, background) -> dict[str, Tensor]:
        n, s = t.shape
        pts = rays_o[:, None, :] + t[..., None] * rays_d[:, None, :]
        dirs = rays_d[:, None, :].expand(n, s, 3)
        sigma, rgb = net(self._normalize(pts).reshape(-1, 3), dirs.reshape(-1, 3))
        return render_dense(sigma.view(n, s), rgb.view(n, s, 3), t, far, background)

    def render_rays(
        self,
        rays_o: Tensor,
        rays_d: Tensor,
        near: Tensor,
        far: Tensor,
        *,
        training: bool,
        background: Tensor,
        colors: bool = True,
    ) -> dict[str, Any]:
        """See :meth:`RadianceModel.render_rays` (its colour comes out of the same network pass as its density, so
        ``colors`` saves nothing and is not used); also returns 'weights' (N, S) of the final pass."""
        t_c = stratified(near, far, self.n_coarse, jitter=training)
        coarse = self._render_net(self.coarse, rays_o, rays_d, t_c, far, background)
        if self.fine is None:
            return {k: coarse[k] for k in ("rgb", "depth", "opacity", "weights")}
        edges = near[:, None] + (far - near)[:, None] * torch.linspace(0.0, 1.0, self.n_coarse + 1, device=near.device, dtype=near.dtype)
        t_f = sample_pdf(edges, coarse["weights"], self.n_fine, deterministic=not training)
        t_all = torch.sort(torch.cat([t_c, t_f], dim=-1), dim=-1).values
        fine = self._render_net(self.fine, rays_o, rays_d, t_all, far, background)
        out: dict[str, Any] = {k: fine[k] for k in ("rgb", "depth", "opacity", "weights")}
        out["aux_rgb"] = [coarse["rgb"]]
        return out

    def density(self, x: Tensor) -> Tensor:
        """World points x (M, 3) -> sigma (M,) of the fine network (1/world unit)."""
        return self._final.density(self._normalize(x))

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        """World points x (M, 3), unit directions d (M, 3) -> RGB (M, 3) of the fine network."""
        return self._final(self._normalize(x), d)[1]

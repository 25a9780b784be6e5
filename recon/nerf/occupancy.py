"""Occupancy grid and packed ray marching: spend field evaluations only where there is matter.

The grid covers the scene box (or, for unbounded scenes, the contracted cube [-2, 2]^3, see
:mod:`recon.nerf.contraction`) with ``res^3`` cells. It keeps an exponential moving *max* of the field's
density at the cell vertices ((res + 1)^3 points): each update evaluates a share of the vertices,
``ema = max(decay * ema, sigma)``, and a cell is occupied when any of its 8 vertices is above
``sigma_threshold``. (instant-ngp also lowers the threshold to mean(ema); on Lego the mean sits near the
initial density, and with that rule an opacity threshold of 0.05 still left 44% of the box occupied after
96 steps, against 8-10% for a fixed threshold just above the initial opacity, so the fixed rule is used.) Using vertices makes the grid
conservative for fields that are trilinear between them (the maximum of a trilinear function on a
cell is at a corner): such a field is never culled where its density exceeds the threshold.
``sigma_threshold`` comes from an opacity per step: ``-log(1 - alpha) / step_size`` (see
:func:`density_threshold`). Before ``warmup_steps`` every cell counts as occupied. A refresh that finds no vertex
above the threshold (a young field still fainter than it everywhere) leaves the grid as it was (``faint``): culling
it all would leave no sample and no gradient to bring the field back.

:func:`march` produces packed samples (variable count per ray, ray-major, ordered along each ray):
candidates are generated per ray with ``repeat_interleave`` (no [rays x max_samples] tensor), filtered
by the grid, and, if a ``sigma_fn`` is given, early-terminated in a second pass: densities of all
surviving candidates are evaluated once without gradients, transmittance is accumulated, and samples
behind ``T < min_transmittance`` (or with negligible alpha) are dropped before the differentiable pass.
The no-grad forward pass costs a fraction of a forward + backward, and removes most samples behind
surfaces. Steps are uniform (``step_size``), or, with ``cone_angle > 0``, grow like ``t * cone_angle``
once that exceeds ``step_size`` (for unbounded scenes).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from recon.nerf.contraction import contract, contracted_intervals, uncontract
from recon.nerf.render import render_weights_packed

__all__ = ["OccupancyGrid", "density_threshold", "march", "march_front_to_back"]


def density_threshold(alpha: float, step_size: float) -> float:
    """Density (1/world unit) whose opacity over one step of ``step_size`` is ``alpha``."""
    if not 0.0 < alpha < 1.0 or step_size <= 0:
        raise ValueError(f"need 0 < alpha < 1 and step_size > 0, got alpha={alpha}, step_size={step_size}")
    return -math.log1p(-alpha) / step_size


class OccupancyGrid(nn.Module):
    """Bool occupancy over a box, refreshed from a density function during training.

    Args:
        aabb: (2, 3) scene box [min_xyz, max_xyz], world units (ignored for the grid extent when
            ``contraction``: the grid then spans the contracted cube [-2, 2]^3).
        resolution: cells per side.
        sigma_threshold: density above which a vertex counts as occupied (1/world unit).
        decay: EMA decay per update (instant-ngp: 0.95).
        warmup_steps: steps during which every cell is occupied.
        contraction: the field lives in contracted space (unbounded scene).
        start_threshold: the threshold at the end of the warm-up (default ``sigma_threshold``), raised linearly to
            ``sigma_threshold`` over ``ramp_steps``: a young object whose density is still rising is not culled
            for good before it has had the steps to pass the final threshold.
    """

    def __init__(
        self,
        aabb: Tensor,
        resolution: int = 128,
        sigma_threshold: float = 0.01,
        decay: float = 0.95,
        warmup_steps: int = 256,
        contraction: bool = False,
        start_threshold: float | None = None,
        ramp_steps: int = 0,
    ) -> None:
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32)
        if aabb.shape != (2, 3) or not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"aabb must be (2, 3) with max > min, got {aabb.tolist()}")
        self.res = int(resolution)
        self.sigma_threshold = float(sigma_threshold)
        self.start_threshold = float(sigma_threshold if start_threshold is None else start_threshold)
        self.ramp_steps = int(ramp_steps)
        self.decay = float(decay)
        self.warmup_steps = int(warmup_steps)
        self.contraction = bool(contraction)
        box = torch.tensor([[-2.0] * 3, [2.0] * 3]) if contraction else aabb
        self.register_buffer("box", box.clone())
        self.register_buffer("ema", torch.zeros((self.res + 1,) * 3))
        self.register_buffer("occupied", torch.ones((self.res,) * 3, dtype=torch.bool))
        self.register_buffer("phase", torch.zeros((), dtype=torch.long))
        self.register_buffer("warm", torch.zeros((), dtype=torch.bool))
        self.faint = False
        """The last refresh found no vertex above the threshold and left the grid as it was."""
        self._warm_on_host: bool | None = None

    def is_warm(self) -> bool:
        """``bool(self.warm)``, read from the device once and then kept (refresh and loading a state update it): a
        model asks before every render, and on CUDA a read waits for the GPU to finish its queued work."""
        if self._warm_on_host is None:
            self._warm_on_host = bool(self.warm)
        return self._warm_on_host

    def _load_from_state_dict(self, *args: Any, **kwargs: Any) -> None:
        self._warm_on_host = None  # the loaded buffer decides
        super()._load_from_state_dict(*args, **kwargs)

    # ------------------------------------------------------------------ coordinates
    def to_grid(self, x: Tensor) -> Tensor:
        """World points (M, 3) -> grid-box coordinates in [0, 1]^3 (contracted first if unbounded)."""
        if self.contraction:
            x = contract(x)
        box = self.box.to(x)
        return (x - box[0]) / (box[1] - box[0])

    def vertex_points(self, flat: Tensor, jitter: Tensor | None = None) -> Tensor:
        """World positions (V, 3) of vertices with flat indices (V,), optionally offset by jitter (V, 3) cells."""
        n = self.res + 1
        ijk = torch.stack((flat // (n * n), (flat // n) % n, flat % n), dim=-1).to(self.box.dtype)
        if jitter is not None:
            ijk = ijk + jitter
        u = (ijk / self.res).clamp(0.0, 1.0)
        p = self.box[0] + u * (self.box[1] - self.box[0])
        if self.contraction:
            p = uncontract(p)
        return p

    def query(self, x: Tensor) -> Tensor:
        """Occupied flag (M,) bool of world points x (M, 3); points outside the grid box are False."""
        u = self.to_grid(x)
        inside = ((u >= 0) & (u <= 1)).all(dim=-1)
        ijk = (u * self.res).floor().long().clamp_(0, self.res - 1)
        occ = self.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        return occ & inside

    def query_rays(self, rays_o: Tensor, rays_d: Tensor, ray_idx: Tensor, t: Tensor) -> Tensor:
        """:meth:`query` at the points ``rays_o[ray_idx] + t * rays_d[ray_idx]`` (M,), for a marcher's candidates.

        A bounded grid maps the rays into cell units once per call, so each candidate costs one multiply-add and
        one flat lookup instead of a world point, its box mapping and a 3-D index.
        """
        if self.contraction:
            return self.query(rays_o[ray_idx] + rays_d[ray_idx] * t[:, None])
        scale = self.res / (self.box[1] - self.box[0])
        p = torch.addcmul(((rays_o - self.box[0]) * scale)[ray_idx], (rays_d * scale)[ray_idx], t[:, None])
        inside = ((p >= 0) & (p <= self.res)).all(dim=-1)
        ijk = p.floor_().long().clamp_(0, self.res - 1)
        flat = (ijk[:, 0] * self.res + ijk[:, 1]) * self.res + ijk[:, 2]
        return self.occupied.view(-1)[flat] & inside

    # ------------------------------------------------------------------ updates
    @torch.no_grad()
    def update(
        self,
        density_fn: Callable[[Tensor], Tensor],
        step: int,
        *,
        share: int = 1,
        jitter: bool = False,
        chunk: int = 1 << 18,
    ) -> None:
        """Refresh the EMA at 1/share of the vertices (rotating, all covered after ``share`` calls).

        density_fn: world points (V, 3) -> densities (V,). ``jitter`` moves each evaluation point
        uniformly within +-half a cell of its vertex (catches features thinner than a cell over time).
        """
        n_vert = (self.res + 1) ** 3
        phase = int(self.phase) % share
        flat = torch.arange(phase, n_vert, share, device=self.ema.device)
        ema = self.ema.view(-1)
        for s in range(0, flat.shape[0], chunk):
            idx = flat[s : s + chunk]
            jit = torch.rand(idx.shape[0], 3, device=idx.device) - 0.5 if jitter else None
            sigma = density_fn(self.vertex_points(idx, jit)).reshape(-1).to(ema.dtype)
            sigma = torch.nan_to_num(sigma, nan=0.0)
            ema[idx] = torch.maximum(ema[idx] * self.decay, sigma)
        self.phase.fill_(phase + 1)
        self.refresh(step)

    @torch.no_grad()
    def refresh(self, step: int) -> None:
        """Recompute the occupied cells from the EMA (all occupied during warm-up)."""
        if step < self.warmup_steps:
            self.occupied.fill_(True)
            return
        above = self.ema > self.threshold_at(step)
        self.faint = not bool(above.any())
        if self.faint:  # nothing would stay: keep marching where the grid marched (all of it, straight after warm-up)
            return
        self.occupied.copy_(cells_with_a_vertex(above))
        self.warm.fill_(True)
        self._warm_on_host = True

    def threshold_at(self, step: int) -> float:
        """The density threshold at ``step``: ``start_threshold`` at the end of the warm-up, ``sigma_threshold``
        from ``ramp_steps`` later on, linear between."""
        done = 1.0 if self.ramp_steps <= 0 else min(max(step - self.warmup_steps, 0) / self.ramp_steps, 1.0)
        return self.start_threshold + done * (self.sigma_threshold - self.start_threshold)

    def occupied_fraction(self) -> float:
        """Share of occupied cells, in [0, 1]."""
        return float(self.occupied.float().mean())

    def core_aabb(self, min_fraction: float = 0.01, above: float | None = None) -> Tensor | None:
        """World box (2, 3) around the connected clusters of occupied cells (26-connectivity) that hold at
        least ``min_fraction`` of them: the object without the scattered floaters of early training.
        ``above``: count only the occupied cells with a vertex whose density is above it (space that has grown, not
        space kept because no ray has emptied it yet). None if unbounded or nothing is occupied."""
        from scipy import ndimage

        if self.contraction:
            return None
        occ = self.occupied if above is None else self.occupied & cells_with_a_vertex(self.ema > above)
        occ = occ.cpu().numpy()
        labels, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
        if n == 0:
            return None
        sizes = np.bincount(labels.ravel())[1:]
        keep = np.flatnonzero(sizes >= min_fraction * sizes.sum()) + 1
        idx = np.argwhere(np.isin(labels, keep))
        lo, hi = idx.min(0), idx.max(0) + 1
        size = (self.box[1] - self.box[0]) / self.res
        lo_t = torch.as_tensor(lo, dtype=self.box.dtype, device=self.box.device)
        hi_t = torch.as_tensor(hi, dtype=self.box.dtype, device=self.box.device)
        return torch.stack((self.box[0] + lo_t * size, self.box[0] + hi_t * size))

    def occupied_aabb(self) -> Tensor | None:
        """World box (2, 3) around the occupied cells (None if unbounded or nothing is occupied)."""
        if self.contraction:
            return None
        idx = self.occupied.nonzero()
        if idx.shape[0] == 0:
            return None
        lo, hi = idx.amin(0).to(self.box.dtype), idx.amax(0).to(self.box.dtype) + 1
        size = (self.box[1] - self.box[0]) / self.res
        return torch.stack((self.box[0] + lo * size, self.box[0] + hi * size))


def cells_with_a_vertex(above: Tensor) -> Tensor:
    """Cells (R, R, R) bool of which at least one of the 8 corner vertices is set in ``above`` (R + 1, R + 1, R + 1):
    ORs of neighbouring slices along each axis in turn, a max-pool of 2 with stride 1 done separably, as torch's CPU
    ``max_pool3d`` is far slower at it (docs/profile.md)."""
    above = above[1:] | above[:-1]
    above = above[:, 1:] | above[:, :-1]
    return above[:, :, 1:] | above[:, :, :-1]


def _sample_counts(t_near: Tensor, t_far: Tensor, step: float, cone: float, max_samples: int):
    """Per-ray number of uniform steps n_u, start of the geometric phase t1, and total count (N,) long."""
    span = (t_far - t_near).clamp_min(0.0)
    n_cap = torch.ceil(span / step)
    if cone <= 0.0:
        n_u = n_cap
        t1 = t_far
        total = n_cap
    else:
        t_switch = step / cone
        n_u_full = torch.ceil(((t_switch - t_near) / step).clamp_min(0.0))
        n_u = torch.minimum(n_u_full, n_cap)
        t1 = (t_near + n_u_full * step).clamp_min(1e-6)
        ratio = (t_far / t1).clamp_min(1.0)
        n_g = torch.ceil(torch.log(ratio) / math.log1p(cone))
        total = torch.where(n_u < n_u_full, n_u, n_u + n_g)
    total = torch.where(t_far > t_near, total, torch.zeros_like(total)).clamp_max(max_samples)
    return n_u, t1, total.long()


def _candidates(
    rays_o: Tensor,
    rays_d: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    counts_info: tuple[Tensor, Tensor, Tensor],
    rays: Tensor,
    k_lo: int,
    k_hi: int,
    step_size: float,
    cone_angle: float,
    u: Tensor | None,
    occupancy: OccupancyGrid | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Steps ``k_lo <= k < k_hi`` of the given rays (R,) that lie in occupied cells: packed t_starts, t_ends and
    ray indices, ray-major in the order of ``rays``. ``counts_info`` is :func:`_sample_counts`' result for all
    rays; ``u`` (N,) the per-ray jitter or None. Step k is the same interval whichever window asks for it."""
    device, dtype = rays_o.device, rays_o.dtype
    n_u, t1, counts = counts_info
    c = (counts[rays].clamp(max=k_hi) - k_lo).clamp_min(0)
    total = int(c.sum())
    if total == 0:
        empty = torch.zeros(0, device=device, dtype=dtype)
        return empty, empty.clone(), torch.zeros(0, device=device, dtype=torch.long)
    ray_idx = torch.repeat_interleave(rays, c, output_size=total)
    first = torch.repeat_interleave(torch.cumsum(c, 0) - c, c, output_size=total)
    k = (torch.arange(total, device=device) - first + k_lo).to(dtype)
    s0 = k + u[ray_idx] if u is not None else k
    t0 = t_near[ray_idx]
    if cone_angle <= 0.0:
        t_starts = t0 + s0 * step_size
        t_ends = t_starts + step_size
    else:
        nu, tg = n_u[ray_idx], t1[ray_idx]

        def t_of(s: Tensor) -> Tensor:
            return torch.where(s < nu, t0 + s * step_size, tg * torch.pow(1.0 + cone_angle, s - nu))

        t_starts, t_ends = t_of(s0), t_of(s0 + 1.0)
    tf = t_far[ray_idx]
    t_ends = torch.minimum(t_ends, tf)
    keep = t_starts < tf
    if occupancy is not None:
        keep &= occupancy.query_rays(rays_o, rays_d, ray_idx, 0.5 * (t_starts + t_ends))
    return t_starts[keep], t_ends[keep], ray_idx[keep]


def _cull(
    ts: Tensor, te: Tensor, ri: Tensor, n_rays: int, sigma_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None,
    min_transmittance: float, alpha_threshold: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """The packed samples worth rendering: transmittance at their start above ``min_transmittance`` (and
    opacity at least ``alpha_threshold``), by one no-grad density pass; all of them without ``sigma_fn``."""
    if sigma_fn is None or ts.shape[0] == 0:
        return ts, te, ri
    with torch.no_grad():
        sigma = sigma_fn(ts, te, ri).reshape(-1)
        _, trans = render_weights_packed(sigma, te - ts, ri, n_rays)
        keep = trans > min_transmittance
        if alpha_threshold > 0:
            keep &= -torch.expm1(-sigma * (te - ts)) >= alpha_threshold
    return ts[keep], te[keep], ri[keep]


def march(
    rays_o: Tensor,
    rays_d: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    occupancy: OccupancyGrid | None,
    step_size: float,
    max_samples: int,
    *,
    cone_angle: float = 0.0,
    jitter: bool = False,
    sigma_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
    min_transmittance: float = 1e-4,
    alpha_threshold: float = 0.0,
    contracted: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Packed samples along rays, only in occupied cells.

    Args:
        rays_o, rays_d: (N, 3) world origins and unit directions.
        t_near, t_far: (N,) ray segment to march (world units); empty when t_far <= t_near.
        occupancy: grid to skip empty cells with (None: keep every candidate).
        step_size: base step (world units); max_samples: cap on candidates per ray.
        cone_angle: > 0 makes steps grow like t * cone_angle (unbounded scenes); 0 = uniform.
        jitter: shift each ray's samples by one random fraction of a step (training).
        sigma_fn: optional (t_starts, t_ends, ray_indices) -> sigma (M,) for early termination
            (called under no_grad; see the module docstring).
        min_transmittance: drop samples whose transmittance at their start is below this.
        alpha_threshold: drop samples with opacity below this (0 keeps all).
        contracted: unbounded scene: steps of ``step_size`` in contracted space
            (:func:`recon.nerf.contraction.contracted_intervals`; ``cone_angle`` is then unused).

    Returns:
        t_starts, t_ends: (M,) interval bounds; ray_indices: (M,) long, sorted ascending; samples of
        a ray are contiguous and ordered by t.
    """
    if contracted:
        return _march_contracted(rays_o, rays_d, t_near, t_far, occupancy, step_size, max_samples, jitter, sigma_fn,
                                 min_transmittance, alpha_threshold)
    n_rays = rays_o.shape[0]
    device, dtype = rays_o.device, rays_o.dtype
    n_u, t1, counts = _sample_counts(t_near, t_far, step_size, cone_angle, max_samples)
    u = torch.rand(n_rays, device=device, dtype=dtype) if jitter else None
    t_starts, t_ends, ray_idx = _candidates(
        rays_o, rays_d, t_near, t_far, (n_u, t1, counts), torch.arange(n_rays, device=device), 0, max_samples,
        step_size, cone_angle, u, occupancy,
    )
    return _cull(t_starts, t_ends, ray_idx, n_rays, sigma_fn, min_transmittance, alpha_threshold)


def _march_contracted(
    rays_o: Tensor, rays_d: Tensor, t_near: Tensor, t_far: Tensor, occupancy: OccupancyGrid | None, step_size: float,
    max_samples: int, jitter: bool, sigma_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None,
    min_transmittance: float, alpha_threshold: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`march` with steps of ``step_size`` in contracted space (unbounded scenes), same filters."""
    ts, te, ri = contracted_intervals(rays_o, rays_d, t_near, t_far, step_size, max_samples, jitter)
    if occupancy is not None and ts.shape[0] > 0:
        keep = occupancy.query(rays_o[ri] + rays_d[ri] * (0.5 * (ts + te))[:, None])
        ts, te, ri = ts[keep], te[keep], ri[keep]
    return _cull(ts, te, ri, rays_o.shape[0], sigma_fn, min_transmittance, alpha_threshold)


@torch.no_grad()
def march_front_to_back(
    rays_o: Tensor,
    rays_d: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    occupancy: OccupancyGrid | None,
    step_size: float,
    max_samples: int,
    sigma_fn: Callable[[Tensor, Tensor, Tensor], Tensor],
    *,
    cone_angle: float = 0.0,
    jitter: bool = False,
    min_transmittance: float = 1e-4,
    first_window: int = 16,
    max_window: int = 256,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`march` with ``sigma_fn`` (early termination), in windows of steps along the rays.

    Each round takes the next window of steps (``first_window``, doubling up to ``max_window``) of the rays
    still open, evaluates the density of its occupied candidates and carries each ray's optical depth on; a
    ray closes once its transmittance falls below ``min_transmittance``. So densities behind an opaque
    surface are never evaluated, where :func:`march` evaluates every occupied candidate up to the ray's end.
    The samples kept are those :func:`march` keeps (same intervals, same jitter draw, same transmittance rule).

    Returns t_starts, t_ends, ray_indices (M,) (packed, sorted by ray, ordered along each ray), their
    densities sigma (M,).
    """
    from recon.nerf.render import optical_thickness

    n_rays = rays_o.shape[0]
    device, dtype = rays_o.device, rays_o.dtype
    info = _sample_counts(t_near, t_far, step_size, cone_angle, max_samples)
    counts = info[2]
    u = torch.rand(n_rays, device=device, dtype=dtype) if jitter else None
    depth = torch.zeros(n_rays, device=device, dtype=torch.float64)  # optical depth so far per ray
    open_rays = (counts > 0).nonzero().squeeze(-1)
    parts: list[tuple[Tensor, Tensor, Tensor, Tensor]] = []
    k_lo, window = 0, first_window
    log_min_t = -math.log(min_transmittance)
    while open_rays.numel() > 0 and k_lo < max_samples:
        k_hi = min(k_lo + window, max_samples)
        ts, te, ri = _candidates(rays_o, rays_d, t_near, t_far, info, open_rays, k_lo, k_hi, step_size, cone_angle,
                                 u, occupancy)
        if ri.numel():
            sigma = sigma_fn(ts, te, ri).reshape(-1)
            tau = optical_thickness(sigma, te - ts).double()
            first = torch.ones_like(ri, dtype=torch.bool)
            first[1:] = ri[1:] != ri[:-1]
            incl = torch.cumsum(tau, 0)
            excl = incl - tau
            seg = torch.cumsum(first.long(), 0) - 1
            before = depth[ri] + (excl - excl[first][seg])  # optical depth at each sample's start
            keep = before < log_min_t
            parts.append((ts[keep], te[keep], ri[keep], sigma[keep]))
            depth.index_add_(0, ri, tau)
        k_lo, window = k_hi, min(2 * window, max_window)
        still = (counts[open_rays] > k_lo) & (depth[open_rays] < log_min_t)
        open_rays = open_rays[still]
    if not parts:
        empty = torch.zeros(0, device=device, dtype=dtype)
        return empty, empty.clone(), torch.zeros(0, device=device, dtype=torch.long), empty.clone()
    ts, te, ri, sigma = (torch.cat(x) for x in zip(*parts))
    order = torch.sort(ri, stable=True).indices  # windows come in order along the rays: a stable sort keeps it
    return ts[order], te[order], ri[order], sigma[order]

"""Volume rendering as pure functions (after nerfacc's ``volrend.py``), plus the model interface.

Emission-absorption model of Max (1995) as used by NeRF (Mildenhall et al. 2020, eq. 3):

    tau_i   = sigma_i * delta_i                       optical thickness of interval i
    alpha_i = 1 - exp(-tau_i)       = -expm1(-tau_i)  (accurate for tiny tau)
    T_i     = exp(-sum_{j<i} tau_j)                   EXCLUSIVE sum, in log space (no cumprod of 1-alpha)
    w_i     = T_i * alpha_i

Two layouts:

* dense  - every ray has the same S samples: ``sigma (N, S)``, ``t (N, S)``;
* packed - rays have different sample counts, concatenated ray after ray: ``sigma (M,)`` with
  ``ray_indices (M,)`` (long, sorted ascending) telling which ray each sample belongs to. The fast
  model uses this to skip empty space without building and masking ``(N, max_samples)`` tensors.

Numerics: densities are clamped to ``[0, SIGMA_MAX]`` (an ``inf`` from a raw activation becomes a
finite opaque value; NaN is left to propagate so that the trainer's guard sees it) and optical
thicknesses to ``[0, TAU_MAX]``. ``exp(-TAU_MAX)`` is 0 even in float64, so the clamp changes no
rendered value, but it bounds the running sums, which keeps the packed float64 cumulative sum exact
enough to subtract per-ray offsets (see :func:`render_weights_packed`).

Example::

    >>> sigma = torch.full((2, 4), 0.5); t = torch.linspace(2.0, 5.0, 4).expand(2, 4)
    >>> out = render_dense(sigma, torch.rand(2, 4, 3), t, t_far=torch.full((2,), 6.0),
    ...                    background=torch.ones(3))
    >>> out["rgb"].shape, out["depth"].shape
    (torch.Size([2, 3]), torch.Size([2]))
"""
from __future__ import annotations

import abc
from typing import Any

import torch
from torch import Tensor, nn

SIGMA_MAX = 1e10
"""Largest density used in rendering (1 / world unit); ``inf`` densities are clamped to it."""

TAU_MAX = 1e3
"""Largest optical thickness of one interval; ``exp(-1e3) == 0`` in float32 and float64."""

__all__ = [
    "SIGMA_MAX",
    "TAU_MAX",
    "RadianceModel",
    "accumulate_packed",
    "alpha_from_density",
    "composite",
    "distortion_packed",
    "optical_thickness",
    "render_dense",
    "render_packed",
    "render_weights",
    "render_weights_packed",
]


# ----------------------------------------------------------------------------- shape checks
def _check_shape(name: str, x: Tensor, shape: tuple[int | None, ...]) -> None:
    """Raise a ValueError naming the argument when ``x`` does not match ``shape`` (None = any size)."""
    if x.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, x.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")


def _as_background(background: Tensor | float, n: int, like: Tensor) -> Tensor:
    """Background color as ``(n, 3)`` on ``like``'s device/dtype from a scalar, ``(3,)`` or ``(n, 3)``."""
    bg = torch.as_tensor(background, device=like.device, dtype=like.dtype)
    if bg.dim() == 0:
        bg = bg.expand(3)
    if bg.shape == (3,):
        return bg.expand(n, 3)
    _check_shape("background", bg, (n, 3))
    return bg


# ----------------------------------------------------------------------------- per-sample terms
def optical_thickness(sigma: Tensor, delta: Tensor) -> Tensor:
    """``tau = sigma * delta`` clamped to ``[0, TAU_MAX]``, with sigma clamped to ``[0, SIGMA_MAX]``.

    sigma: density (1/world unit), any shape; delta: interval length (world units), same shape.
    NaN is kept (so a diverged network is noticed); +inf density becomes opaque but finite.
    """
    return (sigma.clamp(0.0, SIGMA_MAX) * delta.clamp_min(0.0)).clamp(0.0, TAU_MAX)


def alpha_from_density(sigma: Tensor, delta: Tensor) -> Tensor:
    """Opacity of one interval: ``alpha = 1 - exp(-sigma * delta)`` computed as ``-expm1(-tau)``.

    ``expm1`` keeps alpha accurate (and non-zero) for ``tau`` down to 1e-38, where ``1 - exp`` would
    round to 0 in float32. Shapes: sigma and delta broadcast; result has the broadcast shape.
    """
    return -torch.expm1(-optical_thickness(sigma, delta))


# ----------------------------------------------------------------------------- dense layout
def render_weights(
    sigma: Tensor, t: Tensor, far_delta: float | Tensor = 1e10
) -> tuple[Tensor, Tensor]:
    """Compositing weights of dense samples.

    Args:
        sigma: (N, S) densities at the samples (1/world unit, >= 0 after activation).
        t: (N, S) sample distances along each ray (world units, non-decreasing along S).
        far_delta: length of the LAST interval, a float or an (N,) tensor. Interval i is
            ``t[i+1] - t[i]``; the last one has no successor, so it is given here. Pass a finite
            length such as ``t_far - t[:, -1]`` (what :func:`render_dense` does). The default
            1e10 mimics the NeRF paper ("last interval extends to infinity") but stays finite
            after clamping: tau is bounded by ``TAU_MAX`` so nothing overflows.

    Returns:
        weights: (N, S), ``w_i = T_i * alpha_i``, each in [0, 1], summing to <= 1 per ray.
        transmittance: (N, S), ``T_i = exp(-sum_{j<i} tau_j)`` (exclusive sum: T_0 = 1).
    """
    _check_shape("sigma", sigma, (None, None))
    _check_shape("t", t, tuple(sigma.shape))
    n = sigma.shape[0]
    last = torch.as_tensor(far_delta, device=t.device, dtype=t.dtype)
    if last.dim() == 0:
        last = last.expand(n)
    _check_shape("far_delta", last, (n,))
    delta = torch.cat([t[:, 1:] - t[:, :-1], last[:, None]], dim=-1)
    tau = optical_thickness(sigma, delta)
    # exclusive cumulative sum: the inclusive sum shifted right by one, T_0 = exp(0) = 1. Not cumsum(tau) - tau: after
    # an opaque sample (tau ~ 1e2) that subtraction loses the earlier taus to float32 rounding (3e-5 at 260), and the
    # weights then summed to 1 + 4e-6
    excl = torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau[:, :-1], dim=-1)], dim=-1)
    transmittance = torch.exp(-excl)
    weights = transmittance * -torch.expm1(-tau)
    return weights, transmittance


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """Weighted sum along each ray: ``sum_i w_i * v_i``.

    weights: (N, S); values: (N, S, C) -> (N, C), or values (N, S) -> (N,).
    """
    _check_shape("weights", weights, (None, None))
    if values.dim() == 2:
        _check_shape("values", values, tuple(weights.shape))
        return (weights * values).sum(dim=-1)
    _check_shape("values", values, (weights.shape[0], weights.shape[1], None))
    # elementwise, not einsum: einsum becomes a bmm, which autocast would run in bfloat16
    return (weights[..., None] * values).sum(dim=-2)


def render_dense(
    sigma: Tensor,
    rgb: Tensor,
    t: Tensor,
    t_far: Tensor,
    background: Tensor | float,
) -> dict[str, Tensor]:
    """Render rays whose samples form an (N, S) grid.

    Args:
        sigma: (N, S) densities (1/world unit).
        rgb: (N, S, 3) colors in [0, 1].
        t: (N, S) sample distances, non-decreasing along S (world units, rays_d unit length).
        t_far: (N,) end of each ray's interval; the last sample's interval is ``t_far - t[:, -1]``.
        background: (3,), (N, 3) or a scalar gray: color seen through the remaining transmittance.

    Returns dict with:
        rgb: (N, 3) ``sum w_i c_i + (1 - opacity) * background``.
        depth: (N,) expected depth with the transparent remainder placed at ``t_far``:
            ``sum w_i t_i + (1 - opacity) * t_far`` (an empty ray reads ``t_far``).
        median_depth: (N,) ``t`` of the first sample where the accumulated weight reaches half of
            the ray's opacity; ``t_far`` where opacity < 1e-6. Not differentiable w.r.t. sigma.
        opacity: (N,) ``sum w_i`` in [0, 1].
        weights: (N, S).
    """
    _check_shape("sigma", sigma, (None, None))
    n, s = sigma.shape
    _check_shape("rgb", rgb, (n, s, 3))
    _check_shape("t", t, (n, s))
    _check_shape("t_far", t_far, (n,))
    weights, _ = render_weights(sigma, t, far_delta=(t_far - t[:, -1]).clamp_min(0.0))
    opacity = weights.sum(dim=-1)
    remainder = (1.0 - opacity).clamp_min(0.0)
    bg = _as_background(background, n, rgb)
    color = composite(weights, rgb) + remainder[:, None] * bg
    depth = composite(weights, t) + remainder * t_far
    with torch.no_grad():
        cum = torch.cumsum(weights, dim=-1)
        idx = torch.searchsorted(cum.contiguous(), (0.5 * opacity)[:, None].contiguous())
        idx = idx.clamp_max(s - 1)
    median = t.gather(-1, idx).squeeze(-1)
    median = torch.where(opacity.detach() < 1e-6, t_far, median)
    return {"rgb": color, "depth": depth, "median_depth": median, "opacity": opacity, "weights": weights}


# ----------------------------------------------------------------------------- packed layout
def _check_packed(ray_indices: Tensor, m: int, n_rays: int) -> None:
    """Validate a packed layout: (M,) long indices, sorted ascending, within [0, n_rays)."""
    _check_shape("ray_indices", ray_indices, (m,))
    if ray_indices.dtype != torch.long:
        raise ValueError(f"ray_indices must be torch.long, got {ray_indices.dtype}")
    if m == 0:
        return
    bad_order = bool((ray_indices[1:] < ray_indices[:-1]).any()) if m > 1 else False
    if bad_order:
        raise ValueError("ray_indices must be sorted ascending (samples of a ray contiguous, rays in order)")
    lo, hi = int(ray_indices[0]), int(ray_indices[-1])
    if lo < 0 or hi >= n_rays:
        raise ValueError(f"ray_indices must lie in [0, {n_rays}), got range [{lo}, {hi}]")


def _packed_exclusive_cumsum64(x: Tensor, ray_indices: Tensor) -> Tensor:
    """Per-ray exclusive cumulative sum of packed x (M,) (ray_indices sorted), in float64: one global cumulative sum
    minus its value at each ray's first sample (in float32 that subtraction would lose ~1e-7 of the running total
    over all rays)."""
    x64 = x.double()
    excl = torch.cumsum(x64, dim=0) - x64
    if x.shape[0] == 0:
        return excl
    first = torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
    first[1:] = ray_indices[1:] != ray_indices[:-1]
    segment = torch.cumsum(first.long(), dim=0) - 1  # 0-based index of the run each sample is in
    return excl - excl[first][segment]


def render_weights_packed(
    sigma: Tensor, delta: Tensor, ray_indices: Tensor, n_rays: int
) -> tuple[Tensor, Tensor]:
    """Compositing weights for packed samples (variable count per ray).

    Args:
        sigma: (M,) densities (1/world unit).
        delta: (M,) interval lengths (world units), each sample's own interval.
        ray_indices: (M,) long, sorted ascending: the ray of each sample; rays may have no samples.
        n_rays: number of rays N (ray_indices < n_rays).

    Returns:
        weights: (M,) ``T_i * alpha_i``; transmittance: (M,) ``T_i`` (1 at each ray's first sample).

    The per-ray exclusive sum is one global cumulative sum minus the sum at each ray's start. That
    subtraction is done in float64 (float32 would lose ~1e-7 of the running total over all rays,
    i.e. whole units of tau after a few thousand opaque rays); with ``tau <= TAU_MAX`` the total
    stays below 1e3 * M, so even M = 1e8 samples keep errors under 1e-4.
    """
    _check_shape("sigma", sigma, (None,))
    m = sigma.shape[0]
    _check_shape("delta", delta, (m,))
    _check_packed(ray_indices, m, n_rays)
    tau = optical_thickness(sigma, delta)
    if m == 0:
        return tau.clone(), tau.clone()
    excl = _packed_exclusive_cumsum64(tau, ray_indices)
    transmittance = torch.exp(-excl.clamp_min(0.0)).to(sigma.dtype)
    weights = transmittance * -torch.expm1(-tau)
    return weights, transmittance


def accumulate_packed(weights: Tensor, values: Tensor | None, ray_indices: Tensor, n_rays: int) -> Tensor:
    """Per-ray weighted sum of packed samples: ``out[r] = sum_{i: ray(i)=r} w_i * v_i``.

    weights: (M,); values: (M, C) -> (n_rays, C), (M,) -> (n_rays,), or None -> sum of weights (n_rays,).
    Rays without samples get 0.
    """
    _check_shape("weights", weights, (None,))
    m = weights.shape[0]
    _check_shape("ray_indices", ray_indices, (m,))
    if values is None:
        src = weights
    elif values.dim() == 1:
        _check_shape("values", values, (m,))
        src = weights * values
    else:
        _check_shape("values", values, (m, None))
        src = weights[:, None] * values
    out = torch.zeros((n_rays, *src.shape[1:]), device=src.device, dtype=src.dtype)
    return out.index_add(0, ray_indices, src)


def distortion_packed(weights: Tensor, t_mid: Tensor, delta: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """Each ray's mip-NeRF 360 distortion loss (Barron et al. 2022, eq. 15) over its packed samples, (N,):
    ``sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 delta_i``; rays without samples get 0.

    The double sum in O(M) as ``2 sum_i w_i (m_i W_<i - (wm)_<i)`` for samples sorted along each ray (Sun et al.
    2022, DVGO v2). weights, t_mid (sample midpoints), delta (their intervals), ray_indices (sorted): (M,).
    """
    _check_shape("weights", weights, (None,))
    m = weights.shape[0]
    for name, x in (("t_mid", t_mid), ("delta", delta), ("ray_indices", ray_indices)):
        _check_shape(name, x, (m,))
    w_excl = _packed_exclusive_cumsum64(weights, ray_indices).to(weights.dtype)
    wm_excl = _packed_exclusive_cumsum64(weights * t_mid, ray_indices).to(weights.dtype)
    per_sample = 2.0 * weights * (t_mid * w_excl - wm_excl) + weights**2 * delta / 3.0
    return accumulate_packed(per_sample, None, ray_indices, n_rays)


def ray_offsets(ray_indices: Tensor, n_rays: int) -> Tensor:
    """(N + 1,) int64: ray r's samples are ``offsets[r]:offsets[r + 1]`` of sorted ``ray_indices (M,)``."""
    rays = torch.arange(n_rays + 1, device=ray_indices.device, dtype=ray_indices.dtype)
    return torch.searchsorted(ray_indices, rays)


class PackedPasses(abc.ABC):
    """Compositing and the distortion loss of packed samples as passes a ray, forward and back (a Triton kernel on
    CUDA, `recon.nerf.kernels`; a C loop on a CPU, `recon.nerf.native`): what :func:`composite_by` and
    :func:`distortion_by` run. Each fills the float32 outputs it is given; rays are ``offsets`` (N + 1,) of the
    samples; gradients given as None were not asked for, except the per-ray ones (zeros where absent)."""

    @abc.abstractmethod
    def composite(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor, trans: Tensor,
                  opacity: Tensor, depth: Tensor) -> None: ...

    @abc.abstractmethod
    def composite_backward(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor,
                           trans: Tensor, g_w: Tensor | None, g_trans: Tensor | None, g_op: Tensor, g_dep: Tensor,
                           g_sigma: Tensor, g_delta: Tensor, g_t: Tensor) -> None: ...

    @abc.abstractmethod
    def distortion(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, loss: Tensor) -> None: ...

    @abc.abstractmethod
    def distortion_backward(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, g_loss: Tensor,
                            g_w: Tensor, g_mid: Tensor, g_delta: Tensor) -> None: ...


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor,  # type: ignore[override]
                passes: PackedPasses) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        n = offsets.shape[0] - 1
        weights, trans = torch.empty_like(sigma), torch.empty_like(sigma)
        opacity, depth = sigma.new_empty(n), sigma.new_empty(n)
        passes.composite(sigma, delta, t, offsets, weights, trans, opacity, depth)
        ctx.save_for_backward(sigma, delta, t, offsets, weights, trans)
        ctx.passes = passes
        ctx.set_materialize_grads(False)
        return weights, trans, opacity, depth

    @staticmethod
    def backward(ctx, g_w: Tensor | None, g_trans: Tensor | None, g_op: Tensor | None,  # type: ignore[override]
                 g_dep: Tensor | None) -> tuple[Tensor | None, ...]:
        sigma, delta, t, offsets, weights, trans = ctx.saved_tensors
        n = offsets.shape[0] - 1
        per_ray = [sigma.new_zeros(n) if g is None else g.float().contiguous() for g in (g_op, g_dep)]
        g_w, g_trans = (None if g is None else g.float().contiguous() for g in (g_w, g_trans))
        g_sigma, g_delta, g_t = torch.empty_like(sigma), torch.empty_like(sigma), torch.empty_like(sigma)
        ctx.passes.composite_backward(sigma, delta, t, offsets, weights, trans, g_w, g_trans, *per_ray, g_sigma,
                                      g_delta, g_t)
        need = ctx.needs_input_grad
        return g_sigma if need[0] else None, g_delta if need[1] else None, g_t if need[2] else None, None, None


def composite_by(passes: PackedPasses, sigma: Tensor, delta: Tensor, t: Tensor, ray_indices: Tensor,
                 n_rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`render_weights_packed` and :func:`accumulate_packed`'s opacity and depth sum by fused passes: weights,
    transmittance (M,), opacity and depth sum ``sum_i w_i t_i`` (N,) of packed float32 samples sigma, delta, t (M,),
    ray_indices (M,) sorted (not checked: that costs host reads); differentiable in sigma, delta and t."""
    m = sigma.shape[0]
    for name, x in (("sigma", sigma), ("delta", delta), ("t", t), ("ray_indices", ray_indices)):
        _check_shape(name, x, (m,))
    return _Composite.apply(sigma.contiguous(), delta.contiguous(), t.contiguous(),
                            ray_offsets(ray_indices.contiguous(), n_rays), passes)


class _Distortion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor,  # type: ignore[override]
                passes: PackedPasses) -> Tensor:
        loss = w.new_empty(offsets.shape[0] - 1)
        passes.distortion(w, mid, delta, offsets, loss)
        ctx.save_for_backward(w, mid, delta, offsets)
        ctx.passes = passes
        return loss

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        w, mid, delta, offsets = ctx.saved_tensors
        g_w, g_m, g_d = torch.empty_like(w), torch.empty_like(w), torch.empty_like(w)
        ctx.passes.distortion_backward(w, mid, delta, offsets, g.float().contiguous(), g_w, g_m, g_d)
        need = ctx.needs_input_grad
        return g_w if need[0] else None, g_m if need[1] else None, g_d if need[2] else None, None, None


def distortion_by(passes: PackedPasses, weights: Tensor, t_mid: Tensor, delta: Tensor, ray_indices: Tensor,
                  n_rays: int) -> Tensor:
    """:func:`distortion_packed` by fused passes: each ray's distortion loss (N,) of packed float32 weights, t_mid
    (sorted along each ray), delta (M,), ray_indices sorted; differentiable in all three."""
    m = weights.shape[0]
    for name, x in (("weights", weights), ("t_mid", t_mid), ("delta", delta), ("ray_indices", ray_indices)):
        _check_shape(name, x, (m,))
    return _Distortion.apply(weights.contiguous(), t_mid.contiguous(), delta.contiguous(),
                             ray_offsets(ray_indices.contiguous(), n_rays), passes)


def render_packed(
    sigma: Tensor,
    rgb: Tensor,
    t_mid: Tensor,
    delta: Tensor,
    ray_indices: Tensor,
    n_rays: int,
    background: Tensor | float,
    *,
    t_far: Tensor | None = None,
) -> dict[str, Tensor]:
    """Render packed samples (the fast model's path).

    Args:
        sigma: (M,) densities; rgb: (M, 3) colors in [0, 1].
        t_mid: (M,) distance of each sample (interval midpoint), world units.
        delta: (M,) interval lengths; ray_indices: (M,) long sorted ascending; n_rays: N.
        background: (3,), (N, 3) or scalar.
        t_far: optional (N,) ray ends. With it, depth = ``sum w t + (1 - opacity) * t_far`` exactly as
            :func:`render_dense`; without it, depth = ``sum w t / opacity`` (0 for empty rays).

    Returns dict with rgb (N, 3), depth (N,), opacity (N,), weights (M,), transmittance (M,).
    """
    _check_shape("sigma", sigma, (None,))
    m = sigma.shape[0]
    _check_shape("rgb", rgb, (m, 3))
    _check_shape("t_mid", t_mid, (m,))
    weights, transmittance = render_weights_packed(sigma, delta, ray_indices, n_rays)
    opacity = accumulate_packed(weights, None, ray_indices, n_rays)
    remainder = (1.0 - opacity).clamp_min(0.0)
    bg = _as_background(background, n_rays, rgb)
    color = accumulate_packed(weights, rgb, ray_indices, n_rays) + remainder[:, None] * bg
    wt = accumulate_packed(weights, t_mid, ray_indices, n_rays)
    if t_far is not None:
        _check_shape("t_far", t_far, (n_rays,))
        depth = wt + remainder * t_far
    else:
        depth = wt / opacity.clamp_min(1e-10)
    return {"rgb": color, "depth": depth, "opacity": opacity, "weights": weights, "transmittance": transmittance}


# ----------------------------------------------------------------------------- model interface
def checked_aabb(value: Any, owner: str) -> Tensor:
    """The scene box ``[[min x, y, z], [max x, y, z]]`` as float32, or a ValueError naming the config that gave it."""
    aabb = torch.tensor(value, dtype=torch.float32)
    if aabb.shape != (2, 3) or not bool((aabb[1] > aabb[0]).all()):
        raise ValueError(f"{owner}.aabb must be [[min x, y, z], [max x, y, z]] with max > min, got {value}")
    return aabb


class RadianceModel(nn.Module, abc.ABC):
    """What the trainer, renderer and mesher need from a radiance field (classic and fast models).

    Coordinates are in the normalized scene frame (+Z up, object inside ``aabb`` ~ [-1, 1]^3);
    ``rays_d`` are unit length so ``t`` and depths are world units.
    """

    progress: float = 0.0
    """The share of training done, as :meth:`set_progress` last set it (0 before training)."""

    @abc.abstractmethod
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
        """Render rays_o/rays_d (N, 3) between near/far (N,) over background (3,) or (N, 3).

        Returns 'rgb' (N, 3), 'depth' (N,), 'opacity' (N,); optionally 'aux_rgb' (list of (N, 3)
        extra predictions supervised with the same target, e.g. the coarse network) and 'reg'
        (a scalar regularization loss, already weighted). ``training`` enables sample jitter.
        ``colors=False`` asks for depth and opacity only (the mesh stage's depth maps): a model whose colour is
        separate work may skip it and return the background as 'rgb'.
        """

    @abc.abstractmethod
    def density(self, x: Tensor) -> Tensor:
        """World-space density sigma (M,) at points x (M, 3) (1/world unit), for mesh extraction."""

    @abc.abstractmethod
    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        """RGB (M, 3) in [0, 1] emitted at x (M, 3) towards unit view directions d (M, 3)."""

    def current_step(self) -> int:
        """The training step :meth:`step_update` last set (0 before any), kept on the host: models that keep it in a
        ``step`` buffer (saved with the field) would otherwise read the device, which on CUDA waits for the GPU."""
        host = getattr(self, "_host_step", None)
        if host is None:
            step = getattr(self, "step", None)
            host = int(step) if isinstance(step, torch.Tensor) else 0
            self._host_step = host
        return host

    def _load_from_state_dict(self, *args: Any, **kwargs: Any) -> None:
        self._host_step = None  # the loaded buffer decides
        super()._load_from_state_dict(*args, **kwargs)

    def set_step(self, step: int) -> None:
        """Record ``step`` on the host and, where the model has one, in its ``step`` buffer."""
        self._host_step = int(step)
        buffer = getattr(self, "step", None)
        if isinstance(buffer, torch.Tensor):
            buffer.fill_(step)

    def set_progress(self, progress: float) -> None:
        """Record the share of training done (0 to 1: of the steps, or of the time budget when one sets the
        schedule); the trainer calls it before each step, so a loss whose weight follows training can read it."""
        self.progress = float(progress)

    def step_update(self, step: int) -> bool:
        """Per-step hook called by the trainer before each step (e.g. occupancy refresh); no-op here.

        Returns True when it moved parameters in a way that makes the optimizer's moments stale
        (e.g. grids re-sampled onto a new box); the trainer then resets them.
        """
        return False

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """Adam parameter groups; one group at ``lr`` by default. Override for per-part rates."""
        return [{"params": [p for p in self.parameters() if p.requires_grad], "lr": lr}]

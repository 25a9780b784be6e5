"""The fast radiance field: grids for density and color features, a tiny color MLP, occupancy-guided marching.

Design (DVGO-like, tuned for a small CPU; runs unchanged on CUDA):

* density = activation(sum of a grid's channels + bias): no MLP on the many density samples. The bias
  is set so that each step starts with opacity ``init_alpha`` (~1e-2: tiny initial opacities never form
  surfaces, see CPU_NERF_NOTES.md lesson 2). softplus, or an exp whose input is clamped at 15
  (``trunc_exp``), so densities never overflow.
* color = sigmoid(MLP(feature grid, SH(view direction))), evaluated only on samples whose weight
  exceeds ``color_min_weight``: the density pass decides where color matters.
* samples come packed from :func:`recon.nerf.occupancy.march` (occupied cells only, early ray
  termination in a no-grad pre-pass), ordered along each ray (grids read ordered points faster).
  In a bounded scene rays are clipped to the box around the occupied cells once the grid is warm. On the CPU
  rays march in C (:mod:`recon.nerf.native`: the same samples as the torch path, faster; bounded and contracted
  steps), and rendering composites there too. On CUDA, ``kernels="triton"`` marches (bounded steps), composites the
  packed samples and reads the dense grids in fused Triton kernels (:mod:`recon.nerf.kernels`; the torch code is
  their reference).

Coordinates: world = normalized scene frame. Bounded scenes map the ``aabb`` onto the grids'
unit cube; unbounded ones contract (:mod:`recon.nerf.contraction`) into [-2, 2]^3 first.

The trainer must call :meth:`FastModel.step_update` before every training step: it refreshes the
occupancy grid, and until ``occupancy_warmup`` steps have passed training marches with coarse steps.

Why these defaults:

* Density is a coarse-to-fine sum of dense levels: a single fine grid learns the coarse shape much later.
* Density is counted per voxel (``density_scale``): Adam moves a raw value by about lr per step, so a density in
  world units (hundreds for an opaque voxel) takes thousands of steps to become opaque and short runs stay soft.
* The occupancy threshold sits above ``init_alpha``: at the initial opacity nothing is culled and every
  ray marches the whole box.

Current speed and accuracy: docs/presets.md and the records in benchmarks/.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from recon.nerf.contraction import contract, contracted_distance
from recon.nerf.grid import DenseGrid, HashGrid, MultiDenseGrid, VMGrid, add_native_grads, resample_dense
from recon.nerf.kernels import (
    accumulate_packed_triton,
    composite_packed_triton,
    distortion_packed_triton,
    march_dense_triton,
    use_triton,
)
from recon.nerf.model_config import HASH_BASE_RES, HASH_FEATURES, FastConfig, GridKind, density_grid_dim
from recon.nerf.native import (
    DenseDensity,
    composite_packed_native,
    distortion_packed_native,
    march_dense_native,
    march_render_native,
    native_grid_ok,
)
from recon.nerf.occupancy import OccupancyGrid, density_threshold, march, march_front_to_back
from recon.nerf.rays import clip_to_box
from recon.nerf.render import (
    RadianceModel,
    accumulate_packed,
    checked_aabb,
    distortion_packed,
    render_weights_packed,
)

__all__ = ["FastConfig", "FastModel", "sh_encode", "sh_product", "sh_terms", "distortion_loss_packed", "ray_background",
           "SkyColor", "trunc_exp"]

def trunc_exp(x: Tensor, max_input: float = 15.0) -> Tensor:
    """exp of x clamped at ``max_input`` (gradient 0 above it): overflow-free density activation."""
    return torch.exp(x.clamp(max=max_input))


_SH_C = (
    0.28209479177387814,
    0.4886025119029199,
    (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396),
    (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
     1.445305721320277, -0.5900435899266435),
)


def sh_terms(d: Tensor, degree: int) -> Tensor:
    """Real spherical harmonics of unit directions d (M, 3) up to ``degree`` (0..3): (M, (degree+1)^2), term by term.

    The definition, :func:`sh_product`'s reference and what :func:`sh_encode` runs on a CPU."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _SH_C[0])]
    if degree >= 1:
        out += [-_SH_C[1] * y, _SH_C[1] * z, -_SH_C[1] * x]
    if degree >= 2:
        c = _SH_C[2]
        xx, yy, zz = x * x, y * y, z * z
        out += [c[0] * x * y, c[1] * y * z, c[2] * (2 * zz - xx - yy), c[3] * x * z, c[4] * (xx - yy)]
        if degree >= 3:
            c3 = _SH_C[3]
            out += [
                c3[0] * y * (3 * xx - yy), c3[1] * x * y * z, c3[2] * y * (4 * zz - xx - yy),
                c3[3] * z * (2 * zz - 3 * xx - 3 * yy), c3[4] * x * (4 * zz - xx - yy),
                c3[5] * z * (xx - yy), c3[6] * x * (xx - 3 * yy),
            ]
    return torch.stack(out, dim=-1)


def _monomials(d: Tensor, degree: int) -> Tensor:
    """d (M, 3) and its outer powers up to ``degree`` (>= 1), flattened: (M, 3 + 9 + 27) at degree 3, in as many
    operations as degrees (the products are repeated, x·y and y·x, which costs a few multiply-adds, not launches)."""
    parts, power = [d], d
    for _ in range(1, degree):
        power = (power[:, :, None] * d[:, None, :]).flatten(1)
        parts.append(power)
    return torch.cat(parts, 1) if len(parts) > 1 else d


@lru_cache(maxsize=16)
def _sh_matrix(degree: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(the constant term (K,), the (monomials, K) matrix) with ``sh_terms(d) = constant + _monomials(d) @ matrix``.

    Read off :func:`sh_terms` itself (one home for the coefficients): the harmonics are polynomials in x, y, z, so
    their coefficients solve a linear system on generic points, exactly up to float64 rounding (the pseudo-inverse
    splits a coefficient evenly between x·y and y·x)."""
    points = torch.randn(64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    constant = sh_terms(torch.zeros(1, 3, dtype=torch.float64), degree)[0]
    matrix = torch.linalg.pinv(_monomials(points, degree)) @ (sh_terms(points, degree) - constant)
    return constant.to(device, dtype), matrix.to(device, dtype)


def sh_product(d: Tensor, degree: int) -> Tensor:
    """:func:`sh_terms` as one matrix product of d's powers: 4 kernel launches at degree 3 where the terms take 51
    (tests/test_nerf_fast.py holds the two together). Degree 0 (a constant) and a degree out of range are the terms'."""
    if degree < 1:
        return sh_terms(d, degree)
    constant, matrix = _sh_matrix(degree, d.device, d.dtype)  # sh_terms refuses a degree over 3 there
    with torch.autocast(d.device.type, enabled=False):  # the directions' harmonics in their own precision
        return torch.addmm(constant, _monomials(d, degree), matrix)


def sh_encode(d: Tensor, degree: int) -> Tensor:
    """Real spherical harmonics of unit directions d (M, 3) up to ``degree`` (0..3): (M, (degree+1)^2).

    On a GPU, where each operation is a kernel launch, as one matrix product (:func:`sh_product`); on a CPU term by
    term (:func:`sh_terms`), which moves fewer bytes than the product's repeated powers and measured faster there."""
    return sh_terms(d, degree) if d.device.type == "cpu" else sh_product(d, degree)


def distortion_loss_packed(weights: Tensor, t_mid: Tensor, delta: Tensor, ray_indices: Tensor, n_rays: int,
                           fused: bool = False) -> Tensor:
    """The mip-NeRF 360 distortion loss of packed samples, mean over rays: :func:`recon.nerf.render.distortion_packed`,
    or its Triton kernel where ``fused`` (:func:`recon.nerf.kernels.distortion_packed_triton`), or on a CPU its C pass
    (:func:`recon.nerf.native.distortion_packed_native`)."""
    per_ray = (distortion_packed_triton(weights, t_mid, delta, ray_indices, n_rays) if fused
               else distortion_packed_native(weights, t_mid, delta, ray_indices, n_rays))
    if per_ray is None:
        per_ray = distortion_packed(weights, t_mid, delta, ray_indices, n_rays)
    return per_ray.mean() if n_rays else per_ray.sum()


def make_color_mlp(feat: int, color_model: str, sh_degree: int, width: int, layers: int) -> nn.Sequential | None:
    """The color head on ``feat`` grid channels (None for "direct": sigmoid of the first 3 channels)."""
    if color_model == "direct":
        if feat < 3:
            raise ValueError("color_model='direct' needs at least 3 feature channels")
        return None
    in_dim = feat + ((sh_degree + 1) ** 2 if color_model == "mlp_view" else 0)
    mods: list[nn.Module] = []
    for _ in range(layers):
        mods += [nn.Linear(in_dim, width), nn.ReLU(inplace=True)]
        in_dim = width
    mods.append(nn.Linear(in_dim, 3))
    return nn.Sequential(*mods)


def color_from_features(f: Tensor, d: Tensor, mlp: nn.Module | None, color_model: str, sh_degree: int) -> Tensor:
    """RGB (M, 3) in [0, 1] from grid features f (M, C) and unit view directions d (M, 3)."""
    if mlp is None:
        return torch.sigmoid(f[:, :3])
    if color_model == "mlp_view":
        f = torch.cat([f, sh_encode(d, sh_degree).to(f)], dim=-1)
    return torch.sigmoid(mlp(f).float())


def composite_packed(sigma: Tensor, delta: Tensor, t: Tensor, ray_indices: Tensor, n_rays: int,
                     fused: bool) -> tuple[Tensor, Tensor, Tensor]:
    """Weights (M,), opacity and the weighted sum of t (N,) of packed samples (sorted by ray), in one pass a ray
    forward and one back: a Triton kernel where ``fused`` (CUDA), C on a CPU, else the torch reference."""
    composited = (composite_packed_triton(sigma, delta, t, ray_indices, n_rays) if fused
                  else composite_packed_native(sigma, delta, t, ray_indices, n_rays))
    if composited is not None:
        weights, _, opacity, t_sum = composited
        return weights, opacity, t_sum
    weights, _ = render_weights_packed(sigma, delta, ray_indices, n_rays)
    opacity = accumulate_packed(weights, None, ray_indices, n_rays)
    return weights, opacity, accumulate_packed(weights, t, ray_indices, n_rays)


MLP_SLICE = 8192
"""Samples per call of the color MLP on a CPU. A batch's colored samples (~66k per training step, ~125k per 16k-ray
render chunk) in one call push the MLP's 64-wide activations out of the cache: in slices the same work runs
markedly faster on a CPU, forward and backward, with the same results to float rounding. A GPU takes them in one
call: each slice launches the network's kernels again, and there the launches, not the kernels, set the step's
pace (docs/profile_gpu.md)."""


def in_slices(fn: Callable[[Tensor, Tensor], Tensor], f: Tensor, d: Tensor) -> Tensor:
    """``fn(f, d)`` of a row-wise ``fn``, on a CPU computed on slices of ``MLP_SLICE`` rows (differentiably when
    recording); elsewhere in one call."""
    n = f.shape[0]
    if n <= MLP_SLICE or f.device.type != "cpu":
        return fn(f, d)
    if torch.is_grad_enabled():  # split: one backward node joins the slices' gradients, none fills a zeroed copy
        return torch.cat([fn(a, b) for a, b in zip(f.split(MLP_SLICE), d.split(MLP_SLICE))])
    first = fn(f[:MLP_SLICE], d[:MLP_SLICE])
    out = first.new_empty((n, *first.shape[1:]))
    out[:MLP_SLICE] = first
    for s in range(MLP_SLICE, n, MLP_SLICE):
        out[s : s + MLP_SLICE] = fn(f[s : s + MLP_SLICE], d[s : s + MLP_SLICE])
    return out


class _MarchedDensity(torch.autograd.Function):
    """The densities the native march read at its samples (M,), as differentiable in the density levels as reading
    them again: forward hands them on, backward takes the activation's slope from the density itself and adds the
    raw sum's gradient into every level in C, a level a thread (:func:`recon.nerf.grid.add_native_grads`). A training
    step then reads the levels once a sample, not twice (tests/test_native_march.py holds it to
    ``FastModel._sigma_unit``)."""

    @staticmethod
    def forward(ctx, sigma: Tensor, u: Tensor, model: "FastModel", *tables: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(sigma, u)
        ctx.model = model
        return sigma.clone()

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[None, ...]:  # type: ignore[override]
        sigma, u = ctx.saved_tensors
        model = ctx.model
        g_raw = (g * model._activation_slope(sigma))[:, None].contiguous()
        levels = model._density_levels()
        add_native_grads(levels, u, g_raw)
        return (None, None, None, *(None for _ in levels))


def ray_background(
    mode: str, bg_logit: Tensor | None, background: Tensor | None, n: int, like: Tensor, training: bool
) -> Tensor:
    """Background (n, 3) behind n rays: the learned color (mode "learned"), else the caller's (3,) or (n, 3),
    else random colors while training in mode "random", else black or white."""
    if mode == "learned" and bg_logit is not None:
        return torch.sigmoid(bg_logit).to(like).expand(n, 3)
    if background is not None:
        bg = torch.as_tensor(background).to(like)
        return bg.expand(n, 3) if bg.dim() == 1 else bg
    if mode == "random" and training:
        return torch.rand(n, 3, device=like.device, dtype=like.dtype)
    value = 0.0 if mode == "black" else 1.0
    return torch.full((n, 3), value, device=like.device, dtype=like.dtype)


class SkyColor(nn.Module):
    """The colour a ray shows when it meets nothing (FastConfig.background = "sky"): a sigmoid of a linear map of
    the ray direction's spherical harmonics up to degree 3. A clear sky is smooth in direction; a map this smooth
    cannot draw a surface's texture, so the field still has to hold every surface."""

    degree = 3

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear((self.degree + 1) ** 2, 3)
        nn.init.zeros_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)

    def forward(self, d: Tensor) -> Tensor:
        """Unit directions d (N, 3) -> RGB (N, 3) in (0, 1)."""
        return torch.sigmoid(self.linear(sh_encode(F.normalize(d.float(), dim=-1), self.degree)))


def _make_grid(kind: GridKind, res: int, dim: int, *, density: bool, levels: int = 1, table_log2: int = 17) -> nn.Module:
    """A grid encoder of the given kind; ``dim`` as documented on FastConfig.feature_dim."""
    if kind == "dense":
        return DenseGrid(res, dim, init_std=0.0) if levels <= 1 else MultiDenseGrid(res, dim, levels)
    if kind == "vm":
        return VMGrid(res, dim, init_std=0.01 if density else 0.1)
    if kind == "hash":
        return HashGrid(levels=dim, features=HASH_FEATURES, log2_table=table_log2, base_res=HASH_BASE_RES, max_res=res)
    raise ValueError(f"unknown grid kind {kind!r}; choose dense, vm or hash")


class FastModel(RadianceModel):
    """Grid radiance field with occupancy-guided packed marching (see the module docstring)."""

    render_chunk = 16384
    """Rays per chunk when rendering an image (:func:`recon.nerf.evaluate.render_image`). Peak memory of a 400×400
    Lego render grew by 170 MB at 8192 rays and 880 MB at 65536, for no CPU time saved under load."""

    def __init__(self, config: FastConfig | None = None) -> None:
        super().__init__()
        cfg = self.config = config or FastConfig()
        aabb = checked_aabb(cfg.aabb, "FastConfig")
        self.register_buffer("aabb", aabb)
        box = torch.tensor([[-2.0] * 3, [2.0] * 3]) if cfg.unbounded else aabb
        self.register_buffer("grid_box", box.clone())  # shrink_grids moves it; aabb stays the scene box
        extent = float((box[1] - box[0]).max())
        self.step_size = cfg.step_ratio * extent / (cfg.density_res - 1)
        """World step along rays (in contracted units when unbounded)."""

        self.density_grid = _make_grid(
            cfg.density_grid, cfg.density_res, density_grid_dim(cfg.density_grid), density=True,
            levels=cfg.density_levels, table_log2=cfg.hash_table_log2,
        )
        self.density_scale = (cfg.density_res - 1) / extent
        """σ = activation(raw) / voxel size: raw values count opacity per voxel, not per world unit. Adam moves
        a raw value by about lr per step, so in world units (σ of hundreds for an opaque voxel) surfaces
        would need thousands of steps to become sharp; per voxel a raw value of ~3 already is opaque."""
        self.density_bias = self._raw_density(cfg.init_alpha)  # opacity init_alpha per step

        self.color_grid = _make_grid(cfg.grid, cfg.feature_res, cfg.feature_dim, density=False, levels=cfg.feature_levels,
                                     table_log2=cfg.hash_table_log2)
        self.color_mlp = make_color_mlp(self.color_grid.out_dim, cfg.color_model, cfg.sh_degree, cfg.mlp_width, cfg.mlp_layers)
        self.bg_logit = nn.Parameter(torch.zeros(3)) if cfg.background == "learned" else None
        self.sky = SkyColor() if cfg.background == "sky" else None

        self.occupancy_alpha = cfg.unbounded_occupancy_alpha if cfg.unbounded else cfg.occupancy_alpha
        """The opacity per step from which occupancy keeps a vertex (a room's fog culled harder, see FastConfig)."""
        self.distortion_weight = cfg.unbounded_distortion_weight if cfg.unbounded else cfg.distortion_weight
        """The distortion loss's weight: an unbounded capture's is its own, on contracted distance."""
        self.occupancy = OccupancyGrid(
            aabb,
            resolution=cfg.occupancy_res,
            sigma_threshold=density_threshold(self.occupancy_alpha, self.step_size),
            warmup_steps=cfg.occupancy_warmup,
            contraction=cfg.unbounded,
            start_threshold=density_threshold(min(cfg.occupancy_alpha_start, self.occupancy_alpha), self.step_size),
            ramp_steps=cfg.occupancy_ramp,
        )
        self.register_buffer("march_box", aabb.clone())
        self.register_buffer("shrunk", torch.zeros((), dtype=torch.bool))
        self.register_buffer("step", torch.zeros((), dtype=torch.long))
        for grid in (*self.density_grid.modules(), *self.color_grid.modules()):
            if isinstance(grid, (DenseGrid, MultiDenseGrid, HashGrid)):
                grid.kernels = cfg.kernels  # their CUDA reads (recon.nerf.kernels); a CPU reads in torch or C

    @property
    def start_resolution(self) -> int:
        """Vertices a side of the coarsest dense density level: the grid `start_inside` takes its shape on."""
        grid = self.density_grid
        if isinstance(grid, MultiDenseGrid):
            return grid.resolutions[0]
        if isinstance(grid, DenseGrid):
            return grid.res
        raise ValueError(f"a start shape needs a dense density grid, not {self.config.density_grid!r}")

    @torch.no_grad()
    def start_inside(self, inside: Tensor) -> None:
        """Raise the density at the vertices ``inside`` ((r, r, r) bool indexed [ix, iy, iz] over the grid box, r =
        `start_resolution`) to ``config.hull_start_alpha`` opacity a step; the rest keeps ``init_alpha``. Before the
        grids shrink (the box they cover then moves)."""
        alpha = self.config.hull_start_alpha
        if not 0.0 < alpha < 1.0:
            raise ValueError(f"hull_start_alpha must lie in (0, 1) for a start shape, got {alpha}")
        r = self.start_resolution
        inside = torch.as_tensor(inside).bool()  # a numpy array too
        if tuple(inside.shape) != (r, r, r):
            raise ValueError(f"the start shape must be {r}³ (the coarsest density level), got {tuple(inside.shape)}")
        if bool(self.shrunk):
            raise ValueError("the start shape is set before training: the grids have already shrunk")
        grid = self.density_grid.grids[0] if isinstance(self.density_grid, MultiDenseGrid) else self.density_grid
        table = grid.table.view(r ** 3, -1)
        table[inside.reshape(-1).to(table.device), 0] += self._raw_density(alpha) - self.density_bias

    def cull_slowly(self) -> None:
        """Let the occupancy grid cull from ``slow_occupancy_alpha_start`` over ``slow_occupancy_ramp`` steps (see
        there): for a field that starts empty though its photos have silhouettes. Set before training, again when it
        resumes (it is not part of the state)."""
        cfg = self.config
        self.occupancy.start_threshold = density_threshold(min(cfg.slow_occupancy_alpha_start, self.occupancy_alpha),
                                                           self.step_size)
        self.occupancy.ramp_steps = int(cfg.slow_occupancy_ramp)

    def _raw_density(self, alpha: float) -> float:
        """The raw density (before the activation) whose opacity over one step is ``alpha``."""
        sigma = -math.log1p(-alpha) / self.step_size / self.density_scale
        return math.log(math.expm1(sigma)) if self.config.density_activation == "softplus" else math.log(sigma)

    @property
    def voxel_size(self) -> float:
        """Edge of the finest density voxel (scene units; contracted units when unbounded): the thinnest
        layer this field can make opaque. Shrinking the grids onto the object makes it smaller."""
        return float((self.grid_box[1] - self.grid_box[0]).max()) / (self.config.density_res - 1)

    # ------------------------------------------------------------------ fields
    def _unit(self, x: Tensor) -> Tensor:
        """World points (M, 3) -> grid unit cube coordinates (M, 3) (unclamped)."""
        if self.config.unbounded:
            x = contract(x)
        box = self.grid_box.to(x)
        return (x - box[0]) / (box[1] - box[0])

    def _sigma_unit(self, u: Tensor) -> Tensor:
        raw = self.density_grid(u).sum(-1) + self.density_bias
        if self.config.density_activation == "softplus":
            return F.softplus(raw) * self.density_scale
        return trunc_exp(raw) * self.density_scale

    def _activation_slope(self, sigma: Tensor) -> Tensor:
        """d sigma / d raw of :meth:`_sigma_unit` from sigma itself: sigma where the exp is not clamped (0 where it
        is), or the softplus's sigmoid times the scale."""
        scale = self.density_scale
        if self.config.density_activation == "softplus":
            return -torch.expm1(-sigma / scale) * scale
        return torch.where(sigma < math.exp(15.0) * scale * (1.0 - 1e-6), sigma, 0.0)

    def _density_levels(self) -> list[DenseGrid]:
        """The density grid's dense levels (empty for other grids)."""
        grid = self.density_grid
        return [grid] if isinstance(grid, DenseGrid) else list(grid.grids) if isinstance(grid, MultiDenseGrid) else []

    def _marched_sigma(self, sigma: Tensor, u: Tensor) -> Tensor | None:
        """The native march's densities at its points u as the loss's (:class:`_MarchedDensity`), or None where the
        levels do not train in C (the caller reads them again)."""
        tables = [g.table for g in self._density_levels()]
        if not tables or not torch.is_grad_enabled() or not all(t.requires_grad for t in tables) \
                or not native_grid_ok(u, *tables):
            return None
        return _MarchedDensity.apply(sigma, u, self, *tables)

    def _rgb_unit(self, u: Tensor, d: Tensor) -> Tensor:
        return in_slices(self._rgb_from_features, self.color_grid(self._color_unit(u)), d)

    def _color_unit(self, u: Tensor) -> Tensor:
        """Grid unit coordinates (M, 3) -> the colour grid's. A hash grid is not re-sampled when the grids shrink
        (`shrink_grids`): it stays on the scene box, where a point of the shrunk density grid's unit cube lies
        at an offset and scale (exactly 0 and 1 before any shrink)."""
        if not isinstance(self.color_grid, HashGrid) or self.config.unbounded:
            return u
        box, scene = self.grid_box.to(u), self.aabb.to(u)
        extent = scene[1] - scene[0]
        return torch.addcmul((box[0] - scene[0]) / extent, u, (box[1] - box[0]) / extent)

    def _rgb_from_features(self, f: Tensor, d: Tensor) -> Tensor:
        return color_from_features(f, d, self.color_mlp, self.config.color_model, self.config.sh_degree)

    def density(self, x: Tensor) -> Tensor:
        """World-space density sigma (M,) at x (M, 3), 1/world unit; 0 outside the scene box (bounded)."""
        u = self._unit(x)
        sigma = self._sigma_unit(u.clamp(0.0, 1.0))
        if self.config.unbounded:
            return sigma
        inside = ((u >= 0) & (u <= 1)).all(-1)
        return torch.where(inside, sigma, torch.zeros_like(sigma))

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        """RGB (M, 3) in [0, 1] emitted at world points x (M, 3) towards unit directions d (M, 3)."""
        return self._rgb_unit(self._unit(x).clamp(0.0, 1.0), d)

    # ------------------------------------------------------------------ rendering
    def _background(self, background: Tensor | None, rays_d: Tensor, training: bool) -> Tensor:
        if self.sky is not None:
            return self.sky(rays_d).to(rays_d)
        return ray_background(self.config.background, self.bg_logit, background, rays_d.shape[0], rays_d, training)

    def render_rays(
        self,
        rays_o: Tensor,
        rays_d: Tensor,
        near: Tensor,
        far: Tensor,
        *,
        training: bool,
        background: Tensor | None = None,
        colors: bool = True,
    ) -> dict[str, Any]:
        """Render rays (N, 3) between near/far (N,) (see RadianceModel.render_rays).

        Returns rgb (N, 3), depth (N,), opacity (N,), background (N, 3) (the one composited, so a
        trainer using "random" can composite its targets the same way), num_samples (int, packed M),
        and 'reg' (weighted regularizers) when any regularizer weight is non-zero. ``colors=False`` skips the
        feature grid and the colour network (about half a render's time): rgb is then the background.
        """
        cfg = self.config
        n = rays_o.shape[0]
        if cfg.unbounded:
            t_near, t_far = near, far
        else:
            box = self.march_box if self.occupancy.is_warm() else self.aabb
            t_near, t_far = clip_to_box(rays_o, rays_d, near, far, box, cfg.kernels)

        evaluated = [0]  # density evaluations, for tests and profiles

        def sigma_fn(ts: Tensor, te: Tensor, ri: Tensor) -> Tensor:
            evaluated[0] += int(ts.shape[0])
            x = rays_o[ri] + rays_d[ri] * (0.5 * (ts + te))[:, None]
            return self._sigma_unit(self._unit(x).clamp(0.0, 1.0))

        step_size = self.step_size
        if training and self.current_step() < cfg.occupancy_warmup:
            step_size *= cfg.warmup_step_scale
        # march front to back (densities behind opaque surfaces are never evaluated); without gradients
        # (evaluation, recon render, the viewer) the marcher's densities are the ones rendered, not evaluated again
        early_stop = cfg.early_stop_transmittance > 0
        contracted = cfg.unbounded and cfg.unbounded_steps == "contracted"
        no_grad = not training and not torch.is_grad_enabled() and early_stop
        field = self._dense_density() if early_stop else None
        if no_grad and field is not None:  # march and composite natively: only the colored samples come back
            fused = march_render_native(rays_o, rays_d, t_near, t_far, field, step_size, cfg.max_samples,
                                        cfg.early_stop_transmittance, cfg.color_min_weight)
            if fused is not None:
                return self._composite_native(fused, rays_o, rays_d, far, background, colors)
        # the torch contracted marcher has no front-to-back variant: it returns no densities to reuse
        infer = no_grad and not contracted
        u = marched = None
        # without gradients for the points (no pose refinement), the C march's densities and points are the loss's
        points = not (rays_o.requires_grad or rays_d.requires_grad)
        with torch.no_grad():
            native = None
            if field is not None:
                native = march_dense_native(rays_o, rays_d, t_near, t_far, training, field, step_size, cfg.max_samples,
                                            cfg.early_stop_transmittance, points=points)
                if native is not None and points:
                    *native, u = native
                if native is None and use_triton(cfg.kernels, rays_o):  # CUDA: one kernel, one host read
                    native = march_dense_triton(rays_o, rays_d, t_near, t_far, training, field, step_size,
                                                cfg.max_samples, cfg.early_stop_transmittance)
            if native is not None:
                ts, te, ri, sigma = native
                evaluated[0] += int(ts.shape[0])
                infer = no_grad  # the native marcher's densities are the rendered ones
            elif early_stop and not contracted:
                ts, te, ri, sigma = march_front_to_back(
                    rays_o, rays_d, t_near, t_far, self.occupancy, step_size, cfg.max_samples, sigma_fn,
                    cone_angle=cfg.cone_angle, jitter=training, min_transmittance=cfg.early_stop_transmittance,
                )
            else:
                ts, te, ri = march(
                    rays_o, rays_d, t_near, t_far, self.occupancy, step_size, cfg.max_samples,
                    cone_angle=cfg.cone_angle, jitter=training, contracted=contracted,
                    sigma_fn=sigma_fn if early_stop else None, min_transmittance=cfg.early_stop_transmittance,
                )
        mid = 0.5 * (ts + te)
        delta = te - ts
        if not infer:
            if u is not None:
                marched = self._marched_sigma(sigma, u)
            if marched is not None:
                sigma = marched
            else:
                u = self._unit(rays_o[ri] + rays_d[ri] * mid[:, None]).clamp(0.0, 1.0)
                evaluated[0] += int(ri.shape[0])
                sigma = self._sigma_unit(u)
        fused = use_triton(cfg.kernels, sigma, delta)  # CUDA and train.fast.kernels: one kernel (recon.nerf.kernels)
        weights, opacity, depth_sum = composite_packed(sigma, delta, mid, ri, n, fused)
        bg = self._background(background, rays_d, training)
        remainder = (1.0 - opacity).clamp_min(0.0)
        depth = depth_sum + remainder * far
        if not colors:
            rgb = bg.expand(n, 3)
        else:
            if cfg.color_min_weight > 0:
                sel = (weights.detach() > cfg.color_min_weight).nonzero().squeeze(-1)
                ri_c, w_c = ri[sel], weights[sel]
                u_c = (u[sel] if u is not None
                       else self._unit(rays_o[ri_c] + rays_d[ri_c] * mid[sel, None]).clamp(0.0, 1.0))
            else:
                ri_c, w_c = ri, weights
                u_c = u if u is not None else self._unit(rays_o[ri] + rays_d[ri] * mid[:, None]).clamp(0.0, 1.0)
            rgb_s = self._rgb_unit(u_c, rays_d[ri_c])
            if fused:
                rgb = accumulate_packed_triton(w_c, rgb_s.float(), ri_c, n) + remainder[:, None] * bg
            else:
                rgb = accumulate_packed(w_c, rgb_s, ri_c, n) + remainder[:, None] * bg
        out: dict[str, Any] = {"rgb": rgb, "depth": depth, "opacity": opacity, "background": bg,
                               "num_samples": int(ri.shape[0]), "density_evals": evaluated[0]}
        if cfg.unbounded and training and self.distortion_weight_now() > 0:  # the distortion loss in contracted distance
            s_start, s_end = contracted_distance(rays_o, rays_d, t_near, t_far, torch.cat([ts, te]),
                                                 torch.cat([ri, ri])).chunk(2)
            mid, delta = 0.5 * (s_start + s_end), s_end - s_start
        reg = self._regularizers(weights, mid, delta, ri, n, opacity)
        if reg is not None:
            out["reg"] = reg
        return out

    def _dense_density(self) -> DenseDensity | None:
        """The field as the native marcher (:mod:`recon.nerf.native`) takes it, where it applies: dense scalar density
        grids, with uniform steps (bounded) or contracted ones (unbounded). None where it does not (world steps
        through an unbounded scene, cone steps, other grids: the torch marcher runs)."""
        cfg = self.config
        levels = self._density_levels()
        contracted = cfg.unbounded and cfg.unbounded_steps == "contracted"
        if cfg.unbounded and not contracted or not contracted and cfg.cone_angle > 0 or not levels \
                or any(g.channels != 1 for g in levels):  # (contracted steps ignore cone_angle, as torch's do)
            return None
        return DenseDensity(self.occupancy.occupied, self.occupancy.box, [g.table.detach().view(-1) for g in levels],
                            self.grid_box, self.density_bias, self.density_scale, cfg.density_activation != "softplus",
                            contracted)

    def _composite_native(self, fused: dict[str, Tensor], rays_o: Tensor, rays_d: Tensor, far: Tensor,
                          background: Tensor | None, colors: bool = True) -> dict[str, Any]:
        """render_rays' result from :func:`march_render_native`'s per-ray sums and colored samples."""
        n = rays_o.shape[0]
        ri_c, w_c = fused["ray_indices"], fused["weights"]
        opacity = fused["opacity"]
        bg = self._background(background, rays_d, False)
        remainder = (1.0 - opacity).clamp_min(0.0)
        if colors:
            rgb = accumulate_packed(w_c, self._rgb_unit(fused["u"], rays_d[ri_c]), ri_c, n) + remainder[:, None] * bg
        else:
            rgb = bg.expand(n, 3)
        depth = fused["depth_sum"] + remainder * far
        samples = int(fused["samples"].sum())
        return {"rgb": rgb, "depth": depth, "opacity": opacity, "background": bg, "num_samples": samples,
                "density_evals": samples}

    def distortion_weight_now(self) -> float:
        """The distortion loss's weight at this point of training: 0 before ``distortion_from`` of it is done and
        from ``distortion_until`` of it on."""
        cfg = self.config
        started = self.progress >= cfg.distortion_from
        stopped = cfg.distortion_until < 1 and self.progress >= cfg.distortion_until
        return self.distortion_weight if started and not stopped else 0.0

    def _regularizers(self, weights: Tensor, mid: Tensor, delta: Tensor, ri: Tensor, n: int, opacity: Tensor) -> Tensor | None:
        cfg = self.config
        terms = []
        if cfg.tv_weight > 0:
            terms.append(cfg.tv_weight * (self.density_grid.tv_loss() + self.color_grid.tv_loss()))
        weight = self.distortion_weight_now()
        if weight > 0:
            fused = use_triton(cfg.kernels, weights, mid, delta)
            terms.append(weight * distortion_loss_packed(weights, mid, delta, ri, n, fused))
        if cfg.entropy_weight > 0:
            o = opacity.clamp(1e-6, 1 - 1e-6)
            terms.append(cfg.entropy_weight * -(o * torch.log(o) + (1 - o) * torch.log(1 - o)).mean())
        return sum(terms) if terms else None

    # ------------------------------------------------------------------ training hooks
    def step_update(self, step: int) -> bool:
        """Refresh the occupancy grid every ``occupancy_every`` steps (all vertices while warming up), and
        shrink the grids to the occupied box once (``shrink_step``). True when the grids were re-sampled."""
        cfg = self.config
        self.set_step(step)
        if step % cfg.occupancy_every != 0:
            return False
        moved = False
        warming = step < cfg.occupancy_warmup
        self.occupancy.update(self.density, step, share=1 if warming else 4, jitter=not warming)
        if self.occupancy.is_warm():
            box = self.occupancy.occupied_aabb()
            if box is not None:
                if cfg.shrink_step and step >= cfg.shrink_step and not bool(self.shrunk):
                    self.shrunk.fill_(True)
                    # onto what has grown: at twice the initial opacity, not the untouched space the ramp still keeps
                    grown = density_threshold(min(2 * cfg.init_alpha, self.occupancy_alpha), self.step_size)
                    core = self.occupancy.core_aabb(above=grown)
                    moved = self.shrink_grids(core if core is not None else box)
                # march only where the grids are: outside them a sample would read the clamped border
                self.march_box.copy_(torch.stack((torch.maximum(box[0], self.grid_box[0]), torch.minimum(box[1], self.grid_box[1]))))
        return moved

    @torch.no_grad()
    def shrink_grids(self, occupied: Tensor) -> bool:
        """Re-sample the dense grids onto ``occupied`` (2, 3) plus a margin, inside the scene box.

        ``occupied`` comes from :meth:`OccupancyGrid.core_aabb`: clusters of early floaters are left
        outside, where the field is then empty for good.

        The field keeps its values (trilinear re-sampling) while its voxels get smaller by the ratio of
        the boxes' extents. Returns True when the grids moved (the optimizer's moments are then stale).
        """
        cfg = self.config
        if cfg.unbounded or not isinstance(self.density_grid, (DenseGrid, MultiDenseGrid)) or isinstance(
                self.color_grid, VMGrid):  # a hash colour grid stays on the scene box (_color_unit)
            return False
        old = self.grid_box.clone()
        pad = cfg.shrink_margin * float((self.aabb[1] - self.aabb[0]).max())
        new = torch.stack((torch.maximum(occupied[0] - pad, old[0]), torch.minimum(occupied[1] + pad, old[1])))
        if bool((new[1] - new[0] >= 0.9 * (old[1] - old[0])).all()):
            return False  # nothing worth gaining

        def old_from_new(u: Tensor) -> Tensor:
            return (new[0] + u * (new[1] - new[0]) - old[0]) / (old[1] - old[0])

        for grid in (*self.density_grid.modules(), *self.color_grid.modules()):
            if isinstance(grid, DenseGrid):
                resample_dense(grid, old_from_new)
        self.grid_box.copy_(new)
        return True

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """Grids (and the learned background) at lr * grid_lr_scale, the color MLP (and the sky) at lr."""
        grids = list(self.density_grid.parameters()) + list(self.color_grid.parameters())
        if self.bg_logit is not None:
            grids.append(self.bg_logit)
        # masked: a step's rays touch few of the grids' values (MaskedAdam may leave the rest alone)
        groups = [{"params": grids, "lr": lr * self.config.grid_lr_scale, "masked": True}]
        if self.color_mlp is not None:
            groups.append({"params": list(self.color_mlp.parameters()), "lr": lr})
        if self.sky is not None:
            groups.append({"params": list(self.sky.parameters()), "lr": lr})
        return groups

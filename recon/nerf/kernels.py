"""Fused Triton kernels for the fast model's CUDA hot path, each beside the torch code it replaces (its reference).

On a GPU the fast model's step in torch is launch-bound (docs/gpu.md): marching takes a window of steps at a time
with host reads in each, compositing packed samples costs ~15 small torch kernels (clamps, a float64 cumulative sum,
the per-ray offsets' gather, exp, expm1, an index_add per sum), and a three-level density read three
``grid_sample`` calls and their coordinate transform. Here each is one kernel
forward and one backward (recon/nerf/triton_kernels.py), wrapped as ``torch.autograd.Function``s:

* :func:`composite_packed_triton` — alpha = -expm1(-σδ), the exclusive transmittance of each ray over its packed
  samples, the weights, and each ray's opacity and depth sum. Reference: :func:`composite_packed_torch`
  (:func:`recon.nerf.render.render_weights_packed` and :func:`recon.nerf.render.accumulate_packed`).
* :func:`accumulate_packed_triton` — per-ray weighted sums of packed values (the colours), a segmented sum without
  atomics. Reference: :func:`recon.nerf.render.accumulate_packed`.
* :func:`distortion_packed_triton` — each ray's distortion loss (the fast model's regularizer) and its gradients, in
  one pass forward and two backward. Reference: :func:`recon.nerf.render.distortion_packed`.
* :func:`trilinear_levels_triton` — the sum of dense grids' trilinear reads at the same points (the density levels,
  or one feature grid), the tables' gradients by atomic adds. Reference: :func:`recon.nerf.grid.trilinear_levels_torch`
  (the torch reads of :class:`recon.nerf.grid.DenseGrid`).
* :func:`pixel_rays_triton` — a training batch's rays through its pixels and where they meet the scene box, one
  lane a ray. Reference: :meth:`recon.nerf.fitting.RayBatcher._rays_torch`. :func:`ray_box_triton` — rays met with a
  box, or their [near, far] clipped to it. Reference: :func:`recon.nerf.rays.ray_aabb_torch`; on a CPU both are
  passes in C (:func:`recon.nerf.native.pixel_rays_native`, :func:`recon.nerf.native.ray_box_native`).
* :func:`march_dense_triton` — front-to-back marching through the occupancy grid and the dense density levels, a ray a
  lane, in one kernel launched twice (count, then write) with one host read between. Reference:
  :func:`recon.nerf.occupancy.march_front_to_back` (windows of steps, host reads in each); on a CPU the C marcher
  (:func:`recon.nerf.native.march_dense_native`) is the same march.

They run only where ``train.fast.kernels`` asks for them (:func:`kernels_choice`), triton imports and the tensors
are float32 on CUDA; everywhere else the torch code runs unchanged, so CPU results stay bit-identical. Callers pass
what the marcher gives: ray indices sorted ascending (not re-checked here: the check costs host syncs); points that
need no gradient (pose refinement's do, and keep the torch reads). Numerics: float32 sums along each ray in sample
order; the float64 reference differs by ~1e-6 relative. tests/test_triton_kernels.py holds each kernel to its
reference, forward and gradients, compiled on CUDA and under Triton's interpreter on a CPU.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

import torch
from torch import Tensor

from recon.nerf.render import (
    SIGMA_MAX,
    TAU_MAX,
    PackedPasses,
    accumulate_packed,
    composite_by,
    distortion_by,
    ray_offsets,
    render_weights_packed,
)

if TYPE_CHECKING:
    from recon.nerf.native import DenseDensity

__all__ = ["MEASURED_FASTER", "KERNEL_DEVICES", "KernelSetting", "kernels_choice", "triton_status", "use_triton",
           "composite_packed_torch", "composite_packed_triton", "accumulate_packed_triton", "distortion_packed_triton",
           "trilinear_levels_triton", "hash_levels_triton", "march_dense_triton", "ray_box_triton",
           "pixel_rays_triton"]

KernelSetting = Literal["auto", "torch", "triton"]

MEASURED_FASTER = True
"""Whether a GPU check (benchmarks/gpu_check.py) has measured training with the Triton kernels faster than with the
torch code at the same PSNR; ``train.fast.kernels=auto`` uses them only then. It has: more steps in the same
budget and no lower test PSNR (benchmarks/results/gpu_check.json)."""

KERNEL_DEVICES: tuple[str, ...] = ("cuda",)
"""Devices whose tensors the kernels take. Under Triton's interpreter (TRITON_INTERPRET=1) they run on CPU tensors
too: tests/test_triton_kernels.py adds "cpu" there to run the fast model through them; nothing else does."""

COMPOSITE_BLOCK = 64
"""Samples a compositing or colour-sum program reads at a time (rays have tens to hundreds of samples); a first
guess, not tuned on a GPU yet, like GRID_BLOCK."""
ACCUMULATE_BLOCK = 64
GRID_BLOCK = 128
"""Points a grid-read program reads at a time."""
MAX_LEVELS = 4
"""Grid levels one launch reads (more are summed over launches)."""
MARCH_BLOCK = 32
"""Rays a marching program takes, a ray a lane of one warp: a program loops until its longest ray ends."""
RAYS_BLOCK = 128
"""Rays a program makes or meets with the box (a ray a lane, no loop)."""
LAUNCH: dict[str, Any] = {"enable_fp_fusion": True}
"""Compiler options every launch passes: fused multiply-adds, as the kernels were tested and measured with. Triton
3.9 warns on the terminal when a launch leaves this unsaid (its default turns to no fusion in 3.10)."""


def _four_levels(items: Sequence[Any]) -> list[Any]:
    """``items`` (one per grid level, 1 to MAX_LEVELS) padded with its first to MAX_LEVELS: a kernel takes a fixed
    number of level arguments and reads only the first LEVELS."""
    return [*items, *list(items[:1]) * (MAX_LEVELS - len(items))]


@lru_cache(maxsize=1)
def _jit() -> ModuleType:
    from recon.nerf import triton_kernels

    return triton_kernels


@lru_cache(maxsize=1)
def triton_status() -> tuple[bool, str]:
    """(triton imports?, its version or why not). Imports triton, once."""
    try:
        import triton
    except Exception as exc:  # not installed, or a build that fails to load: the torch code runs
        first = str(exc).splitlines()[0][:120] if str(exc) else ""
        return False, f"triton does not import ({type(exc).__name__}: {first})"
    return True, f"triton {triton.__version__}"


def kernels_choice(setting: KernelSetting, device_type: str) -> tuple[bool, str]:
    """(use the Triton kernels?, why, in one sentence) for ``train.fast.kernels=setting`` on a ``device_type``
    ("cpu", "cuda") device."""
    if setting == "torch":
        return False, "kernels: torch (train.fast.kernels=torch)"
    if device_type != "cuda":
        return False, (f"kernels: torch on the {device_type} (train.fast.kernels={setting}: the Triton kernels run on "
                       "CUDA only)")
    if setting == "auto" and not MEASURED_FASTER:
        return False, ("kernels: torch (train.fast.kernels=auto stays on the torch path until a GPU check measures the "
                       "Triton kernels faster; train.fast.kernels=triton uses them)")
    ok, why = triton_status()
    if not ok:
        return False, f"kernels: torch (train.fast.kernels={setting}, but {why})"
    return True, (f"kernels: Triton marching, compositing and dense-grid reads on CUDA (train.fast.kernels={setting}, "
                  f"{why}); the torch code is their reference")


@lru_cache(maxsize=4)
def _cuda_choice(setting: str) -> bool:
    return kernels_choice(setting, "cuda")[0]  # type: ignore[arg-type]


def use_triton(setting: str, *tensors: Tensor) -> bool:
    """Run the Triton kernels on these tensors? Only for a setting that wants them and float32 CUDA tensors (False on
    a CPU before anything is imported or looked up: the CPU path is the torch code, unchanged)."""
    if setting == "torch" or not all(t.device.type in KERNEL_DEVICES and t.dtype == torch.float32 for t in tensors):
        return False
    return _cuda_choice(setting)


def _check_1d(name: str, x: Tensor, m: int) -> None:
    if x.shape != (m,):
        raise ValueError(f"{name} must have shape ({m},), got {tuple(x.shape)}")


# ----------------------------------------------------------------------------- packed compositing
def composite_packed_torch(sigma: Tensor, delta: Tensor, t: Tensor, ray_indices: Tensor,
                           n_rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The reference: weights (M,), transmittance (M,), opacity (N,) and depth sum (N,) ``sum_i w_i t_i`` of packed
    samples ``sigma, delta, t (M,)`` (ray_indices (M,) sorted), by render_weights_packed and accumulate_packed."""
    weights, transmittance = render_weights_packed(sigma, delta, ray_indices, n_rays)
    opacity = accumulate_packed(weights, None, ray_indices, n_rays)
    depth = accumulate_packed(weights, t, ray_indices, n_rays)
    return weights, transmittance, opacity, depth


class _TritonPasses(PackedPasses):
    """Compositing and the distortion loss in Triton kernels, one program a ray (recon/nerf/triton_kernels.py)."""

    def composite(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor, trans: Tensor,
                  opacity: Tensor, depth: Tensor) -> None:
        n = offsets.shape[0] - 1
        if n:
            _jit().composite_fwd[(n,)](sigma, delta, t, offsets, weights, trans, opacity, depth,
                                       SIGMA_MAX=SIGMA_MAX, TAU_MAX=TAU_MAX, BLOCK=COMPOSITE_BLOCK, **LAUNCH)

    def composite_backward(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor,
                           trans: Tensor, g_w: Tensor | None, g_trans: Tensor | None, g_op: Tensor, g_dep: Tensor,
                           g_sigma: Tensor, g_delta: Tensor, g_t: Tensor) -> None:
        n = offsets.shape[0] - 1
        if not n:  # no ray, so no sample either
            return
        _jit().composite_bwd[(n,)](sigma, delta, t, offsets, weights, trans, sigma if g_w is None else g_w,
                                   sigma if g_trans is None else g_trans, g_op, g_dep, g_sigma, g_delta, g_t,
                                   SIGMA_MAX=SIGMA_MAX, TAU_MAX=TAU_MAX, BLOCK=COMPOSITE_BLOCK,
                                   HAS_GW=g_w is not None, HAS_GT=g_trans is not None, **LAUNCH)

    def distortion(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, loss: Tensor) -> None:
        n = offsets.shape[0] - 1
        if n:
            _jit().distortion_fwd[(n,)](w, mid, delta, offsets, loss, BLOCK=COMPOSITE_BLOCK, **LAUNCH)

    def distortion_backward(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, g_loss: Tensor,
                            g_w: Tensor, g_mid: Tensor, g_delta: Tensor) -> None:
        n = offsets.shape[0] - 1
        if n:  # every sample is some ray's: all are written
            _jit().distortion_bwd[(n,)](w, mid, delta, offsets, g_loss, g_w, g_mid, g_delta, BLOCK=COMPOSITE_BLOCK,
                                        **LAUNCH)


TRITON_PASSES = _TritonPasses()


def composite_packed_triton(sigma: Tensor, delta: Tensor, t: Tensor, ray_indices: Tensor,
                            n_rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`composite_packed_torch` in one kernel forward (one program per ray) and one backward.

    sigma (M,) densities, delta (M,) interval lengths, t (M,) sample depths, all float32; ray_indices (M,) long,
    sorted ascending (rays may have no samples); differentiable in sigma, delta and t.
    Returns weights (M,), transmittance (M,), opacity (N,), depth sum (N,)."""
    return composite_by(TRITON_PASSES, sigma, delta, t, ray_indices, n_rays)


# ----------------------------------------------------------------------------- per-ray weighted sums
class _AccumulatePacked(torch.autograd.Function):
    @staticmethod
    def forward(ctx, weights: Tensor, values: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:  # type: ignore[override]
        c = values.shape[1]
        offsets = ray_offsets(ray_indices, n_rays)
        out = values.new_empty(n_rays, c)
        if n_rays:
            _jit().accumulate_fwd[(n_rays,)](weights, values, offsets, out, C=c, CP=max(2, 1 << (c - 1).bit_length()),
                                              BLOCK=ACCUMULATE_BLOCK, **LAUNCH)
        ctx.save_for_backward(weights, values, ray_indices)
        return out

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        weights, values, ray_indices = ctx.saved_tensors
        m, c = values.shape
        g_w, g_v = torch.empty_like(weights), torch.empty_like(values)
        if m:
            _jit().accumulate_bwd[(-(-m // ACCUMULATE_BLOCK),)](
                weights, values, ray_indices, g.contiguous(), g_w, g_v, m, C=c,
                CP=max(2, 1 << (c - 1).bit_length()), BLOCK=ACCUMULATE_BLOCK, **LAUNCH)
        need = ctx.needs_input_grad
        return g_w if need[0] else None, g_v if need[1] else None, None, None


def accumulate_packed_triton(weights: Tensor, values: Tensor, ray_indices: Tensor, n_rays: int) -> Tensor:
    """:func:`recon.nerf.render.accumulate_packed` with values: ``out[r] = sum_{i: ray(i)=r} w_i * v_i``, one program
    per ray. weights (M,) float32, values (M, C) -> (N, C) or (M,) -> (N,); ray_indices (M,) sorted ascending.
    Differentiable in weights and values."""
    m = weights.shape[0]
    _check_1d("weights", weights, m)
    _check_1d("ray_indices", ray_indices, m)
    if values.shape[:1] != (m,) or values.dim() not in (1, 2):
        raise ValueError(f"values must have shape ({m},) or ({m}, C), got {tuple(values.shape)}")
    flat = values.dim() == 1
    out = _AccumulatePacked.apply(weights.contiguous(), (values[:, None] if flat else values).contiguous(),
                                  ray_indices.contiguous(), n_rays)
    return out[:, 0] if flat else out


# ----------------------------------------------------------------------------- the distortion loss
def distortion_packed_triton(weights: Tensor, t_mid: Tensor, delta: Tensor, ray_indices: Tensor,
                             n_rays: int) -> Tensor:
    """:func:`recon.nerf.render.distortion_packed`, each ray's distortion loss (N,), in one kernel forward and one
    backward (one program per ray) instead of the reference's float64 cumulative sums, gathers and index_adds.

    weights, t_mid (sorted along each ray), delta: (M,) float32; ray_indices (M,) sorted ascending. Differentiable in
    all three."""
    return distortion_by(TRITON_PASSES, weights, t_mid, delta, ray_indices, n_rays)


# ----------------------------------------------------------------------------- dense grids' trilinear reads
class _TrilinearLevels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x01: Tensor, resolutions: tuple[int, ...], *tables: Tensor) -> Tensor:  # type: ignore[override]
        m, c = x01.shape[0], tables[0].shape[1]
        out = tables[0].new_empty(m, c)
        if m:
            _jit().trilinear_fwd[(-(-m // GRID_BLOCK),)](x01, out, m, *_four_levels(tables),
                                                          *_four_levels(resolutions), LEVELS=len(tables), C=c,
                                                          CP=max(2, 1 << (c - 1).bit_length()), BLOCK=GRID_BLOCK,
                                                          **LAUNCH)
        ctx.save_for_backward(x01, *tables)
        ctx.resolutions = resolutions
        return out

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x01, *tables = ctx.saved_tensors
        need = ctx.needs_input_grad[2:]
        grads = [torch.zeros_like(t) for t in tables]
        m, c = x01.shape[0], tables[0].shape[1]
        if m and any(need):
            _jit().trilinear_bwd[(-(-m // GRID_BLOCK),)](x01, g.contiguous(), m, *_four_levels(grads),
                                                          *_four_levels(ctx.resolutions),
                                                          LEVELS=len(tables), C=c, CP=max(2, 1 << (c - 1).bit_length()),
                                                          BLOCK=GRID_BLOCK, **LAUNCH)
        return (None, None, *(gr if n else None for gr, n in zip(grads, need)))


def trilinear_levels_triton(x01: Tensor, tables: list[Tensor], resolutions: list[int]) -> Tensor:
    """:func:`recon.nerf.grid.trilinear_levels_torch` in one kernel per four levels: x01 (M, 3) float32 in the unit
    cube (no gradient to the points), tables (R_k³, C) float32 -> (M, C); differentiable in the tables."""
    if not tables or len(tables) != len(resolutions):
        raise ValueError(f"one resolution per table, at least one table (got {len(tables)} and {len(resolutions)})")
    if x01.dim() != 2 or x01.shape[1] != 3:
        raise ValueError(f"x01 must have shape (M, 3), got {tuple(x01.shape)}")
    c = tables[0].shape[1]
    for t, r in zip(tables, resolutions, strict=True):
        if t.shape != (r**3, c) or not t.is_contiguous():
            raise ValueError(f"a level of {r} vertices per side needs a contiguous ({r**3}, {c}) table, "
                             f"got {tuple(t.shape)}")
    x01 = x01.detach().contiguous()
    out = None
    for k in range(0, len(tables), MAX_LEVELS):
        part = _TrilinearLevels.apply(x01, tuple(resolutions[k:k + MAX_LEVELS]), *tables[k:k + MAX_LEVELS])
        out = part if out is None else out + part
    assert out is not None
    return out


# ----------------------------------------------------------------------------- hash grids' reads
class _HashLevels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x01: Tensor, table: Tensor, layout: tuple[Tensor, ...], mask: int) -> Tensor:  # type: ignore[override]
        m, f, levels = x01.shape[0], table.shape[1], layout[0].shape[0]
        out = table.new_empty(m, levels * f)
        if m:
            _jit().hash_fwd[(-(-m // GRID_BLOCK),)](x01, table, out, *layout, m, mask, LEVELS=levels, F=f,
                                                     BLOCK=GRID_BLOCK, **LAUNCH)
        ctx.save_for_backward(x01, table)
        ctx.layout, ctx.mask = layout, mask
        return out

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x01, table = ctx.saved_tensors
        if not ctx.needs_input_grad[1]:
            return None, None, None, None
        grad = torch.zeros_like(table)
        m, f, levels = x01.shape[0], table.shape[1], ctx.layout[0].shape[0]
        if m:
            _jit().hash_bwd[(-(-m // GRID_BLOCK),)](x01, g.contiguous(), grad, *ctx.layout, m, ctx.mask, LEVELS=levels,
                                                     F=f, BLOCK=GRID_BLOCK, **LAUNCH)
        return None, grad, None, None


def hash_levels_triton(x01: Tensor, table: Tensor, verts: Tensor, offsets: Tensor, hashed: Tensor,
                       log2_table: int) -> Tensor:
    """:meth:`recon.nerf.grid.HashGrid.forward` in one kernel: x01 (M, 3) float32 in the unit cube (no gradient to
    the points), the levels' one table (rows, F) float32, per level (L,) int64 its vertices per side, first row and
    whether it is hashed -> (M, L · F), level-major; differentiable in the table."""
    if x01.dim() != 2 or x01.shape[1] != 3:
        raise ValueError(f"x01 must have shape (M, 3), got {tuple(x01.shape)}")
    if not table.is_contiguous() or table.dim() != 2:
        raise ValueError(f"the table must be a contiguous (rows, F) tensor, got {tuple(table.shape)}")
    layout = tuple(t.to(device=x01.device, dtype=torch.int64).contiguous() for t in (verts, offsets, hashed))
    if not layout[0].shape == layout[1].shape == layout[2].shape or layout[0].dim() != 1:
        raise ValueError("verts, offsets and hashed need one value per level")
    return _HashLevels.apply(x01.detach().contiguous(), table, layout, (1 << log2_table) - 1)


# ----------------------------------------------------------------------------- marching
@lru_cache(maxsize=8)
def _log_min_transmittance(min_transmittance: float, device: torch.device) -> Tensor:
    """-log(min_transmittance) as a float64 tensor on ``device``: a Python float reaches a kernel as float32."""
    return torch.tensor([-math.log(min_transmittance)], dtype=torch.float64, device=device)


def march_dense_triton(rays_o: Tensor, rays_d: Tensor, t_near: Tensor, t_far: Tensor, jitter: bool,
                       field: DenseDensity, step_size: float, max_samples: int,
                       min_transmittance: float) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """:func:`recon.nerf.occupancy.march_front_to_back` with the fast model's dense density in two launches of one
    kernel (count, then write) and one host read (how many samples), where the torch marcher takes a window of
    steps at a time, each with its own host reads; :func:`recon.nerf.native.march_dense_native` is the same march
    in C for a CPU. None where it does not apply (contracted steps, more than MAX_LEVELS density levels, tensors
    that are not float32 on a kernel device): the caller then marches in torch.

    jitter: each ray's steps offset by one uniform draw, drawn as the torch marcher draws it (one float32 per ray).
    Returns t_starts, t_ends, ray_indices, sigma (M,), sorted by ray and along each ray."""
    tensors = (rays_o, rays_d, t_near, t_far, field.occupancy_box, field.grid_box, *field.tables)
    if field.contracted or not 0 < len(field.tables) <= MAX_LEVELS or not all(
            t.device.type in KERNEL_DEVICES and t.dtype == torch.float32 for t in tensors):
        return None
    device = rays_o.device
    n = rays_o.shape[0]
    u = torch.rand(n, device=device, dtype=torch.float32) if jitter else None
    rays_o, rays_d, t_near, t_far = (t.contiguous() for t in (rays_o, rays_d, t_near, t_far))
    tables = [t.contiguous() for t in field.tables]
    res = [round(t.numel() ** (1 / 3)) for t in tables]
    occupied = field.occupied.contiguous().view(torch.uint8)
    empty = torch.zeros(0, device=device, dtype=torch.float32)
    if n == 0:
        return empty, empty.clone(), torch.zeros(0, device=device, dtype=torch.long), empty.clone()
    counts = torch.empty(n, dtype=torch.int32, device=device)
    grid = (-(-n // MARCH_BLOCK),)
    box = field.occupancy_box.contiguous()
    gbox = field.grid_box.contiguous()

    def launch(offsets: Tensor, outs: list[Tensor], write: bool) -> None:
        _jit().march_dense[grid](
            rays_o, rays_d, t_near, t_far, u if u is not None else t_near, occupied, box, gbox,
            _log_min_transmittance(float(min_transmittance), device), *_four_levels(tables), *_four_levels(res),
            counts, offsets, *outs,
            n, occupied.shape[0], float(step_size), int(max_samples), float(field.bias), float(field.density_scale),
            LEVELS=len(tables), EXP=bool(field.exp_activation), JITTER=u is not None, WRITE=write,
            SIGMA_MAX=SIGMA_MAX, TAU_MAX=TAU_MAX, BLOCK=MARCH_BLOCK, num_warps=1, **LAUNCH)

    launch(counts, [counts] * 4, False)
    ends = torch.cumsum(counts, 0)
    total = int(ends[-1])  # the one host read: how many samples to make room for
    out = [empty.new_empty(total), empty.new_empty(total), torch.empty(total, dtype=torch.long, device=device),
           empty.new_empty(total)]
    if total:
        launch(ends - counts, out, True)
    ts, te, ri, sigma = out
    return ts, te, ri, sigma


# ----------------------------------------------------------------------------- rays
def ray_box_triton(rays_o: Tensor, rays_d: Tensor, box: Tensor, near: Tensor | None = None,
                   far: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`recon.nerf.rays.ray_aabb_torch` (t_near, t_far, hit (N,)) of rays (N, 3) float32 and a box (2, 3) in one
    kernel; given near and far (N,), each ray's [near, far] clipped to the box instead (:func:`recon.nerf.rays.
    clip_to_box`). No gradients."""
    if rays_o.shape != rays_d.shape or rays_o.dim() != 2 or rays_o.shape[1] != 3 or box.shape != (2, 3):
        raise ValueError(f"rays (N, 3) and a box (2, 3), got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}, "
                         f"{tuple(box.shape)}")
    n = rays_o.shape[0]
    t_near, t_far = rays_o.new_empty(n), rays_o.new_empty(n)
    hit = torch.empty(n, dtype=torch.int8, device=rays_o.device)
    clip = near is not None and far is not None
    if n:
        _jit().ray_box_fwd[(-(-n // RAYS_BLOCK),)](
            rays_o.detach().contiguous(), rays_d.detach().contiguous(), box.detach().to(rays_o).contiguous(),
            near.detach().contiguous() if clip else t_near, far.detach().contiguous() if clip else t_far,
            t_near, t_far, hit, n, CLIP=clip, BLOCK=RAYS_BLOCK, **LAUNCH)
    return t_near, t_far, hit.view(torch.bool)


def pixel_rays_triton(flat: Tensor, offsets: Tensor, widths: Tensor, c2w: Tensor, intrinsics: Tensor,
                      box: Tensor | None, near_far: Tensor | None) -> tuple[Tensor, ...]:
    """:meth:`recon.nerf.fitting.RayBatcher._rays_torch` in one kernel: flat pixel indices (B,) into photos stacked
    from ``offsets`` (photos + 1,) on, ``widths`` (photos,) pixels a row, camera-to-world ``c2w`` (photos, 3, 4) and
    ``intrinsics`` (photos, 4) float32 -> origins, unit directions (B, 3), near, far (B,) (where the rays meet
    ``box`` (2, 3), else their photo's ``near_far`` (photos, 2)), hit (B,) bool, each ray's photo (B,) long."""
    if (box is None) == (near_far is None):
        raise ValueError("give exactly one of box and near_far")
    b, photos, device = flat.shape[0], c2w.shape[0], c2w.device
    o, d = torch.empty(b, 3, device=device), torch.empty(b, 3, device=device)
    near, far = torch.empty(b, device=device), torch.empty(b, device=device)
    hit = torch.empty(b, dtype=torch.int8, device=device)
    img = torch.empty(b, dtype=torch.int64, device=device)
    if b:
        bounds = box if box is not None else near_far
        _jit().pixel_rays_fwd[(-(-b // RAYS_BLOCK),)](
            flat.to(torch.int64).contiguous(), offsets.to(torch.int64).contiguous(),
            widths.to(torch.int64).contiguous(), c2w[:, :3, :4].contiguous(), intrinsics.contiguous(),
            bounds.contiguous(), bounds.contiguous(), o, d, near, far, hit, img, b, photos, HAS_BOX=box is not None,
            BLOCK=RAYS_BLOCK, **LAUNCH)
    return o, d, near, far, hit.view(torch.bool), img

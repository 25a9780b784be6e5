"""Grid encodings in plain PyTorch: dense voxel grid, TensoRF-VM planes + lines, multiresolution hash.

All encoders take points already mapped into the unit cube, ``x01: (M, 3)`` in [0, 1] (the caller maps its
scene box, or the contracted [-2, 2]^3 box, onto it), and return features ``(M, C)``. Interpolation is
"align corners": a grid of ``R`` vertices per side puts vertex 0 at 0 and vertex ``R - 1`` at 1.

Every encoder stores its values as a channels-last table ``(rows, C)`` and interpolates with one call of
:func:`gather_interp` (``F.embedding_bag`` forward, ``index_add_`` backward), except scalar dense grids,
which use ``F.grid_sample`` on a view of the same storage: no custom CUDA, runs anywhere, CPU and GPU. (Dense and
hash grids read on a CPU in C where no point gradient is needed, :mod:`recon.nerf.native`; on CUDA in a Triton
kernel when the fast model's ``kernels`` asks, :mod:`recon.nerf.kernels`.)
Plain reference implementations (:func:`trilinear_reference`, :func:`hash_reference`) are slow
per-corner loops that the tests compare the fast path against.

Why each encoder reads the way it does (ratios measured back to back on a CPU; `recon bench --profile` measures
them on yours):
* Scalar dense grids read through ``F.grid_sample``, which is faster than the gather for one channel; feature
  grids (many channels) use the gather, whose channels-last rows are read and written contiguously.
  ``F.embedding_bag``'s own (sort-based) backward is slow for millions of rows, so the gather uses ``index_add_``.
* Corner indices and weights are built as per-axis outer products, not (M, 8, 3) temporaries (several times faster).
* A big dense grid pays per *parameter* every step (zeroing its gradient, the Adam update): at the small color
  batches of NeRF training that dominates, which is why the VM factorization can fit faster in wall time despite
  a higher per-point cost. The hash encoding learns the most per step, but its 16 levels x 8 corners of integer
  work cost several times a dense lookup on a CPU.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.graph import increment_version

from recon.nerf.kernels import hash_levels_triton, trilinear_levels_triton, use_triton
from recon.nerf.masked_adam import touched_blocks
from recon.nerf.model_config import hash_level_layout
from recon.nerf.native import (hash_backward_native, hash_features_native, native_grid_ok,
                               trilinear_backward_levels_native, trilinear_backward_native, trilinear_features_native)

_PRIMES = (1, 2654435761, 805459861)  # instant-ngp spatial hash (Teschner et al. 2003 / Müller et al. 2022)


def _corner_offsets(dims: int, device: torch.device) -> Tensor:
    """Binary corner offsets of a unit cell: (2**dims, dims) long, corner c has bit d = offset along axis d."""
    c = torch.arange(2**dims, device=device)
    return torch.stack([(c >> (dims - 1 - d)) & 1 for d in range(dims)], dim=-1)


def axis_cells(x01: Tensor, res: int) -> tuple[Tensor, Tensor]:
    """Lower vertex index and fraction per axis of points in a grid of ``res`` vertices per side.

    x01: (M, D) in [0, 1] (clamped). Returns i0 (M, D) long in [0, res - 2] and frac (M, D) in [0, 1].
    The cell index is clamped to res - 2 so a point on the far face gets frac 1 on vertex res - 1 and
    never reads past it.
    """
    if res < 2:
        raise ValueError(f"a grid needs at least 2 vertices per side, got res={res}")
    pos = x01.clamp(0.0, 1.0) * (res - 1)
    # NaN (a diverged network upstream) reads cell 0 and keeps frac NaN: the output is NaN for the trainer's
    # guard to name, instead of an int64-min index
    i0 = pos.detach().nan_to_num(0.0).floor().clamp_(0, res - 2)
    return i0.long(), pos - i0


def corner_weights(frac: Tensor) -> Tensor:
    """(Bi/tri)linear corner weights (M, 2**D) from per-axis fractions (M, D); corner bit d = axis d high.

    Built as an outer product of per-axis (1 - f, f) pairs: a few small ops instead of (M, 8, 3) temporaries.
    """
    pairs = torch.stack((1.0 - frac, frac), dim=-1)  # (M, D, 2)
    w = pairs[:, 0]
    for d in range(1, frac.shape[-1]):
        w = (w[:, :, None] * pairs[:, d, None, :]).reshape(frac.shape[0], 2 ** (d + 1))
    return w


def corner_rows(i0: Tensor, res: int) -> Tensor:
    """Row-major flat vertex indices (M, 2**D) of the corners of the cells with lower vertex i0 (M, D).

    Row of vertex (i_0, ..., i_{D-1}) = sum_d i_d * res**(D - 1 - d); corner order as in corner_weights.
    """
    dims = i0.shape[-1]
    strides = res ** torch.arange(dims - 1, -1, -1, device=i0.device)
    base = (i0 * strides).sum(-1)
    return base[:, None] + (_corner_offsets(dims, i0.device) * strides).sum(-1)


class _GatherInterp(torch.autograd.Function):
    """out[b] = sum_k w[b, k] * table[idx[b, k]]; backward scatters with index_add_ (fast on CPU)."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, w: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(table, idx, w)
        return F.embedding_bag(idx, table, per_sample_weights=w.to(table.dtype), mode="sum")

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor | None, None, Tensor | None]:  # type: ignore[override]
        table, idx, w = ctx.saved_tensors
        g_table = g_w = None
        if ctx.needs_input_grad[0]:
            contrib = (g[:, None, :] * w[..., None].to(g.dtype)).reshape(-1, table.shape[1])
            g_table = torch.zeros_like(table).index_add_(0, idx.reshape(-1), contrib)
        if ctx.needs_input_grad[2]:
            g_w = (table[idx] * g[:, None, :]).sum(-1).to(w.dtype)
        return g_table, None, g_w


def gather_interp(table: Tensor, idx: Tensor, w: Tensor) -> Tensor:
    """Weighted sum of table rows: table (T, C), idx (B, K) long in [0, T), w (B, K) -> (B, C).

    Differentiable in ``table`` and in ``w`` (so in the query points, for normals).
    """
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= table.shape[0]):
        raise IndexError(f"grid index out of range [0, {table.shape[0]}): min {int(idx.min())}, max {int(idx.max())}")
    return _GatherInterp.apply(table, idx, w)


def grid_sample_coords(x01: Tensor, dtype: torch.dtype) -> Tensor:
    """Points (M, 3) in [0, 1] as ``F.grid_sample``'s (1, 1, 1, M, 3) grid for a table indexed [ix, iy, iz]
    (align_corners: -1..1, axes reversed). Shared by the levels of a grid, which see the same points."""
    return (x01.clamp(0.0, 1.0) * 2.0 - 1.0).flip(-1).view(1, 1, 1, -1, 3).to(dtype)


class _NativeRead(torch.autograd.Function):
    """A dense or hash grid's read in C (:mod:`recon.nerf.native`), differentiable in the table only (the torch
    paths stay for points that need a gradient: normals, pose refinement).

    The backward scatters straight into the table's ``.grad``: into the gradient already there (accumulating, as
    autograd would), or, when there is none (optimizers drop gradients between steps), into a buffer the grid keeps
    and hands over as ``.grad``. A fresh zeroed gradient per step (42 MB for the fast preset's feature grid) cost its
    page faults on every step; autograd would copy a returned buffer that the grid still holds. It flags the blocks
    it adds into (:class:`recon.nerf.masked_adam.TouchedBlocks`) while the flags speak for that gradient."""

    @staticmethod
    def forward(ctx, table: Tensor, x01: Tensor, grid: "DenseGrid | HashGrid") -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x01)
        ctx.grid = grid
        return grid._native_read(x01)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[None, None, None]:  # type: ignore[override]
        (x01,) = ctx.saved_tensors
        add_native_grad(ctx.grid, x01, g)
        return None, None, None


def add_native_grad(grid: "DenseGrid | HashGrid", x01: Tensor, g: Tensor) -> None:
    """Add the gradient ``g`` (M, C) of the grid's read at x01 (M, 3) to its table's ``.grad``, in C, as
    :class:`_NativeRead` describes (the backward of every native read of a table, wherever its forward ran)."""
    out, flags, finish = _native_grad_target(grid)
    grid._native_add_grad(x01, g, out, flags)
    finish()


def add_native_grads(levels: "list[DenseGrid]", x01: Tensor, g: Tensor) -> None:
    """:func:`add_native_grad` for one-channel dense grids read at the same points with the same gradient (the
    density levels): a level a thread in one C call where the library can (`trilinear_backward_levels_native`), else
    a level at a time. The same sums either way."""
    targets = [_native_grad_target(level) for level in levels]
    if all(isinstance(level, DenseGrid) and level.channels == 1 for level in levels) and \
            trilinear_backward_levels_native(x01, g, [level.res for level in levels], [t[0] for t in targets],
                                             [t[1] for t in targets]):
        for _, _, finish in targets:
            finish()
        return
    for level, (out, flags, finish) in zip(levels, targets, strict=True):
        level._native_add_grad(x01, g, out, flags)
        finish()


def _native_grad_target(grid: "DenseGrid | HashGrid") -> tuple[Tensor, Tensor | None, Callable[[], None]]:
    """Where a C backward adds the grid's gradient: (the tensor, its touched-block flags or None, what to call after
    the add). The table's own ``.grad`` where it can take it, flagged while the flags vouch for it; else the grid's
    zeroed buffer, then given to (or added into) ``.grad``."""
    table = grid.table
    held, touched = table.grad, touched_blocks(table)
    if held is not None and held.is_contiguous() and held.dtype == torch.float32 and held.shape == table.shape:
        flagging = touched.valid_for(held)

        def held_done() -> None:
            increment_version(held)  # written through a pointer: say so (MaskedAdam keeps only unchanged zero grads)
            if flagging:
                touched.vouch(held)

        return held, touched.flags if flagging else None, held_done
    buffer = grid._grad_buffer
    if buffer is None or buffer.shape != table.shape or buffer is held:
        buffer = torch.empty_like(table)
    grid._grad_buffer = buffer
    touched.reset(buffer.zero_())  # vouched for: only the C add writes into it, and flags it

    def buffer_done() -> None:
        table.grad = buffer if held is None else held + buffer

    return buffer, touched.flags, buffer_done


def _read_in_c(grid: "DenseGrid | HashGrid", x01: Tensor) -> Tensor | None:
    """The grid's read in C where no point gradient is needed and the library takes the tensors (through
    :class:`_NativeRead` when the table trains), else None: the caller reads in torch."""
    if x01.requires_grad or not native_grid_ok(x01, grid.table):
        return None
    if torch.is_grad_enabled() and grid.table.requires_grad:
        return _NativeRead.apply(grid.table, x01, grid)
    return grid._native_read(x01)


class DenseGrid(nn.Module):
    """Dense voxel grid (DVGO / Plenoxels style) of ``res`` vertices per side, trilinear interpolation.

    Parameters: res**3 * channels. Table row of vertex (i, j, k) along (x, y, z) is (i * res + j) * res + k.
    """

    def __init__(self, res: int, channels: int, init_std: float = 0.0) -> None:
        super().__init__()
        self.res, self.channels = int(res), int(channels)
        self.table = nn.Parameter(torch.randn(self.res**3, self.channels) * init_std)
        self._grad_buffer: Tensor | None = None  # see _NativeRead
        # train.fast.kernels, set by the fast model: "triton" (or "auto", once measured) reads CUDA points in a Triton
        # kernel (recon.nerf.kernels.use_triton decides); "torch" never
        self.kernels = "torch"

    @property
    def out_dim(self) -> int:
        return self.channels

    def volume(self) -> Tensor:
        """The grid as (res, res, res, C) indexed [ix, iy, iz] (a view of the parameter)."""
        return self.table.view(self.res, self.res, self.res, self.channels)

    def forward(self, x01: Tensor) -> Tensor:
        """x01: (M, 3) in [0, 1] -> (M, C): in Triton on CUDA when asked, in C where no point gradient is needed,
        else in torch (:func:`trilinear_torch`)."""
        if self.kernels != "torch" and not x01.requires_grad and use_triton(self.kernels, x01, self.table):
            return trilinear_levels_triton(x01, [self.table], [self.res])  # CUDA only: the CPU takes the paths below
        native = _read_in_c(self, x01)
        return native if native is not None else trilinear_torch(x01, self.table, self.res)

    def _native_read(self, x01: Tensor) -> Tensor:
        return trilinear_features_native(x01, self.table, self.res)

    def _native_add_grad(self, x01: Tensor, g: Tensor, out: Tensor, touched: Tensor | None) -> None:
        trilinear_backward_native(x01, g, self.res, out=out, accumulate=True, touched=touched)

    def sample_scalar(self, g: Tensor) -> Tensor:
        """A one-channel grid at points already in ``grid_sample``'s layout (:func:`grid_sample_coords`) -> (M, 1)."""
        r = self.res
        return F.grid_sample(self.table.view(1, 1, r, r, r), g, mode="bilinear", align_corners=True).view(-1, 1)

    def tv_loss(self, n: int = 65536) -> Tensor:
        """Total variation (mean squared forward difference) on ``n`` random vertices: cheap, unbiased."""
        r = self.res
        ijk = torch.randint(0, r - 1, (n, 3), device=self.table.device)
        base = (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]
        v0 = self.table[base]
        return sum(((self.table[base + s] - v0) ** 2).mean() for s in (r * r, r, 1)) / 3.0


@torch.no_grad()
def resample_dense(grid: DenseGrid, old_from_new: Callable[[Tensor], Tensor], chunk: int = 1 << 18) -> None:
    """Re-sample a dense grid in place after its box moved: vertex ``u`` of the new grid takes the old
    grid's value at ``old_from_new(u)`` (unit-cube coordinates, (M, 3) -> (M, 3)). Shapes are unchanged,
    so optimizers and checkpoints stay valid; values outside the old box take the clamped border value.
    """
    r = grid.res
    lin = torch.linspace(0.0, 1.0, r, device=grid.table.device)
    new_table = torch.empty_like(grid.table)
    for s in range(0, r**3, chunk):
        idx = torch.arange(s, min(s + chunk, r**3), device=lin.device)
        u = torch.stack((lin[idx // (r * r)], lin[(idx // r) % r], lin[idx % r]), dim=-1)
        new_table[s : s + idx.shape[0]] = grid(old_from_new(u)).to(new_table.dtype)
    grid.table.copy_(new_table)


def level_resolutions(res: int, levels: int, min_res: int = 16) -> list[int]:
    """Vertices per side of a :class:`MultiDenseGrid`'s levels, coarsest first: the finest ``res``, each level half
    the one before (in cells), none under ``min_res``; levels that would coincide are one."""
    return sorted({max(min_res, int(round((res - 1) / 2**k)) + 1) for k in range(levels)})


class MultiDenseGrid(nn.Module):
    """Sum of dense grids at several resolutions (finest ``res``, each level half the previous).

    The coarse levels see many samples per vertex, so low frequencies are learned in a few steps while
    the fine level adds detail: the same role as DVGO's coarse stage or TensoRF's upsampling schedule,
    with fixed parameter shapes (an optimizer made once stays valid).
    """

    def __init__(self, res: int, channels: int, levels: int = 3, min_res: int = 16, init_std: float = 0.0) -> None:
        super().__init__()
        self.resolutions = resolutions = level_resolutions(res, levels, min_res)
        self.channels = int(channels)
        self.grids = nn.ModuleList(DenseGrid(r, channels, init_std) for r in resolutions)
        self.kernels = "torch"  # as DenseGrid.kernels; the Triton kernel reads every level in one pass over the points

    @property
    def out_dim(self) -> int:
        return self.channels

    def forward(self, x01: Tensor) -> Tensor:
        """x01: (M, 3) in [0, 1] -> (M, C), the sum over levels."""
        tables = [g.table for g in self.grids] if self.kernels != "torch" else []
        if tables and not x01.requires_grad and use_triton(self.kernels, x01, *tables):
            return trilinear_levels_triton(x01, tables, self.resolutions)  # CUDA only: the CPU takes the paths below
        native = not x01.requires_grad and native_grid_ok(x01, self.grids[0].table)  # then each level reads in C
        if self.channels == 1 and not native:  # one coordinate transform for every level
            g = grid_sample_coords(x01, self.grids[0].table.dtype)
            out = self.grids[0].sample_scalar(g)
            for grid in self.grids[1:]:
                out = out + grid.sample_scalar(g)
            return out
        out = self.grids[0](x01)
        for g in self.grids[1:]:
            out = out + g(x01)
        return out

    def tv_loss(self, n: int = 65536) -> Tensor:
        """Sum of the levels' sampled TV losses."""
        return sum(g.tv_loss(n) for g in self.grids)


def trilinear_torch(x01: Tensor, table: Tensor, r: int) -> Tensor:
    """The trilinear read of one dense table ``(r³, C)`` at x01 (M, 3) in [0, 1] -> (M, C), in torch. One channel goes
    through ``F.grid_sample`` on a view of the same storage (its fused kernel beats building corner indices for a
    scalar grid); more channels use the channels-last gather, whose backward beats grid_sample's at 12 channels."""
    if table.shape[1] == 1:
        g = grid_sample_coords(x01, table.dtype)
        return F.grid_sample(table.view(1, 1, r, r, r), g, mode="bilinear", align_corners=True).view(-1, 1)
    i0, frac = axis_cells(x01, r)
    return gather_interp(table, corner_rows(i0, r), corner_weights(frac))


def trilinear_levels_torch(x01: Tensor, tables: list[Tensor], resolutions: list[int]) -> Tensor:
    """Sum over levels of the trilinear read of table ``(R³, C)`` at x01 (M, 3) -> (M, C), as :class:`DenseGrid` reads
    in torch (one channel: ``grid_sample``; more: the gather): the reference of
    :func:`recon.nerf.kernels.trilinear_levels_triton`, which reads them all in one pass on CUDA."""
    out = None
    for table, r in zip(tables, resolutions, strict=True):
        level = trilinear_torch(x01, table, r)
        out = level if out is None else out + level
    assert out is not None
    return out


class VMGrid(nn.Module):
    """TensoRF vector-matrix factorization (Chen et al. 2022): three planes times three lines.

    f(x) = concat_a( P_a(x_b, x_c) * L_a(x_a) ) over a = x, y, z with (b, c) the other two axes; each
    factor has ``components`` channels, so the output has 3 * components channels. Parameters:
    3 * (res**2 + res) * components (e.g. 128 vertices, 16 components: 0.8 M).
    """

    def __init__(self, res: int, components: int, init_std: float = 0.1) -> None:
        super().__init__()
        self.res, self.components = int(res), int(components)
        r, c = self.res, self.components
        self.planes = nn.Parameter(torch.randn(3, r * r, c) * init_std)
        self.lines = nn.Parameter(torch.randn(3, r, c) * init_std)

    @property
    def out_dim(self) -> int:
        return 3 * self.components

    def forward(self, x01: Tensor) -> Tensor:
        """x01: (M, 3) in [0, 1] -> (M, 3 * components)."""
        r = self.res
        outs = []
        for a, (b, c) in enumerate(((1, 2), (0, 2), (0, 1))):
            i0, frac = axis_cells(x01[:, (b, c)], r)
            p = gather_interp(self.planes[a], corner_rows(i0, r), corner_weights(frac))
            i0, frac = axis_cells(x01[:, a : a + 1], r)
            ln = gather_interp(self.lines[a], corner_rows(i0, r), corner_weights(frac))
            outs.append(p * ln)
        return torch.cat(outs, dim=-1)

    def tv_loss(self, n: int = 0) -> Tensor:
        """Total variation of the planes and lines (mean squared forward difference)."""
        r, c = self.res, self.components
        pl = self.planes.view(3, r, r, c)
        return ((pl[:, 1:] - pl[:, :-1]) ** 2).mean() + ((pl[:, :, 1:] - pl[:, :, :-1]) ** 2).mean() + (
            (self.lines[:, 1:] - self.lines[:, :-1]) ** 2
        ).mean()


class HashGrid(nn.Module):
    """Multiresolution hash encoding (Müller et al. 2022) in plain torch: levels x features output channels.

    All levels live in one table (sum of rows, features) so one gather serves every level. Hash:
    (i * 1) xor (j * 2654435761) xor (k * 805459861) mod 2**log2_table, on non-negative int64 so the row
    is always in range, including at the box faces and corners.
    """

    def __init__(
        self,
        levels: int = 16,
        features: int = 2,
        log2_table: int = 17,
        base_res: int = 16,
        max_res: int = 512,
        init_scale: float = 1e-4,
    ) -> None:
        super().__init__()
        self.levels, self.features, self.log2_table = int(levels), int(features), int(log2_table)
        self.verts, rows, self.hashed = hash_level_layout(levels, base_res, max_res, log2_table)
        offsets = torch.tensor([0] + rows).cumsum(0)
        # per level (3, L) int64: vertices per side, first row, hashed (1) or dense (0); the C read takes it whole
        self.register_buffer("layout", torch.stack((torch.tensor(self.verts), offsets[:-1],
                                                    torch.tensor(self.hashed, dtype=torch.int64))), persistent=False)
        self.table = nn.Parameter((torch.rand(int(offsets[-1]), self.features) * 2 - 1) * init_scale)
        self.kernels = "torch"  # as DenseGrid.kernels
        self._grad_buffer: Tensor | None = None  # see _NativeRead

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    @property
    def verts_t(self) -> Tensor:
        """(L,) vertices per side of each level."""
        return self.layout[0]

    @property
    def offsets(self) -> Tensor:
        """(L,) each level's first row in the table."""
        return self.layout[1]

    @property
    def hashed_t(self) -> Tensor:
        """(L,) 1 where a level is hashed, 0 where it is dense-indexed."""
        return self.layout[2]

    def level_rows(self, i0: Tensor, level: int) -> Tensor:
        """Table rows (M, 8) of the cell corners with lower vertex i0 (M, 3) at one level (offset included).

        The hash xor-s per-axis terms, so it is built from three (M, 2) tensors by broadcasting.
        """
        n = self.verts[level]
        if self.hashed[level]:
            m = i0.shape[0]
            ax = [torch.stack((i0[:, d], i0[:, d] + 1), -1) * _PRIMES[d] for d in range(3)]
            h = ax[0][:, :, None, None] ^ ax[1][:, None, :, None] ^ ax[2][:, None, None, :]
            local = h.reshape(m, 8) & (2**self.log2_table - 1)
        else:
            local = corner_rows(i0, n)
        return local + self.offsets[level]

    def forward(self, x01: Tensor) -> Tensor:
        """x01: (M, 3) in [0, 1] -> (M, levels * features), level-major: in one Triton kernel on CUDA when asked
        (:func:`recon.nerf.kernels.hash_levels_triton`), in C where no point gradient is needed, else in torch (the
        reference)."""
        if (self.kernels != "torch" and not x01.requires_grad and use_triton(self.kernels, x01, self.table)
                and hash_kernel_check(str(x01.device), self.levels, self.features)[0]):
            return hash_levels_triton(x01, self.table, self.verts_t, self.offsets, self.hashed_t, self.log2_table)
        native = _read_in_c(self, x01)
        return native if native is not None else self.read_torch(x01)

    def read_torch(self, x01: Tensor) -> Tensor:
        """The forward in torch: the reference the C and Triton reads are tested against."""
        m = x01.shape[0]
        idxs, ws = [], []
        for lv in range(self.levels):
            i0, frac = axis_cells(x01, self.verts[lv])
            idxs.append(self.level_rows(i0, lv))
            ws.append(corner_weights(frac))
        idx = torch.stack(idxs, dim=1).reshape(m * self.levels, 8)
        w = torch.stack(ws, dim=1).reshape(m * self.levels, 8)
        return gather_interp(self.table, idx, w).reshape(m, self.levels * self.features)

    def _native_read(self, x01: Tensor) -> Tensor:
        return hash_features_native(x01, self.table, self.layout, self.log2_table)

    def _native_add_grad(self, x01: Tensor, g: Tensor, out: Tensor, touched: Tensor | None) -> None:
        hash_backward_native(x01, g, self.layout, self.log2_table, out, touched)

    def tv_loss(self, n: int = 0) -> Tensor:
        """Hash tables have no spatial neighbourhood: no TV term (weight decay is the usual substitute)."""
        return self.table.new_zeros(())


@lru_cache(maxsize=8)
def hash_kernel_check(device: str, levels: int = 4, features: int = 2) -> tuple[bool, str]:
    """(does the hash grid's Triton kernel agree with its torch read on ``device``?, why, in one sentence): a probe
    of hashed and dense levels, forward and table gradient, once per device and grid shape; where the kernel fails
    to compile or disagrees, hash grids read in torch there (slower, the same values) and the train stage says so.
    ``levels``, ``features``: the grid's own, so the probe compiles (and checks) the very kernel training launches
    (the kernel is specialized on both) instead of a second one."""
    probe = HashGrid(levels=levels, features=features, log2_table=10, base_res=4, max_res=40,
                     init_scale=1.0).to(device)
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(0)).to(device)
    try:
        fused = hash_levels_triton(x, probe.table, probe.verts_t, probe.offsets, probe.hashed_t, probe.log2_table)
        (g_fused,) = torch.autograd.grad(fused.square().sum(), probe.table)
    except Exception as exc:  # a compiler or driver that cannot build it: the torch read serves
        first = str(exc).splitlines()[0][:160] if str(exc) else ""
        return False, f"hash grid: read in torch (its Triton kernel failed on {device}: {type(exc).__name__}: {first})"
    reference = probe.read_torch(x)
    (g_ref,) = torch.autograd.grad(reference.square().sum(), probe.table)
    error = max(float((fused - reference).detach().abs().max()), float((g_fused - g_ref).abs().max()))
    if not error <= 1e-3:
        return False, f"hash grid: read in torch (its Triton kernel differed from the torch read by {error:.3g})"
    return True, f"hash grid: read in one Triton kernel (a probe agreed with the torch read within {error:.1g})"


# ----------------------------------------------------------------------------------------------------------
# Plain references: per-corner loops with independent index arithmetic, for the tests.


def trilinear_reference(volume: Tensor, x01: Tensor) -> Tensor:
    """Naive trilinear interpolation: volume (R, R, R, C) indexed [ix, iy, iz], x01 (M, 3) -> (M, C)."""
    r = volume.shape[0]
    out = torch.zeros(x01.shape[0], volume.shape[-1], dtype=volume.dtype, device=volume.device)
    pos = x01.clamp(0, 1) * (r - 1)
    base = torch.minimum(pos.floor(), torch.full_like(pos, r - 2))
    t = pos - base
    b = base.long()
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                wx = t[:, 0] if dx else 1 - t[:, 0]
                wy = t[:, 1] if dy else 1 - t[:, 1]
                wz = t[:, 2] if dz else 1 - t[:, 2]
                out += (wx * wy * wz)[:, None] * volume[b[:, 0] + dx, b[:, 1] + dy, b[:, 2] + dz]
    return out


def hash_reference(grid: HashGrid, x01: Tensor) -> Tensor:
    """Loop-over-levels-and-corners hash encoding with the hash done in Python integers (mod 2**64)."""
    table = grid.table.detach()
    out = []
    mask = 2**grid.log2_table - 1
    for lv, n in enumerate(grid.verts):
        off = int(grid.offsets[lv])
        vol_feat = torch.zeros(x01.shape[0], grid.features, dtype=table.dtype)
        for p in range(x01.shape[0]):
            pos = [min(max(float(v), 0.0), 1.0) * (n - 1) for v in x01[p]]
            base = [min(math.floor(v), n - 2) for v in pos]
            t = [v - b for v, b in zip(pos, base)]
            for dx in (0, 1):
                for dy in (0, 1):
                    for dz in (0, 1):
                        i, j, k = base[0] + dx, base[1] + dy, base[2] + dz
                        if grid.hashed[lv]:
                            row = ((i * _PRIMES[0]) ^ (j * _PRIMES[1]) ^ (k * _PRIMES[2])) & mask
                        else:
                            row = (i * n + j) * n + k
                        w = (t[0] if dx else 1 - t[0]) * (t[1] if dy else 1 - t[1]) * (t[2] if dz else 1 - t[2])
                        vol_feat[p] += w * table[off + row]
        out.append(vol_feat)
    return torch.cat(out, dim=-1)

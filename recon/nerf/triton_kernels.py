"""The @triton.jit kernels behind :mod:`recon.nerf.kernels` (which launches them, wraps them as autograd functions
and keeps their torch references). Importing this module imports triton; nothing else in recon does.

Layouts (float32, contiguous):
* packed samples: ``sigma, delta, t (M,)``, ray ``r``'s samples at ``offsets[r]:offsets[r + 1]`` (``offsets (N + 1,)``
  int64, from sorted ray indices);
* grids: a level's table ``(R³, C)``, row of vertex ``(i, j, k)`` = ``(i * R + j) * R + k``; points ``x01 (M, 3)`` in
  the unit cube, "align corners" (vertex 0 at 0, vertex R - 1 at 1), as :class:`recon.nerf.grid.DenseGrid`.

min, max and clamp propagate NaN (a diverged network) as torch's clamp does, so the trainer's guard sees it.
Sizes that change every step (a batch's sample count) are not specialized on (``do_not_specialize``): triton
would otherwise compile a second variant the first time one is a multiple of 16, inside a time budget.
Under ``TRITON_INTERPRET=1`` (set before triton is imported) the same kernels run on CPU tensors with numpy: that
is how tests/test_triton_kernels.py checks them on a machine without a GPU.
"""
from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def _optical_thickness(sigma, delta, SIGMA_MAX: tl.constexpr, TAU_MAX: tl.constexpr):
    """tau = clamp(clamp(sigma, 0, SIGMA_MAX) * max(delta, 0), 0, TAU_MAX): render.optical_thickness."""
    s = tl.clamp(sigma, 0.0, SIGMA_MAX, propagate_nan=tl.PropagateNan.ALL)
    d = tl.maximum(delta, 0.0, propagate_nan=tl.PropagateNan.ALL)
    return tl.clamp(s * d, 0.0, TAU_MAX, propagate_nan=tl.PropagateNan.ALL)


@triton.jit
def _alpha(tau):
    """1 - exp(-tau) = -expm1(-tau) for tau >= 0: its Taylor series below 0.5 (1 - exp would cancel there; triton
    has no expm1 that runs both compiled and interpreted), 1 - exp(-tau) above. Relative error ~1e-7."""
    series = tau * (1.0 - tau * 0.5 * (1.0 - tau * (1.0 / 3.0) * (1.0 - tau * 0.25 * (1.0 - tau * 0.2 * (
        1.0 - tau * (1.0 / 6.0) * (1.0 - tau * (1.0 / 7.0) * (1.0 - tau * 0.125)))))))
    return tl.where(tau < 0.5, series, 1.0 - tl.exp(-tau))


# ----------------------------------------------------------------------------- packed compositing
@triton.jit
def composite_fwd(sigma, delta, t, offsets, weights, trans, opacity, depth,
                  SIGMA_MAX: tl.constexpr, TAU_MAX: tl.constexpr, BLOCK: tl.constexpr):
    """One program per ray, its samples front to back in chunks of BLOCK: T_i = exp(-sum_{j<i} tau_j),
    w_i = T_i * alpha_i; the ray's opacity sum w_i and depth sum w_i t_i.

    The exclusive sum is a cumulative sum of the previous samples' taus (loaded shifted by one), not an inclusive
    sum minus tau_i: after an opaque sample that subtraction would lose the earlier taus to rounding."""
    ray = tl.program_id(0)
    start = tl.load(offsets + ray)
    end = tl.load(offsets + ray + 1)
    carry = tl.zeros([], dtype=tl.float32)  # optical depth of the ray's samples before this chunk
    op = tl.zeros([], dtype=tl.float32)
    dep = tl.zeros([], dtype=tl.float32)
    for s in range(start, end, BLOCK):
        i = s + tl.arange(0, BLOCK)
        m = i < end
        tau = _optical_thickness(tl.load(sigma + i, mask=m, other=0.0), tl.load(delta + i, mask=m, other=0.0),
                                 SIGMA_MAX, TAU_MAX)
        prev = m & (i > s)
        tau_prev = _optical_thickness(tl.load(sigma + i - 1, mask=prev, other=0.0),
                                      tl.load(delta + i - 1, mask=prev, other=0.0), SIGMA_MAX, TAU_MAX)
        tr = tl.exp(-(carry + tl.cumsum(tau_prev, 0)))
        w = tr * _alpha(tau)
        tl.store(trans + i, tr, mask=m)
        tl.store(weights + i, w, mask=m)
        carry += tl.sum(tau, 0)
        w = tl.where(m, w, 0.0)
        op += tl.sum(w, 0)
        dep += tl.sum(w * tl.load(t + i, mask=m, other=0.0), 0)
    tl.store(opacity + ray, op)
    tl.store(depth + ray, dep)


@triton.jit
def composite_bwd(sigma, delta, t, offsets, weights, trans, g_w, g_trans, g_op, g_dep, g_sigma, g_delta, g_t,
                  SIGMA_MAX: tl.constexpr, TAU_MAX: tl.constexpr, BLOCK: tl.constexpr,
                  HAS_GW: tl.constexpr, HAS_GT: tl.constexpr):
    """Gradients of composite_fwd, one program per ray, its samples back to front.

    With G_i = dL/dw_i + dL/dopacity + dL/ddepth * t_i (the dL/dw each sample gets in all) and
    x_i = G_i w_i + dL/dT_i T_i (dw_i/dtau_k = -w_i and dT_i/dtau_k = -T_i for every earlier sample k):
        dL/dtau_k = G_k T_k exp(-tau_k) - sum_{i > k} x_i
    then through the clamps of the optical thickness as torch's clamp passes gradients (inside its closed range).
    The later samples' sum is a reverse cumulative sum of x loaded shifted by one (no subtraction)."""
    ray = tl.program_id(0)
    start = tl.load(offsets + ray)
    end = tl.load(offsets + ray + 1)
    gop = tl.load(g_op + ray)
    gdep = tl.load(g_dep + ray)
    carry = tl.zeros([], dtype=tl.float32)  # sum of x over the ray's samples after this chunk
    chunks = tl.cdiv(end - start, BLOCK)
    for c in range(0, chunks):
        s = start + (chunks - 1 - c) * BLOCK
        i = s + tl.arange(0, BLOCK)
        m = i < end
        j = i + 1
        mj = j < end
        g_next = gop + gdep * tl.load(t + j, mask=mj, other=0.0)
        if HAS_GW:
            g_next += tl.load(g_w + j, mask=mj, other=0.0)
        x_next = g_next * tl.load(weights + j, mask=mj, other=0.0)
        if HAS_GT:
            x_next += tl.load(g_trans + j, mask=mj, other=0.0) * tl.load(trans + j, mask=mj, other=0.0)
        later = carry + tl.cumsum(x_next, 0, reverse=True)
        carry += tl.sum(x_next, 0)

        sg = tl.load(sigma + i, mask=m, other=0.0)
        d = tl.load(delta + i, mask=m, other=0.0)
        sc = tl.clamp(sg, 0.0, SIGMA_MAX, propagate_nan=tl.PropagateNan.ALL)
        dc = tl.maximum(d, 0.0, propagate_nan=tl.PropagateNan.ALL)
        prod = sc * dc
        tau = tl.clamp(prod, 0.0, TAU_MAX, propagate_nan=tl.PropagateNan.ALL)
        g = gop + gdep * tl.load(t + i, mask=m, other=0.0)
        if HAS_GW:
            g += tl.load(g_w + i, mask=m, other=0.0)
        g_tau = g * tl.load(trans + i, mask=m, other=0.0) * tl.exp(-tau) - later
        g_tau = tl.where((prod >= 0.0) & (prod <= TAU_MAX), g_tau, 0.0)
        tl.store(g_sigma + i, tl.where((sg >= 0.0) & (sg <= SIGMA_MAX), g_tau * dc, 0.0), mask=m)
        tl.store(g_delta + i, tl.where(d >= 0.0, g_tau * sc, 0.0), mask=m)
        tl.store(g_t + i, gdep * tl.load(weights + i, mask=m, other=0.0), mask=m)


# ----------------------------------------------------------------------------- per-ray weighted sums
@triton.jit
def accumulate_fwd(w, v, offsets, out, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr):
    """out[r, :] = sum of w_i v_i[:] over ray r's samples: one program per ray, a segmented sum (no atomics, the
    same result every run). v (M, C), out (N, C); CP = C rounded up to a power of two."""
    ray = tl.program_id(0)
    start = tl.load(offsets + ray)
    end = tl.load(offsets + ray + 1)
    cols = tl.arange(0, CP)
    cm = cols < C
    acc = tl.zeros([CP], dtype=tl.float32)
    for s in range(start, end, BLOCK):
        i = s + tl.arange(0, BLOCK)
        m = i < end
        wi = tl.load(w + i, mask=m, other=0.0)
        vi = tl.load(v + i[:, None] * C + cols[None, :], mask=m[:, None] & cm[None, :], other=0.0)
        acc += tl.sum(wi[:, None] * vi, 0)
    tl.store(out + ray.to(tl.int64) * C + cols, acc, mask=cm)


@triton.jit(do_not_specialize=["M"])
def accumulate_bwd(w, v, ray_indices, g_out, g_w, g_v, M, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr):
    """dL/dw_i = <dL/dout[r_i], v_i>, dL/dv_i = dL/dout[r_i] w_i: one program per BLOCK samples."""
    i = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    m = i < M
    cols = tl.arange(0, CP)
    mm = m[:, None] & (cols < C)[None, :]
    r = tl.load(ray_indices + i, mask=m, other=0)
    g = tl.load(g_out + r[:, None] * C + cols[None, :], mask=mm, other=0.0)
    vi = tl.load(v + i[:, None] * C + cols[None, :], mask=mm, other=0.0)
    tl.store(g_w + i, tl.sum(g * vi, 1), mask=m)
    tl.store(g_v + i[:, None] * C + cols[None, :], g * tl.load(w + i, mask=m, other=0.0)[:, None], mask=mm)


# ----------------------------------------------------------------------------- the distortion loss
@triton.jit
def _distortion_chunk(w, m, d, m0, i, s, end, carry_w, carry_wm):
    """One chunk of a ray's samples i (from s, masked at end): w, m - m0, d and the exclusive sums W_<i, (wm)_<i, each
    a cumulative sum of the previous samples' values (loaded shifted by one) on top of the earlier chunks'.

    Midpoints are taken from the ray's first one, m0: the loss depends only on their differences, and m W_<i - (wm)_<i
    cancels less in float32 near 0 than far from the origin."""
    mask = i < end
    prev = mask & (i > s)
    wi = tl.load(w + i, mask=mask, other=0.0)
    mi = tl.load(m + i, mask=mask, other=0.0) - m0
    di = tl.load(d + i, mask=mask, other=0.0)
    w_prev = tl.load(w + i - 1, mask=prev, other=0.0)
    wm_prev = w_prev * (tl.load(m + i - 1, mask=prev, other=0.0) - m0)
    return wi, mi, di, carry_w + tl.cumsum(w_prev, 0), carry_wm + tl.cumsum(wm_prev, 0)


@triton.jit
def distortion_fwd(w, m, d, offsets, loss, BLOCK: tl.constexpr):
    """One program per ray: loss_r = sum_i 2 w_i (m_i W_<i - (wm)_<i) + w_i^2 d_i / 3 over its samples (sorted by
    m), the mip-NeRF 360 distortion loss in O(samples)."""
    ray = tl.program_id(0)
    start = tl.load(offsets + ray)
    end = tl.load(offsets + ray + 1)
    m0 = tl.load(m + start, mask=start < end, other=0.0)
    carry_w = tl.zeros([], dtype=tl.float32)
    carry_wm = tl.zeros([], dtype=tl.float32)
    acc = tl.zeros([], dtype=tl.float32)
    for s in range(start, end, BLOCK):
        i = s + tl.arange(0, BLOCK)
        wi, mi, di, before_w, before_wm = _distortion_chunk(w, m, d, m0, i, s, end, carry_w, carry_wm)
        acc += tl.sum(2.0 * wi * (mi * before_w - before_wm) + wi * wi * di * (1.0 / 3.0), 0)
        carry_w += tl.sum(wi, 0)
        carry_wm += tl.sum(wi * mi, 0)
    tl.store(loss + ray, acc)


@triton.jit
def distortion_bwd(w, m, d, offsets, g_loss, g_w, g_m, g_d, BLOCK: tl.constexpr):
    """Gradients of distortion_fwd, one program per ray in two passes (the ray's totals W, WM first). With the later
    samples' sums W_>i = W - W_<i - w_i and (wm)_>i = WM - (wm)_<i - w_i m_i:
        dL/dw_i = 2 (m_i W_<i - (wm)_<i) + 2 ((wm)_>i - m_i W_>i) + 2/3 w_i d_i
        dL/dm_i = 2 w_i (W_<i - W_>i),   dL/dd_i = w_i^2 / 3."""
    ray = tl.program_id(0)
    start = tl.load(offsets + ray)
    end = tl.load(offsets + ray + 1)
    g = tl.load(g_loss + ray)
    m0 = tl.load(m + start, mask=start < end, other=0.0)
    total_w = tl.zeros([], dtype=tl.float32)
    total_wm = tl.zeros([], dtype=tl.float32)
    for s in range(start, end, BLOCK):
        i = s + tl.arange(0, BLOCK)
        mask = i < end
        wi = tl.load(w + i, mask=mask, other=0.0)
        total_w += tl.sum(wi, 0)
        total_wm += tl.sum(wi * (tl.load(m + i, mask=mask, other=0.0) - m0), 0)
    carry_w = tl.zeros([], dtype=tl.float32)
    carry_wm = tl.zeros([], dtype=tl.float32)
    for s in range(start, end, BLOCK):
        i = s + tl.arange(0, BLOCK)
        mask = i < end
        wi, mi, di, before_w, before_wm = _distortion_chunk(w, m, d, m0, i, s, end, carry_w, carry_wm)
        after_w = total_w - before_w - wi
        after_wm = total_wm - before_wm - wi * mi
        gw = 2.0 * (mi * before_w - before_wm) + 2.0 * (after_wm - mi * after_w) + wi * di * (2.0 / 3.0)
        tl.store(g_w + i, g * gw, mask=mask)
        tl.store(g_m + i, g * 2.0 * wi * (before_w - after_w), mask=mask)
        tl.store(g_d + i, g * wi * wi * (1.0 / 3.0), mask=mask)
        carry_w += tl.sum(wi, 0)
        carry_wm += tl.sum(wi * mi, 0)


# ----------------------------------------------------------------------------- dense grids' trilinear reads
@triton.jit
def _program_points(x, M, BLOCK: tl.constexpr):
    """This program's BLOCK point indices (int64), which of them exist (< M), and their coordinates from x (M, 3)."""
    i = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    pm = i < M
    return (i, pm, tl.load(x + i * 3, mask=pm, other=0.0), tl.load(x + i * 3 + 1, mask=pm, other=0.0),
            tl.load(x + i * 3 + 2, mask=pm, other=0.0))


@triton.jit
def _cell(p, R):
    """Lower vertex (int64, in [0, R - 2]) and fraction of unit coordinates p in a grid of R vertices per side, as
    grid.axis_cells: clamped to [0, 1]; a NaN reads vertex 0 with a NaN fraction (the output stays NaN)."""
    pos = tl.clamp(p, 0.0, 1.0, propagate_nan=tl.PropagateNan.ALL) * (R - 1)
    lo = tl.minimum(tl.maximum(tl.floor(tl.where(pos == pos, pos, 0.0)), 0.0), R - 2.0)
    return lo.to(tl.int64), pos - lo


@triton.jit
def _cell3(px, py, pz, R):
    """A point's cell in a grid of R vertices per side: lower vertex per axis, fractions and their complements."""
    ix, fx = _cell(px, R)
    iy, fy = _cell(py, R)
    iz, fz = _cell(pz, R)
    return ix, iy, iz, fx, fy, fz, 1.0 - fx, 1.0 - fy, 1.0 - fz


@triton.jit
def _corner_read(acc, table, R, ix, iy, iz, w, pm, cols, cm, C: tl.constexpr):
    row = (ix * R + iy) * R + iz
    vals = tl.load(table + row[:, None] * C + cols[None, :], mask=pm[:, None] & cm[None, :], other=0.0)
    return acc + w[:, None] * vals


@triton.jit
def _level_read(acc, table, R, px, py, pz, pm, cols, cm, C: tl.constexpr):
    ix, iy, iz, fx, fy, fz, gx, gy, gz = _cell3(px, py, pz, R)
    acc = _corner_read(acc, table, R, ix, iy, iz, gx * gy * gz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix, iy, iz + 1, gx * gy * fz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix, iy + 1, iz, gx * fy * gz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix, iy + 1, iz + 1, gx * fy * fz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix + 1, iy, iz, fx * gy * gz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix + 1, iy, iz + 1, fx * gy * fz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix + 1, iy + 1, iz, fx * fy * gz, pm, cols, cm, C)
    acc = _corner_read(acc, table, R, ix + 1, iy + 1, iz + 1, fx * fy * fz, pm, cols, cm, C)
    return acc


@triton.jit(do_not_specialize=["M"])
def trilinear_fwd(x, out, M, t0, t1, t2, t3, r0, r1, r2, r3,
                  LEVELS: tl.constexpr, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr):
    """out (M, C) = the sum over LEVELS (1..4) grids t0..t3 of r0..r3 vertices per side of their trilinear reads at
    x (M, 3): one pass over the points for every level (the torch path reads each level separately)."""
    i, pm, px, py, pz = _program_points(x, M, BLOCK)
    cols = tl.arange(0, CP)
    cm = cols < C
    acc = tl.zeros([BLOCK, CP], dtype=tl.float32)
    acc = _level_read(acc, t0, r0, px, py, pz, pm, cols, cm, C)
    if LEVELS > 1:
        acc = _level_read(acc, t1, r1, px, py, pz, pm, cols, cm, C)
    if LEVELS > 2:
        acc = _level_read(acc, t2, r2, px, py, pz, pm, cols, cm, C)
    if LEVELS > 3:
        acc = _level_read(acc, t3, r3, px, py, pz, pm, cols, cm, C)
    tl.store(out + i[:, None] * C + cols[None, :], acc, mask=pm[:, None] & cm[None, :])


@triton.jit
def _corner_add(grad, g, R, ix, iy, iz, w, pm, cols, cm, C: tl.constexpr):
    row = (ix * R + iy) * R + iz
    tl.atomic_add(grad + row[:, None] * C + cols[None, :], w[:, None] * g, mask=pm[:, None] & cm[None, :])


@triton.jit
def _level_add(grad, g, R, px, py, pz, pm, cols, cm, C: tl.constexpr):
    ix, iy, iz, fx, fy, fz, gx, gy, gz = _cell3(px, py, pz, R)
    _corner_add(grad, g, R, ix, iy, iz, gx * gy * gz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix, iy, iz + 1, gx * gy * fz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix, iy + 1, iz, gx * fy * gz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix, iy + 1, iz + 1, gx * fy * fz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix + 1, iy, iz, fx * gy * gz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix + 1, iy, iz + 1, fx * gy * fz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix + 1, iy + 1, iz, fx * fy * gz, pm, cols, cm, C)
    _corner_add(grad, g, R, ix + 1, iy + 1, iz + 1, fx * fy * fz, pm, cols, cm, C)


@triton.jit(do_not_specialize=["M"])
def trilinear_bwd(x, g_out, M, g0, g1, g2, g3, r0, r1, r2, r3,
                  LEVELS: tl.constexpr, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr):
    """The tables' gradients of trilinear_fwd: each point's dL/dout times its corner weights, atomically added to
    the 8 corners' rows of every level's gradient g0..g3 (zeroed by the caller)."""
    i, pm, px, py, pz = _program_points(x, M, BLOCK)
    cols = tl.arange(0, CP)
    cm = cols < C
    g = tl.load(g_out + i[:, None] * C + cols[None, :], mask=pm[:, None] & cm[None, :], other=0.0)
    _level_add(g0, g, r0, px, py, pz, pm, cols, cm, C)
    if LEVELS > 1:
        _level_add(g1, g, r1, px, py, pz, pm, cols, cm, C)
    if LEVELS > 2:
        _level_add(g2, g, r2, px, py, pz, pm, cols, cm, C)
    if LEVELS > 3:
        _level_add(g3, g, r3, px, py, pz, pm, cols, cm, C)


# ----------------------------------------------------------------------------- hash grids' reads
@triton.jit
def _hash_row(ix, iy, iz, R, off, hashed, MASK):
    """Table row of vertex (ix, iy, iz) of a level of R vertices per side starting at row ``off``: the dense index,
    or where ``hashed`` the instant-ngp hash (ix · 1 xor iy · 2654435761 xor iz · 805459861) & MASK, as
    grid.HashGrid.level_rows computes it."""
    dense = (ix * R + iy) * R + iz
    h = (ix ^ (iy * 2654435761) ^ (iz * 805459861)) & MASK
    return off + tl.where(hashed != 0, h, dense)


@triton.jit
def _hash_corner_read(acc, table, R, off, hashed, MASK, ix, iy, iz, w, pm, cols, F: tl.constexpr):
    row = _hash_row(ix, iy, iz, R, off, hashed, MASK)
    return acc + w[:, None] * tl.load(table + row[:, None] * F + cols[None, :], mask=pm[:, None], other=0.0)


@triton.jit(do_not_specialize=["M"])
def hash_fwd(x, table, out, res, offsets, hashed, M, MASK, LEVELS: tl.constexpr, F: tl.constexpr,
             BLOCK: tl.constexpr):
    """out (M, LEVELS · F): every level's trilinear read of the one (rows, F) table at x (M, 3), level-major, in one
    pass over the points (the torch path gathers 8 rows per level through index tensors). res, offsets, hashed:
    (LEVELS,) int64 per level: vertices per side, first row, hashed (1) or dense (0)."""
    i, pm, px, py, pz = _program_points(x, M, BLOCK)
    cols = tl.arange(0, F)
    for lv in tl.static_range(LEVELS):
        R, off, hs = tl.load(res + lv), tl.load(offsets + lv), tl.load(hashed + lv)
        ix, iy, iz, fx, fy, fz, gx, gy, gz = _cell3(px, py, pz, R)
        acc = tl.zeros([BLOCK, F], dtype=tl.float32)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix, iy, iz, gx * gy * gz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix, iy, iz + 1, gx * gy * fz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix, iy + 1, iz, gx * fy * gz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix, iy + 1, iz + 1, gx * fy * fz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix + 1, iy, iz, fx * gy * gz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix + 1, iy, iz + 1, fx * gy * fz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix + 1, iy + 1, iz, fx * fy * gz, pm, cols, F)
        acc = _hash_corner_read(acc, table, R, off, hs, MASK, ix + 1, iy + 1, iz + 1, fx * fy * fz, pm, cols, F)
        tl.store(out + i[:, None] * (LEVELS * F) + lv * F + cols[None, :], acc, mask=pm[:, None])


@triton.jit
def _hash_corner_add(grad, g, R, off, hashed, MASK, ix, iy, iz, w, pm, cols, F: tl.constexpr):
    row = _hash_row(ix, iy, iz, R, off, hashed, MASK)
    tl.atomic_add(grad + row[:, None] * F + cols[None, :], w[:, None] * g, mask=pm[:, None])


@triton.jit(do_not_specialize=["M"])
def hash_bwd(x, g_out, grad, res, offsets, hashed, M, MASK, LEVELS: tl.constexpr, F: tl.constexpr,
             BLOCK: tl.constexpr):
    """The table's gradient of hash_fwd: each point's dL/dout of a level times its corner weights, atomically added
    to the 8 corners' rows (``grad`` zeroed by the caller)."""
    i, pm, px, py, pz = _program_points(x, M, BLOCK)
    cols = tl.arange(0, F)
    for lv in tl.static_range(LEVELS):
        R, off, hs = tl.load(res + lv), tl.load(offsets + lv), tl.load(hashed + lv)
        g = tl.load(g_out + i[:, None] * (LEVELS * F) + lv * F + cols[None, :], mask=pm[:, None], other=0.0)
        ix, iy, iz, fx, fy, fz, gx, gy, gz = _cell3(px, py, pz, R)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix, iy, iz, gx * gy * gz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix, iy, iz + 1, gx * gy * fz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix, iy + 1, iz, gx * fy * gz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix, iy + 1, iz + 1, gx * fy * fz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix + 1, iy, iz, fx * gy * gz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix + 1, iy, iz + 1, fx * gy * fz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix + 1, iy + 1, iz, fx * fy * gz, pm, cols, F)
        _hash_corner_add(grad, g, R, off, hs, MASK, ix + 1, iy + 1, iz + 1, fx * fy * fz, pm, cols, F)


# ----------------------------------------------------------------------------- marching
@triton.jit
def _scalar_level(acc, table, R, px, py, pz, m):
    """acc plus the trilinear read of a one-channel level (R³,) at unit points (px, py, pz), lanes ``m`` only; the
    corners in trilinear_fwd's order, so a point reads the same value here as there."""
    ix, iy, iz, fx, fy, fz, gx, gy, gz = _cell3(px, py, pz, R)
    row = (ix * R + iy) * R + iz
    rr = R * R
    acc += gx * gy * gz * tl.load(table + row, mask=m, other=0.0)
    acc += gx * gy * fz * tl.load(table + row + 1, mask=m, other=0.0)
    acc += gx * fy * gz * tl.load(table + row + R, mask=m, other=0.0)
    acc += gx * fy * fz * tl.load(table + row + R + 1, mask=m, other=0.0)
    acc += fx * gy * gz * tl.load(table + row + rr, mask=m, other=0.0)
    acc += fx * gy * fz * tl.load(table + row + rr + 1, mask=m, other=0.0)
    acc += fx * fy * gz * tl.load(table + row + rr + R, mask=m, other=0.0)
    acc += fx * fy * fz * tl.load(table + row + rr + R + 1, mask=m, other=0.0)
    return acc


@triton.jit
def _softplus(x):
    """torch's softplus (threshold 20): x above 20, else log1p(exp(x)), log1p by Goldberg's correction
    (log(1 + y) * y / ((1 + y) - 1)): triton has no log1p that runs both compiled and interpreted."""
    y = tl.exp(tl.minimum(x, 20.0))
    v = 1.0 + y
    log1p = tl.where(v == 1.0, y, tl.log(v) * (y / (v - 1.0)))
    return tl.where(x > 20.0, x, log1p)


@triton.jit(do_not_specialize=["N"])
def march_dense(rays_o, rays_d, t_near, t_far, jitter, occupied, occ_box, grid_box, log_min_t,
                t0, t1, t2, t3, r0, r1, r2, r3, counts, offsets, out_ts, out_te, out_ri, out_sigma,
                N, OCC_RES, step, max_samples, bias, density_scale,
                LEVELS: tl.constexpr, EXP: tl.constexpr, JITTER: tl.constexpr, WRITE: tl.constexpr,
                SIGMA_MAX: tl.constexpr, TAU_MAX: tl.constexpr, BLOCK: tl.constexpr):
    """Front-to-back marching of BLOCK rays a program, a ray a lane: recon/nerf/march.c's samples mode for bounded
    uniform steps (step k spans tn + (k + u) step to the next, kept where its midpoint's occupancy cell is occupied,
    its density the levels' trilinear sum through the activation; a ray stops before the first sample whose optical
    depth so far, a float64 sum, reaches log_min_t). The first launch (WRITE false) counts each ray's samples into
    ``counts``; the second writes them at ``offsets`` (the counts' exclusive sum): ray-major, in order along each ray.
    A program's loop ends when its last ray has."""
    r = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    rm = r < N
    ox = tl.load(rays_o + r * 3, mask=rm, other=0.0)
    oy = tl.load(rays_o + r * 3 + 1, mask=rm, other=0.0)
    oz = tl.load(rays_o + r * 3 + 2, mask=rm, other=0.0)
    dx = tl.load(rays_d + r * 3, mask=rm, other=0.0)
    dy = tl.load(rays_d + r * 3 + 1, mask=rm, other=0.0)
    dz = tl.load(rays_d + r * 3 + 2, mask=rm, other=0.0)
    tn = tl.load(t_near + r, mask=rm, other=0.0)
    tf = tl.load(t_far + r, mask=rm, other=0.0)
    if JITTER:
        u = tl.load(jitter + r, mask=rm, other=0.0)
    else:
        u = tl.zeros([BLOCK], dtype=tl.float32)
    limit = tl.load(log_min_t)  # float64
    # occupancy cells: the ray in cell units once (OccupancyGrid.query_rays)
    lo_x = tl.load(occ_box)
    lo_y = tl.load(occ_box + 1)
    lo_z = tl.load(occ_box + 2)
    cells = OCC_RES * 1.0
    sx = cells / (tl.load(occ_box + 3) - lo_x)
    sy = cells / (tl.load(occ_box + 4) - lo_y)
    sz = cells / (tl.load(occ_box + 5) - lo_z)
    pox = (ox - lo_x) * sx
    poy = (oy - lo_y) * sy
    poz = (oz - lo_z) * sz
    pdx = dx * sx
    pdy = dy * sy
    pdz = dz * sz
    g_x = tl.load(grid_box)
    g_y = tl.load(grid_box + 1)
    g_z = tl.load(grid_box + 2)
    gs_x = tl.load(grid_box + 3) - g_x
    gs_y = tl.load(grid_box + 4) - g_y
    gs_z = tl.load(grid_box + 5) - g_z

    n = tl.minimum(tl.ceil(tl.maximum(tf - tn, 0.0) / step), max_samples * 1.0)
    n = tl.where(rm & (tf > tn), n, 0.0).to(tl.int32)
    kmax = tl.max(n, 0)
    depth = tl.zeros([BLOCK], dtype=tl.float64)
    kept = tl.zeros([BLOCK], dtype=tl.int32)
    alive = n > 0
    if WRITE:
        base = tl.load(offsets + r, mask=rm, other=0)
    k = tl.zeros([], dtype=tl.int32)
    while k < kmax:
        ts = tn + (k.to(tl.float32) + u) * step
        alive = alive & (k < n) & (ts < tf)
        te = tl.minimum(ts + step, tf)
        tm = 0.5 * (ts + te)
        px = pox + pdx * tm
        py = poy + pdy * tm
        pz = poz + pdz * tm
        inside = alive & (px >= 0.0) & (px <= cells) & (py >= 0.0) & (py <= cells) & (pz >= 0.0) & (pz <= cells)
        ix = tl.minimum(tl.floor(px), cells - 1.0).to(tl.int64)
        iy = tl.minimum(tl.floor(py), cells - 1.0).to(tl.int64)
        iz = tl.minimum(tl.floor(pz), cells - 1.0).to(tl.int64)
        occ = tl.load(occupied + (ix * OCC_RES + iy) * OCC_RES + iz, mask=inside, other=0)
        take = inside & (occ != 0)
        ux = tl.clamp((ox + dx * tm - g_x) / gs_x, 0.0, 1.0)
        uy = tl.clamp((oy + dy * tm - g_y) / gs_y, 0.0, 1.0)
        uz = tl.clamp((oz + dz * tm - g_z) / gs_z, 0.0, 1.0)
        raw = tl.zeros([BLOCK], dtype=tl.float32)
        raw = _scalar_level(raw, t0, r0, ux, uy, uz, take)
        if LEVELS > 1:
            raw = _scalar_level(raw, t1, r1, ux, uy, uz, take)
        if LEVELS > 2:
            raw = _scalar_level(raw, t2, r2, ux, uy, uz, take)
        if LEVELS > 3:
            raw = _scalar_level(raw, t3, r3, ux, uy, uz, take)
        raw = raw + bias
        if EXP:
            sigma = tl.exp(tl.minimum(raw, 15.0)) * density_scale
        else:
            sigma = _softplus(raw) * density_scale
        tau = _optical_thickness(sigma, te - ts, SIGMA_MAX, TAU_MAX)
        if WRITE:
            at = base + kept
            tl.store(out_ts + at, ts, mask=take)
            tl.store(out_te + at, te, mask=take)
            tl.store(out_ri + at, r, mask=take)
            tl.store(out_sigma + at, sigma, mask=take)
        kept += take.to(tl.int32)
        depth += tl.where(take, tau.to(tl.float64), 0.0)
        alive = alive & (depth < limit)  # no later sample of this ray is kept
        k = tl.where(tl.max(alive.to(tl.int32), 0) > 0, k + 1, kmax)
    if not WRITE:
        tl.store(counts + r, kept, mask=rm)


# ----------------------------------------------------------------------------- rays
@triton.jit
def _slab(o, d, b0, b1):
    """One axis of the slab test: the interval of t inside [b0, b1], all of it or none for a ray parallel to it."""
    parallel = d == 0.0
    dd = tl.where(parallel, 1.0, d)
    t0 = tl.div_rn(b0 - o, dd)
    t1 = tl.div_rn(b1 - o, dd)
    always = tl.where((o >= b0) & (o <= b1), float("inf"), -float("inf"))
    return (tl.where(parallel, -always, tl.minimum(t0, t1, propagate_nan=tl.PropagateNan.ALL)),
            tl.where(parallel, always, tl.maximum(t0, t1, propagate_nan=tl.PropagateNan.ALL)))


@triton.jit
def _ray_box(ox, oy, oz, dx, dy, dz, box):
    """(t_near, t_far, hit) of rays and a box (2, 3): recon.nerf.rays.ray_aabb_torch, its divisions rounded as
    torch's."""
    lo_x, hi_x = _slab(ox, dx, tl.load(box), tl.load(box + 3))
    lo_y, hi_y = _slab(oy, dy, tl.load(box + 1), tl.load(box + 4))
    lo_z, hi_z = _slab(oz, dz, tl.load(box + 2), tl.load(box + 5))
    lo = tl.maximum(lo_x, lo_y, propagate_nan=tl.PropagateNan.ALL)
    lo = tl.maximum(lo, lo_z, propagate_nan=tl.PropagateNan.ALL)
    lo = tl.maximum(lo, 0.0, propagate_nan=tl.PropagateNan.ALL)
    hi = tl.minimum(hi_x, hi_y, propagate_nan=tl.PropagateNan.ALL)
    hi = tl.minimum(hi, hi_z, propagate_nan=tl.PropagateNan.ALL)
    hit = hi > lo
    return tl.where(hit, lo, 0.0), tl.where(hit, hi, 0.0), hit


@triton.jit(do_not_specialize=["N"])
def ray_box_fwd(o, d, box, near, far, t_near, t_far, hit, N, CLIP: tl.constexpr, BLOCK: tl.constexpr):
    """ray_aabb of N rays (o, d (N, 3)); with CLIP each ray's [near, far] clipped to the box instead, empty at near
    where the ray misses it (recon.nerf.rays.clip_to_box)."""
    i = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    m = i < N
    ox, oy, oz = tl.load(o + 3 * i, mask=m), tl.load(o + 3 * i + 1, mask=m), tl.load(o + 3 * i + 2, mask=m)
    dx, dy, dz = tl.load(d + 3 * i, mask=m), tl.load(d + 3 * i + 1, mask=m), tl.load(d + 3 * i + 2, mask=m)
    tn, tf, h = _ray_box(ox, oy, oz, dx, dy, dz, box)
    if CLIP:
        tn = tl.maximum(tl.load(near + i, mask=m), tn, propagate_nan=tl.PropagateNan.ALL)
        tf = tl.where(h, tl.minimum(tl.load(far + i, mask=m), tf, propagate_nan=tl.PropagateNan.ALL), tn)
    tl.store(t_near + i, tn, mask=m)
    tl.store(t_far + i, tf, mask=m)
    tl.store(hit + i, h.to(tl.int8), mask=m)


@triton.jit(do_not_specialize=["N"])
def pixel_rays_fwd(flat, offsets, widths, c2w, intrinsics, box, near_far, out_o, out_d, out_near, out_far, out_hit,
                   out_img, N, PHOTOS, HAS_BOX: tl.constexpr, BLOCK: tl.constexpr):
    """The rays through N flat pixel indices into stacked photos (recon.nerf.fitting.RayBatcher._rays_torch): each
    pixel's photo by a binary search of offsets (PHOTOS + 1,), the same steps in every lane; the ray through its
    centre with a unit direction; its near and far (the box's, or its photo's near_far)."""
    i = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    m = i < N
    f = tl.load(flat + i, mask=m, other=0)
    img = tl.zeros_like(f)
    span = PHOTOS
    while span > 1:
        half = span // 2
        img = tl.where(tl.load(offsets + img + half, mask=m, other=0) <= f, img + half, img)
        span -= half
    local = f - tl.load(offsets + img, mask=m, other=0)
    w = tl.load(widths + img, mask=m, other=1)
    row = local // w
    px = (local - row * w).to(tl.float32) + 0.5
    py = row.to(tl.float32) + 0.5
    k = intrinsics + 4 * img
    x = tl.div_rn(px - tl.load(k + 2, mask=m, other=0.0), tl.load(k, mask=m, other=1.0))
    y = -tl.div_rn(py - tl.load(k + 3, mask=m, other=0.0), tl.load(k + 1, mask=m, other=1.0))
    c = c2w + 12 * img
    dx = tl.load(c, mask=m, other=0.0) * x + tl.load(c + 1, mask=m, other=0.0) * y - tl.load(c + 2, mask=m, other=1.0)
    dy = (tl.load(c + 4, mask=m, other=0.0) * x + tl.load(c + 5, mask=m, other=0.0) * y
          - tl.load(c + 6, mask=m, other=0.0))
    dz = (tl.load(c + 8, mask=m, other=0.0) * x + tl.load(c + 9, mask=m, other=0.0) * y
          - tl.load(c + 10, mask=m, other=0.0))
    norm = tl.sqrt_rn(dx * dx + dy * dy + dz * dz)
    dx, dy, dz = tl.div_rn(dx, norm), tl.div_rn(dy, norm), tl.div_rn(dz, norm)
    ox, oy, oz = tl.load(c + 3, mask=m), tl.load(c + 7, mask=m), tl.load(c + 11, mask=m)
    tl.store(out_o + 3 * i, ox, mask=m)
    tl.store(out_o + 3 * i + 1, oy, mask=m)
    tl.store(out_o + 3 * i + 2, oz, mask=m)
    tl.store(out_d + 3 * i, dx, mask=m)
    tl.store(out_d + 3 * i + 1, dy, mask=m)
    tl.store(out_d + 3 * i + 2, dz, mask=m)
    if HAS_BOX:
        tn, tf, h = _ray_box(ox, oy, oz, dx, dy, dz, box)
    else:
        tn = tl.load(near_far + 2 * img, mask=m, other=0.0)
        tf = tl.load(near_far + 2 * img + 1, mask=m, other=0.0)
        h = tf > tn
    tl.store(out_near + i, tn, mask=m)
    tl.store(out_far + i, tf, mask=m)
    tl.store(out_hit + i, h.to(tl.int8), mask=m)
    tl.store(out_img + i, img, mask=m)

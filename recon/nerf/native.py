"""The native marcher (``march.c``): built with the system's C compiler on first use, the torch marcher otherwise.

Why: the torch marcher costs ~25 tensor passes over every candidate step (8.3 M per 400×400 Lego view, 72% of
them in empty cells) and three ``grid_sample`` calls per density; in C a candidate is a few flops. The
library is plain C with no Python or torch headers, so it builds in about a second with ``cc``; it is
cached under ``~/.cache/recon`` (``$XDG_CACHE_HOME``) keyed by the source's hash, and loaded with ctypes.
Nothing depends on it: with no compiler, a failed build, a CUDA tensor, or ``RECON_NATIVE=0``, callers use
the torch path, which marches the same samples (``tests/test_native_march.py`` holds the two together).
Rays are split over threads (ctypes releases the GIL), one per torch CPU thread.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import TypeVar

import torch
from torch import Tensor

__all__ = ["native_marcher", "native_status", "march_dense_native", "trilinear_features_native"]

SOURCE = Path(__file__).with_name("march.c")
CFLAGS = ["-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno"]
"""No fused multiply-adds, so steps and cells round as torch's separate multiply and add do."""

_status = "not loaded yet"
T = TypeVar("T")


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "recon" / "native"


def _build(compiler: str, target: Path) -> None:
    """Compile to a temporary file beside ``target`` and move it in place (atomic: concurrent builds are safe)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        subprocess.run([compiler, *CFLAGS, "-o", tmp, str(SOURCE), "-lm"], check=True, capture_output=True, timeout=120)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@lru_cache(maxsize=1)
def native_marcher() -> ctypes.CDLL | None:
    """The loaded library, or None (why: :func:`native_status`)."""
    global _status
    if os.environ.get("RECON_NATIVE", "1").lower() in ("0", "off", "false", "no"):
        _status = "torch (RECON_NATIVE=0)"
        return None
    compiler = next((c for c in (os.environ.get("CC"), "cc", "gcc", "clang") if c and shutil.which(c)), None)
    key = hashlib.sha256(SOURCE.read_bytes() + " ".join(CFLAGS).encode()).hexdigest()[:16]
    target = _cache_dir() / f"march-{key}.so"
    try:
        if not target.exists():
            if compiler is None:
                _status = "torch: no C compiler (cc, gcc or clang) on PATH to build recon/nerf/march.c"
                return None
            _build(compiler, target)
        lib = ctypes.CDLL(str(target))
    except (OSError, subprocess.SubprocessError) as exc:
        detail = getattr(exc, "stderr", b"") or b""
        _status = f"torch: building recon/nerf/march.c failed ({exc} {detail.decode(errors='replace')[:200]})"
        return None
    p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    lib.recon_march_dense.restype = i64
    lib.recon_march_dense.argtypes = [i64, p, p, p, p, p, p, i64, p, p, f32, i64, ctypes.c_double, i64, p, p, p, p,
                                      f32, f32, ctypes.c_int32, f32, f32, i64, p, p, p, p, i64]
    lib.recon_trilinear_features.restype = None
    lib.recon_trilinear_features.argtypes = [i64, p, p, i64, i64, p]
    _status = (f"native C (recon/nerf/march.c, built once into {target.parent}): bounded scenes' rays are marched in C, "
               "and renders read the feature grid in C (RECON_NATIVE=0: torch throughout)")
    return lib


def native_status() -> str:
    """Whether the native marcher is in use, and why not when it is not."""
    native_marcher()
    return _status


def march_dense_native(
    rays_o: Tensor,
    rays_d: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    jitter: bool,
    occupied: Tensor,
    occupancy_box: Tensor,
    step_size: float,
    max_samples: int,
    min_transmittance: float,
    tables: list[Tensor],
    grid_box: Tensor,
    bias: float,
    density_scale: float,
    exp_activation: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """:func:`recon.nerf.occupancy.march_front_to_back` with the fast model's dense density, natively; None when
    the library is not available or the tensors are not float32 on the CPU (the caller then marches in torch).

    jitter: offset each ray's steps by one uniform draw per ray, drawn as the torch marcher draws it (only when
    this marcher runs, so a fallback draws the same numbers). tables: each density level's (res³,) values, indexed
    [ix][iy][iz]; grid_box (2, 3) maps points onto them.
    Returns t_starts, t_ends, ray_indices, sigma (M,), sorted by ray and along each ray.
    """
    lib = native_marcher()
    tensors = [rays_o, rays_d, t_near, t_far, occupancy_box, grid_box, *tables]
    if lib is None or any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors):
        return None
    from recon.nerf.render import SIGMA_MAX, TAU_MAX

    rays_o, rays_d, t_near, t_far = (t.contiguous() for t in (rays_o, rays_d, t_near, t_far))
    jit = torch.rand(rays_o.shape[0], dtype=torch.float32) if jitter else None
    occ = occupied.contiguous().view(torch.uint8)
    occ_box = occupancy_box.contiguous()
    gbox = grid_box.contiguous()
    tabs = [t.contiguous() for t in tables]
    table_ptrs = (ctypes.c_void_p * len(tabs))(*[t.data_ptr() for t in tabs])
    level_res = (ctypes.c_int64 * len(tabs))(*[round(t.numel() ** (1 / 3)) for t in tabs])
    log_min_t = -float(torch.log(torch.tensor(min_transmittance, dtype=torch.float64)))

    def run(lo: int, hi: int, capacity: int) -> tuple[int, list[Tensor]]:
        out = [torch.empty(capacity), torch.empty(capacity), torch.empty(capacity, dtype=torch.long), torch.empty(capacity)]
        m = lib.recon_march_dense(
            hi - lo, rays_o[lo].data_ptr() if hi > lo else None, rays_d[lo].data_ptr() if hi > lo else None,
            t_near.data_ptr() + 4 * lo, t_far.data_ptr() + 4 * lo, None if jit is None else jit.data_ptr() + 4 * lo,
            occ.data_ptr(), occ.shape[0], occ_box[0].data_ptr(), occ_box[1].data_ptr(),
            float(step_size), int(max_samples), log_min_t, len(tabs), ctypes.cast(table_ptrs, ctypes.c_void_p),
            ctypes.cast(level_res, ctypes.c_void_p), gbox[0].data_ptr(), gbox[1].data_ptr(),
            float(bias), float(density_scale), int(exp_activation), SIGMA_MAX, TAU_MAX,
            capacity, *(t.data_ptr() for t in out), lo,
        )
        return m, out

    def part(lo: int, hi: int) -> list[Tensor]:
        m, out = run(lo, hi, 48 * (hi - lo))
        if m > out[0].shape[0]:
            m, out = run(lo, hi, m)
        return [t[:m] for t in out]

    parts = _in_slices(rays_o.shape[0], part)
    ts, te, ri, sigma = (torch.cat(x) for x in zip(*parts))
    return ts, te, ri, sigma


def trilinear_features_native(x01: Tensor, table: Tensor, res: int) -> Tensor | None:
    """A dense grid's trilinear features (M, C) at unit points x01 (M, 3) from its (res³, C) table, natively;
    None when the library is not available or the tensors are not float32 on the CPU."""
    lib = native_marcher()
    if lib is None or any(t.device.type != "cpu" or t.dtype != torch.float32 for t in (x01, table)):
        return None
    x01, table = x01.contiguous(), table.contiguous()
    channels = table.shape[1]
    out = torch.empty(x01.shape[0], channels)

    def part(lo: int, hi: int) -> None:
        if hi > lo:
            lib.recon_trilinear_features(hi - lo, x01[lo].data_ptr(), table.data_ptr(), res, channels, out[lo].data_ptr())

    _in_slices(x01.shape[0], part)
    return out


_pool: ThreadPoolExecutor | None = None


def _in_slices(n: int, fn: Callable[[int, int], T]) -> list[T]:
    """``fn(lo, hi)`` over contiguous slices of ``range(n)`` on one thread per torch CPU thread; results in order.
    Four slices a thread: an image's rays come in rows, and the rows through the object cost the most."""
    global _pool
    workers = max(1, min(torch.get_num_threads(), n // 1024))
    if workers == 1:
        return [fn(0, n)]
    slices = 4 * workers
    bounds = [n * i // slices for i in range(slices + 1)]
    if _pool is None or _pool._max_workers < workers:
        _pool = ThreadPoolExecutor(workers, thread_name_prefix="recon-native")
    return list(_pool.map(fn, bounds[:-1], bounds[1:]))

"""The fast model's hot loops in C (``march.c``): built with the system's C compiler on first use, torch otherwise.

Why: the torch marcher costs ~25 tensor passes over every candidate step (millions per view, most of them in
empty cells) and three ``grid_sample`` calls per density; in C a candidate is a few flops. Here: the
march (occupancy, empty-block jumps, density levels, early termination; when rendering, compositing too), and
dense and hash grids' trilinear reads and their tables' gradients. The library is plain C with no Python or torch headers,
so it builds in about a second with ``cc``, for this machine's CPU (its vector instructions) where the compiler can;
it is cached under ``~/.cache/recon`` (``$XDG_CACHE_HOME``) keyed by the source's hash, the flags and the CPU, and
loaded with ctypes. Nothing depends on it: with no compiler, a failed build, a CUDA
tensor, or ``RECON_NATIVE=0``, callers use the torch paths, which compute the same samples and values
(``tests/test_native_march.py`` holds the two together). Work is split over one thread per torch CPU thread: built
with OpenMP, on torch's own OpenMP threads within one C call (march.c's `_all` entry points); otherwise on threads of
recon's, a C call a slice (ctypes releases the GIL). Measurements: docs/profile.md.
"""
from __future__ import annotations

import contextlib
import ctypes
import hashlib
import itertools
import math
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TypeVar

import torch
from torch import Tensor

from recon.nerf.render import SIGMA_MAX, TAU_MAX, PackedPasses, composite_by, distortion_by

__all__ = ["DenseDensity", "load_c_library", "native_marcher", "native_status", "march_dense_native",
           "march_render_native", "native_grid_ok", "trilinear_features_native", "trilinear_backward_native", "hash_features_native",
           "hash_backward_native", "adam_native", "ADAM_BLOCK", "adam_blocks", "ray_box_native", "pixel_rays_native",
           "composite_packed_native", "distortion_packed_native",
           "trilinear_backward_levels_native"]

ADAM_BLOCK = 64
"""Values an Adam block holds (march.c's ADAM_BLOCK): the C update looks at a block's gradient, or its flag, once."""


def adam_blocks(numel: int) -> int:
    """How many blocks of :data:`ADAM_BLOCK` values ``numel`` values make (the last one may be short)."""
    return -(-numel // ADAM_BLOCK)


SOURCE = Path(__file__).with_name("march.c")
CFLAGS = ["-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno"]
"""No fused multiply-adds, so steps and cells round as torch's separate multiply and add do."""
HOST_CFLAGS = ["-march=native"]
"""Tried first: the loops vectorize over the CPU's widest registers (AVX-512 where there is one, not SSE2's four
floats); the same IEEE operations in the same order, so the same results. A compiler that refuses it gets CFLAGS
alone. Such a build runs only on CPUs like the one it was built on, so the cache key holds the CPU's model and
feature flags (a home folder shared by several machines keeps one build per kind of CPU)."""

OPENMP_CFLAGS = ["-fopenmp"]
"""Tried first: the `_all` entry points run their parts on OpenMP's threads, which are torch's (the library links the
libgomp torch loaded), not on threads of recon's competing with torch's spinning ones for the cores. A compiler
without OpenMP (Apple's clang) gets the build without, and recon splits the work over threads of its own."""

_status = "not loaded yet"
BUILT_FOR: dict[str, str] = {}
"""recon/<C file> -> how its loaded library was built: for this CPU, or portable and why."""
T = TypeVar("T")


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "recon" / "native"


@lru_cache(maxsize=1)
def _cpu_signature() -> str:
    """This CPU's model and feature flags (Linux: /proc/cpuinfo's first processor), for the cache key of a build
    for this CPU."""
    lines: list[str] = []
    with contextlib.suppress(OSError):
        lines = Path("/proc/cpuinfo").read_text(errors="replace").split("\n\n")[0].splitlines()
    picked = [line for line in lines if line.split(":")[0].strip() in ("model name", "flags", "Features",
                                                                         "CPU implementer", "CPU part")]
    return "\n".join(picked) or f"{platform.machine()} {platform.processor()} {platform.platform()}"


def _build(compiler: str, flags: list[str], source: Path, target: Path) -> None:
    """Compile to a temporary file beside ``target`` and move it in place (atomic: concurrent builds are safe)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        subprocess.run([compiler, *flags, "-o", tmp, str(source), "-lm"], check=True, capture_output=True, timeout=120)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _target(source: Path, flags: list[str]) -> Path:
    """The cached build of ``source`` with ``flags`` (for this CPU when they are HOST_CFLAGS)."""
    key = source.read_bytes() + " ".join(flags).encode()
    if any(f in flags for f in HOST_CFLAGS):
        key += _cpu_signature().encode()
    return _cache_dir() / f"{source.stem}-{hashlib.sha256(key).hexdigest()[:16]}.so"


def load_c_library(source: Path) -> tuple[ctypes.CDLL | None, str]:
    """(`source` built once with the system's C compiler into the cache and loaded, or None; why not, when None).
    Shared by every C file of recon (this marcher, recon/geometry/raster.c); ``RECON_NATIVE=0`` turns all off."""
    name = f"recon/{source.relative_to(Path(__file__).parents[1]).as_posix()}"
    if os.environ.get("RECON_NATIVE", "1").lower() in ("0", "off", "false", "no"):
        return None, "RECON_NATIVE=0"
    compiler = next((c for c in (os.environ.get("CC"), "cc", "gcc", "clang") if c and shutil.which(c)), None)
    failed = ""
    # for this CPU and with OpenMP where the compiler can, else without one or both
    for flags in ([*CFLAGS, *HOST_CFLAGS, *OPENMP_CFLAGS], [*CFLAGS, *HOST_CFLAGS], [*CFLAGS, *OPENMP_CFLAGS], CFLAGS):
        target = _target(source, flags)
        refused = target.with_suffix(".refused")  # a compiler that refused these flags once is not asked again
        if flags != CFLAGS and refused.exists():
            continue
        try:
            if not target.exists():
                if compiler is None:
                    return None, f"no C compiler (cc, gcc or clang) on PATH to build {name}"
                try:
                    _build(compiler, flags, source, target)
                except subprocess.CalledProcessError:
                    if flags != CFLAGS:
                        refused.touch()
                    raise
            lib = ctypes.CDLL(str(target))
            host = all(f in flags for f in HOST_CFLAGS)
            BUILT_FOR[name] = (f"for this CPU with {' '.join(HOST_CFLAGS)}" if host else
                               f"portable, as the compiler refused {' '.join(HOST_CFLAGS)}")
            BUILT_FOR[name] += ", with OpenMP" if all(f in flags for f in OPENMP_CFLAGS) else ", without OpenMP"
            return lib, ""
        except (OSError, subprocess.SubprocessError) as exc:
            detail = getattr(exc, "stderr", b"") or b""
            failed = f"building {name} failed ({exc} {detail.decode(errors='replace')[:200]})"
    return None, failed


@lru_cache(maxsize=1)
def native_marcher() -> ctypes.CDLL | None:
    """The loaded library, or None (why: :func:`native_status`)."""
    global _status
    lib, why = load_c_library(SOURCE)
    if lib is None:
        _status = f"torch ({why})" if why == "RECON_NATIVE=0" else f"torch: {why}"
        return None
    p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    lib.recon_march_dense.restype = i64
    i32 = ctypes.c_int32
    field = [p, i64, p, p, p, i64, f32, i64, ctypes.c_double, i64, p, p, p, p, f32, f32, i32, f32, f32, i32]
    lib.recon_march_dense.argtypes = [i64, p, p, p, p, p, *field, i64, p, p, p, p, p, i64]
    lib.recon_march_render.restype = i64
    lib.recon_march_render.argtypes = [i64, p, p, p, p, *field, i64, p, p, p, i64, f32, p, p, p]
    lib.recon_trilinear_features.restype = None
    lib.recon_trilinear_features.argtypes = [i64, p, p, i64, i64, p]
    lib.recon_trilinear_backward.restype = None
    lib.recon_trilinear_backward.argtypes = [i64, p, p, i64, i64, p, p, i64, i64]
    lib.recon_hash_features.restype = None
    lib.recon_hash_features.argtypes = [i64, p, p, i64, p, p, p, i64, i64, p]
    lib.recon_hash_backward.restype = None
    lib.recon_hash_backward.argtypes = [i64, p, p, i64, p, p, p, i64, i64, i64, i64, p, p]
    lib.recon_adam.restype = None
    lib.recon_adam.argtypes = [i64, p, p, p, p, f32, f32, f32, f32, f32, f32, i32, i32, p]
    lib.openmp = bool(lib.recon_openmp())
    lib.recon_march_dense_all.restype = None
    lib.recon_march_dense_all.argtypes = [i64, p, p, p, p, p, *field, i64, i64, p, p, p, p, p, p, p]
    lib.recon_march_offsets.restype = None
    lib.recon_march_offsets.argtypes = [i64, p, p, f32, i64, i32, i64, i64, p]
    lib.recon_march_render_all.restype = None
    lib.recon_march_render_all.argtypes = [i64, p, p, p, p, *field, i64, i64, p, p, p, p, f32, p, p, p, p]
    lib.recon_trilinear_features_all.restype = None
    lib.recon_trilinear_features_all.argtypes = [i64, p, p, i64, i64, p, i64, i64]
    lib.recon_trilinear_backward_all.restype = None
    lib.recon_trilinear_backward_all.argtypes = [i64, p, p, i64, i64, p, p, i64]
    lib.recon_hash_features_all.restype = None
    lib.recon_hash_features_all.argtypes = [i64, p, p, i64, p, p, p, i64, i64, p, i64, i64]
    lib.recon_hash_backward_all.restype = None
    lib.recon_hash_backward_all.argtypes = [i64, p, p, i64, p, p, p, i64, i64, i64, p, p]
    lib.recon_adam_all.restype = None
    lib.recon_adam_all.argtypes = [i64, p, p, p, p, f32, f32, f32, f32, f32, f32, i32, i32, p, i64, i64]
    lib.recon_trilinear_backward_levels_all.restype = None
    lib.recon_trilinear_backward_levels_all.argtypes = [i64, p, p, i64, p, p, p, i64]
    lib.recon_ray_box.restype = None
    lib.recon_ray_box.argtypes = [i64, p, p, p, p, p, p, p, p]
    lib.recon_pixel_rays.restype = None
    lib.recon_pixel_rays.argtypes = [i64, p, i64, p, p, p, p, p, p, p, p, p, p, p, p]
    lib.recon_composite_all.restype = None
    lib.recon_composite_all.argtypes = [i64, p, p, p, p, f32, f32, p, p, p, p, i64, i64]
    lib.recon_composite_backward_all.restype = None
    lib.recon_composite_backward_all.argtypes = [i64, p, p, p, p, p, p, p, p, p, p, f32, f32, p, p, p, i64, i64]
    lib.recon_distortion_all.restype = None
    lib.recon_distortion_all.argtypes = [i64, p, p, p, p, p, i64, i64]
    lib.recon_distortion_backward_all.restype = None
    lib.recon_distortion_backward_all.argtypes = [i64, p, p, p, p, p, p, p, p, i64, i64]
    _status = (f"native C (recon/nerf/march.c, built {BUILT_FOR.get('recon/nerf/march.c', '')}, cached in "
               f"{_cache_dir()}): rays are marched in C (bounded and "
               "contracted steps), "
               "and renders read the feature grid in C (RECON_NATIVE=0: torch throughout)")
    return lib


def native_status() -> str:
    """Whether the native marcher is in use, and why not when it is not."""
    native_marcher()
    return _status


@dataclass
class DenseDensity:
    """What the native marcher needs of a field: its occupancy grid, its density levels and their activation.

    tables: each density level's (res³,) values, indexed [ix][iy][iz]; grid_box (2, 3) maps points onto them;
    density = activation(sum of levels + bias) * density_scale (softplus, or exp clamped at 15).
    contracted: an unbounded field: rays take :func:`recon.nerf.contraction.contracted_intervals`' steps and points
    are contracted before the occupancy grid (over the contracted cube) and the density grids read them."""

    occupied: Tensor
    occupancy_box: Tensor
    tables: list[Tensor]
    grid_box: Tensor
    bias: float
    density_scale: float
    exp_activation: bool
    contracted: bool = False

    def runnable(self, *rays: Tensor) -> bool:
        return native_marcher() is not None and all(
            t.device.type == "cpu" and t.dtype == torch.float32 for t in (*rays, self.occupancy_box, self.grid_box, *self.tables))

    def args(self, step_size: float, max_samples: int, min_transmittance: float) -> list:
        """The library's arguments from the occupancy grid to tau_max (the tensors are kept alive by self)."""
        from recon.nerf.render import SIGMA_MAX, TAU_MAX

        blocks = None if self.contracted else _empty_blocks(self.occupied)  # contracted steps do not jump
        self._keep = [t.contiguous() for t in (self.occupied.view(torch.uint8), self.occupancy_box, self.grid_box, *self.tables)]
        occ, occ_box, gbox, *tabs = self._keep
        self._ptrs = (ctypes.c_void_p * len(tabs))(*[t.data_ptr() for t in tabs])
        self._res = (ctypes.c_int64 * len(tabs))(*[round(t.numel() ** (1 / 3)) for t in tabs])
        return [occ.data_ptr(), occ.shape[0], occ_box[0].data_ptr(), occ_box[1].data_ptr(),
                None if blocks is None else blocks.data_ptr(), BLOCK, float(step_size),
                int(max_samples), -math.log(min_transmittance), len(tabs), ctypes.cast(self._ptrs, ctypes.c_void_p),
                ctypes.cast(self._res, ctypes.c_void_p), gbox[0].data_ptr(), gbox[1].data_ptr(), float(self.bias),
                float(self.density_scale), int(self.exp_activation), SIGMA_MAX, TAU_MAX, int(self.contracted)]


BLOCK = 8
"""Occupancy cells per side of a block: a ray in an empty block jumps to the block's far side in one step of the
march; in an occupied block it steps on. 8 is where larger blocks stopped making a view's march faster, and
jumping over single empty cells is slower than not jumping at all."""

_blocks: tuple[Tensor, int, Tensor] | None = None


def _empty_blocks(occupied: Tensor) -> Tensor | None:
    """Which BLOCK³ blocks of the occupancy grid hold an occupied cell, (res/BLOCK)³ uint8; None when res is not a
    multiple of BLOCK. Kept while that very tensor is unchanged (a render's chunks share it): the cache holds the
    tensor itself, so its identity cannot pass to another, and any in-place update bumps its version."""
    global _blocks
    res = occupied.shape[0]
    if res % BLOCK:
        return None
    if _blocks is None or _blocks[0] is not occupied or _blocks[1] != occupied._version:
        pooled = torch.nn.functional.max_pool3d(occupied[None, None].float(), BLOCK)[0, 0]
        _blocks = (occupied, occupied._version, (pooled > 0).to(torch.uint8).contiguous())
    return _blocks[2]


MARCH_ROOM = 1 << 20
"""The most samples' room one native march allots (more rays than this allows their step counts: each ray an equal
share, and a slice that needs more is marched again). Room no sample fills is never touched, but a buffer this size
(12 MB of points) still comes from the heap's reused pages, where a larger one is mapped afresh, and faulted in, each
call."""

MARCH_RAYS_A_THREAD = 128
"""The fewest rays a thread of a native march takes: a ray through the object costs tens of microseconds, so the few
hundred rays of a depth prior or of smoothness patches are worth a second thread."""


def _fitted(run: Callable[[int, int, int], tuple[int, list[Tensor]]], lo: int, hi: int, capacity: int) -> list[Tensor]:
    """``run(lo, hi, capacity)``'s outputs cut to the samples it made, run again when ``capacity`` was too small."""
    m, out = run(lo, hi, capacity)
    if m > out[0].shape[0]:
        m, out = run(lo, hi, m)
    return [t[:m] for t in out]


def _march_room(t_near: Tensor, t_far: Tensor, step_size: float, max_samples: int,
                contracted: bool) -> Callable[[int, int, int], Tensor]:
    """``room(lo, hi, slices)``: where each of ``slices`` slices of rays lo..hi writes its samples, as offsets
    (slices + 1,) long: each ray given its step count (the most samples it can keep, so no slice runs out; a contracted
    ray max_samples), at most an equal share of :data:`MARCH_ROOM`."""
    lib, n = native_marcher(), t_near.shape[0]
    cap = max(16, MARCH_ROOM // max(n, 1))

    def room(lo: int, hi: int, slices: int) -> Tensor:
        offsets = torch.empty(slices + 1, dtype=torch.long)
        lib.recon_march_offsets(hi - lo, *_rays_args(lo, hi, t_near, t_far), float(step_size), int(max_samples),
                                int(contracted), cap, slices, offsets.data_ptr())
        return offsets
    return room


def _march_slices(n: int, room: Callable[[int, int, int], Tensor],
                  run: Callable[[int, int, int], tuple[int, list[Tensor]]],
                  run_all: Callable[[int, int, Tensor, Tensor], list[Tensor]]) -> list[list[Tensor]]:
    """A march's outputs slice by slice (as :func:`_fitted` cuts them): from one ``run_all(slices, threads, offsets,
    counts)`` call on OpenMP's threads (slice s written from offsets[s] on, with the room :func:`_march_room` gives
    it), a slice that needed more room marched again alone; or, in a library without OpenMP, ``run`` over
    :func:`_in_slices`."""
    if n == 0 or not _parallel_in_c(native_marcher()):
        return _in_slices(n, lambda lo, hi: _fitted(run, lo, hi, int(room(lo, hi, 1)[1])), MARCH_RAYS_A_THREAD)
    slices, threads = _slices_for(n, MARCH_RAYS_A_THREAD)
    offsets = room(0, n, slices)
    counts = torch.empty(slices, dtype=torch.long)
    out = run_all(slices, threads, offsets, counts)
    at = offsets.tolist()
    parts = []
    for s, m in enumerate(counts.tolist()):
        if m > at[s + 1] - at[s]:
            m, again = run(n * s // slices, n * (s + 1) // slices, m)  # march.c's slice_lo
            parts.append([t[:m] for t in again])
        else:
            parts.append([t[at[s]: at[s] + m] for t in out])
    return parts


def _rays_args(lo: int, hi: int, *per_ray: Tensor | None) -> list:
    """Pointers to row ``lo`` of each contiguous per-ray tensor (None stays NULL)."""
    return [None if t is None or hi <= lo else t[lo].data_ptr() for t in per_ray]


def march_dense_native(
    rays_o: Tensor, rays_d: Tensor, t_near: Tensor, t_far: Tensor, jitter: bool, field: DenseDensity,
    step_size: float, max_samples: int, min_transmittance: float, points: bool = False,
) -> tuple[Tensor, ...] | None:
    """:func:`recon.nerf.occupancy.march_front_to_back` with the fast model's dense density, natively; None when
    the library is not available or the tensors are not float32 on the CPU (the caller then marches in torch).

    jitter: offset each ray's steps by one uniform draw per ray, drawn as the torch marcher draws it (float32 for
    bounded steps, float64 for contracted ones; only when this marcher runs, so a fallback draws the same numbers).
    A contracted field's reference is :func:`recon.nerf.occupancy.march` with ``contracted=True`` and a ``sigma_fn``.
    Returns t_starts, t_ends, ray_indices, sigma (M,), sorted by ray and along each ray; with ``points``, also each
    sample's midpoint in the density grids' unit cube (M, 3), clamped to it, where its density was read.
    """
    if not field.runnable(rays_o, rays_d, t_near, t_far):
        return None
    lib = native_marcher()
    rays_o, rays_d, t_near, t_far = (t.contiguous() for t in (rays_o, rays_d, t_near, t_far))
    jit = None
    if jitter:
        jit = torch.rand(rays_o.shape[0], dtype=torch.float64 if field.contracted else torch.float32).double()
    common = field.args(step_size, max_samples, min_transmittance)

    def buffers(capacity: int) -> list[Tensor]:
        """t_starts, t_ends, ray_indices, sigma (and points) for ``capacity`` samples."""
        out = [torch.empty(capacity), torch.empty(capacity), torch.empty(capacity, dtype=torch.long), torch.empty(capacity)]
        return [*out, torch.empty(capacity, 3)] if points else out

    def run(lo: int, hi: int, capacity: int) -> tuple[int, list[Tensor]]:
        out = buffers(capacity)
        m = lib.recon_march_dense(hi - lo, *_rays_args(lo, hi, rays_o, rays_d, t_near, t_far, jit), *common,
                                  capacity, *(t.data_ptr() for t in out[:4]), out[4].data_ptr() if points else None, lo)
        return m, out

    def run_all(slices: int, threads: int, offsets: Tensor, counts: Tensor) -> list[Tensor]:
        n = rays_o.shape[0]
        out = buffers(int(offsets[-1]))
        lib.recon_march_dense_all(n, *_rays_args(0, n, rays_o, rays_d, t_near, t_far, jit), *common,
                                  slices, threads, offsets.data_ptr(), *(t.data_ptr() for t in out[:4]),
                                  out[4].data_ptr() if points else None, counts.data_ptr())
        return out

    room = _march_room(t_near, t_far, step_size, max_samples, field.contracted)
    parts = _march_slices(rays_o.shape[0], room, run, run_all)
    return tuple(torch.cat(x) for x in zip(*parts))


def march_render_native(
    rays_o: Tensor, rays_d: Tensor, t_near: Tensor, t_far: Tensor, field: DenseDensity,
    step_size: float, max_samples: int, min_transmittance: float, color_min_weight: float,
) -> dict[str, Tensor] | None:
    """March and composite without gradients, natively (None where :func:`march_dense_native` is None).

    Returns per ray (N,): opacity (sum of weights), depth_sum (sum of weight × midpoint distance), samples (long);
    and the samples worth coloring (weight above ``color_min_weight``), sorted by ray: u (K, 3) their points in the
    grids' unit cube, weights (K,), ray_indices (K,). Weights as :func:`recon.nerf.render.render_weights_packed`.
    """
    if not field.runnable(rays_o, rays_d, t_near, t_far):
        return None
    lib = native_marcher()
    rays_o, rays_d, t_near, t_far = (t.contiguous() for t in (rays_o, rays_d, t_near, t_far))
    n = rays_o.shape[0]
    common = field.args(step_size, max_samples, min_transmittance)
    opacity, depth_sum, samples = torch.empty(n), torch.empty(n), torch.empty(n, dtype=torch.long)

    def buffers(capacity: int) -> list[Tensor]:
        """u, weights, ray_indices for ``capacity`` coloured samples."""
        return [torch.empty(capacity, 3), torch.empty(capacity), torch.empty(capacity, dtype=torch.long)]

    def run(lo: int, hi: int, capacity: int) -> tuple[int, list[Tensor]]:
        out = buffers(capacity)
        m = lib.recon_march_render(hi - lo, *_rays_args(lo, hi, rays_o, rays_d, t_near, t_far), *common, capacity,
                                   *(t.data_ptr() for t in out), lo, float(color_min_weight),
                                   *_rays_args(lo, hi, opacity, depth_sum, samples))
        return m, out

    def run_all(slices: int, threads: int, offsets: Tensor, counts: Tensor) -> list[Tensor]:
        out = buffers(int(offsets[-1]))
        lib.recon_march_render_all(n, *_rays_args(0, n, rays_o, rays_d, t_near, t_far), *common, slices, threads,
                                   offsets.data_ptr(), *(t.data_ptr() for t in out), float(color_min_weight),
                                   *_rays_args(0, n, opacity, depth_sum, samples), counts.data_ptr())
        return out

    room = _march_room(t_near, t_far, step_size, max_samples, field.contracted)
    u, weights, ri = (torch.cat(x) for x in zip(*_march_slices(n, room, run, run_all)))
    return {"opacity": opacity, "depth_sum": depth_sum, "samples": samples, "u": u, "weights": weights, "ray_indices": ri}


def native_grid_ok(*tensors: Tensor) -> bool:
    """Can the native grid reads take these tensors (library loaded, float32 on the CPU)?"""
    return native_marcher() is not None and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)


def trilinear_features_native(x01: Tensor, table: Tensor, res: int) -> Tensor | None:
    """A dense grid's trilinear features (M, C) at unit points x01 (M, 3) from its (res³, C) table, natively;
    None when :func:`native_grid_ok` is not. No gradient: :class:`recon.nerf.grid.DenseGrid` wraps it for training."""
    if not native_grid_ok(x01, table):
        return None
    lib = native_marcher()
    x01, table = x01.detach().contiguous(), table.detach().contiguous()
    channels = table.shape[1]
    out = torch.empty(x01.shape[0], channels)

    def part(lo: int, hi: int) -> None:
        if hi > lo:
            lib.recon_trilinear_features(hi - lo, x01[lo].data_ptr(), table.data_ptr(), res, channels, out[lo].data_ptr())

    if _parallel_in_c(lib):
        lib.recon_trilinear_features_all(x01.shape[0], x01.data_ptr(), table.data_ptr(), res, channels, out.data_ptr(),
                                         *_slices_for(x01.shape[0]))
    else:
        _in_slices(x01.shape[0], part)
    return out


def trilinear_backward_native(x01: Tensor, grad_out: Tensor, res: int, out: Tensor | None = None,
                              accumulate: bool = False, touched: Tensor | None = None) -> Tensor:
    """The table's gradient (res³, C) of :func:`trilinear_features_native` given the features' gradient (M, C):
    in a new tensor, or written into ``out`` (a contiguous float32 (res³, C) tensor; zeroed first unless
    ``accumulate``, which adds to what it holds). ``touched`` (uint8, a flag per 64 values of the table, or None):
    the blocks added into are flagged (:class:`recon.nerf.masked_adam.TouchedBlocks`). With several channels a part
    per thread, each adding into x-planes of its own (march.c's backward_of): the same sums for any number of
    threads."""
    lib = native_marcher()
    x01, grad_out = x01.detach().contiguous(), grad_out.detach().to(torch.float32).contiguous()
    if out is None:
        grad_table = torch.zeros(res**3, grad_out.shape[1])
    else:
        grad_table = out if accumulate else out.zero_()
    flags, n = _flags_pointer(touched, grad_table), x01.shape[0]
    # every part passes over every point, so one channel (a density level), where that pass costs about what the
    # scatter does, stays in one part; with more each part saves its share of the scatter
    parts = _threads_for(n) if grad_out.shape[1] > 1 else 1
    if _parallel_in_c(lib):
        lib.recon_trilinear_backward_all(n, x01.data_ptr(), grad_out.data_ptr(), res, grad_out.shape[1],
                                         grad_table.data_ptr(), flags, parts)
        return grad_table

    def part(i: int) -> None:
        lib.recon_trilinear_backward(n, x01.data_ptr(), grad_out.data_ptr(), res, grad_out.shape[1],
                                     grad_table.data_ptr(), flags, i, parts)

    _on_threads(parts, parts, part)
    return grad_table


def _levels_order(resolutions: list[int]) -> list[int]:
    """The levels' indices, finest first (the C call hands them to threads in this order as each frees): the finest
    level, the most work, starts at once and the coarse ones share the other threads, instead of the finest starting
    last and running alone."""
    return sorted(range(len(resolutions)), key=lambda i: -resolutions[i])


def trilinear_backward_levels_native(x01: Tensor, grad_out: Tensor, resolutions: list[int], outs: list[Tensor],
                                     touched: list[Tensor | None]) -> bool:
    """:func:`trilinear_backward_native` (accumulating) of one-channel grids read at the same points x01 (M, 3) with
    the same gradient (M, 1), into ``outs`` (each a contiguous float32 (res³, 1) tensor) with ``touched`` flags: a
    level a thread where the library runs its parts on OpenMP's threads (the levels' sums are each their own, the
    same for any number of threads). False, having done nothing, where it does not: the caller adds a level at a
    time."""
    lib = native_marcher()
    if lib is None or not _parallel_in_c(lib) or len(outs) < 2 or grad_out.shape[1:] != (1,):
        return False
    x01, grad_out = x01.detach().contiguous(), grad_out.detach().to(torch.float32).contiguous()
    order = _levels_order(resolutions)
    res = torch.tensor([resolutions[i] for i in order], dtype=torch.int64)
    tables = (ctypes.c_void_p * len(outs))(*(outs[i].data_ptr() for i in order))
    flags = (ctypes.c_void_p * len(outs))(*(_flags_pointer(touched[i], outs[i]) for i in order))
    lib.recon_trilinear_backward_levels_all(x01.shape[0], x01.data_ptr(), grad_out.data_ptr(), len(outs),
                                            res.data_ptr(), tables, flags, min(len(outs), _threads_for(x01.shape[0])))
    return True


def hash_features_native(x01: Tensor, table: Tensor, levels: Tensor, log2_table: int) -> Tensor | None:
    """A hash grid's features (M, L · F) at unit points x01 (M, 3) from its (rows, F) table, natively; None when
    :func:`native_grid_ok` is not. ``levels`` (3, L) int64: each level's vertices a side, first row and hashed
    (1) or dense (0). No gradient: :class:`recon.nerf.grid.HashGrid` wraps it for training."""
    if not native_grid_ok(x01, table):
        return None
    lib = native_marcher()
    x01, table, levels = x01.detach().contiguous(), table.detach().contiguous(), levels.contiguous()
    n_levels, features = levels.shape[1], table.shape[1]
    out = torch.empty(x01.shape[0], n_levels * features)

    def part(lo: int, hi: int) -> None:
        if hi > lo:
            lib.recon_hash_features(hi - lo, x01[lo].data_ptr(), table.data_ptr(), n_levels, levels[0].data_ptr(),
                                    levels[1].data_ptr(), levels[2].data_ptr(), log2_table, features,
                                    out[lo].data_ptr())

    if _parallel_in_c(lib):
        lib.recon_hash_features_all(x01.shape[0], x01.data_ptr(), table.data_ptr(), n_levels, levels[0].data_ptr(),
                                    levels[1].data_ptr(), levels[2].data_ptr(), log2_table, features, out.data_ptr(),
                                    *_slices_for(x01.shape[0]))
    else:
        _in_slices(x01.shape[0], part)
    return out


def hash_backward_native(x01: Tensor, grad_out: Tensor, levels: Tensor, log2_table: int, out: Tensor,
                         touched: Tensor | None = None) -> Tensor:
    """Add the table's gradient of :func:`hash_features_native`, given the features' gradient (M, L · F), into
    ``out`` (the contiguous float32 (rows, F) table gradient) and return it; ``touched`` as in
    :func:`trilinear_backward_native`. The levels are dealt out to the threads (each level's rows are its own, so no
    two threads add into one value)."""
    lib = native_marcher()
    x01, grad_out = x01.detach().contiguous(), grad_out.detach().to(torch.float32).contiguous()
    levels = levels.contiguous()
    n_levels, flags = levels.shape[1], _flags_pointer(touched, out)
    workers = max(1, min(torch.get_num_threads(), n_levels, x01.shape[0] // 1024))
    if _parallel_in_c(lib):
        lib.recon_hash_backward_all(x01.shape[0], x01.data_ptr(), grad_out.data_ptr(), n_levels, levels[0].data_ptr(),
                                    levels[1].data_ptr(), levels[2].data_ptr(), log2_table, out.shape[1], workers,
                                    out.data_ptr(), flags)
        return out

    def part(first: int) -> None:
        lib.recon_hash_backward(x01.shape[0], x01.data_ptr(), grad_out.data_ptr(), n_levels, levels[0].data_ptr(),
                                levels[1].data_ptr(), levels[2].data_ptr(), log2_table, out.shape[1], first, workers,
                                out.data_ptr(), flags)

    _on_threads(workers, workers, part)
    return out


def adam_native(param: Tensor, grad: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, *, beta1: float, beta2: float,
                step_size: float, bias2_sqrt: float, eps: float, masked: bool, clear: bool = False,
                touched: Tensor | None = None) -> bool:
    """:func:`recon.nerf.masked_adam.adam_step_torch` in C over contiguous float32 CPU tensors, split over threads;
    False (nothing done) where it does not apply: no library, another device or dtype, a strided tensor.
    ``clear`` (with ``masked``): set the gradients it used to 0, leaving ``grad`` all 0. ``touched`` (with both): the
    flags of the blocks of :data:`ADAM_BLOCK` values that may have a gradient; only those are visited, and their
    flags cleared."""
    tensors = (param, grad, exp_avg, exp_avg_sq)
    if not native_grid_ok(*tensors) or not all(t.is_contiguous() and t.shape == param.shape for t in tensors):
        return False
    if touched is not None and not (masked and clear):
        raise ValueError("adam_native: touched flags need masked=True and clear=True (they are cleared as used)")
    lib = native_marcher()
    flat = [t.detach().view(-1) for t in tensors]
    n, flags = flat[0].shape[0], _flags_pointer(touched, flat[0])

    def part(lo: int, hi: int) -> None:
        if hi > lo:
            lib.recon_adam(hi - lo, *(t[lo:].data_ptr() for t in flat), 1.0 - beta1, beta2, 1.0 - beta2, step_size,
                           bias2_sqrt, eps, int(masked), int(clear), None if flags is None else flags + lo // ADAM_BLOCK)

    if _parallel_in_c(lib):
        lib.recon_adam_all(n, *(t.data_ptr() for t in flat), 1.0 - beta1, beta2, 1.0 - beta2, step_size, bias2_sqrt,
                           eps, int(masked), int(clear), flags, *_slices_for(n))
    elif flags is None:
        _in_slices(n, part)
    else:  # slices of whole blocks, so that each slice's flags start at its own
        _in_slices(adam_blocks(n), lambda lo, hi: part(lo * ADAM_BLOCK, min(hi * ADAM_BLOCK, n)))
    return True


def _pointer(t: Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def ray_box_native(rays_o: Tensor, rays_d: Tensor, box: Tensor, near: Tensor | None = None,
                   far: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor] | None:
    """:func:`recon.nerf.rays.ray_aabb` (t_near, t_far, hit) of rays (N, 3) and a box (2, 3) in one C pass, the same
    values bit for bit; given near and far (N,), each ray's [near, far] clipped to the box instead (a ray that misses
    it: empty at near). None unless :func:`native_grid_ok` takes the tensors."""
    given = [t for t in (near, far) if t is not None]
    if not native_grid_ok(rays_o, rays_d, box, *given):
        return None
    n = rays_o.shape[0]
    rays_o, rays_d, box = rays_o.detach().contiguous(), rays_d.detach().contiguous(), box.detach().contiguous()
    near, far = (None if t is None else t.detach().contiguous() for t in (near, far))
    t_near, t_far, hit = torch.empty(n), torch.empty(n), torch.empty(n, dtype=torch.bool)
    native_marcher().recon_ray_box(n, rays_o.data_ptr(), rays_d.data_ptr(), box.data_ptr(), _pointer(near),
                                   _pointer(far), t_near.data_ptr(), t_far.data_ptr(), hit.data_ptr())
    return t_near, t_far, hit


def pixel_rays_native(flat: Tensor, offsets: Tensor, widths: Tensor, c2w: Tensor, intrinsics: Tensor,
                      box: Tensor | None, near_far: Tensor | None) -> tuple[Tensor, ...] | None:
    """:meth:`recon.nerf.fitting.RayBatcher._rays` in one C pass: the rays through flat pixel indices (B,) into photos
    stacked from ``offsets`` (photos + 1,) on, ``widths`` (photos,) pixels a row, with camera-to-world ``c2w``
    (photos, 3, 4) and ``intrinsics`` (photos, 4): origins and unit directions (B, 3), near, far (B,) (where the
    rays meet ``box`` (2, 3), else their photo's ``near_far`` (photos, 2)), hit (B,) bool and each ray's photo (B,).
    The directions agree with the torch code's to a float32 rounding (its matrix product may sum in another order).
    None unless the library is loaded and the tensors are on the CPU."""
    floats = [t for t in (c2w, intrinsics, box, near_far) if t is not None]
    if not native_grid_ok(*floats) or any(t.device.type != "cpu" for t in (flat, offsets, widths)):
        return None
    b, photos = flat.shape[0], c2w.shape[0]
    flat, offsets, widths = (t.to(torch.int64).contiguous() for t in (flat, offsets, widths))
    c2w, intrinsics = c2w[:, :3, :4].contiguous(), intrinsics.contiguous()
    box, near_far = (None if t is None else t.contiguous() for t in (box, near_far))
    o, d, near, far = torch.empty(b, 3), torch.empty(b, 3), torch.empty(b), torch.empty(b)
    hit, img = torch.empty(b, dtype=torch.bool), torch.empty(b, dtype=torch.int64)
    native_marcher().recon_pixel_rays(b, flat.data_ptr(), photos, offsets.data_ptr(), widths.data_ptr(),
                                      c2w.data_ptr(), intrinsics.data_ptr(), _pointer(box), _pointer(near_far),
                                      o.data_ptr(), d.data_ptr(), near.data_ptr(), far.data_ptr(), hit.data_ptr(),
                                      img.data_ptr())
    return o, d, near, far, hit, img


class _CPasses(PackedPasses):
    """Compositing and the distortion loss in C, a ray at a time on OpenMP's threads (march.c's recon_composite_all,
    recon_distortion_all and their backwards), the running sums in float64 as the torch references' cumulative sums."""

    def composite(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor, trans: Tensor,
                  opacity: Tensor, depth: Tensor) -> None:
        n = offsets.shape[0] - 1
        native_marcher().recon_composite_all(n, offsets.data_ptr(), sigma.data_ptr(), delta.data_ptr(), t.data_ptr(),
                                             SIGMA_MAX, TAU_MAX, weights.data_ptr(), trans.data_ptr(),
                                             opacity.data_ptr(), depth.data_ptr(), *_slices_for(n))

    def composite_backward(self, sigma: Tensor, delta: Tensor, t: Tensor, offsets: Tensor, weights: Tensor,
                           trans: Tensor, g_w: Tensor | None, g_trans: Tensor | None, g_op: Tensor, g_dep: Tensor,
                           g_sigma: Tensor, g_delta: Tensor, g_t: Tensor) -> None:
        n = offsets.shape[0] - 1
        native_marcher().recon_composite_backward_all(
            n, offsets.data_ptr(), sigma.data_ptr(), delta.data_ptr(), t.data_ptr(), weights.data_ptr(),
            trans.data_ptr(), _pointer(g_w), _pointer(g_trans), g_op.data_ptr(), g_dep.data_ptr(), SIGMA_MAX, TAU_MAX,
            g_sigma.data_ptr(), g_delta.data_ptr(), g_t.data_ptr(), *_slices_for(n))

    def distortion(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, loss: Tensor) -> None:
        n = offsets.shape[0] - 1
        native_marcher().recon_distortion_all(n, offsets.data_ptr(), w.data_ptr(), mid.data_ptr(), delta.data_ptr(),
                                              loss.data_ptr(), *_slices_for(n))

    def distortion_backward(self, w: Tensor, mid: Tensor, delta: Tensor, offsets: Tensor, g_loss: Tensor,
                            g_w: Tensor, g_mid: Tensor, g_delta: Tensor) -> None:
        n = offsets.shape[0] - 1
        native_marcher().recon_distortion_backward_all(n, offsets.data_ptr(), w.data_ptr(), mid.data_ptr(),
                                                       delta.data_ptr(), g_loss.data_ptr(), g_w.data_ptr(),
                                                       g_mid.data_ptr(), g_delta.data_ptr(), *_slices_for(n))


C_PASSES = _CPasses()


def composite_packed_native(sigma: Tensor, delta: Tensor, t: Tensor, ray_indices: Tensor,
                            n_rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """`recon.nerf.kernels.composite_packed_torch` (weights, transmittance (M,), opacity, depth sum (N,) of packed
    samples sigma, delta, t (M,), ray_indices (M,) sorted; differentiable in sigma, delta and t) in one C pass a ray
    forward and one back (:func:`recon.nerf.render.composite_by`). None unless :func:`native_grid_ok` takes the
    tensors."""
    if not native_grid_ok(sigma, delta, t):
        return None
    return composite_by(C_PASSES, sigma, delta, t, ray_indices, n_rays)


def distortion_packed_native(weights: Tensor, t_mid: Tensor, delta: Tensor, ray_indices: Tensor,
                             n_rays: int) -> Tensor | None:
    """`recon.nerf.render.distortion_packed`, each ray's distortion loss (N,) (weights, t_mid sorted along each ray,
    delta, ray_indices sorted: (M,)), in one C pass a ray forward and two back, its sums in float64; differentiable
    in all three. None unless :func:`native_grid_ok` takes the tensors."""
    if not native_grid_ok(weights, t_mid, delta):
        return None
    return distortion_by(C_PASSES, weights, t_mid, delta, ray_indices, n_rays)


def _flags_pointer(touched: Tensor | None, values: Tensor) -> int | None:
    """The address of ``touched``, checked to be a flag (uint8) per :data:`ADAM_BLOCK` values of ``values``; None
    for None."""
    if touched is None:
        return None
    blocks = adam_blocks(values.numel())
    if touched.dtype != torch.uint8 or touched.device.type != "cpu" or not touched.is_contiguous() or \
            touched.numel() != blocks:
        raise ValueError(f"touched flags: need {blocks} contiguous uint8 CPU values, one per {ADAM_BLOCK} of the "
                         f"{values.numel()}; got {touched.numel()} {touched.dtype} on {touched.device}")
    return touched.data_ptr()


_pool: ThreadPoolExecutor | None = None


def _threads_for(n: int, fewest: int = 1024) -> int:
    """Threads for a native call over n items: one per torch CPU thread, none with under ``fewest`` items to itself."""
    return max(1, min(torch.get_num_threads(), n // fewest))


def _slices_for(n: int, fewest: int = 1024) -> tuple[int, int]:
    """(slices, threads) of a native call over n items: four slices a thread (see :func:`_in_slices`)."""
    threads = _threads_for(n, fewest)
    return (4 * threads if threads > 1 else 1), threads


def _parallel_in_c(lib: ctypes.CDLL) -> bool:
    """Whether ``lib`` runs its `_all` entry points' parts on OpenMP's threads (march.c built with OpenMP)."""
    return bool(getattr(lib, "openmp", False))


def _in_slices(n: int, fn: Callable[[int, int], T], fewest: int = 1024) -> list[T]:
    """``fn(lo, hi)`` over contiguous slices of ``range(n)`` on one thread per torch CPU thread (none with under
    ``fewest`` items to itself); results in order. Four slices a thread: an image's rays come in rows, and the rows
    through the object cost the most."""
    workers = _threads_for(n, fewest)
    if workers == 1:
        return [fn(0, n)]
    slices = 4 * workers
    bounds = [n * i // slices for i in range(slices + 1)]
    return _on_threads(slices, workers, lambda i: fn(bounds[i], bounds[i + 1]))


def _on_threads(count: int, workers: int, fn: Callable[[int], T]) -> list[T]:
    """``fn(i)`` for i in ``range(count)``, each on one of ``workers`` threads; results in order.

    The calling thread takes parts too, and the helpers take what is left when they start: right after torch's own
    parallel work its threads keep the cores spinning for a while, and a helper thread may wait that long for one, so
    the caller never waits for a helper that has not begun a part (`benchmarks/native_step_cost.py --against
    pool-map`)."""
    results: list[T | None] = [None] * count
    taken = itertools.count()  # its next() is atomic under the GIL: each part goes to one thread
    stop = False

    def drain() -> None:
        while not stop:
            i = next(taken)
            if i >= count:
                return
            results[i] = fn(i)

    helpers = [_thread_pool(workers).submit(drain) for _ in range(workers - 1)]
    try:
        drain()
    except BaseException:
        stop = True  # the helpers take no new part; the ones they hold end before the error goes up
        raise
    finally:
        for helper in helpers:
            if not helper.cancel():  # a helper that never started is dropped; one that started ends its part
                helper.result()
    return results  # type: ignore[return-value]


def _thread_pool(workers: int) -> ThreadPoolExecutor:
    """The native calls' threads (ctypes releases the GIL), at least ``workers`` of them, made once."""
    global _pool
    if _pool is None or _pool._max_workers < workers:
        _pool = ThreadPoolExecutor(workers, thread_name_prefix="recon-native")
    return _pool

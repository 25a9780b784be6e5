"""What a change to recon's native code costs a CPU training step: this checkout's against another revision's build of
recon/nerf/march.c (`--against REV`), against handing every slice of a native call to the thread pool and waiting for
all of them (`--against pool-map`, how `recon.nerf.native._in_slices` shared them before the calling thread took slices
too), against reading the density levels again for the loss (`--against reads-again`, as before the march's densities
were the loss's: `FastModel._marched_sigma`), against a dense grid's backward on one thread (`--against
serial-backward`, as before it took a part a thread: `trilinear_backward_native`), against the library's parts on
threads of recon's instead of OpenMP's (`--against python-threads`, as before march.c was built with OpenMP:
`_parallel_in_c`), against a batch's rays and their box in torch operations (`--against torch-rays`, as before they were
C passes: `pixel_rays_native`, `ray_box_native`), against compositing and the distortion loss in torch operations
(`--against torch-compositing`, as before they were C passes: `composite_packed_native`, the fast and surface models',
`distortion_packed_native`), against the density levels' backward a level at a time (`--against serial-levels`, as
before they took a thread each: `trilinear_backward_levels_native`), against a march that guesses 48 samples a ray (24
coloured in a render), marches a slice that needed more again on one thread, and takes a second thread only from 1,024
rays on (`--against guessed-room`, as before each ray was given its steps: `_march_room`), or the colour network's
slices recorded as views of the features (`--against slice-views`, as before they were split:
`recon.nerf.fast.in_slices`), or the density levels handed to the backward's threads coarsest first (`--against
coarsest-first`, as before they were ordered finest first: `recon.nerf.native._levels_order`).

    python benchmarks/native_step_cost.py --scene ~/.cache/recon/bench/lego-half-fast --against python-threads \\
        --out benchmarks/results/lego_half_openmp_step_cost.json

Two trainings are built as the train stage builds them (`recon.plans.training`) on the scene's 02_scene and take
`--warmup` steps each; then they take turns (step_cost.py's `take_turns`), `--rounds` rounds of `--block` steps, the
second's turns with the other library (REV's march.c built with recon's flags for this CPU; its functions must take the
same arguments, or it is refused), the other slicing, the second read, the one-thread backward, recon's threads, the
torch rays, the torch compositing, the levels in turn, the guessed room or the levels coarsest first. The record
gives each one's ms a step and the ratio, the sliced native calls a step. Both compute the same values
(tests/test_native_march.py, tests/test_masked_adam.py; the C rays and compositing to a float32 rounding); their
trainings draw rays from one random stream in turns, so they do not end equal. With `--renders N`, the first
training's field then renders N test views with each in turns (ms a render). A measurement: it asserts nothing.
"""
from __future__ import annotations

import ctypes
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_syncs import build_step, scene_row, step_parser  # noqa: E402  (gpu_syncs puts this checkout's recon first)
from step_cost import take_turns, turn_arguments, turn_rows  # noqa: E402

T = TypeVar("T")


def pool_map(n: int, fn: Callable[[int, int], T]) -> list[T]:
    """The slices of `_in_slices`, each handed to the thread pool, the caller waiting for all of them."""
    from recon.nerf.native import _thread_pool

    workers = max(1, min(torch.get_num_threads(), n // 1024))
    if workers == 1:
        return [fn(0, n)]
    slices = 4 * workers
    bounds = [n * i // slices for i in range(slices + 1)]
    return list(_thread_pool(workers).map(fn, bounds[:-1], bounds[1:]))


def serial_backward(x01: torch.Tensor, grad_out: torch.Tensor, res: int, out: torch.Tensor, accumulate: bool,
                    touched: torch.Tensor | None) -> torch.Tensor:
    """`recon.nerf.native.trilinear_backward_native` into a grid's gradient, all of it as one part on this thread."""
    from recon.nerf.native import _flags_pointer, native_marcher

    x01, grad_out = x01.detach().contiguous(), grad_out.detach().contiguous()
    native_marcher().recon_trilinear_backward(x01.shape[0], x01.data_ptr(), grad_out.data_ptr(), res,
                                              grad_out.shape[1], out.data_ptr(), _flags_pointer(touched, out), 0, 1)
    return out


def in_slice_views(fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], f: torch.Tensor,
                   d: torch.Tensor) -> torch.Tensor:
    """`recon.nerf.fast.in_slices` recording on views f[s : s + MLP_SLICE]: each view's backward fills a zeroed
    gradient of all of f and adds it in."""
    from recon.nerf.fast import MLP_SLICE

    if f.shape[0] <= MLP_SLICE or not torch.is_grad_enabled():
        return fn(f, d)
    return torch.cat([fn(f[s: s + MLP_SLICE], d[s: s + MLP_SLICE]) for s in range(0, f.shape[0], MLP_SLICE)])


def guessed_room(*args: Any) -> Callable[[int, int, int], torch.Tensor]:
    """`recon.nerf.native._march_room` as the fixed guess it replaced: 48 samples a ray for a training march, 24
    coloured samples a ray for a render's (slice s of rays lo..hi from its first ray times the guess on)."""
    per_ray = 24 if sys._getframe(1).f_code.co_name == "march_render_native" else 48

    def room(lo: int, hi: int, slices: int) -> torch.Tensor:
        return torch.tensor([per_ray * ((hi - lo) * s // slices) for s in range(slices + 1)], dtype=torch.long)
    return room


def render_turns(args: Any, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The first training's field renders ``args.renders`` test views (training resolution, no gradients) with each
    run's setting in turns: rounds of every view once."""
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import load_views
    from recon.nerf.evaluate import render_image

    scene = load_scene(args.scene / "02_scene", recorded_source(args.scene))
    frames = (scene.split("test") or scene.split("val") or scene.split("train"))[: args.renders]
    views = load_views(scene, frames, load_config(args.preset, args.set).train.max_side)
    model = runs[0]["step"].model

    def render(i: int) -> None:
        view = views[i % len(views)]
        box: dict[str, Any] = ({"near": view.near, "far": view.far} if model.config.unbounded
                               else {"aabb": model.aabb})
        with torch.no_grad():
            render_image(model, torch.tensor(view.c2w, dtype=torch.float32), view.intrinsics, *view.hw, **box)

    turns = [{"value": run["value"], "step": render, "next": 0, "enter": run["enter"]} for run in runs]
    take_turns(turns, args.rounds, len(views), lambda: None)
    return {"views": [v.name for v in views], "size": [list(v.hw) for v in views], "runs": turns}


def prototypes(c_source: str) -> dict[str, str]:
    """Each exported `recon_*` function of a C source -> its parameter list, whitespace made single spaces."""
    return {m[1]: " ".join(m[2].split()) for m in re.finditer(r"^\w+\s+(recon_\w+)\(([^)]*)\)", c_source, re.M)}


def library_of(rev: str, folder: Path) -> ctypes.CDLL:
    """REV's march.c, built as recon builds this checkout's (`recon.nerf.native`), its functions' signatures set."""
    import recon.nerf.native as native

    source = folder / "march.c"
    source.write_text(subprocess.run(["git", "show", f"{rev}:recon/nerf/march.c"], capture_output=True, text=True,
                                     check=True, cwd=native.SOURCE.parent).stdout)
    theirs_, ours_ = prototypes(source.read_text()), prototypes(native.SOURCE.read_text())
    changed = sorted(name for name in theirs_.keys() & ours_.keys() if theirs_[name] != ours_[name])
    if changed:
        raise SystemExit(f"error: {rev}'s march.c takes other arguments in {', '.join(changed)}: measure it against "
                         "a revision whose functions take this checkout's arguments (or run this script at that one)")
    native._build(os.environ.get("CC") or "cc", [*native.CFLAGS, *native.HOST_CFLAGS], source, folder / "march.so")
    lib = ctypes.CDLL(str(folder / "march.so"))
    ours = native.native_marcher()
    for name in dir(ours):
        if name.startswith("recon_") and hasattr(getattr(ours, name), "argtypes") and hasattr(lib, name):
            theirs, mine = getattr(lib, name), getattr(ours, name)
            theirs.argtypes, theirs.restype = mine.argtypes, mine.restype
    return lib


def main(argv: list[str] | None = None) -> int:
    import recon.nerf.fast as fast
    import recon.nerf.fitting as fitting
    import recon.nerf.grid as grid
    import recon.nerf.native as native
    import recon.nerf.rays as rays
    from recon.atomic import write_json_atomic
    from recon.nerf.fast import FastModel

    parser = step_parser(__doc__)
    parser.add_argument("--against", required=True,
                        help="a git revision, pool-map, reads-again, serial-backward, python-threads, torch-rays, "
                             "torch-compositing, serial-levels, guessed-room, slice-views or coarsest-first")
    turn_arguments(parser, warmup=300)
    parser.add_argument("--renders", type=int, default=0,
                        help="then the first training's field renders this many test views with each in turns")
    args = parser.parse_args(argv)
    row = scene_row("native_step_cost", args)
    if row is None:
        return 2
    if native.native_marcher() is None:
        print(f"error: the native library is not loaded here ({native.native_status()})", file=sys.stderr)
        return 2
    calls = {"n": 0}
    patched = [(native, "_in_slices"), (native, "native_marcher"), (FastModel, "_marched_sigma"),
               (grid, "trilinear_backward_native"), (native, "_parallel_in_c"), (fitting, "pixel_rays_native"),
               (rays, "ray_box_native"), (fast, "composite_packed_native"), (fast, "distortion_packed_native"),
               (grid, "trilinear_backward_levels_native"), (native, "_march_room"), (native, "MARCH_RAYS_A_THREAD"),
               (fast, "in_slices"), (native, "_levels_order")]
    originals = {(owner, name): getattr(owner, name) for owner, name in patched}

    def counted(slices: Callable[[int, Callable[[int, int], T]], list[T]]) -> Callable[..., list[T]]:
        def call(n: int, fn: Callable[[int, int], T]) -> list[T]:
            calls["n"] += 1
            return slices(n, fn)
        return call

    with tempfile.TemporaryDirectory() as tmp:
        ours = {**originals, (native, "_in_slices"): counted(originals[(native, "_in_slices")])}
        if args.against == "pool-map":
            other: dict[tuple[Any, str], Any] = {(native, "_in_slices"): counted(pool_map)}
        elif args.against == "reads-again":
            other = {(FastModel, "_marched_sigma"): lambda self, sigma, u: None}
        elif args.against == "serial-backward":
            other = {(grid, "trilinear_backward_native"): serial_backward}
        elif args.against == "python-threads":
            other = {(native, "_parallel_in_c"): lambda lib: False}
        elif args.against == "torch-rays":
            other = {(fitting, "pixel_rays_native"): lambda *args: None, (rays, "ray_box_native"): lambda *args: None}
        elif args.against == "torch-compositing":
            other = {(fast, "composite_packed_native"): lambda *args: None,
                     (fast, "distortion_packed_native"): lambda *args: None}
        elif args.against == "serial-levels":
            other = {(grid, "trilinear_backward_levels_native"): lambda *args: False}
        elif args.against == "slice-views":
            other = {(fast, "in_slices"): in_slice_views}
        elif args.against == "coarsest-first":
            other = {(native, "_levels_order"): lambda resolutions: list(range(len(resolutions)))}
        elif args.against == "guessed-room":
            other = {(native, "_march_room"): guessed_room, (native, "MARCH_RAYS_A_THREAD"): 1024}
        else:
            base = library_of(args.against, Path(tmp))
            other = {(native, "native_marcher"): lambda: base}
        settings = {"this checkout": ours, args.against: {**ours, **other}}
        runs = []
        for value, names in settings.items():
            def enter(names=names) -> None:
                for (owner, name), fn in names.items():
                    setattr(owner, name, fn)

            enter()
            step, plan, device = build_step(args.scene, args.preset, args.set)
            for i in range(args.warmup):
                step(i)
            runs.append({"value": value, "step": step, "next": args.warmup, "enter": enter})
        try:
            calls["n"] = 0
            take_turns(runs, args.rounds, args.block, lambda: None)
            renders = render_turns(args, runs) if args.renders else None
        finally:
            for (owner, name), fn in originals.items():
                setattr(owner, name, fn)
    row.update({"against": args.against, "device": str(device), "batch_rays": plan.batch_rays,
                "warmup": args.warmup, "rounds": args.rounds, "block": args.block, "threads": torch.get_num_threads(),
                "values": turn_rows(runs),
                "sliced_native_calls_a_step": round(calls["n"] / (2 * args.rounds * args.block), 1)})
    if renders is not None:
        row["renders"] = {"views": renders["views"], "size": renders["size"], "values": turn_rows(renders["runs"])}
    write_json_atomic(args.out, [row])
    for v in row["values"]:
        print(f"{v['value']}: {v['ms_per_step_median']} ms a step (median of {args.rounds} rounds), "
              f"{v['cost_vs_first']}x the first")
    print(f"{row['sliced_native_calls_a_step']} sliced native calls a step")
    for v in row.get("renders", {}).get("values", []):
        print(f"{v['value']}: {v['ms_per_step_median']} ms a render (median of {args.rounds} rounds), "
              f"{v['cost_vs_first']}x the first")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Compile the fast model's Triton kernels for NVIDIA cards on a machine without one, as a card's training launches
them.

    python benchmarks/triton_compile.py --out benchmarks/results/triton_compile.json        # sm_90 (H100/H200), sm_80

Triton compiles for a named target ahead of time (the LLVM and ptxas it needs ship in its wheel), so a CPU machine
can say whether each kernel builds for a card, with how many registers a thread and spills: a kernel the
interpreter runs can still fail to compile (types, constexprs), and the one-per-session device time is better spent
measuring than finding that out. The launches compiled are recorded, not written out by hand: a child process runs
the card-sized fast model (`recon.config.device_sizing` for `--memory-gib`; the hash grid's probe, a training render
and its backward with the distortion loss on, a no-gradient render; the same with the colour features in dense
grids, and an unbounded scene; a ray batcher's batches) under Triton's interpreter on CPU tensors, and notes each
launch's argument types, constexprs and warps. Each distinct launch is then compiled for each `--targets` capability.

Writes one record (with the commit, machine and Triton version, as every record in benchmarks/results/): per launch
and target, compiled or the compiler's error, registers a thread, local (spilled) and shared bytes, and the seconds it
took to compile in a fresh cache (a card's first run compiles the same before its time budget). Exits 1 when a launch
fails to compile. A measurement of what a card would be given; it runs nothing on one.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon (its commit is the one recorded)

TARGETS = (90, 80)
"""Compute capabilities compiled for by default: Hopper (H100, H200) and Ampere (A100)."""
LAUNCH_OPTIONS = ("num_warps", "num_stages", "enable_fp_fusion")
"""Launch keywords that are compiler options, not kernel arguments."""


# ----------------------------------------------------------------------------------------------------------------
# the child: a card's launches under the interpreter
SMALL_GRIDS = {"density_res": 48, "feature_res": 96, "occupancy_res": 16, "hash_table_log2": 12}
"""--small: the card's models at these grid sizes (the same kernels and constexprs, a faster interpreter run)."""


CARD_MODELS = {"card-sized fast preset": [], "dense colour features": ["train.fast.grid=dense"], "unbounded scene": []}
"""The models a card trains and the overrides that make each (dense features: gpu_check's dense column)."""


def card_models(memory_gib: float, small: bool = False, only: int = len(CARD_MODELS)) -> list[tuple[str, Any]]:
    """(what, FastConfig) of the models a card trains: the fast preset sized for the card (colour features in a hash
    grid), the same with dense feature grids (a --set of a feature key), and an unbounded scene's (the first ``only``
    of them); ``small``: at SMALL_GRIDS' sizes."""
    from recon.config import device_sizing, load_config

    models = []
    for what, overrides in list(CARD_MODELS.items())[:only]:
        config = load_config("fast", overrides)
        keep = frozenset(o.partition("=")[0] for o in overrides)
        config, _ = device_sizing(config, int(memory_gib * 2**30), f"{memory_gib:g} GiB", keep)
        fast = dataclasses.replace(config.train.fast, kernels="triton", unbounded=what == "unbounded scene",
                                   **(SMALL_GRIDS if small else {}))
        models.append((what, fast))
    return models


def record_launches(memory_gib: float, rays: int, small: bool = False, models: int = len(CARD_MODELS)
                    ) -> list[dict[str, Any]]:
    """Every Triton launch (kernel, argument types, constexprs, options) of a card's training and rendering, run
    under the interpreter (TRITON_INTERPRET=1 must be set before triton is imported)."""
    import torch
    import triton.runtime.interpreter as interpreter
    from triton.runtime.jit import mangle_type

    from recon.nerf import kernels
    from recon.nerf.fast import FastModel
    from recon.nerf.fitting import RayBatcher
    from recon.nerf.grid import hash_kernel_check
    from recon.nerf.model_config import HASH_FEATURES

    seen: dict[str, dict[str, Any]] = {}
    run = interpreter.InterpretedFunction.run
    where = [""]

    def noted_run(self: Any, *args: Any, grid: Any, warmup: bool, **kwargs: Any) -> Any:
        arguments = dict(zip(self.arg_names, args))
        arguments.update({k: v for k, v in kwargs.items() if k not in LAUNCH_OPTIONS})
        params = inspect.signature(self.fn).parameters
        constexpr = {k for k, p in params.items() if "constexpr" in str(p.annotation)}
        launch = {"kernel": self.fn.__name__,  # a constexpr's value, any other argument's type
                  "arguments": {k: (v if k in constexpr else mangle_type(v)) for k, v in arguments.items()},
                  "options": {k: kwargs[k] for k in LAUNCH_OPTIONS if k in kwargs}}
        key = json.dumps(launch, sort_keys=True)
        seen.setdefault(key, {**launch, "from": where[0]})
        return run(self, *args, grid=grid, warmup=warmup, **kwargs)

    kernels.KERNEL_DEVICES = ("cuda", "cpu")
    interpreter.InterpretedFunction.run = noted_run
    try:
        for what, cfg in card_models(memory_gib, small, models):
            if cfg.grid == "hash":  # as the train stage probes it, before training
                where[0] = f"{what}: the hash grid's probe"
                hash_kernel_check("cpu", cfg.feature_dim, HASH_FEATURES)
            torch.manual_seed(0)
            model = FastModel(cfg)
            model.progress = 0.5  # the distortion loss on (a card starts it at a tenth of training)
            g = torch.Generator().manual_seed(1)
            rays_d = torch.nn.functional.normalize(torch.randn(rays, 3, generator=g) * 0.2
                                                   + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
            rays_o = torch.tensor([0.0, 0.0, 2.5]) + 0.2 * torch.randn(rays, 3, generator=g)
            near, far = torch.full((rays,), 0.5), torch.full((rays,), 4.5)
            where[0] = f"{what}: training render and backward"
            out = model.render_rays(rays_o, rays_d, near, far, training=True, background=torch.ones(3))
            loss = out["rgb"].square().sum() + out.get("reg", 0.0)
            loss.backward()
            where[0] = f"{what}: render without gradients"
            with torch.no_grad():
                model.eval().render_rays(rays_o, rays_d, near, far, training=False, background=torch.ones(3))
        where[0] = "a batch's rays (a scene box; photos' near and far)"
        photos = [torch.rand(6, 8, 3) for _ in range(3)]
        c2w = torch.eye(4).repeat(3, 1, 1)
        c2w[:, 2, 3] = 3.0
        intrinsics = torch.tensor([[8.0, 8.0, 4.0, 3.0]]).repeat(3, 1)
        for bounds in ({"aabb": torch.tensor([[-1.0] * 3, [1.0] * 3])}, {"near_far": torch.tensor([0.5, 6.0])}):
            RayBatcher(photos, c2w, intrinsics, kernels="triton", **bounds).next_batch(16)
    finally:
        interpreter.InterpretedFunction.run = run
        kernels.KERNEL_DEVICES = ("cuda",)
    return list(seen.values())


# ----------------------------------------------------------------------------------------------------------------
# the parent: compile each launch for each target
def compile_launch(launch: dict[str, Any], capability: int) -> dict[str, Any]:
    """Compile one recorded launch for a CUDA ``capability`` (e.g. 90): ok, registers, spills, shared bytes, seconds,
    or the compiler's error."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from recon.nerf import triton_kernels

    fn = getattr(triton_kernels, launch["kernel"])
    signature, constexprs = {}, {}
    for param in fn.params:
        value = launch["arguments"][param.name]
        if param.is_constexpr:
            signature[param.name], constexprs[param.name] = "constexpr", value
        else:  # the recorded type; a scalar's never specialized on its value: the general kernel
            signature[param.name] = value
    t0 = time.perf_counter()
    try:
        compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=constexprs),
                                  target=GPUTarget("cuda", capability, 32), options=launch["options"])
    except Exception as exc:  # the compiler's message is the result
        return {"ok": False, "error": f"{type(exc).__name__}: {str(exc).strip()[:2000]}",
                "seconds": round(time.perf_counter() - t0, 1)}
    seconds = round(time.perf_counter() - t0, 1)
    return {"ok": True, **cubin_resources(compiled.asm["cubin"], launch["kernel"]),
            "num_warps": int(compiled.metadata.num_warps), "seconds": seconds}


def cubin_resources(cubin: bytes, kernel: str) -> dict[str, int]:
    """What the compiled kernel asks of a card (cuobjdump, shipped with Triton, reads the cubin): registers a thread,
    stack and local (spilled) bytes a thread, static shared bytes."""
    from triton import knobs

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"{kernel}.cubin"
        path.write_bytes(cubin)
        text = subprocess.run([knobs.nvidia.cuobjdump.path, "--dump-resource-usage", str(path)], check=True,
                              capture_output=True, text=True).stdout
    usage = text.split(f"Function {kernel}:", 1)[1].split()
    fields = dict(item.split(":", 1) for item in usage if ":" in item)
    return {"registers": int(fields["REG"]), "stack_bytes": int(fields["STACK"]), "local_bytes": int(fields["LOCAL"]),
            "shared_bytes": int(fields["SHARED"])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="the record to write (JSON)")
    parser.add_argument("--targets", default=",".join(str(t) for t in TARGETS),
                        help="CUDA compute capabilities, comma-separated (90: H100/H200, 80: A100, 89: L4/L40)")
    parser.add_argument("--memory-gib", type=float, default=80.0, help="the card's memory, for the sizing (H100: 80)")
    parser.add_argument("--rays", type=int, default=16, help="rays a recorded render (the interpreter's pace)")
    parser.add_argument("--kernels", default="", help="compile only these kernels (comma-separated names)")
    parser.add_argument("--small", action="store_true", help="record the launches at small grids (the same kernels)")
    parser.add_argument("--models", type=int, default=len(CARD_MODELS),
                        help=f"record the first N of the card's models ({', '.join(CARD_MODELS)})")
    parser.add_argument("--record-launches", type=Path, help=argparse.SUPPRESS)  # the child's output
    args = parser.parse_args(argv)
    if args.record_launches:
        args.record_launches.write_text(json.dumps(record_launches(args.memory_gib, args.rays, args.small,
                                                                  args.models)))
        return 0
    if args.out is None:
        parser.error("--out is required")
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic

    row: dict[str, Any] = {"name": "triton_compile", "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **provenance(),
                           "load_average_start": [round(x, 2) for x in os.getloadavg()],
                           "memory_gib": args.memory_gib, "small_grids": args.small,
                           "targets": [int(t) for t in args.targets.split(",")]}
    scratch = tempfile.TemporaryDirectory(prefix="triton_compile_")
    launches_file = Path(scratch.name) / "launches.json"
    t0 = time.perf_counter()
    child = subprocess.run([sys.executable, __file__, "--record-launches", str(launches_file),
                            "--memory-gib", str(args.memory_gib), "--rays", str(args.rays),
                            "--models", str(args.models),
                            *(["--small"] if args.small else [])],
                           env={**os.environ, "TRITON_INTERPRET": "1", "RECON_NATIVE": "0"},
                           capture_output=True, text=True)
    if child.returncode:
        print(child.stdout[-4000:], child.stderr[-4000:], sep="\n", file=sys.stderr)
        print("error: recording the launches under Triton's interpreter failed (above)", file=sys.stderr)
        return 1
    launches = json.loads(launches_file.read_text())
    scratch.cleanup()
    row["record_seconds"] = round(time.perf_counter() - t0, 1)
    import triton

    row["triton"] = triton.__version__
    cache = tempfile.TemporaryDirectory(prefix="triton_cache_")
    os.environ["TRITON_CACHE_DIR"] = cache.name  # compile every launch (the seconds are a first run's)
    wanted = {k for k in args.kernels.split(",") if k}
    rows = []
    for launch in launches:
        if wanted and launch["kernel"] not in wanted:
            continue
        for capability in row["targets"]:
            result = compile_launch(launch, capability)
            rows.append({**launch, "target": f"sm_{capability}", **result})
            shown = (f"{result['registers']} registers, {result['local_bytes']} B local, "
                     f"{result['shared_bytes']} B shared" if result["ok"] else result["error"].splitlines()[0][:200])
            print(f"{launch['kernel']:16s} sm_{capability}  {'ok ' if result['ok'] else 'FAILED'}  {shown}  "
                  f"({result['seconds']} s; {launch['from']})", flush=True)
    cache.cleanup()
    row["launches"] = rows
    row["failed"] = sum(not r["ok"] for r in rows)
    write_json_atomic(args.out, [row])
    print(f"{len(rows) - row['failed']} of {len(rows)} compiled; record: {args.out}")
    return 1 if row["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())

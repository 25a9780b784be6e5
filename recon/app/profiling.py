"""`recon bench --profile`: where one training step and one test render of the grid model spend their time.

Builds the model and ray batcher exactly as the train stage does (same preset, same scene), trains
``warmup`` steps so the occupancy grid and the grid shrink are in their steady state, then records
``steps`` steps and one full-size test render with ``torch.profiler``. Time is attributed to the parts of a
step (ray batch, occupancy refresh, marcher, density and color grids, compositing, backward per kind,
Adam) by labels wrapped around the model's functions from here, so the library carries no profiling code.
Each part is compared with what this CPU does at best: a large matmul's GFLOP/s and a memory copy's GB/s,
measured in the same process. On CUDA (where `train.device` puts training) the same parts are also given in GPU
time, the kernels each part launched: a part whose host milliseconds exceed its GPU milliseconds waits on launches
and host reads, not on the card. A benchmark measures; it asserts nothing.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from recon.capture.scene import Scene
    from recon.config import TrainConfig
    from recon.evaluation.views import View
    from recon.plans.training import TrainPlan, TrainSetup

BACKWARD_KINDS = (
    ("GridSampler", "density grid bwd"),
    ("GatherInterp", "feature grid bwd"),
    ("NativeRead", "grid bwd (native: density levels + features)"),
    ("MarchedDensity", "grid bwd (native: density levels + features)"),  # the march's densities, differentiable
    ("Addmm", "MLP bwd"), ("Mm", "MLP bwd"), ("Relu", "MLP bwd"), ("Threshold", "MLP bwd"), ("TBackward", "MLP bwd"),
    ("Sigmoid", "MLP bwd"), ("CatBackward", "MLP bwd"), ("SliceBackward", "MLP bwd"),  # the MLP's slices
)
"""Autograd node name fragments -> part of the step (everything else in backward is 'compositing bwd')."""


def machine_limits(seconds: float = 1.0) -> dict[str, float]:
    """This CPU's plain throughput, measured now: fp32 (and bf16) matmul GFLOP/s, memory copy GB/s
    (bytes read + written), random row gather GB/s (the access pattern of a grid lookup), on torch's threads."""

    def rate(fn: Callable[[], Any]) -> float:
        fn()
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            fn()
            n += 1
        return n / (time.perf_counter() - t0)

    out: dict[str, float] = {"threads": float(torch.get_num_threads())}
    a = torch.randn(2048, 2048)
    out["matmul_fp32_gflops"] = 2 * 2048**3 * rate(lambda: a @ a) / 1e9
    ab = a.bfloat16()
    out["matmul_bf16_gflops"] = 2 * 2048**3 * rate(lambda: ab @ ab) / 1e9
    x, w = torch.randn(65536, 64), torch.randn(64, 64)
    out["matmul_mlp_shape_gflops"] = 2 * 65536 * 64 * 64 * rate(lambda: x @ w) / 1e9
    src = torch.empty(64 << 20, dtype=torch.float32).fill_(1.0)  # 256 MB
    dst = torch.empty_like(src)
    out["copy_gbs"] = 2 * src.numel() * 4 * rate(lambda: dst.copy_(src)) / 1e9
    table = torch.randn(96**3, 12)
    idx = torch.randint(0, table.shape[0], (1 << 20,))
    out["gather_gbs"] = idx.numel() * 12 * 4 * rate(lambda: table.index_select(0, idx)) / 1e9
    return out


@contextlib.contextmanager
def _labelled(targets: list[tuple[Any, ...]]) -> Iterator[dict[str, list[int]]]:
    """Wrap ``owner.name`` in a profiler label for the duration, per target ``(owner, name, label[, aside])``;
    yields, per function name, the row count (first dimension of the first tensor argument) of every call. Calls
    made inside an ``aside`` target (the depth prior's own rays) are left out of the counts: they are not the
    batch's rays."""
    counts: dict[str, list[int]] = defaultdict(list)
    aside_depth = [0]
    saved = []
    for owner, name, label, *rest in targets:
        fn = owner.__dict__[name]
        saved.append((owner, name, fn))

        def wrapper(*args: Any, _fn: Callable = fn, _label: str = label, _name: str = name,
                    _aside: bool = bool(rest and rest[0]), **kwargs: Any) -> Any:
            aside_depth[0] += _aside
            try:
                with torch.profiler.record_function(_label):
                    result = _fn(*args, **kwargs)
            finally:
                aside_depth[0] -= _aside
            if aside_depth[0]:
                return result
            first = next((a for a in args if isinstance(a, torch.Tensor)), None)
            rows = None if first is None else int(first.shape[0])
            # the native marchers evaluate the densities of the samples they keep (None: they did not run)
            if _name in ("march_dense_native", "march_dense_triton"):
                rows = None if result is None else int(result[2].shape[0])
            elif _name == "march_render_native":
                rows = None if result is None else int(result["samples"].sum())
            if rows is not None:
                counts[_name].append(rows)
            return result

        setattr(owner, name, wrapper)
    try:
        yield counts
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


@contextlib.contextmanager
def reference_marching() -> Iterator[None]:
    """The fast model marches as before front-to-back marching (for A/B runs and tests): :func:`march` evaluates
    every occupied candidate's density, and the kept samples' densities are evaluated again."""
    import recon.nerf.fast as fast
    from recon.nerf.occupancy import march

    def reference(rays_o: Any, rays_d: Any, t_near: Any, t_far: Any, occupancy: Any, step_size: float, max_samples: int,
                  sigma_fn: Callable, *, cone_angle: float = 0.0, jitter: bool = False,
                  min_transmittance: float = 1e-4) -> tuple:
        ts, te, ri = march(rays_o, rays_d, t_near, t_far, occupancy, step_size, max_samples, cone_angle=cone_angle,
                           jitter=jitter, sigma_fn=sigma_fn, min_transmittance=min_transmittance)
        return ts, te, ri, sigma_fn(ts, te, ri)

    saved = fast.march_front_to_back, fast.march_dense_native, fast.march_render_native
    fast.march_front_to_back = reference
    fast.march_dense_native = fast.march_render_native = lambda *args, **kwargs: None  # torch, not the native marcher
    try:
        yield
    finally:
        fast.march_front_to_back, fast.march_dense_native, fast.march_render_native = saved


def _part(event: Any) -> str:
    """The part of the step a top-level profiler event belongs to."""
    name = event.name
    if name.startswith("autograd::engine::evaluate_function"):
        node = name.split(":")[-1]
        return next((part for frag, part in BACKWARD_KINDS if frag in node), "compositing bwd")
    if name.startswith("Optimizer.step"):
        return "Adam step"
    if name.startswith("Optimizer.zero_grad"):
        return "zero_grad"
    if name.startswith("recon:"):
        return name[len("recon:"):]
    return "other ops (loss, glue)"


def attribute(prof: torch.profiler.profile, gpu: bool = False) -> dict[str, float]:
    """Seconds per part: each top-level event (no parent) counted once, by its label or autograd node; its host
    time, or with `gpu` the time of the GPU kernels it (and the events under it) launched."""
    parts: dict[str, float] = defaultdict(float)
    for ev in prof.events():
        if ev.cpu_parent is None and ev.device_type == torch.autograd.DeviceType.CPU:
            parts[_part(ev)] += (ev.device_time_total if gpu else ev.cpu_time_total) / 1e6
    return dict(parts)


def _activities(device: torch.device) -> list[Any]:
    cuda = [torch.profiler.ProfilerActivity.CUDA] if device.type == "cuda" else []
    return [torch.profiler.ProfilerActivity.CPU, *cuda]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _labels(model: Any) -> list[tuple[Any, ...]]:
    import recon.nerf.fast as fast
    from recon.nerf.depth_prior import DepthPrior
    from recon.nerf.fitting import RayBatcher
    from recon.nerf.smoothness import PatchSmoothness

    return [
        (fast, "march", "recon:marcher (occupancy skip + no-grad density pre-pass)"),
        (fast, "march_front_to_back", "recon:marcher (occupancy skip + no-grad density pre-pass)"),
        (fast, "march_dense_native", "recon:marcher (occupancy skip + no-grad density pre-pass)"),
        (fast, "march_dense_triton", "recon:marcher (occupancy skip + no-grad density pre-pass)"),
        (fast, "march_render_native", "recon:marcher (native, with compositing)"),
        (type(model), "_sigma_unit", "recon:density grid fwd"),
        (type(model), "_rgb_unit", "recon:feature grid + color MLP fwd"),
        (fast, "render_weights_packed", "recon:compositing fwd"),
        (fast, "accumulate_packed", "recon:compositing fwd"),
        (type(model), "step_update", "recon:occupancy refresh"),
        (RayBatcher, "next_batch", "recon:ray batch"),
        (DepthPrior, "__call__", "recon:depth prior fwd (its own rays: march, render, loss)", True),
        (PatchSmoothness, "__call__", "recon:depth smoothness fwd (its own patches: march, render, loss)", True),
    ]


def _table(parts: dict[str, float], per: int, wall: float, unit: str,
           gpu: dict[str, float] | None = None) -> list[str]:
    """A part's host milliseconds and share of the wall per `unit`; with `gpu` (CUDA) its GPU kernels' milliseconds."""
    g = (lambda name: f" {1000 * gpu.get(name, 0.0) / per:.1f} |") if gpu is not None else (lambda name: "")
    lines = [f"| part | ms per {unit} | share of wall |" + (" GPU ms |" if gpu is not None else ""),
             "|---|---|---|" + ("---|" if gpu is not None else "")]
    for name, s in sorted(parts.items(), key=lambda kv: -kv[1]):
        lines.append(f"| {name} | {1000 * s / per:.1f} | {100 * s / wall:.0f}% |" + g(name))
    untracked = wall - sum(parts.values())
    lines.append(f"| Python between ops (wall − ops) | {1000 * untracked / per:.1f} | {100 * untracked / wall:.0f}% |"
                 + (" |" if gpu is not None else ""))
    total = f" **{1000 * sum(gpu.values()) / per:.1f}** |" if gpu is not None else ""
    lines.append(f"| **wall** | **{1000 * wall / per:.1f}** | 100% |" + total)
    return lines


def profile_training(cfg: TrainConfig, scene: Scene, views: list[View], report: Any, *, warmup: int = 200,
                     steps: int = 8, title: str = "", device: torch.device | None = None,
                     ) -> tuple[dict[str, Any], TrainPlan, TrainSetup]:
    """Plan and build training on `device` (default the CPU) as the train stage does (`recon.plans.training`), train
    ``warmup`` steps, then profile ``steps`` more: (the numbers, the plan, what was built). ``views``: the training
    photos."""
    from recon.nerf.trainer import train
    from recon.plans.training import build_training, plan_training

    device = device or torch.device("cpu")
    plan = plan_training(cfg, scene, views, device)
    if plan.kind != "fast":
        raise ValueError(f"--profile measures the fast grid model; {title or 'this configuration'} trains '{plan.kind}'")
    setup = build_training(plan, device)
    prof = torch.profiler.profile(activities=_activities(device))
    marks: dict[str, float] = {}

    def on_step(p: Any) -> None:
        if p.step == warmup:
            _sync(device)
            marks["t0"] = time.perf_counter()
            prof.start()
        elif p.step == warmup + steps:
            _sync(device)
            prof.stop()
            marks["t1"] = time.perf_counter()

    with report.task(f"{title}: {warmup} warm-up + {steps} profiled steps", total=None):
        with _labelled(_labels(setup.model)) as counts:
            result = train(setup.model, setup.batcher, steps=warmup + steps, **setup.step_kwargs, callbacks=[on_step])
            # the samples composited: counted where torch composites them, else where a fused marcher made them
            samples = (counts["render_weights_packed"] or counts["march_dense_triton"]
                       or counts["march_dense_native"])[-steps:]
            colored = counts["_rgb_unit"][-steps:]
    res: dict[str, Any] = {
        "warmup": warmup, "profiled_steps": steps, "batch_rays": plan.batch_rays, "wall_s": marks["t1"] - marks["t0"],
        "parts": attribute(prof), "train_psnr": result["psnr"], "device": str(device),
        "samples_per_ray": float(np.mean(samples)) / plan.batch_rays if samples else float("nan"),
        "colored_per_ray": float(np.mean(colored)) / plan.batch_rays if colored else float("nan"),
        "params": sum(p.numel() for p in setup.model.parameters()),
        "pieces": [type(p).__name__ for p in setup.step_kwargs["pieces"]],
        "reasons": plan.reasons,
        "top_ops": prof.key_averages().table(sort_by=_sort_key(device), row_limit=15),
    }
    if device.type == "cuda":
        res["gpu_parts"] = attribute(prof, gpu=True)
    return res, plan, setup


def _sort_key(device: torch.device) -> str:
    return "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"


def profile_preset(data: str, preset: str, out_dir: Path, overrides: list[str], report: Any, *,
                   warmup: int = 200, steps: int = 8, render: bool = True) -> dict[str, Any]:
    """Profile ``steps`` training steps of ``preset`` after ``warmup`` steps, and one test render; return the numbers
    and write nothing (the caller writes profile.md)."""
    from recon.app.bench import prepare_scene
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import load_views
    from recon.nerf.device import select_device
    from recon.nerf.evaluate import render_image
    from recon.plans.training import training_side

    config = load_config(preset, overrides)
    scene_dir = prepare_scene(data, out_dir, load_config(None, overrides), report)
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    cfg = replace(config.train, max_side=training_side(config.train, scene, scene.split("train"))[0])  # as train does
    views = load_views(scene, scene.split("train"), cfg.max_side, report, "training photos")
    device = select_device(cfg.device)
    step, plan, setup = profile_training(cfg, scene, views, report, warmup=warmup, steps=steps, title=preset,
                                         device=device)
    res: dict[str, Any] = {"preset": preset, "data": data, **step}
    if render:
        model, aabb, background = setup.model, setup.aabb, torch.tensor(plan.background)
        test = scene.split("test") or scene.split("val") or scene.split("train")
        view = load_views(scene, test[:1], cfg.max_side)[0]
        h, w = view.hw
        c2w_t = torch.tensor(view.c2w, dtype=torch.float32, device=device)
        box: dict[str, Any] = {"aabb": aabb} if aabb is not None else {"near": view.near, "far": view.far}
        render_image(model, c2w_t, view.intrinsics, 32, 32, autocast=plan.autocast, **box)  # first-call costs out of the timing
        rprof = torch.profiler.profile(activities=_activities(device))
        with _labelled(_labels(model)) as rcounts:
            _sync(device)
            t0 = time.perf_counter()
            with rprof:
                render_image(model, c2w_t, view.intrinsics, h, w, background=background, autocast=plan.autocast, **box)
                _sync(device)
            rwall = time.perf_counter() - t0
        res["render"] = {"view": view.name, "size": f"{w}×{h}", "wall_s": rwall, "parts": attribute(rprof),
                         "samples": sum(rcounts["_sigma_unit"]) + sum(rcounts["march_dense_native"])
                         + sum(rcounts["march_dense_triton"])
                         + sum(rcounts["march_render_native"]),
                         "rays": h * w,
                         "top_ops": rprof.key_averages().table(sort_by=_sort_key(device), row_limit=12)}
        if device.type == "cuda":
            res["render"]["gpu_parts"] = attribute(rprof, gpu=True)
    return res


def markdown(results: list[dict[str, Any]], limits: dict[str, float], where: dict[str, Any]) -> str:
    """profile.md: where it ran, the machine's limits, then per preset the step and render tables and the op
    tables."""
    from recon.app.bench import machine_name

    def load(values: list[float] | None) -> str:
        return " / ".join(f"{v:.2f}" for v in values) if values else "unknown"

    def rate(value: float) -> str:  # a CPU without bf16 units runs its matmul at a fraction of one GFLOP/s
        return f"{value:,.0f}" if value >= 10 else f"{value:.2g}"

    commit = (where.get("commit") or "unknown")[:7] + (" with uncommitted changes" if where.get("uncommitted_changes")
                                                       else "")
    lines = [
        "# recon bench --profile",
        "",
        f"Commit {commit}, {where['date']}, on {machine_name(where['machine'])}. "
        f"Load average (1 / 5 / 15 min) {load(where['load_average_start'])} at the start, "
        f"{load(where['load_average_end'])} at the end; {int(limits['threads'])} torch threads, "
        f"{os.cpu_count()} CPUs.",
        "",
        "| this CPU, measured in the same process | |",
        "|---|---|",
        f"| matmul 2048² fp32 | {rate(limits['matmul_fp32_gflops'])} GFLOP/s |",
        f"| matmul 2048² bf16 | {rate(limits['matmul_bf16_gflops'])} GFLOP/s |",
        f"| matmul 65536×64 · 64×64 fp32 (the color MLP's shape) | {rate(limits['matmul_mlp_shape_gflops'])} "
        "GFLOP/s |",
        f"| memory copy 256 MB (read + write) | {limits['copy_gbs']:.1f} GB/s |",
        f"| random row gather, 96³×12 fp32 table | {limits['gather_gbs']:.1f} GB/s |",
        "",
    ]
    for r in results:
        lines += [
            f"## {r['preset']} on {r['data']}: {r['profiled_steps']} steps after {r['warmup']}",
            "",
            f"Device {r['device']}.",
            "",
            f"{r['batch_rays']} rays/step, {r['samples_per_ray']:.1f} samples/ray after the marcher, "
            f"{r['colored_per_ray']:.1f} colored/ray, {r['params'] / 1e6:.1f} M parameters, "
            f"{r['profiled_steps'] * r['batch_rays'] / r['wall_s']:,.0f} rays/s while profiled; the step's pieces (as the train "
            f"stage plans them): {', '.join(r['pieces']) or 'none'}.",
            "",
            *_table(r["parts"], r["profiled_steps"], r["wall_s"], "step", r.get("gpu_parts")),
            "",
        ]
        if "render" in r:
            rr = r["render"]
            lines += [
                f"Test render {rr['view']} ({rr['size']}): {rr['wall_s']:.2f} s, "
                f"{rr['samples'] / rr['rays']:.1f} density evaluations/ray.",
                "",
                *_table(rr["parts"], 1, rr["wall_s"], "render", rr.get("gpu_parts")),
                "",
            ]
        lines += ["<details><summary>top ops (step)</summary>", "", "```", r["top_ops"], "```", "", "</details>", ""]
        if "render" in r:
            lines += ["<details><summary>top ops (render)</summary>", "", "```", r["render"]["top_ops"], "```", "",
                      "</details>", ""]
    return "\n".join(lines)


def run_profile(data: str, presets: list[str], out_dir: Path, overrides: list[str], report: Any, *,
                warmup: int = 200, steps: int = 8) -> Path:
    """Profile each preset on ``data``; write ``out_dir/profile.md`` (and profile.json) and return its path."""
    from recon.app.bench import claim_bench_folder, load_average, provenance, resolve_dataset
    from recon.atomic import write_bytes_atomic, write_json_atomic

    resolve_dataset(data)  # a data set that is not there fails before the folder is claimed
    claim_bench_folder(out_dir)
    where = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), **provenance(),
             "load_average_start": load_average()}
    limits = machine_limits()
    results = [profile_preset(data, p, out_dir, overrides, report, warmup=warmup, steps=steps) for p in presets]
    where["load_average_end"] = load_average()
    path = out_dir / "profile.md"
    write_bytes_atomic(path, markdown(results, limits, where))
    write_json_atomic(out_dir / "profile.json", [  # one row a preset, as bench.json
        {"name": r["preset"], **where, "limits": limits, **{k: v for k, v in r.items() if k != "top_ops"}}
        | ({"render": {k: v for k, v in r["render"].items() if k != "top_ops"}} if "render" in r else {})
        for r in results])
    return path

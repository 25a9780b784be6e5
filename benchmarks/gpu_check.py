"""GPU check: one preset on the Lego (known poses: no pycolmap, no network) on the device recon picks, measured.

    python benchmarks/gpu_check.py --out /tmp/gpu_check                 # ≤ 8 min on an H100/H200
    python benchmarks/gpu_check.py --out /tmp/gpu_check --set train.device_sizing=off --set train.compile=off
    python benchmarks/gpu_check.py --out /tmp/smoke --smoke              # ≤ 2 min on a CPU: that it runs

Runs the real pipeline (poses imported from transforms_*.json, normalize, train, mesh) with the preset as
`recon run --preset` would, then prints one table and writes gpu_check.json (with the commit and machine, as every
record in benchmarks/results/): training steps and rays/s, held-out PSNR over the test views (all 200 unless
--test-views), render milliseconds per 400² view (timed after a warm-up, the device synchronized), the mesh stage's
seconds, and the CPU-vs-device agreement: the trained field rendered on the CPU and on the device for the same
views, as the PSNR of one render against the other (the CPU's C marcher against CUDA's torch or Triton path; 40 dB
and up means the two paths draw the same image). A check measures; it asserts nothing.

On CUDA it trains once per column (`--columns`, each the same run but for its overrides): `default` (what recon
does on this card: the preset sized to it, the Triton kernels where recon.nerf.kernels.MEASURED_FASTER, all stages),
`torch` (train.fast.kernels=torch: the kernels' torch references) and `unsized` (train.device_sizing=off: the CPU's
preset values on the GPU), the others training only; before them each Triton kernel is timed against its torch
reference at the preset's batch (which also compiles them before training). On a CPU only the default column runs:
the others are the same run there.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # measure this checkout's recon (its commit is the one recorded), not another install
LEGO_HALF = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_half"

SMOKE = ["train.budget=", "train.steps=80", "train.max_side=50", "train.eval_every=0", "train.appearance=off",
         "train.fast.max_samples=32", "mesh.max_resolution=32", "mesh.texture_faces=0"]
"""--smoke: 80 steps on 50-px photos and a 32³ mesh: that every part runs, not what it measures. Steps, not
seconds: on a busy host a few seconds train too few steps to leave anything to mesh. A field trained for 80 steps is
still fog: every ray marches to its sample cap, and each render (the final
evaluation, the timing, the mesh stage's depth maps of its baking views) pays that cap; 32 samples a ray keep them
to seconds on a CPU. The appearance check (feature matching between photos) is skipped: the Lego's exposure is
constant."""
COLUMNS: dict[str, list[str]] = {
    "default": [],
    "torch": ["train.fast.kernels=torch"],
    "triton": ["train.fast.kernels=triton"],
    "torch-march": [],
    "unsized": ["train.device_sizing=off"],
    "rays16k": ["train.batch_rays=16384", "train.depth_rays=1024"],
    "rays8k": ["train.batch_rays=8192", "train.depth_rays=512"],
    "nodist": ["train.fast.distortion_weight=0"],
    "dist-from-start": ["train.fast.distortion_from=0"],
    "cpu-shuffle": [],
    "no-warmup": [],
    "reverted": ["train.fast.distortion_weight=0"],
    "sh2": ["train.fast.sh_degree=2"],
    "dist-until-half": ["train.fast.distortion_until=0.5"],
    "features288": ["train.fast.feature_res=288"],
    "features288x3": ["train.fast.feature_res=288", "train.fast.feature_levels=3"],
    "features1level": ["train.fast.feature_levels=1"],
    "dense": ["train.fast.grid=dense"],
    "empty-start": ["train.hull_start=off"],
    "lr-flat": ["train.lr=0.01"],
}
"""--columns: each column's overrides on top of the check's own. All but `default` compare something CUDA has:
`torch-march` is the default run with the Triton marcher swapped for the torch one it replaced (the marcher's
share of the step), `rays16k` and `rays8k` the sized preset with fewer rays a step (more steps in the budget).
`nodist`, `cpu-shuffle`, `no-warmup` and `reverted` (all three) undo, one at a time, what changed on the CUDA path
after the record at 223fc2c: the distortion loss, the epoch's shuffle drawn on the GPU, the warm-up render.
`dist-from-start` runs the distortion loss from the first step, as before GPU sizing started it later; `sh2` the
colour's view dependence at the presets' second degree, as before GPU sizing took it to the third.
`dist-until-half` stops the distortion loss halfway through training (is it the loss's last steps that cost the
Lego its detail?); `features288` a feature grid of 288³ (and 144³ under it) instead of the sized 192³ (and
96³) (is the card's field short of capacity, and what does Adam over every value of a larger grid cost a step?),
`features288x3` the same in three levels (288³, 144³, 72³), `features1level` the sized 192³ feature grid without
the coarser level GPU sizing puts under it (each of the three keeps dense feature grids: a --set of a feature key
does). `dense` the colour features in the sized dense grids (192³ and 96³ under it, 96 M values), as before GPU
sizing put them in a hash grid (16 levels of 2 features up to what the pixels resolve, 2^19 rows a level: at most
11.4 M values, read in one Triton kernel). `empty-start` starts the field empty instead of inside the Lego's
visual hull (`train.hull_start=auto` turns that on for photos with silhouettes). `lr-flat` trains at the fast
model's rate for 4,096 rays a step, 0.01, as before the default grew with the batch (`recon.plans.training.grid_lr`:
0.02 at the sized 32,768)."""


PATCHED_LABELS = {
    "torch-march": "the torch marcher instead of the Triton one",
    "cpu-shuffle": "each epoch's shuffle drawn on the CPU",
    "no-warmup": "no warm-up render before training",
    "reverted": "train.fast.distortion_weight=0, the shuffle on the CPU, no warm-up",
}
"""What the columns that patch recon (`column_patches`) change, in words: their overrides alone do not say it."""


def column_label(column: str) -> str:
    """What a column changes, for the table's header."""
    return PATCHED_LABELS.get(column) or ", ".join(COLUMNS[column]) or "as recon runs"


@contextlib.contextmanager
def column_patches(column: str) -> Iterator[None]:
    """The check's patches of recon for a column, undone after it: `torch-march` makes the fast model's Triton
    marcher decline (it returns None where it does not apply), so the model marches in torch as before it;
    `cpu-shuffle` draws each epoch's shuffle on the CPU (the batcher's code before 33677a6); `no-warmup` skips the
    train stage's warm-up render; `reverted` does the last two. Other columns run recon as it is."""
    from recon.nerf import fast, fitting, trainer

    saved = fast.march_dense_triton, fitting.RayBatcher._new_epoch, trainer.warm_up
    if column == "torch-march":
        fast.march_dense_triton = lambda *args, **kwargs: None
    if column in ("cpu-shuffle", "reverted"):
        def cpu_epoch(self: Any) -> None:
            if self._perm_gen.device.type != "cpu":
                self._perm_gen = torch.Generator().manual_seed(self.seed)
            self._epoch_gen_state = self._perm_gen.get_state()
            self._perm = torch.randperm(self.n_rays, generator=self._perm_gen).to(self.device)
            self._cursor = 0
        fitting.RayBatcher._new_epoch = cpu_epoch
    if column in ("no-warmup", "reverted"):
        trainer.warm_up = lambda *args, **kwargs: 0.0
    try:
        yield
    finally:
        fast.march_dense_triton, fitting.RayBatcher._new_epoch, trainer.warm_up = saved


def not_nerf_synthetic(data: Path) -> str | None:
    """The error for a --data folder without NeRF-synthetic poses, or None."""
    if (data / "transforms_train.json").is_file():
        return None
    return f"error: {data} has no transforms_train.json: pass --data with a NeRF-synthetic folder"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def loaded_field(field: Path, device: torch.device) -> tuple[Any, torch.Tensor | None, np.ndarray]:
    """The trained field on `device`: (model, its box when bounded, its background), what render_view takes."""
    from recon.field import load_field

    model, meta = load_field(field, device)
    aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=device) if meta.get("bounded") else None
    return model, aabb, np.asarray(meta["background"], np.float32)


def one_ray_psnr(field: tuple[Any, torch.Tensor | None, np.ndarray], views: list[Any]) -> float:
    """The mean PSNR over `views` rendered with one ray through each pixel's centre: what the check scored before
    views coarser than the training photos got k×k rays a pixel (recon.evaluation.views.rays_a_side)."""
    from recon.evaluation.views import evaluate

    model, aabb, background = field
    return round(float(evaluate(model, views, aabb, background)["psnr"]), 2)


def render_timing(field: tuple[Any, torch.Tensor | None, np.ndarray], views: list[Any], device: torch.device,
                  chunk: int | None = None) -> float:
    """Milliseconds per view to render `views` with the `loaded_field` on `device`, `chunk` rays at a time (None: the
    default, recon.nerf.evaluate.default_render_chunk), after one warm-up render (allocation, compilation)."""
    from recon.evaluation.views import render_view

    model, aabb, background = field
    render_view(model, views[0], aabb, background, chunk)
    _sync(device)
    t0 = time.perf_counter()
    for view in views:
        render_view(model, view, aabb, background, chunk)
    _sync(device)
    return 1000.0 * (time.perf_counter() - t0) / len(views)


def chunk_sweep(field: tuple[Any, torch.Tensor | None, np.ndarray], views: list[Any], device: torch.device,
                chunks: list[int]) -> dict[str, Any]:
    """Render milliseconds per view at each of `chunks` rays a chunk (on CUDA; a CPU keeps its chunk), and the
    default chunk on this device: what sets recon.nerf.evaluate.CUDA_CHUNK_GIB."""
    from recon.nerf.evaluate import default_render_chunk

    if device.type != "cuda":
        return {"skipped": "the render chunk is swept on CUDA only"}
    return {"default_chunk": default_render_chunk(field[0], device),
            "ms_per_view": {str(c): round(render_timing(field, views, device, c), 1) for c in chunks}}


def device_agreement(field: Path, views: list[Any], device: torch.device) -> dict[str, Any]:
    """The same trained field rendered on the CPU and on `device`: PSNR of one render against the other (min, mean)
    and the largest pixel difference; skipped when `device` is the CPU."""
    from recon.evaluation.metrics import psnr
    from recon.evaluation.views import render_view
    from recon.field import load_field

    if device.type == "cpu":
        return {"skipped": "the device is the CPU: nothing to compare with"}
    renders = {}
    for where in (torch.device("cpu"), device):
        model, meta = load_field(field, where)
        aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=where) if meta.get("bounded") else None
        renders[where.type] = [render_view(model, v, aabb, np.asarray(meta["background"], np.float32))["rgb"] for v in views]
    db = [float(psnr(torch.from_numpy(a), torch.from_numpy(b))) for a, b in zip(renders["cpu"], renders[device.type], strict=True)]
    diff = max(float(np.abs(a - b).max()) for a, b in zip(renders["cpu"], renders[device.type], strict=True))
    return {"views": len(views), "psnr_min_db": round(min(db), 2), "psnr_mean_db": round(float(np.mean(db)), 2),
            "max_abs_diff": round(diff, 4)}


def _timed_ms(fn: Any, device: torch.device, repeats: int = 20) -> float:
    """Milliseconds per call of `fn()` on `device`, after three warm-up calls (allocation, compilation)."""
    for _ in range(3):
        fn()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    _sync(device)
    return 1000.0 * (time.perf_counter() - t0) / repeats


def kernel_timings(config: Any, device: torch.device) -> dict[str, Any]:
    """Each Triton kernel against its torch reference, forward and backward, at the preset's batch (its rays, ~48
    samples a ray, the density levels and feature grid of its resolutions): milliseconds per call and the largest
    difference of the forward outputs. Run before training, it also compiles the kernels the Triton run uses."""
    if device.type != "cuda":
        return {"skipped": f"the Triton kernels run on CUDA only (this device: {device.type})"}
    from recon.nerf import kernels as K
    from recon.nerf.grid import HashGrid, level_resolutions, trilinear_levels_torch
    from recon.nerf.model_config import HASH_BASE_RES, HASH_FEATURES
    from recon.nerf.render import accumulate_packed, distortion_packed

    ok, why = K.triton_status()
    if not ok:
        return {"skipped": why}
    fast = config.train.fast
    gen = torch.Generator(device=device).manual_seed(0)
    rays = config.train.batch_rays
    counts = torch.randint(0, 97, (rays,), device=device, generator=gen)
    ri = torch.repeat_interleave(torch.arange(rays, device=device), counts)
    m = int(ri.shape[0])
    sigma = torch.rand(m, device=device, generator=gen) * 50.0
    delta = torch.full((m,), 0.01, device=device)
    t = torch.rand(m, device=device, generator=gen) + 2.0
    rgb = torch.rand(m, 3, device=device, generator=gen)
    weights = torch.rand(m, device=device, generator=gen) / 48.0
    x01 = torch.rand(m, 3, device=device, generator=gen)
    density_res = level_resolutions(fast.density_res, fast.density_levels)
    density = [torch.randn(r**3, 1, device=device, generator=gen) for r in density_res]

    def composite(fn: Any) -> Any:
        s = sigma.clone().requires_grad_()
        out = fn(s, delta, t, ri, rays)
        (out[0].sum() + out[2].sum() + out[3].sum()).backward()
        return out

    def colour(fn: Any) -> Any:
        w, c = weights.clone().requires_grad_(), rgb.clone().requires_grad_()
        out = fn(w, c, ri, rays)
        out.sum().backward()
        return out

    t_sorted = t.sort().values  # midpoints ascending along each ray, as the marcher gives them

    def distortion(fn: Any) -> Any:
        w = weights.clone().requires_grad_()
        out = fn(w, t_sorted, delta, ri, rays)
        out.mean().backward()
        return out

    def grid(fn: Any, tables: list[torch.Tensor]) -> Any:
        params = [tb.clone().requires_grad_() for tb in tables]
        out = fn(x01, params, [round(tb.shape[0] ** (1 / 3)) for tb in tables])
        out.sum().backward()
        return out

    cases = {
        f"compositing ({m:,} samples)": (lambda: composite(K.composite_packed_torch),
                                          lambda: composite(K.composite_packed_triton)),
        "colour sums": (lambda: colour(accumulate_packed), lambda: colour(K.accumulate_packed_triton)),
        "distortion loss": (lambda: distortion(distortion_packed), lambda: distortion(K.distortion_packed_triton)),
        f"density read ({'+'.join(f'{r}³' for r in density_res)})": (
            lambda: grid(trilinear_levels_torch, density), lambda: grid(K.trilinear_levels_triton, density)),
    }
    if fast.grid == "hash":  # a dense table of the hash grid's finest resolution would not fit a card
        table = HashGrid(fast.feature_dim, HASH_FEATURES, fast.hash_table_log2, HASH_BASE_RES, fast.feature_res).to(device)

        def hash_read(fused: bool) -> Any:
            table.kernels = "triton" if fused else "torch"
            table.zero_grad(set_to_none=True)
            out = table(x01)
            out.sum().backward()
            return out

        cases[f"feature read (hash grid, {fast.feature_dim} levels up to {fast.feature_res}³)"] = (
            lambda: hash_read(False), lambda: hash_read(True))
    else:
        feature_res = level_resolutions(fast.feature_res, fast.feature_levels)
        features = [torch.randn(r**3, fast.feature_dim, device=device, generator=gen) for r in feature_res]
        cases[f"feature read ({'+'.join(f'{r}³' for r in feature_res)}×{fast.feature_dim})"] = (
            lambda: grid(trilinear_levels_torch, features), lambda: grid(K.trilinear_levels_triton, features))
    result: dict[str, Any] = {"triton": why}
    for name, (reference, fused) in cases.items():
        a, b = (torch.cat([x.detach().flatten() for x in (out if isinstance(out, tuple) else (out,))])
                for out in (reference(), fused()))
        result[name] = {"torch_ms": round(_timed_ms(reference, device), 3),
                        "triton_ms": round(_timed_ms(fused, device), 3), "max_abs_diff": float((a - b).abs().max())}
    return result


def run_one(args: argparse.Namespace, column: str, until: str | None, sweep: bool) -> tuple[dict[str, Any], Any, Any]:
    """One pipeline run with `column`'s overrides (until the stage `until`, all when None; the render chunk swept
    when `sweep`): its column."""
    from recon.app.progress import Reporter
    from recon.capture.scene import load_scene, spread_evenly
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import load_views
    from recon.nerf.device import select_device
    from recon.stages import default_pipeline

    overrides = [*(SMOKE if args.smoke else []), f"train.final_eval_views={args.test_views}",
                 *COLUMNS[column], *args.set]
    if args.budget:
        overrides.append(f"train.budget={args.budget}")
    config = load_config(args.preset, overrides)
    device = select_device(config.train.device)
    scene = args.out / f"lego-{args.preset}-{column}"
    if scene.exists() and not args.keep:
        shutil.rmtree(scene)
    report = Reporter(quiet=args.quiet)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.perf_counter()
    outcomes = default_pipeline().run(scene, config, report, source=args.data.resolve(), preset=args.preset,
                                      until_stage=until)
    wall = time.perf_counter() - t0
    metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
    mesh = json.loads((scene / "04_mesh" / "mesh_report.json").read_text()) if until is None else {}
    stage_s = {o.name: round(o.wall_s, 1) for o in outcomes}
    peak_gib = round(torch.cuda.max_memory_allocated(device) / 2**30, 2) if device.type == "cuda" else None
    normalized = load_scene(scene / "02_scene", recorded_source(scene))
    tests = normalized.split("test") or normalized.split("val")
    timing_views = load_views(normalized, spread_evenly(tests, args.render_views + 1), config.train.max_side)
    timed = timing_views[1:] or timing_views  # the first is the warm-up's
    field = loaded_field(scene / "03_field", device)
    agree_views = load_views(normalized, spread_evenly(tests, args.agreement_views), config.train.max_side)
    supersampled = [v for v in metrics["test"]["views"] if v.get("rays_a_side", 1) > 1]
    column = {
        "kernels": next((r for r in metrics["reasons"] if "kernels:" in r), "kernels: C and torch (a CPU)"),
        "sizing": next((r for r in metrics["reasons"] if r.startswith("GPU sizing")), "the preset's values"),
        "batch_rays": config.train.batch_rays,
        "overrides": overrides,
        "steps": metrics["steps"],
        "train_time_s": metrics["train_time_s"],
        "rays_per_s": metrics["rays_per_s"],
        "ms_per_step": round(1000.0 * metrics["train_time_s"] / max(1, metrics["steps"]), 2),
        "psnr": round(metrics["test"]["psnr"], 2),
        "ssim": round(metrics["test"]["ssim"], 4),
        "test_views": len(metrics["test"]["views"]),
        "psnr_per_view": {v["view"]: round(v["psnr"], 2) for v in metrics["test"]["views"]},
        "supersampled_views": {"views": len(supersampled), "rays_a_side": max(v["rays_a_side"] for v in supersampled),
                               "psnr_one_ray": one_ray_psnr(field, load_views(
                                   normalized, spread_evenly(tests, args.test_views), config.train.max_side))}
                              if supersampled else None,
        "render_ms_per_view": round(render_timing(field, timed, device), 1),
        "render_size": list(timing_views[0].hw),
        "mesh_stage_s": stage_s.get("mesh"),
        "mesh_timings_s": mesh.get("timings_s"),
        "texture_timings_s": (mesh.get("textured") or {}).get("timings_s"),  # decimate, unwrap, bake, the wait
        "render_chunks": (chunk_sweep(field, timed, device, args.render_chunks)
                          if sweep else {"skipped": "swept in the first column"}),
        "evals": metrics.get("evals", []),
        "peak_gpu_memory_gib": peak_gib,
        "stage_wall_s": stage_s,
        "train_phases_s": metrics.get("phases_s"),
        "wall_s": round(wall, 1),
        "cpu_vs_device": device_agreement(scene / "03_field", agree_views, device),
        "reasons": metrics["reasons"],
    }
    return column, config, device


def host_probe() -> dict[str, Any]:
    """The host's CPU side, where the stages around training and most of the mesh stage run: the CPUs this process
    may use (affinity, a cgroup's quota), torch's threads, and one projection of a million points timed through BLAS
    (`recon.camera.world_to_camera`, what the masks' hull and the mesh stage's visibility tests do per photo) and
    without it. The H100 hosts measured so far ran the normalize stage several times slower than a 2-core CPU does
    (docs/gpu.md); a quota below the CPU count, or BLAS threads fighting over few cores, would show here."""
    import numpy as np

    from recon.camera import world_to_camera

    quota = Path("/sys/fs/cgroup/cpu.max")
    rng = np.random.default_rng(0)
    points, c2w = rng.random((1_000_000, 3)), np.eye(4)
    c2w[:3, :3] = np.linalg.qr(rng.random((3, 3)))[0]

    def best_ms(fn: Any) -> float:
        times = []
        for _ in range(5):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return round(1000 * min(times), 1)

    plain = lambda: sum((points[:, i : i + 1] - c2w[i, 3]) * c2w[i, :3] for i in range(3))  # noqa: E731
    return {
        "cpu_count": os.cpu_count(),
        "affinity_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "cgroup_cpu_max": quota.read_text().strip() if quota.exists() else None,
        "torch_threads": torch.get_num_threads(),
        "project_1m_blas_ms": best_ms(lambda: world_to_camera(points, c2w)),
        "project_1m_plain_ms": best_ms(plain),
    }


def run_check(args: argparse.Namespace) -> dict[str, Any]:
    """Kernel timings, then a column per `--columns` entry; gpu_check.json is rewritten after each part, so a check
    cut short (a time limit on a lent machine) keeps what it measured."""
    from recon.app.bench import provenance
    from recon.config import load_config
    from recon.nerf.device import select_device

    t0 = time.perf_counter()
    probe = load_config(args.preset, [*(SMOKE if args.smoke else []), *args.set])
    device = select_device(probe.train.device)
    row: dict[str, Any] = {
        "name": args.preset,
        "data": str(args.data),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **provenance(),
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "load_average_start": [round(x, 2) for x in os.getloadavg()],
        "host": host_probe(),
        "sizing": probe.train.adjusted,
        "batch_rays": probe.train.batch_rays,
        "kernel_timings": {},
        "runs": {},
        "not_run": {},
        "wall_s": None,
    }

    def save() -> None:
        row["wall_s"] = round(time.perf_counter() - t0, 1)
        write_record(args.out, row)

    row["kernel_timings"] = kernel_timings(probe, device)
    save()
    for column in args.columns:
        if column != "default" and device.type != "cuda":
            row["not_run"][column] = f"not run: on a {device.type} it is the default column's run"
            continue
        # the mesh stage and the render-chunk sweep once, in the first column; the others stop after training
        first = not row["runs"]
        until = None if first and not args.no_mesh else "train"
        with column_patches(column):  # its training, renders and timings
            row["runs"][column], config, device = run_one(args, column, until, sweep=first)
        if first:  # the record's headline: the first column (default: what recon does on this device)
            head = row["runs"][column]
            row.update(sizing=config.train.adjusted, batch_rays=config.train.batch_rays, steps=head["steps"],
                       rays_per_s=head["rays_per_s"], psnr=head["psnr"])
        save()
    return row


def write_record(out: Path, row: dict[str, Any]) -> None:
    """gpu_check.json (the record, a list of one row as every file in benchmarks/results/) and gpu_check.md."""
    from recon.atomic import write_bytes_atomic, write_json_atomic

    write_json_atomic(out / "gpu_check.json", [row])
    write_bytes_atomic(out / "gpu_check.md", f"# GPU check — {row['name']} on {Path(row['data']).name}\n\n{table(row)}\n")


def table(row: dict[str, Any]) -> str:
    """The check's one table (Markdown): a column per `--columns` entry run, the kernels' timings below."""
    runs = row["runs"]
    names = list(runs)

    def agreement(agree: dict[str, Any]) -> str:
        return (agree["skipped"] if "skipped" in agree else
                f"{agree['psnr_min_db']:.1f} dB min / {agree['psnr_mean_db']:.1f} dB mean over {agree['views']} views")

    measures: list[tuple[str, Any]] = [
        ("rays a step", lambda r: f"{r['batch_rays']:,}"),
        ("kernels", lambda r: r["kernels"].removeprefix("kernels: ").split(" (")[0]),
        ("steps", lambda r: f"{r['steps']:,} in {r['train_time_s']:.0f} s ({r['ms_per_step']:.1f} ms/step)"),
        ("rays/s", lambda r: f"{r['rays_per_s']:,.0f}"),
        ("test PSNR", lambda r: f"{r['psnr']:.2f} dB, SSIM {r['ssim']:.3f} over {r['test_views']} views" + (
            "" if not r.get("supersampled_views") else
            f" ({r['supersampled_views']['views']} coarser than the training photos, up to "
            f"{r['supersampled_views']['rays_a_side']}² rays a pixel; one ray a pixel: "
            f"{r['supersampled_views']['psnr_one_ray']:.2f} dB)")),
        ("render", lambda r: f"{r['render_ms_per_view']:.0f} ms per {r['render_size'][1]}×{r['render_size'][0]} view"),
        ("render by rays a chunk", lambda r: r["render_chunks"].get("skipped") or ", ".join(
            f"{int(c):,}: {ms:.0f} ms" for c, ms in r["render_chunks"]["ms_per_view"].items())
            + f" (default {r['render_chunks']['default_chunk']:,})"),
        ("peak GPU memory", lambda r: "—" if r["peak_gpu_memory_gib"] is None else f"{r['peak_gpu_memory_gib']:.1f} GiB"),
        ("mesh stage", lambda r: "not run (training only)" if r["mesh_stage_s"] is None else f"{r['mesh_stage_s']} s"),
        ("CPU vs device", lambda r: agreement(r["cpu_vs_device"])),
        ("wall", lambda r: f"{r['wall_s']:.0f} s (its stages)"),
        ("train stage's parts", lambda r: ", ".join(f"{k.replace('_', ' ')} {v:.1f} s"
                                                    for k, v in (r.get("train_phases_s") or {}).items()) or "—"),
    ]
    host = row.get("host") or {}
    lines = [f"device {row['device']} ({row['device_name']}); preset {row['name']}: {row['batch_rays']:,} rays/step; "
             f"check {row['wall_s']:.0f} s in all",
             "",
             f"host: {host.get('cpu_count')} CPUs ({host.get('affinity_cpus')} this process may use, cgroup quota "
             f"{host.get('cgroup_cpu_max')}), {host.get('torch_threads')} torch threads; 1 M points projected through "
             f"BLAS in {host.get('project_1m_blas_ms')} ms, without it in {host.get('project_1m_plain_ms')} ms",
             "",
             "| measure | " + " | ".join(f"{n} ({column_label(n)})" if n in COLUMNS else n for n in names) + " |",
             "|---|" + "---|" * len(names)]
    lines += [f"| {label} | " + " | ".join(cell(runs[n]) for n in names) + " |" for label, cell in measures]
    timings = row["kernel_timings"]
    for name, t in timings.items():
        if isinstance(t, dict):
            ratio = t["torch_ms"] / t["triton_ms"] if t["triton_ms"] else float("inf")
            lines.append(f"| kernel: {name}, fwd+bwd | torch {t['torch_ms']:.2f} ms | Triton {t['triton_ms']:.2f} ms "
                         f"({ratio:.1f}×, max diff {t['max_abs_diff']:.1e}) |"
                         + " |" * (len(names) - 2))
    notes = [f"{k}: {v}" for k, v in row["not_run"].items()]
    if "skipped" in timings:
        notes.append(f"kernel timings: {timings['skipped']}")
    return "\n".join(lines + ([""] + notes if notes else []))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the scene, gpu_check.json and gpu_check.md")
    parser.add_argument("--data", type=Path, default=LEGO_HALF, help="a NeRF-synthetic folder (default: the half-res Lego)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--budget", default="60s",
                        help="training budget of each run (issue 37's target: 33 dB in 60 s); '' keeps the preset's")
    parser.add_argument("--columns", default="default,torch,unsized",
                        help=f"runs to compare, comma-separated, of {', '.join(COLUMNS)} (on a CPU only default runs)")
    parser.add_argument("--test-views", type=int, default=0, help="held-out views scored (0: all)")
    parser.add_argument("--render-views", type=int, default=10, help="views timed for render ms/view")
    parser.add_argument("--agreement-views", type=int, default=3, help="views rendered on both the CPU and the device")
    parser.add_argument("--render-chunks", default="16384,65536,262144",
                        help="rays a chunk to time renders at on CUDA, comma-separated (besides the default)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override, as recon --set")
    parser.add_argument("--smoke", action="store_true",
                        help="tiny run (5 s budget, 50-px photos, 32 samples a ray, 32³ mesh): that it runs")
    parser.add_argument("--no-mesh", action="store_true", help="train only: no column runs the mesh stage")
    parser.add_argument("--keep", action="store_true", help="reuse the scene folder's cached stages")
    parser.add_argument("--quiet", action="store_true", help="only warnings and errors while the pipeline runs")
    args = parser.parse_args(argv)
    args.columns = [c.strip() for c in args.columns.split(",") if c.strip()]
    try:
        args.render_chunks = [int(c) for c in args.render_chunks.split(",") if c.strip()]
    except ValueError:
        print(f"error: --render-chunks takes whole numbers (comma-separated), got {args.render_chunks!r}", file=sys.stderr)
        return 2
    if not args.columns or any(c not in COLUMNS for c in args.columns) or len(set(args.columns)) < len(args.columns):
        print(f"error: --columns takes {', '.join(COLUMNS)} (comma-separated, each once), got {args.columns}",
              file=sys.stderr)
        return 2
    if error := not_nerf_synthetic(args.data):
        print(error, file=sys.stderr)
        return 2
    if args.smoke:
        args.budget = ""
        args.test_views = args.test_views or 2
        args.render_views, args.agreement_views = min(args.render_views, 1), min(args.agreement_views, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    row = run_check(args)
    print(table(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())

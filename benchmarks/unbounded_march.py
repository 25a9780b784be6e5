"""Unbounded (contracted) against bounded training steps of the `fast` preset, and the native contracted marcher
against the torch one, measured in one process so that the machine's load cancels out of every ratio.

    python benchmarks/unbounded_march.py [--warmup 80] [--rounds 5] [--work DIR]

Builds the fox and the half-size Lego
(bounded) as the train stage and `recon bench --profile` build them (recon.plans.training.plan_training and
build_training: the same model, rays and step pieces), the fox from its reference poses
with masks off and trained as an unbounded capture (contracted), as the fox is after SfM (without SfM's sparse points
normalize calls the reference-posed fox an object capture; SfM itself would take most of this script's time), trains
each ``--warmup`` steps,
then alternates, round by round, one fox step with the native marcher, one fox step with the torch marcher
(recon.app.profiling.reference_marching) and one Lego step, recording each step's process CPU time and wall time,
samples, density evaluations and colored samples per ray. Then the two marchers alone, alternately, on the same fox rays (no
gradients): candidates, occupied candidates and kept samples per ray, and CPU time. Writes
benchmarks/results/unbounded_march.json.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import statistics
import tempfile
import time
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
FOX = REPO.parent / "shared" / "data" / "fox"
RESULT = REPO / "benchmarks" / "results" / "unbounded_march.json"


def build(data: str, work: Path, overrides: list[str], unbounded: bool = False) -> dict[str, Any]:
    """The fast preset's model, ray batcher and training step on ``data``, planned and built as the train stage plans
    and builds them (recon.plans.training); ``unbounded`` trains the scene as an unbounded capture (contracted)
    whatever normalize classified it as."""
    from recon.app.bench import prepare_scene
    from recon.app.progress import Reporter
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import load_views
    from recon.nerf.trainer import TrainStep
    from recon.plans.training import build_training, plan_training

    config = load_config("fast", overrides)
    scene_dir = prepare_scene(data, work, load_config(None, overrides), Reporter())
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    if unbounded:
        scene.capture = "unbounded"
    cfg = config.train
    plan = plan_training(cfg, scene, load_views(scene, scene.split("train"), cfg.max_side), torch.device("cpu"))
    setup = build_training(plan, torch.device("cpu"))
    step = TrainStep(setup.model, setup.batcher, steps=cfg.steps, **setup.step_kwargs)
    return {"model": setup.model, "batcher": setup.batcher, "take_step": step, "rays": plan.batch_rays, "step": 0,
            "background": plan.background,
            "pieces": [type(p).__name__ for p in setup.step_kwargs["pieces"]]}


@contextlib.contextmanager
def counting_colored(model: Any) -> Iterator[list[int]]:
    """Within the block, the model's colored samples per call (its color head's batch sizes) append to the list."""
    colored: list[int] = []
    color = type(model)._rgb_unit
    model._rgb_unit = lambda u, d: (colored.append(u.shape[0]), color(model, u, d))[1]
    try:
        yield colored
    finally:
        del model._rgb_unit


def train_step(run: dict[str, Any]) -> dict[str, float]:
    """One step of the train stage's training (recon.nerf.trainer.TrainStep, its pieces included): CPU and wall
    seconds, samples and density evaluations per ray of the batch, colored samples per ray (a depth prior's own
    rays included: the step colors them too), the batch's PSNR."""
    with counting_colored(run["model"]) as colored:
        c0, w0 = time.process_time(), time.perf_counter()
        result = run["take_step"](run["step"])
        cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - w0
    run["step"] += 1
    n, out = run["rays"], result.out
    return {"cpu_s": cpu_s, "wall_s": wall_s,
            "samples_per_ray": out["num_samples"] / n, "density_evals_per_ray": out["density_evals"] / n,
            "colored_per_ray": sum(colored) / n,
            "psnr": float(-10 * math.log10(result.rgb_mse))}


def marcher_ab(run: dict[str, Any], repeats: int) -> dict[str, Any]:
    """The torch contracted marcher (intervals, occupancy, no-grad density cut) and the native one, alternately on
    the same training rays: counts per ray and CPU seconds per call."""
    import recon.nerf.native as native
    from recon.nerf.contraction import contracted_intervals
    from recon.nerf.occupancy import march

    model = run["model"]
    cfg = model.config
    batch = run["batcher"].next_batch(run["rays"])
    o, d, tn, tf = batch["rays_o"], batch["rays_d"], batch["near"], batch["far"]
    n = o.shape[0]

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model._sigma_unit(model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0))

    def torch_march() -> torch.Tensor:
        ts, te, ri = march(o, d, tn, tf, model.occupancy, model.step_size, cfg.max_samples, jitter=False,
                           contracted=True, sigma_fn=sigma_fn, min_transmittance=cfg.early_stop_transmittance)
        sigma_fn(ts, te, ri)  # the torch path evaluates the kept samples' densities again
        return ri

    def native_march() -> torch.Tensor:
        return native.march_dense_native(o, d, tn, tf, False, model._dense_density(), model.step_size,
                                         cfg.max_samples, cfg.early_stop_transmittance)[2]

    with torch.no_grad():
        ts, te, ri = contracted_intervals(o, d, tn, tf, model.step_size, cfg.max_samples, False)
        occupied = int(model.occupancy.query(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).sum())
        times: dict[str, list[float]] = {"torch": [], "native": []}
        kept = {}
        for _ in range(repeats):
            for name, fn in (("torch", torch_march), ("native", native_march)):
                c0 = time.process_time()
                kept[name] = int(fn().shape[0])
                times[name].append(time.process_time() - c0)
    return {
        "rays": n, "candidates_per_ray": ri.shape[0] / n, "occupied_candidates_per_ray": occupied / n,
        "kept_samples_per_ray": {k: v / n for k, v in kept.items()},
        "density_evals_per_ray": {"torch": (occupied + kept["torch"]) / n, "native": kept["native"] / n},
        "cpu_s_per_call_median": {k: statistics.median(v) for k, v in times.items()},
        "cpu_s_per_call": times,
        "speedup_cpu": statistics.median(times["torch"]) / statistics.median(times["native"]),
    }


def top_ops(run: dict[str, Any], steps: int, limit: int = 12) -> list[tuple[str, float]]:
    """The ops that took the most CPU (self time, ms per step) over ``steps`` training steps, by torch.profiler."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            train_step(run)
    ops = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)[:limit]
    return [(e.key, round(e.self_cpu_time_total / 1e3 / steps, 1)) for e in ops]


def summarize(steps: list[dict[str, float]], rays: int) -> dict[str, Any]:
    cpu = statistics.median(s["cpu_s"] for s in steps)
    return {"steps": len(steps), "cpu_s_per_step_median": cpu, "wall_s_per_step_median":
            statistics.median(s["wall_s"] for s in steps), "rays_per_cpu_s": rays / cpu,
            "samples_per_ray": statistics.mean(s["samples_per_ray"] for s in steps),
            "density_evals_per_ray": statistics.mean(s["density_evals_per_ray"] for s in steps),
            "colored_per_ray": statistics.mean(s["colored_per_ray"] for s in steps),
            "train_psnr_last": steps[-1]["psnr"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warmup", type=int, default=80, help="steps trained before measuring")
    parser.add_argument("--rounds", type=int, default=5, help="measured rounds (fox native, fox torch, Lego)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the prepared scenes (default: a temp dir)")
    args = parser.parse_args()
    from recon.app.bench import provenance
    from recon.app.profiling import reference_marching
    from recon.atomic import write_json_atomic

    work = args.work or Path(tempfile.mkdtemp(prefix="recon-unbounded-march-"))
    load_start = [round(x, 2) for x in os.getloadavg()]
    fox = build(str(FOX), work, ["normalize.masks=off"], unbounded=True)
    lego = build("lego-half", work, [])
    if not fox["model"].config.unbounded or lego["model"].config.unbounded:
        raise SystemExit("expected the fox unbounded and the Lego bounded")
    for run in (fox, lego):
        for _ in range(args.warmup):
            train_step(run)
    rounds: dict[str, list[dict[str, float]]] = {"fox_native": [], "fox_torch": [], "lego_native": []}
    for _ in range(args.rounds):
        rounds["fox_native"].append(train_step(fox))
        with reference_marching():
            rounds["fox_torch"].append(train_step(fox))
        rounds["lego_native"].append(train_step(lego))
    steps = {k: summarize(v, fox["rays"] if k.startswith("fox") else lego["rays"]) for k, v in rounds.items()}
    record = {
        **provenance(),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "load_average_start": load_start,
        "load_average_end": [round(x, 2) for x in os.getloadavg()],
        "preset": "fast", "warmup_steps": args.warmup, "rounds": args.rounds,
        "step_pieces": {"fox": fox["pieces"], "lego": lego["pieces"]},
        "data": {"fox": f"{FOX} (reference poses, normalize.masks=off, trained unbounded: contracted)", "lego": "lego-half (bounded)"},
        "training_steps": steps,
        "fox_step_cpu_torch_over_native": steps["fox_torch"]["cpu_s_per_step_median"]
        / steps["fox_native"]["cpu_s_per_step_median"],
        "fox_over_lego_step_cpu": steps["fox_native"]["cpu_s_per_step_median"]
        / steps["lego_native"]["cpu_s_per_step_median"],
        "marcher_fox": marcher_ab(fox, repeats=args.rounds),
    }
    with reference_marching():
        torch_ops = top_ops(fox, 2)
    record["top_ops_ms_per_step"] = {"fox_torch": torch_ops, "fox_native": top_ops(fox, 2), "lego_native": top_ops(lego, 2)}
    write_json_atomic(RESULT, as_rows(record))
    print(json.dumps({k: v for k, v in record.items() if k not in ("training_steps",)}, indent=1, default=str))
    print(json.dumps(steps, indent=1))


def as_rows(record: dict[str, Any]) -> list[dict[str, Any]]:
    """The record as benchmarks/README.md's rows, one per measured run (fox native, fox torch, Lego): provenance,
    ``steps`` measured, ``rays_per_s`` (rays per CPU second: wall time here is mostly other jobs' share), ``psnr`` of
    the last measured training batch (no held-out views are rendered), the counts; the comparisons on the first row."""
    shared = {k: v for k, v in record.items() if k not in ("training_steps", "data", "top_ops_ms_per_step",
                                                            "marcher_fox", "fox_step_cpu_torch_over_native",
                                                            "fox_over_lego_step_cpu")}
    rows = []
    for name, steps in record["training_steps"].items():
        data, marcher = name.split("_")
        rows.append({"name": name, "data": record["data"][data], "marcher": marcher, **shared, **steps,
                     "rays_per_s": round(steps["rays_per_cpu_s"], 1), "psnr": round(steps["train_psnr_last"], 2),
                     "psnr_of": "the last measured training batch", "top_ops_ms_per_step": record["top_ops_ms_per_step"][name]})
    rows[0] |= {k: record[k] for k in ("marcher_fox", "fox_step_cpu_torch_over_native", "fox_over_lego_step_cpu")}
    return rows


if __name__ == "__main__":
    main()

"""train stage: fit a radiance field to the training photos, evaluate held-out views, keep renders.

Writes `field.pt` (the model), `metrics.json` (PSNR/SSIM per held-out view and their means, the
training curve, the choices made and why), `curves.png` (PSNR vs step and vs wall time) and
`renders/NAME.png` (photo | render | depth) for a few test views, and `trained_state.pt` (the finished training's
state beside the field). A checkpoint is written to the stage's work folder every `checkpoint_every` steps and on
Ctrl-C; running the same command again resumes from it, and so does the command with another time budget (a budget
found too short goes on) or another of `recon.stages.TRAINS_ON_UNDER`. A finished field trains on the same way under
a longer budget, from its trained state.
"""
from __future__ import annotations

import math
import time
import warnings
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recon.atomic import (atomic_open, checksum_matches, checksum_path, fault_point, interrupts_deferred,
                          write_checksummed, write_json_atomic)
from recon.capture.scene import Scene, load_scene, spread_evenly
from recon.config import TrainConfig
from recon.errors import ReconError
from recon.evaluation.views import (View, evaluate, fitted_note, load_views, supersampling_note, training_focal,
                                    write_previews)
from recon.field import FIELD_FILE, save_field
from recon.plans.training import TrainPlan, TrainSetup, build_training, photo_sides, plan_training, training_side
from recon.runner.pipeline import SCRATCH_NOTE, StageContext

CHECKPOINT = "checkpoint.pt"
TRAINED_STATE = "trained_state.pt"
"""Beside the field: what a checkpoint holds less the weights and the optimizer's moments (the step, the batch stream,
the pieces' fitted corrections, the curves, the seconds trained under which budget): a longer budget trains the
finished field on from it, with the optimizer's moments started again, instead of training again from step 0."""


def _pose_metrics(refine: Any, why: str, views: list[View], focal: list[float], distance: list[float]) -> dict[str, Any]:
    """metrics.json's record of the pose-refinement choice and, when on, each photo's correction."""
    if refine is None:
        return {"on": False, "reason": why}
    per_photo = refine.summary([v.name for v in views], focal, distance)
    worst = sorted(per_photo, key=lambda r: -r["pixels"])
    return {"on": True, "reason": why, "median_pixels": float(np.median([r["pixels"] for r in per_photo])),
            "largest": worst[:5], "per_photo": per_photo}


def _appearance_metrics(appearance: Any, why: str, views: list[View]) -> dict[str, Any]:
    """metrics.json's record of the appearance choice, the held-out protocol and the photos' fitted gains."""
    from recon.nerf.evaluate import HELD_OUT_PROTOCOL

    if appearance is None:
        return {"on": False, "reason": why, "held_out": "plain: the neutral render against the whole photo"}
    return {"on": True, "reason": why, "held_out": HELD_OUT_PROTOCOL, "kind": appearance.kind,
            "per_photo": appearance.summary([v.name for v in views])}


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Atomically write a checkpoint and its sha256 sidecar (checked before loading); Ctrl-C waits until both are whole."""
    write_checksummed(path, lambda f: torch.save(state, f))
    fault_point("train/checkpoint")


def _load_checkpoint(path: Path, report: Any) -> dict[str, Any] | None:
    """The checkpoint if its bytes match the checksum recorded when it was written, else None (start over)."""
    if not path.exists():
        return None
    try:
        if not checksum_matches(path):
            raise ValueError("its bytes do not match the checksum recorded when it was written")
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # truncated or corrupt: start over rather than load garbage
        report.warn(f"The training checkpoint {path} is unusable ({exc}); training starts over.")
        path.unlink(missing_ok=True)
        checksum_path(path).unlink(missing_ok=True)
        return None


def _save_trained_state(path: Path, kept: dict[str, Any]) -> None:
    with interrupts_deferred(), atomic_open(path, "wb") as f:
        torch.save(kept, f)


def _load_trained_state(previous: Path | None, model: torch.nn.Module, report: Any) -> dict[str, Any] | None:
    """A checkpoint made of the finished field in `previous` (`StageContext.previous`: made under another budget) and
    its TRAINED_STATE, without optimizer moments; None where there is none, or it is unreadable or not a field of
    `model`'s shapes (start over)."""
    if previous is None or not (previous / TRAINED_STATE).is_file():
        return None
    try:
        kept = torch.load(previous / TRAINED_STATE, map_location="cpu", weights_only=True)
        weights = torch.load(previous / FIELD_FILE, map_location="cpu", weights_only=True)["state_dict"]
        shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        if {k: tuple(v.shape) for k, v in weights.items()} != shapes:
            raise ValueError("its weights are not of the shapes this run builds")
        kept["state"]["model"] = weights
    except Exception as exc:  # truncated, or made by another version: start over rather than load garbage
        report.warn(f"The finished field in {previous} cannot be trained on ({exc}); training starts over.")
        return None
    return kept


def _held_out_note(appearance: bool, poses: bool) -> str:
    """The headline's note on how held-out photos are scored when something is fitted on their left halves."""
    fitted = " and ".join(w for w, on in (("appearance", appearance), ("pose", poses)) if on)
    return f"; right halves, each photo’s {fitted} fitted on its left half" if fitted else ""


def _object_distance(views: list[View], scene: Scene) -> list[float]:
    """Each photo's distance to the middle of the scene box (or the origin of an unbounded scene)."""
    centre = np.asarray(scene.aabb, np.float64).mean(0) if scene.aabb is not None else np.zeros(3)
    return [float(np.linalg.norm(np.asarray(v.c2w)[:3, 3] - centre)) for v in views]


def run(ctx: StageContext) -> dict:
    """Plan (recon.plans.training) and say why, build, train from the checkpoint if any, evaluate, write the outputs."""
    from recon.nerf.device import select_device
    from recon.plots import training_curves

    cfg: TrainConfig = ctx.config
    if cfg.steps <= 0 or cfg.batch_rays <= 0:
        raise ReconError(f"train.steps and train.batch_rays must be positive (got {cfg.steps}, {cfg.batch_rays}).")
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ReconError(f"train.device={cfg.device}: {exc}") from None
    phases = _Phases()
    scene = load_scene(ctx.inputs["normalize"], ctx.source)
    train_frames = scene.split("train")
    held_out = scene.split("val") or scene.split("test") or train_frames[:1]
    test_frames = scene.split("test") or held_out
    if not train_frames:
        raise ReconError("The scene has no training views. Re-run normalize (recon normalize SCENE).")
    side, side_why = training_side(cfg, scene, train_frames)
    cfg = replace(cfg, max_side=side)  # what loads, plans, evaluates and is saved for the mesh and renders
    sides, sides_why = photo_sides(cfg, scene, train_frames)
    photos = load_views(scene, train_frames, cfg.max_side, ctx.report, "training photos", sides=sides)
    phases.done("load_photos")
    plan = plan_training(cfg, scene, photos, device)
    phases.done("plan")
    ctx.report.info(f"device: {device}; background: {plan.background_why}")
    plan.reasons += [why for why in (side_why, sides_why) if why]
    for r in plan.reasons:
        ctx.report.info(f"model: {r}")
    for protocol in _held_out_protocols(plan):
        ctx.report.info(f"held-out evaluation: {protocol}")
    setup = build_training(plan, device)
    phases.done("build")
    if device.type == "cuda":
        from recon.nerf.trainer import warm_up

        seconds = warm_up(setup.model, setup.batcher, plan.batch_rays, plan.autocast)
        setup.notes.append(f"warm-up: one training render and its backward before training ({seconds:.1f} s): on "
                           "CUDA the kernels compile there, not in the first steps of the time budget")
        phases.done("warm_up")
    for note in setup.notes:
        ctx.report.info(f"model: {note}")
    focal = training_focal(train_frames, cfg.max_side)
    eval_views = load_views(scene, spread_evenly(held_out, cfg.eval_views), cfg.max_side)
    test_views = load_views(scene, spread_evenly(test_frames, cfg.final_eval_views), cfg.max_side)  # a spiral's first N would be one viewpoint
    scored = {v.name for v in eval_views}
    note = supersampling_note(eval_views + [v for v in test_views if v.name not in scored], focal)
    if note:
        ctx.report.info(f"held-out evaluation: {note}")
    phases.done("load_held_out")
    result, evals, history, train_time = _fit(ctx, cfg, plan, setup, eval_views, focal)
    trained_state = result.pop("trained_state")
    phases.done("train")

    with ctx.report.task("evaluating test views", total=len(test_views), unit="views") as bar:
        final = evaluate(setup.model, test_views, setup.aabb, plan.background, keep=True, autocast=plan.autocast,
                         appearance=plan.appearance, align_poses=plan.pose_refine, focal=focal, on_view=bar.advance)
    phases.done("final_evaluation")
    write_previews(final.pop("renders"), ctx.out / "renders")
    _save(ctx.out / FIELD_FILE, scene, plan, setup, cfg.max_side)
    _save_trained_state(ctx.out / TRAINED_STATE, trained_state)
    phases.done("save")
    metrics = _metrics(scene, device, plan, setup, result, final, evals, history, train_time)
    metrics["phases_s"] = phases.seconds
    if setup.pose_refine is not None:
        largest = metrics["pose_refine"]["largest"][:3]
        ctx.report.info("pose refinement: median correction {:.2f} px; largest {}".format(
            metrics["pose_refine"]["median_pixels"], ", ".join(f"{r['photo']} {r['pixels']:.2f} px" for r in largest)))
    if note := fitted_note(final):
        ctx.report.info(note)
    write_json_atomic(ctx.out / "metrics.json", metrics)
    training_curves(history, evals, ctx.out / "curves.png", title=f"{plan.kind} model — test PSNR {final['psnr']:.2f} dB",
                    resumes=result["resumes"])
    # the checkpoint stays until the pipeline has recorded this stage as done (it then removes ctx.work):
    # a crash between here and the manifest resumes from it instead of training again from step 0
    return {
        "headline": (f"{plan.kind} model, {result['step']} steps in {train_time:.0f} s: "
                     f"{'test' if scene.split('test') else 'training-photo (none held out)'} PSNR {final['psnr']:.2f} dB, "
                     f"SSIM {final['ssim']:.3f} ({len(test_views)} view{'s' if len(test_views) != 1 else ''}"
                     f"{_held_out_note(plan.appearance, plan.pose_refine)})"),
        "psnr": round(final["psnr"], 3),
        "ssim": round(final["ssim"], 4),
        "train_time_s": round(train_time, 1),
    }


class _Phases:
    """Seconds of each part of the stage, in the order they ran (metrics.json's "phases_s"): what the stage spends
    around its time budget (loading photos, planning, building, a CUDA warm-up, the final evaluation), which on a
    GPU can rival the budget itself. "train" holds the budget and the held-out evaluations during it."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._since = time.perf_counter()

    def done(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = round(now - self._since, 3)
        self._since = now


def _held_out_protocols(plan: TrainPlan) -> list[str]:
    """How held-out photos are scored when something is fitted per photo (said before training starts)."""
    from recon.nerf.evaluate import HELD_OUT_PROTOCOL, POSE_PROTOCOL

    return [p for p, on in ((HELD_OUT_PROTOCOL, plan.appearance), (POSE_PROTOCOL, plan.pose_refine)) if on]


ESTIMATE_AFTER_S = 3.0
"""Training seconds over which the step rate is measured before the steps a budget allows are estimated."""
RATE_WINDOW_S = 30.0
"""The step rate is that of the last this-many training seconds: steps get faster as occupancy culls empty space."""


FEW_STEPS = 1_000
"""Fewer steps than this in a time budget leave a soft field and a torn mesh, so the train stage says so while there
is time to stop. The `fast` records' held-out PSNR at step 1,000 is 0.4-3.5 dB under their end, and at step 500
1.1-5.8 dB (sample_fast, fox_fast_masks, tabletop_realistic_seeds in benchmarks/results). On a CPU with a seventh of
the matmul rate, the sample's 1,005 steps still mesh at F@1% 0.945 against 0.949 at 4,506 (sample_fast_slow_cpu,
sample_fast), while the fox's 297 steps mesh 91% of its masks' pixels against 97.5% at 2,549 steps, 27.62 against
29.27 dB (fox_fast_slow_cpu, fox_fast_masks)."""
FEW_STEPS_CHECK = 0.5
"""The share of the budget after which the steps it allows are judged, at the rate of the last RATE_WINDOW_S: the
first steps are the slowest (occupancy has culled no empty space yet: on the sample, step 30 marches 53.5 samples a
ray and colours 34.1, 1.0 s a step on a slow CPU, where step 400 marches 14.9, colours 8.7, 0.33 s; records
sample_profile_cpu_step30 and _step400), so a rate taken earlier foretells too few steps."""


def few_steps_warning(total: int, step: int, used_s: float, rate: float, budget: str, cap: int) -> str | None:
    """A sentence for a budget that will end training at `total` steps, under FEW_STEPS (None otherwise, or when the
    step cap stops it first): `step` done in `used_s` training seconds, now at `rate` steps a second; the budget
    that would reach FEW_STEPS at that rate (steps still get faster, so it is an upper bound)."""
    if rate <= 0 or total >= min(FEW_STEPS, cap):
        return None
    minutes = math.ceil((used_s + max(FEW_STEPS - step, 0) / rate) / 60.0)
    return (f"at this machine's pace ({rate:.1f} steps/s) the {budget} budget trains about {total:,} steps, under "
            f"the {FEW_STEPS:,} a field needs to settle: expect a soft field and a torn mesh. `--budget "
            f"{minutes}m` trains {FEW_STEPS:,} or more here (`--set train.budget={minutes}m` in recon batch; Ctrl-C, "
            "or let it finish, and run again with it: training goes on from where it stopped)")


def resumed_budget_note(was: str, now: str, spent_s: float, budget_s: float) -> str:
    """What a checkpoint or finished field made under the time budget `was` ("" for none) does under `now` (the
    stage's scratch outlives a change of budget: `recon.stages.TRAINS_ON_UNDER`), after `spent_s` training seconds: ""
    where it just goes on under the same budget."""
    made = f"trained {spent_s:.0f} s under " + (f"a {was} budget" if was else "no budget")
    if budget_s and spent_s >= budget_s:
        return (f" ({made}: the {now} budget is spent already, so the field is kept as it is; a longer --budget "
                "trains on from here)")
    if was == now:
        return ""
    if not budget_s:
        return f" ({made}; without a budget it goes on to the step cap)"
    return (f" ({made}: the {now} budget trains about {budget_s - spent_s:.0f} s more from here, on its own learning "
            "rate schedule, as if it had been given from the start)")


def expected_steps(step: int, used_s: float, since_step: int, since_s: float, budget_s: float, cap: int) -> int:
    """The step count training will end at, for the progress bar's total (and so its ETA): the cap without a
    budget; with one, the steps the recent rate fits in what is left of it (to tens of steps), when that is fewer.

    A budget stops training before the cap on most machines: a bar out of the cap would end at a fraction and its
    ETA would count steps that never run. used_s: training seconds spent; the rate is measured since step
    `since_step` at `since_s` training seconds.
    """
    if budget_s <= 0 or used_s - since_s < ESTIMATE_AFTER_S or step <= since_step:
        return cap
    rate = (step - since_step) / (used_s - since_s)
    return int(min(cap, max(step, round((step + rate * max(budget_s - used_s, 0.0)) / 10.0) * 10)))


def _fit(ctx: StageContext, cfg: TrainConfig, plan: TrainPlan, setup: TrainSetup,
         eval_views: list[View], focal: float) -> tuple[dict[str, Any], list[dict], list[dict], float]:
    """Train from the stage's checkpoint when there is one, else from its finished field made under another budget
    (TRAINED_STATE), checkpointing as it goes; (train's result, with "resumes": where training went on from either,
    under which budgets, and "trained_state": what TRAINED_STATE keeps; the held-out evaluations, the training curve,
    the training time in seconds, evaluation excluded). focal: the training photos' focal length, for views coarser
    than them (`recon.evaluation.views.rays_a_side`)."""
    from recon.nerf.trainer import TrainingDiverged, TrainingInterrupted, train

    model, aabb, background = setup.model, setup.aabb, plan.background
    ckpt_path = ctx.work / CHECKPOINT
    checkpoint, from_field = _load_checkpoint(ckpt_path, ctx.report), False
    if checkpoint is None and (checkpoint := _load_trained_state(ctx.previous, model, ctx.report)):
        from_field = True
    evals: list[dict] = checkpoint["evals"] if checkpoint else []
    history: list[dict] = checkpoint["history"] if checkpoint else []
    time_before = checkpoint["train_time_s"] if checkpoint else 0.0
    resumes: list[dict] = checkpoint.get("resumes", []) if checkpoint else []
    if checkpoint:
        at = checkpoint["state"]["step"]
        resumes.append({"step": at, "time_s": round(time_before, 3), "from": "finished field" if from_field else
                        "checkpoint", "budget_before": checkpoint.get("budget", cfg.budget), "budget": cfg.budget})
        ctx.report.info(
            ("training on from the finished field" if from_field else "resuming from the checkpoint")
            + f" at step {at:,} of {cfg.steps:,}"
            + (" (the step cap, reached: the field is kept as it is)" if at >= cfg.steps else
               resumed_budget_note(checkpoint.get("budget", cfg.budget), cfg.budget, time_before, plan.budget_s))
            + (f". To train from step 0 instead, delete {ctx.previous} and run again" if from_field else ""))
    eval_time = [0.0]

    def eval_fn(m: torch.nn.Module, step: int) -> dict[str, float]:
        t = time.perf_counter()
        r = evaluate(m, eval_views, aabb, background, autocast=plan.autocast, appearance=plan.appearance, fitted=False,
                     align_poses=plan.pose_refine, focal=focal)
        eval_time[0] += time.perf_counter() - t
        return {"psnr": r["psnr"], "ssim": r["ssim"]}

    t_start = time.perf_counter()

    def train_time() -> float:
        return time_before + time.perf_counter() - t_start - eval_time[0]

    def record(state: dict[str, Any]) -> dict[str, Any]:
        """The trainer's state with the curves so far, the time spent under which budget and where training went on:
        a checkpoint, or (its state without weights) the finished field's TRAINED_STATE."""
        return {"state": state, "evals": evals, "history": history, "train_time_s": train_time(),
                "budget": cfg.budget, "resumes": resumes}

    def keep(state: dict[str, Any]) -> None:
        """Checkpoint the trainer's state (`record`); say so for `recon status`."""
        kept = record(state)
        _save_checkpoint(ckpt_path, kept)
        spent = kept["train_time_s"]
        under = f"a {cfg.budget} budget" if cfg.budget else f"a cap of {cfg.steps:,} steps"
        write_json_atomic(ctx.work / SCRATCH_NOTE, {"headline": (
            f"training checkpoint at step {state['step']:,}, {spent:.0f} s trained under {under}: running again goes "
            "on from it, also with another --budget")})

    first_step = checkpoint["state"]["step"] if checkpoint else 0
    with ctx.report.task("training", total=cfg.steps, unit="steps") as bar:
        bar.update(completed=first_step)

        recent = deque([(time_before, first_step)])  # (training seconds, step) over the last RATE_WINDOW_S
        judged = [time_before >= FEW_STEPS_CHECK * plan.budget_s > 0]  # whether the budget's steps have been judged

        def on_step(p: Any) -> None:
            now = train_time()
            recent.append((now, p.step))
            while len(recent) > 2 and now - recent[1][0] >= RATE_WINDOW_S:
                recent.popleft()
            total = expected_steps(p.step, now, recent[0][1], recent[0][0], plan.budget_s, p.steps)
            if not judged[0] and plan.budget_s and now >= FEW_STEPS_CHECK * plan.budget_s and p.step > recent[0][1]:
                judged[0] = True
                rate = (p.step - recent[0][1]) / max(now - recent[0][0], 1e-9)  # the bar's, over RATE_WINDOW_S
                if warning := few_steps_warning(total, p.step, now, rate, cfg.budget, p.steps):
                    ctx.report.warn(warning)
            bar.update(completed=p.step, total=total,
                       info=f"loss {p.loss:.4f}  PSNR {p.psnr:.2f} dB  {p.rays_per_s:,.0f} rays/s")
            if p.step % 10 == 0 or p.step == p.steps:
                history.append({"step": p.step, "loss": p.loss, "psnr": p.psnr, "time_s": round(train_time(), 3)})
            if p.metrics is not None:
                evals.append({"step": p.step, "time_s": round(train_time(), 3), **p.metrics})
                ctx.report.info(f"step {p.step}: held-out PSNR {p.metrics['psnr']:.2f} dB, SSIM {p.metrics['ssim']:.3f}")
            if ctx.report.observers:  # a live viewer (recon run --view): it renders the model on this thread
                ctx.report.observe("train_step", {"progress": p, "model": model, "view": eval_views[0], "aabb": aabb, "background": background})
            if cfg.checkpoint_every and p.step % cfg.checkpoint_every == 0 and p.step < p.steps:
                keep(p.state_dict())

        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", UserWarning)
                result = train(
                    model, setup.batcher, steps=cfg.steps, **setup.step_kwargs, eval_fn=eval_fn,
                    eval_every=cfg.eval_every or cfg.steps, callbacks=[on_step],
                    state=checkpoint["state"] if checkpoint else None, budget_s=plan.budget_s, spent_s=time_before,
                )
            for w in caught:
                if "training is not improving" in str(w.message):
                    ctx.report.warn(str(w.message))
            bar.update(completed=result["step"], total=result["step"])  # the budget ended it: the bar ends full
        except TrainingInterrupted as stop:
            keep(stop.state)
            raise KeyboardInterrupt from None
        except TrainingDiverged as exc:
            raise ReconError(
                f"Training diverged at step {exc.step}: {exc.cause}. {exc.advice} "
                f"(e.g. --set train.lr={plan.lr / 3:.3g}; the last checkpoint is kept in {ctx.work})."
            ) from None
    result["resumes"], result["trained_state"] = resumes, record(result.pop("state"))
    return result, evals, history, result["trained_state"]["train_time_s"]


def _save(path: Path, scene: Scene, plan: TrainPlan, setup: TrainSetup, max_side: int) -> None:
    """The field file: the model and what reading it needs (box, background, the photos' fitted corrections)."""
    meta = {
        "aabb": np.asarray(scene.aabb).tolist(),
        "bounded": scene.capture == "object",
        "background": plan.background.tolist(),
        "max_side": max_side,
        "capture": scene.capture,
    }
    if setup.appearance is not None:  # the field stays neutral; the photos' transforms are kept for whoever needs them
        meta["appearance"] = setup.appearance.summary([v.name for v in plan.views])
    if setup.pose_refine is not None:  # the mesh stage bakes the photos' colours from where the field saw them
        corrected = setup.pose_refine.corrected_c2w(setup.c2w.double().cpu()).tolist()
        meta["refined_c2w"] = {v.name: m for v, m in zip(plan.views, corrected, strict=True)}
    save_field(path, plan.kind, plan.kwargs, setup.model.cpu(), meta)


def _metrics(scene: Scene, device: torch.device, plan: TrainPlan, setup: TrainSetup, result: dict[str, Any],
             final: dict[str, Any], evals: list[dict], history: list[dict], train_time: float) -> dict[str, Any]:
    """metrics.json: the choices and why, the training curve, the held-out scores, the fitted corrections."""
    views = plan.views
    return {
        "model": plan.kind,
        "reasons": plan.reasons + setup.notes + [f"background: {plan.background_why}"],
        "steps": result["step"],
        "budget_s": plan.budget_s,
        "train_time_s": round(train_time, 2),
        "rays_per_s": round(result["rays_per_s"], 1),
        "device": str(device),
        "test": {k: v for k, v in final.items()},
        "evals": evals,
        "history": history,
        "resumes": result["resumes"],
        "n_train_views": len(views),
        "hull_start": plan.hull_start,
        "slow_culling": plan.slow_culling,
        "smoothness": plan.smoothness is not None,
        "n_rays_dropped_missing_box": int(setup.batcher.n_dropped),
        "appearance": _appearance_metrics(setup.appearance, plan.appearance_why, views),
        "pose_refine": _pose_metrics(setup.pose_refine, plan.pose_why, views, [float(v.intrinsics[0]) for v in views],
                                     _object_distance(views, scene)),
    }


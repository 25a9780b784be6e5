"""train stage: fit a radiance field to the training photos, evaluate held-out views, keep renders.

Writes `field.pt` (the model), `metrics.json` (PSNR/SSIM per held-out view and their means, the
training curve, the choices made and why), `curves.png` (PSNR vs step and vs wall time) and
`renders/NAME.png` (photo | render | depth) for a few test views. A checkpoint is written to the
stage's work folder every `checkpoint_every` steps and on Ctrl-C; running the same command again
resumes from it.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recon.atomic import checksum_matches, checksum_path, fault_point, write_checksummed, write_json_atomic
from recon.config import TrainConfig, parse_duration
from recon.errors import ReconError
from recon.field import FIELD_FILE, build_model, save_field
from recon.model_choice import choose_background, key_backdrop_for, model_spec, sky_for, surface_start, with_sky
from recon.pipeline import Stage, StageContext
from recon.scene import Frame, Scene, load_scene, spread_evenly
from recon.views import View, evaluate, load_views, view_tensors, write_previews

CHECKPOINT = "checkpoint.pt"


SURFACE_DEPTH_WHY = (
    "the surface model starts from a closed shape, and the photos' colours alone do not open a concavity it has "
    "closed over (a bowl keeps a lid at its rim); the SfM points' depths say the rays pass through to the floor"
)

UNBOUNDED_DEPTH_WHY = (
    "an unbounded capture without masks: where the object's colour matches what lies behind it the photos alone leave "
    "the surface soft and holed at any depth; the SfM points say at which depth the surface is"
)


def depth_prior_for(cfg: TrainConfig, kind: str, scene: Scene, frames: list[Frame], views: list[View],
                    kwargs: dict[str, Any], aabb: torch.Tensor | None, near_far: torch.Tensor,
                    device: torch.device) -> tuple[Any, str | None]:
    """The sparse-depth prior (`recon.nerf.depth_prior.DepthPrior`) or None, and why (printed either way).

    auto: on with few photos, for the surface model (`SURFACE_DEPTH_WHY`) and for unbounded captures
    (`UNBOUNDED_DEPTH_WHY`); off with masks."""
    from recon.nerf.depth_prior import DepthPrior, sparse_depth_targets
    from recon.normalization import FEW_PHOTOS

    if cfg.depth_prior == "off":
        return None, "depth prior: off (train.depth_prior=off)"
    visible = [np.asarray(scene.point_visibility.get(f.name, []), np.int64) for f in frames]
    n_obs = sum(len(v) for v in visible)
    few = len(frames) < FEW_PHOTOS
    if cfg.depth_prior == "auto" and not few and kind != "surface" and scene.capture != "unbounded":
        return None, (f"depth prior: off ({len(frames)} training photos >= {FEW_PHOTOS} of an object capture: the "
                      f"photos constrain the geometry; train.depth_prior=on forces it)")
    if cfg.depth_prior == "auto" and scene.has_alpha:
        return None, (f"depth prior: off ({len(frames)} training photos, but masks: their silhouettes already constrain "
                      f"the geometry, and with masks the prior makes the surface lumpy; train.depth_prior=on forces it)")
    if n_obs == 0:
        return None, "depth prior: off (the scene has no sparse points seen by the training photos)"
    scale = float(np.median([v.hw[1] / f.w for f, v in zip(frames, views, strict=True)]))
    errors = (np.ones(len(scene.points)) if scene.point_errors is None else np.asarray(scene.point_errors)) * scale
    box = np.asarray(scene.aabb, np.float64)
    model_cfg = kwargs.get("config", {})
    res = int(model_cfg.get("density_res") or model_cfg.get("sdf_res") or 128)
    voxel = float((box[1] - box[0]).max()) / res if scene.capture == "object" else 2.0 / res
    alpha = [v.image[..., 3] if v.image.shape[-1] == 4 else None for v in views]
    targets = sparse_depth_targets(
        scene.points, visible, np.stack([v.c2w for v in views]), np.array([v.intrinsics for v in views]),
        np.array([[v.hw[1], v.hw[0]] for v in views]), errors, alpha=alpha if scene.has_alpha else None, min_sigma=voxel,
    )
    prior = DepthPrior(targets, cfg.depth_weight, cfg.depth_rays, aabb=None if aabb is None else aabb.cpu(),
                       near_far=None if aabb is not None else near_far.cpu(), seed=cfg.seed).to(device)
    if cfg.depth_prior != "auto":
        why = "train.depth_prior=on"
    elif kind == "surface":
        why = SURFACE_DEPTH_WHY
    elif not few:
        why = UNBOUNDED_DEPTH_WHY
    else:
        why = f"{len(frames)} training photos (< {FEW_PHOTOS}): few views leave the geometry ambiguous"
    sig = prior.sigma.cpu().numpy() if len(prior) else np.zeros(1)
    return prior, (f"depth prior: on ({why}): {len(prior):,} depth targets from the SfM points the photos observe "
                   f"(DS-NeRF; uncertainty from reprojection error and triangulation angle, median {np.median(sig):.3g} "
                   f"units), {cfg.depth_rays} of them rendered per step, weight {cfg.depth_weight:g}")


def choose_appearance(cfg: TrainConfig, kind: str, views: list[View]) -> tuple[bool, str]:
    """(model the photos' exposure / white balance per photo?, why) — see recon.nerf.appearance."""
    from recon.nerf.appearance import decide, exposure_spread

    if kind == "classic" and cfg.appearance != "off":
        return False, "per-photo appearance off: it is built for the grid models (fast, surface), not the classic MLP"
    if cfg.appearance == "off":
        return False, "per-photo appearance off (train.appearance=off)"
    return decide(cfg.appearance, exposure_spread([v.image for v in views], np.stack([v.c2w for v in views])))


POSE_REFINE_WHY = (
    "it finds the photos SfM misplaced, but has not raised the held-out PSNR or the mesh's fine accuracy "
    "(docs/real_captures.md)"
)


def choose_pose_refine(cfg: TrainConfig, kind: str) -> tuple[bool, str]:
    """(learn per-photo camera corrections?, why) — see recon.nerf.pose_refine."""
    if cfg.pose_refine == "on" and kind == "classic":
        return False, "pose refinement off: it is built for the grid models (fast, surface), not the classic MLP"
    if cfg.pose_refine == "on":
        return True, ("pose refinement on (train.pose_refine=on): each training photo's camera gets a small rotation "
                      "and shift learned with the field")
    return False, f"pose refinement off (train.pose_refine=on turns it on; {POSE_REFINE_WHY})"


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


def _held_out_note(appearance: bool, poses: bool) -> str:
    """The headline's note on how held-out photos are scored when something is fitted on their left halves."""
    fitted = " and ".join(w for w, on in (("appearance", appearance), ("pose", poses)) if on)
    return f"; right halves, each photo’s {fitted} fitted on its left half" if fitted else ""


def _object_distance(views: list[View], scene: Scene) -> list[float]:
    """Each photo's distance to the middle of the scene box (or the origin of an unbounded scene)."""
    centre = np.asarray(scene.aabb, np.float64).mean(0) if scene.aabb is not None else np.zeros(3)
    return [float(np.linalg.norm(np.asarray(v.c2w)[:3, 3] - centre)) for v in views]


def run(ctx: StageContext) -> dict:
    from recon.nerf.device import select_device
    from recon.nerf.fitting import RayBatcher
    from recon.nerf.trainer import TrainingDiverged, TrainingInterrupted, train
    from recon.plots import training_curves

    cfg: TrainConfig = ctx.config
    if cfg.steps <= 0 or cfg.batch_rays <= 0:
        raise ReconError(f"train.steps and train.batch_rays must be positive (got {cfg.steps}, {cfg.batch_rays}).")
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ReconError(f"train.device={cfg.device}: {exc}") from None
    budget_s = parse_duration(cfg.budget)
    autocast = torch.bfloat16 if cfg.precision == "bf16" else None
    torch.manual_seed(cfg.seed)
    scene = load_scene(ctx.inputs["normalize"])
    train_frames = scene.split("train")
    held_out = scene.split("val") or scene.split("test") or train_frames[:1]
    test_frames = scene.split("test") or held_out
    if not train_frames:
        raise ReconError("The scene has no training views. Re-run normalize (recon normalize SCENE).")
    views = load_views(scene, train_frames, cfg.max_side, ctx.report, "training photos")
    kind, kwargs, lr, reasons = model_spec(cfg, scene, views)
    if cfg.adjusted:
        reasons.insert(0, cfg.adjusted)
    use_appearance, appearance_why = choose_appearance(cfg, kind, views)
    reasons.append(appearance_why)
    use_pose_refine, pose_why = choose_pose_refine(cfg, kind)
    reasons.append(pose_why)
    views, backdrop, key_why = key_backdrop_for(cfg, kind, scene, views)
    reasons.append(key_why)
    start_sdf = None
    if kind == "surface":
        kwargs, start_sdf, start_why = surface_start(kwargs, scene, views)
        reasons.append(start_why)
    background, random_bg, bg_why = choose_background(cfg, scene, views, backdrop)
    sky, sky_why = sky_for(cfg, kind, scene, train_frames, views)
    reasons.append(sky_why)
    if sky is not None:
        kwargs = with_sky(kwargs)
        bg_why = "the field's sky colour per ray direction (see sky:)"
    if budget_s:
        reasons.append(f"time budget {cfg.budget}: at most {cfg.steps} steps, stopping when the budget is spent")
    if kind == "fast" and device.type == "cpu":
        from recon.nerf.native import native_status

        reasons.append(f"marcher: {native_status()}")
    ctx.report.info(f"device: {device}; background: {bg_why}")
    for r in reasons:
        ctx.report.info(f"model: {r}")
    if use_appearance:
        from recon.nerf.evaluate import HELD_OUT_PROTOCOL

        ctx.report.info(f"held-out evaluation: {HELD_OUT_PROTOCOL}")
    if use_pose_refine:
        from recon.nerf.evaluate import POSE_PROTOCOL

        ctx.report.info(f"held-out evaluation: {POSE_PROTOCOL}")
    bounded = scene.capture == "object"
    aabb = torch.tensor(np.asarray(scene.aabb), dtype=torch.float32, device=device) if bounded else None

    model = build_model(kind, kwargs)
    if start_sdf is not None:
        model.set_initial_sdf(start_sdf)
    model = model.to(device)
    if kind == "fast":
        from recon.nerf.compiled import compile_color_network, compile_wanted

        if compile_wanted(cfg.compile, device)[0]:  # on a CPU with train.compile=auto nothing changes, nothing is said
            reasons.append(compile_color_network(model, device, cfg.compile))
            ctx.report.info(f"model: {reasons[-1]}")
    images, c2w, intr, near_far = view_tensors(views, device)
    depth_prior, depth_why = depth_prior_for(cfg, kind, scene, train_frames, views, kwargs, aabb, near_far, device)
    if depth_why:
        reasons.append(depth_why)
        ctx.report.info(f"model: {depth_why}")
    batcher = RayBatcher(
        images, c2w, intr,
        aabb=aabb, near_far=None if bounded else near_far,
        background=torch.tensor(background), random_background=random_bg, seed=cfg.seed, device=device,
        empty=sky,
    )
    appearance = None
    if use_appearance:
        from recon.nerf.appearance import PhotoAppearance

        appearance = PhotoAppearance(len(views), include_background=not batcher.has_alpha).to(device)
    pose_refine = None
    if use_pose_refine:
        from recon.nerf.pose_refine import PoseRefinement

        pose_refine = PoseRefinement(len(views), centres=c2w[:, :3, 3]).to(device)
    eval_views = load_views(scene, spread_evenly(held_out, cfg.eval_views), cfg.max_side)

    ckpt_path = ctx.work / CHECKPOINT
    checkpoint = _load_checkpoint(ckpt_path, ctx.report)
    evals: list[dict] = checkpoint["evals"] if checkpoint else []
    history: list[dict] = checkpoint["history"] if checkpoint else []
    time_before = checkpoint["train_time_s"] if checkpoint else 0.0
    if checkpoint:
        ctx.report.info(f"resuming from the checkpoint at step {checkpoint['state']['step']} of {cfg.steps}")
    eval_time = [0.0]

    def eval_fn(m: torch.nn.Module, step: int) -> dict[str, float]:
        t = time.perf_counter()
        r = evaluate(m, eval_views, aabb, background, autocast=autocast, appearance=use_appearance,
                     align_poses=pose_refine is not None)
        eval_time[0] += time.perf_counter() - t
        return {"psnr": r["psnr"], "ssim": r["ssim"]}

    t_start = time.perf_counter()

    def train_time() -> float:
        return time_before + time.perf_counter() - t_start - eval_time[0]

    with ctx.report.task("training", total=cfg.steps, unit="steps") as bar:
        bar.update(completed=checkpoint["state"]["step"] if checkpoint else 0)

        def on_step(p: Any) -> None:
            bar.update(completed=p.step, info=f"loss {p.loss:.4f}  PSNR {p.psnr:.2f} dB  {p.rays_per_s:,.0f} rays/s")
            if p.step % 10 == 0 or p.step == p.steps:
                history.append({"step": p.step, "loss": p.loss, "psnr": p.psnr, "time_s": round(train_time(), 3)})
            if p.metrics is not None:
                evals.append({"step": p.step, "time_s": round(train_time(), 3), **p.metrics})
                ctx.report.info(f"step {p.step}: held-out PSNR {p.metrics['psnr']:.2f} dB, SSIM {p.metrics['ssim']:.3f}")
            if ctx.report.observers:  # a live viewer (recon run --view): it renders the model on this thread
                ctx.report.observe("train_step", {"progress": p, "model": model, "view": eval_views[0], "aabb": aabb, "background": background})
            if cfg.checkpoint_every and p.step % cfg.checkpoint_every == 0 and p.step < p.steps:
                _save_checkpoint(ckpt_path, {"state": p.state_dict(), "evals": evals, "history": history, "train_time_s": train_time()})

        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", UserWarning)
                result = train(
                    model, batcher, steps=cfg.steps, lr=lr, lr_final=lr * cfg.lr_decay, batch_rays=cfg.batch_rays,
                    eval_fn=eval_fn, eval_every=cfg.eval_every or cfg.steps, callbacks=[on_step],
                    state=checkpoint["state"] if checkpoint else None,
                    budget_s=budget_s, spent_s=time_before, autocast=autocast, extra_loss=depth_prior,
                    appearance=appearance, pose_refine=pose_refine, empty_weight=cfg.sky_weight,
                )
            for w in caught:
                if "training is not improving" in str(w.message):
                    ctx.report.warn(str(w.message))
        except TrainingInterrupted as stop:
            _save_checkpoint(ckpt_path, {"state": stop.state, "evals": evals, "history": history, "train_time_s": train_time()})
            raise KeyboardInterrupt from None
        except TrainingDiverged as exc:
            raise ReconError(
                f"Training diverged at step {exc.step}: {exc.cause}. {exc.advice} "
                f"(e.g. --set train.lr={lr / 3:.3g}; the last checkpoint is kept in {ctx.work})."
            ) from None
    total_train_time = train_time()

    test_views = load_views(scene, spread_evenly(test_frames, cfg.final_eval_views), cfg.max_side)  # a spiral's first N would be one viewpoint
    with ctx.report.task("evaluating test views", total=None):
        final = evaluate(model, test_views, aabb, background, keep=True, autocast=autocast, appearance=use_appearance,
                         align_poses=pose_refine is not None)
    write_previews(final.pop("renders"), ctx.out / "renders")
    meta = {
        "aabb": np.asarray(scene.aabb).tolist(),
        "bounded": bounded,
        "background": background.tolist(),
        "max_side": cfg.max_side,
        "capture": scene.capture,
    }
    if appearance is not None:  # the field stays neutral; the photos' transforms are kept for whoever needs them
        meta["appearance"] = appearance.summary([v.name for v in views])
    if pose_refine is not None:  # the mesh stage bakes the photos' colours from where the field saw them
        corrected = pose_refine.corrected_c2w(c2w.double().cpu()).tolist()
        meta["refined_c2w"] = {v.name: m for v, m in zip(views, corrected, strict=True)}
    save_field(ctx.out / FIELD_FILE, kind, kwargs, model.cpu(), meta)
    metrics = {
        "model": kind,
        "reasons": reasons + [f"background: {bg_why}"],
        "steps": result["step"],
        "budget_s": budget_s,
        "train_time_s": round(total_train_time, 2),
        "rays_per_s": round(result["rays_per_s"], 1),
        "device": str(device),
        "test": {k: v for k, v in final.items()},
        "evals": evals,
        "history": history,
        "n_train_views": len(views),
        "n_rays_dropped_missing_box": int(batcher.n_dropped),
        "appearance": _appearance_metrics(appearance, appearance_why, views),
        "pose_refine": _pose_metrics(pose_refine, pose_why, views, [float(v.intrinsics[0]) for v in views],
                                     _object_distance(views, scene)),
    }
    if pose_refine is not None:
        largest = metrics["pose_refine"]["largest"][:3]
        ctx.report.info("pose refinement: median correction {:.2f} px; largest {}".format(
            metrics["pose_refine"]["median_pixels"], ", ".join(f"{r['photo']} {r['pixels']:.2f} px" for r in largest)))
    write_json_atomic(ctx.out / "metrics.json", metrics)
    training_curves(history, evals, ctx.out / "curves.png", title=f"{kind} model — test PSNR {final['psnr']:.2f} dB")
    # the checkpoint stays until the pipeline has recorded this stage as done (it then removes ctx.work):
    # a crash between here and the manifest resumes from it instead of training again from step 0
    return {
        "headline": (f"{kind} model, {result['step']} steps in {total_train_time:.0f} s: "
                     f"{'test' if scene.split('test') else 'training-photo (none held out)'} PSNR {final['psnr']:.2f} dB, "
                     f"SSIM {final['ssim']:.3f} ({len(test_views)} views"
                     f"{_held_out_note(use_appearance, pose_refine is not None)})"),
        "psnr": round(final["psnr"], 3),
        "ssim": round(final["ssim"], 4),
        "train_time_s": round(total_train_time, 1),
    }


# version 2: train.depth_prior=auto turns the prior on for the surface model, so a cached surface field is stale
# version 3: the surface model keys a plain backdrop (train.backdrop_key) and starts from the SfM points' hull
# version 4: train.sky=auto gives an unbounded capture with a clear sky a sky colour and trains its sky pixels empty
# version 5: train.depth_prior=auto turns the prior on for unbounded captures without masks
# version 6: the surface model starts from the photos' visual hull when they have silhouettes
STAGE = Stage(name="train", folder="03_field", inputs=("normalize",), version=6, run=run)

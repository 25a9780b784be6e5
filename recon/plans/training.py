"""Which model a scene gets, with what settings, background and training pieces, and why: the train stage's plan
(`plan_training`) and what it builds (`build_training`), shared with `recon bench --profile` and the benchmarks,
which must time the very step the stage trains."""
from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch

from recon.camera import pixel_footprint, project
from recon.capture.auto_masks import HULL_RES, HULL_TOLERANCE
from recon.capture.region import support_kind
from recon.capture.scene import Frame, Scene
from recon.capture.sky import SKY_MIN_FRACTION, sky_mask
from recon.config import TrainConfig
from recon.errors import ReconError
from recon.evaluation.views import (
    BACKDROP_TOLERANCE,
    PLAIN_BACKDROP_FRACTION,
    View,
    border_color,
    key_backdrop,
    plain_backdrop,
    training_focal,
    view_tensors,
)
from recon.geometry.visual_hull import carve, free_space, hull_silhouettes
from recon.nerf.appearance import PhotoAppearance, decide, exposure_spread
from recon.nerf.depth_prior import DepthPrior, sparse_depth_targets
from recon.nerf.smoothness import PatchSmoothness
from recon.nerf.fitting import RayBatcher
from recon.nerf.pose_refine import PoseRefinement
from recon.nerf.surface import hull_planes

BACKDROP_KEY_WHY = (
    "a surface colored like the backdrop is as bright as the backdrop itself, so the photos' colours cannot tell it "
    "from empty space; keyed, the backdrop's pixels say where the object is not"
)


def key_backdrop_for(cfg: TrainConfig, kind: str, scene: Scene, views: list[View]) -> tuple[list[View], np.ndarray | None, str]:
    """(the training views, keyed to RGBA when the backdrop key applies; the backdrop colour or None; why).

    auto keys the surface model's photos when their borders are a plain backdrop (`recon.evaluation.views.plain_backdrop`):
    its zero set is closed, and without the key it closed over what only the backdrop shows, such as a hole
    seen through or space under the object that no camera sees against anything else."""
    if cfg.backdrop_key == "off":
        return views, None, "backdrop key: off (train.backdrop_key=off)"
    if scene.has_alpha:
        return views, None, "backdrop key: not needed (the photos have masks or alpha: their background is known)"
    if cfg.backdrop_key == "auto" and (kind != "surface" or scene.capture != "object"):
        return views, None, ("backdrop key: off (auto keys the surface model's photos only; train.backdrop_key=on forces it)")
    color, plain = plain_backdrop(views)
    share = f"{plain:.0%} of the photos' border pixels are within {BACKDROP_TOLERANCE} of {np.round(color, 3).tolist()}"
    if cfg.backdrop_key == "auto" and plain < PLAIN_BACKDROP_FRACTION:
        return views, None, f"backdrop key: off (no plain backdrop: {share}, fewer than {PLAIN_BACKDROP_FRACTION:.0%})"
    keyed = [replace(v, image=key_backdrop(v.image, color)) for v in views]
    why = "train.backdrop_key=on" if cfg.backdrop_key == "on" else BACKDROP_KEY_WHY
    return keyed, color.astype(np.float32), (f"backdrop key: on ({share}; {why}): pixels of the backdrop's colour train "
                                             f"as empty space")


SKY_WHY = (
    "a single background colour cannot show a sky that brightens towards the horizon, so the field paints it into "
    "its density as blobs above the roofs, and they become mesh"
)


def sky_for(cfg: TrainConfig, kind: str, scene: Scene, frames: list[Frame],
            views: list[View]) -> tuple[list[np.ndarray] | None, str]:
    """(per training photo, the (H, W) bool mask of its sky pixels, or None; why) — see `recon.capture.sky`.

    auto: on for the fast model of an unbounded capture without masks when at least `SKY_MIN_FRACTION` of the
    training pixels are sky; the field then shows a sky colour per ray direction behind everything, and the sky
    pixels train as empty space (`train.sky_weight`)."""
    if cfg.sky == "off":
        return None, "sky: off (train.sky=off)"
    if kind != "fast":
        return None, f"sky: off (the {kind} model has no sky colour)"
    if scene.has_alpha:
        return None, "sky: off (the photos have masks: their background is known)"
    if cfg.sky == "auto" and scene.capture == "object":
        return None, "sky: off (an object capture: nothing is modelled outside its box; train.sky=on forces it)"
    points = np.asarray(scene.points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return None, "sky: off (no sparse points: nothing tells a clear sky from a smooth blue surface)"
    masks = []
    for frame, view in zip(frames, views, strict=True):
        seen = scene.observed_points(frame)
        uv, z = project(points if seen is None else seen, np.asarray(view.c2w, np.float64),
                        np.asarray(view.intrinsics, np.float64))
        masks.append(sky_mask(view.image, uv[z > 0]))
    share = float(sum(m.sum() for m in masks)) / max(1, sum(m.size for m in masks))
    with_sky = sum(bool(m.any()) for m in masks)
    found = (f"{share:.1%} of the training pixels in {with_sky} of {len(masks)} photos are sky "
             f"(smooth, blue or pale beside the blue, no SfM point near)")
    if cfg.sky == "auto" and share < SKY_MIN_FRACTION:
        return None, f"sky: off ({found}; fewer than {SKY_MIN_FRACTION:.0%})"
    why = "train.sky=on" if cfg.sky == "on" else SKY_WHY
    return masks, (f"sky: on ({found}; {why}): a sky colour per ray direction behind the field, and the sky pixels "
                   f"train as empty space (weight {cfg.sky_weight:g})")


def transparent_for(cfg: TrainConfig, kind: str, scene: Scene,
                    views: list[View]) -> tuple[list[np.ndarray] | None, str]:
    """(per training photo, the (H, W) mask of its pixels known to show nothing, or None; why): bool, or the float
    weight of each pixel's opacity loss when the disputed pixels pay a share of it.

    Photos with masks or alpha train on random backgrounds, which tell the field that their transparent pixels show
    nothing only through their colour; the fast field also pays for its opacity there (`train.transparent_weight`).
    Known means the photos agree: a transparent pixel that the hull of all the training photos' masks still covers
    (a thin part one photo's mask cut away, or space under a base only the lowest photos see) pays
    `train.transparent_disputed_share` of the weight: the other photos' colour keeps a thin part against one wrong
    mask, while space in which no photo shows anything is still cleared."""
    if not views or views[0].image.shape[-1] != 4:
        return None, ""
    if kind != "fast":
        return None, f"transparent pixels: trained by their colour on random backgrounds (the {kind} model)"
    if cfg.transparent_weight <= 0:
        return None, "transparent pixels: trained by their colour alone (train.transparent_weight=0)"
    in_hull, _ = hull_silhouettes(np.asarray(scene.aabb, np.float64), HULL_RES, [v.c2w for v in views],
                                  [v.intrinsics for v in views], silhouettes(views), HULL_TOLERANCE)
    transparent = [v.image[..., 3] == 0 for v in views]
    agreed = [t & ~s for t, s in zip(transparent, in_hull, strict=True)]
    total = max(1, sum(m.size for m in agreed))
    share, disputed = (float(sum(m.sum() for m in agreed)) / total,
                       float(sum((t & s).sum() for t, s in zip(transparent, in_hull, strict=True))) / total)
    why = (f"transparent pixels: {share:.0%} of the training pixels lie outside the masks and outside the hull they "
           f"carve together, and train as empty space (weight {cfg.transparent_weight:g}): random backgrounds alone "
           f"leave a faint haze there; {disputed:.1%} more are transparent in their photo but inside the hull")
    part = cfg.transparent_disputed_share
    if part <= 0:
        return agreed, f"{why}, and train by their colour only (train.transparent_disputed_share=0)"
    weights = (transparent if part >= 1 else  # all of the weight: every transparent pixel alike, as bools
               [np.where(a, np.float32(1), np.float32(part) * t) for a, t in zip(agreed, transparent, strict=True)])
    return weights, (f"{why} (other photos may show a thin part there, or only the lowest photos see past a base), "
                     f"and train as empty space at {part:.0%} of that weight (train.transparent_disputed_share): the "
                     "colour loss alone leaves a blob under a base in every low view")


def with_sky(kwargs: dict[str, Any]) -> dict[str, Any]:
    """`model_spec`'s model kwargs with the fast field's background set to its sky colour (`sky_for` said on)."""
    return {**kwargs, "config": {**kwargs["config"], "background": "sky"}}


SMALL_OBJECT_SHARE = 0.5
"""An object capture trains larger than max_side only where its box spans under this share of max_side: a capture
framing its object as usual (the sample, the fox: the box spans about the whole side) or a little wider keeps the
preset's size and time per step, and a small object in wide photos gets the pixels it lacks
(`benchmarks/results/small_object_sample.json`)."""
MAX_OBJECT_SIDE = 1600
"""The longest side `training_side` raises the photos to."""
MAX_OBJECT_PIXELS = 50_000_000
"""The training photos' pixels, all together, that `training_side` raises them to at most: each pixel stays in memory
with its ray's bookkeeping while training, so many photos rise less than a few."""


def training_side(cfg: TrainConfig, scene: Scene, frames: list[Frame]) -> tuple[int, str]:
    """(the longest side the training photos load at, why; "" where it is max_side), `train.small_object`.

    The presets' sizes suit an object that fills the frame. A small object in wide photos spans few pixels at
    max_side: the field's grids and the mesh grid are sized to the pixel footprint, so its surface comes out coarse and
    off by up to a pixel. Rays that miss the scene box are never trained (`RayBatcher`), so larger photos add rays on
    the object only."""
    if cfg.small_object == "off" or scene.capture != "object" or scene.aabb is None or not frames:
        return cfg.max_side, ""
    box = np.asarray(scene.aabb, np.float64)
    centre, radius = box.mean(axis=0), float(np.linalg.norm(box[1] - box[0])) / 2
    spans = [2 * f.fl_x * min(1.0, cfg.max_side / max(f.w, f.h)) * radius
             / max(float(np.linalg.norm(f.c2w[:3, 3] - centre)), radius) for f in frames]
    span = float(np.median(spans))  # the box's bounding sphere, in pixels of the photos at max_side
    if span >= SMALL_OBJECT_SHARE * cfg.max_side:
        return cfg.max_side, ""
    own = int(np.median([max(f.w, f.h) for f in frames]))
    fits = math.sqrt(MAX_OBJECT_PIXELS / sum(f.w * f.h / max(f.w, f.h) ** 2 for f in frames))  # pixels ∝ side²
    side = min(round(cfg.max_side * cfg.max_side / span), own, MAX_OBJECT_SIDE, int(fits))
    if side <= cfg.max_side:
        return cfg.max_side, ""
    return side, (f"training size: the object's box spans {span:.0f} px of the {cfg.max_side}-px photos (median), "
                  f"under half of them: they train at {side} px, where it spans {span * side / cfg.max_side:.0f}, so "
                  f"the grids and the mesh see it as finely as an object filling the frame "
                  f"(train.small_object=off keeps {cfg.max_side} px)")


FOOTPRINT_PERCENTILE = 75
FOOTPRINT_SLACK = 1.25
"""A photo trains at the pixel footprint on the object (its distance to the box's centre over its focal length at
max_side) of the FOOTPRINT_PERCENTILE-th percentile photo when its own is over FOOTPRINT_SLACK times finer."""


def photo_sides(cfg: TrainConfig, scene: Scene, frames: list[Frame]) -> tuple[dict[str, int], str]:
    """({frame name: the longest side it trains at}, for the close-ups only; why), `train.photo_footprint`.

    A close-up at max_side sees the object several times finer than the photos around it: the field's grids cannot
    hold that detail, its colour loss pulls the surface apart trying, and with as many pixels as a whole-object photo
    it takes as many of every step's rays for one part of the object. Downscaled to the others' footprint it adds
    its view of that part and no more. Empty when every photo sees the object at about the same scale."""
    if cfg.photo_footprint == "off":
        return {}, "photo footprint: every photo at max_side (train.photo_footprint=off)"
    if len(frames) < 2:
        return {}, ""
    center = np.asarray(scene.aabb, np.float64).mean(axis=0)
    footprint = {f.name: float(np.linalg.norm(f.c2w[:3, 3] - center)) / training_focal([f], cfg.max_side) for f in frames}
    target = float(np.percentile(list(footprint.values()), FOOTPRINT_PERCENTILE))
    sides = {name: max(16, round(cfg.max_side * fp / target)) for name, fp in footprint.items()
             if fp * FOOTPRINT_SLACK < target}
    if not sides:
        return {}, ""
    finest = target / min(footprint[n] for n in sides)
    return sides, (f"photo footprint: {len(sides)} of {len(frames)} training photos see the object up to "
                   f"{finest:.1f}x finer than most (close-ups): they train downscaled to the others' pixel footprint "
                   f"({min(sides.values())}-{max(sides.values())} px instead of {cfg.max_side}), so their detail and "
                   f"their share of the rays match the rest (train.photo_footprint=off keeps them at max_side)")


def choose_background(cfg: TrainConfig, scene: Scene, views: list[View], backdrop: np.ndarray | None = None) -> tuple[np.ndarray, bool, str]:
    """(evaluation background color, train on random backgrounds?, why); `backdrop`: the keyed backdrop's colour."""
    if backdrop is not None and cfg.background == "auto":
        return backdrop, True, ("the backdrop is keyed (known background): trained on random backgrounds so nothing paints "
                                f"it, shown on its colour {np.round(backdrop, 3).tolist()}")
    if cfg.background == "white":
        return np.ones(3, np.float32), False, "white (train.background=white)"
    if cfg.background == "black":
        return np.zeros(3, np.float32), False, "black (train.background=black)"
    if cfg.background == "random" or (cfg.background == "auto" and scene.has_alpha):
        return np.ones(3, np.float32), scene.has_alpha, (
            "photos have alpha (known background): trained on random backgrounds so nothing paints the backdrop, shown on white"
            if scene.has_alpha else "random backgrounds requested but the photos have no alpha: white"
        )
    color = border_color(views)
    return color.astype(np.float32), False, f"the photos' border color {np.round(color, 3).tolist()} (median of edge pixels)"


def model_spec(cfg: TrainConfig, scene: Scene, views: list[View]) -> tuple[str, dict[str, Any], float, list[str]]:
    """(model kind, constructor kwargs, learning rate, reasons) — the simplest model the scene needs."""
    aabb = np.asarray(scene.aabb, dtype=np.float64)
    reasons = []
    if cfg.model == "surface":
        return surface_spec(cfg, scene)
    kind = "fast" if cfg.model in ("auto", "fast") else "classic"
    if kind == "classic":
        c = cfg.classic
        reasons.append(f"classic NeRF (train.model={cfg.model}): {c.depth}×{c.width} MLP, L={c.pos_freqs}/{c.dir_freqs}, {c.n_coarse}+{c.n_fine} samples")
        kwargs = {"aabb": aabb.tolist(), **asdict(c)}
        return kind, kwargs, cfg.lr or 5e-4, reasons
    footprint, _ = pixel_footprint(aabb, np.stack([v.c2w[:3, 3] for v in views]), np.array([v.intrinsics[0] for v in views]))
    fast_cfg, why = auto_fast_config(cfg.fast, scene, footprint)
    reasons.append("fast grid model" + (" (train.model=auto: the practical choice on a CPU)" if cfg.model == "auto" else ""))
    reasons += why
    if cfg.model == "auto":
        reasons.append(
            "surface model not chosen: its renders are softer than the density models' (coarser grids); for a "
            "closed, smooth and more accurate mesh of this object capture use --preset surface (train.model=surface; "
            "docs/surface.md)" if scene.capture == "object"
            else "surface model not offered: it needs an object capture (this scene is unbounded)"
        )
    lr, lr_why = grid_lr(cfg, kind)
    return kind, {"config": asdict(fast_cfg)}, lr, reasons + ([lr_why] if lr_why else [])


def surface_spec(cfg: TrainConfig, scene: Scene) -> tuple[str, dict[str, Any], float, list[str]]:
    """The surface (SDF) model for an object capture; refused, with what to do, for an unbounded scene. Its start
    shape is settled by `surface_start` once the training photos have their silhouettes."""
    if scene.capture != "object":
        raise ReconError(
            f"train.model=surface needs an object capture (a bounded box around one object); this scene is "
            f"'{scene.capture}'. Use --preset balanced (or train.model=fast) for unbounded scenes."
        )
    aabb = np.asarray(scene.aabb, dtype=np.float64)
    surf = replace(cfg.surface, aabb=tuple(tuple(float(x) for x in row) for row in aabb))
    why = ("surface model (train.model=surface): signed distance on "
           f"{surf.sdf_levels} dense levels up to {surf.sdf_res}³, NeuS opacity with learned sharpness, Eikonal "
           "and curvature terms; its mesh is the closed zero level set")
    lr, lr_why = grid_lr(cfg, "surface")
    return "surface", {"config": asdict(surf)}, lr, [why] + ([lr_why] if lr_why else [])


def has_silhouettes(views: list[View]) -> bool:
    """Whether every training photo has its silhouette (alpha: masks, or the backdrop keyed)."""
    return bool(views) and all(v.image.shape[-1] == 4 for v in views)


def silhouettes(views: list[View]) -> list[np.ndarray]:
    """Each photo's object pixels (H, W) bool: its alpha at least half."""
    return [v.image[..., 3] >= 128 for v in views]


def slow_culling(fast: dict[str, Any]) -> str:
    """Why an empty fast field with silhouettes culls untouched space late (`FastConfig.slow_occupancy_alpha_start`)."""
    return (f"occupancy culls from {fast['slow_occupancy_alpha_start']:.1%} opacity a step, below the initial "
            f"{fast['init_alpha']:.0%}, rising over {fast['slow_occupancy_ramp']:,} steps, so a patch the colours "
            "cannot place yet is not culled before it forms")


def hull_start_for(cfg: TrainConfig, kind: str, kwargs: dict[str, Any], scene: Scene,
                   views: list[View]) -> tuple[bool, bool, str]:
    """(whether the fast model starts with matter inside the photos' visual hull, whether it starts empty though the
    photos have silhouettes and so culls slowly (`FastModel.cull_slowly`), why); why is "" where there is nothing to
    say: another model, an unbounded field, no silhouettes."""
    fast = kwargs["config"] if kind == "fast" else {}
    if kind != "fast" or fast.get("unbounded") or fast.get("density_grid", "dense") != "dense":
        return False, False, ""
    if not has_silhouettes(views):
        return False, False, ("start: an empty field (train.hull_start=on needs silhouettes: masks or alpha)"
                              if cfg.hull_start == "on" else "")
    hull = (f"inside the visual hull of the {len(views)} training photos' silhouettes at opacity "
            f"{fast['hull_start_alpha']:g} a step")
    if cfg.hull_start == "on":
        return True, False, f"start: {hull} (train.hull_start=on)"
    if cfg.hull_start == "off":
        return False, True, f"start: an empty field (train.hull_start=off); {slow_culling(fast)}"
    if scene.ground is not None and support_kind(scene.ground) == "wall":
        return False, True, ("start: an empty field: the object hangs on a wall, so the photos see it from one side "
                             "and their hull reaches out towards them; a plain face would form on the hull, in front "
                             f"of the true one (train.hull_start=on starts it in the hull); {slow_culling(fast)}")
    return True, False, (f"start: {hull}: where the colours cannot place a surface (a plain or glossy patch), a field "
                         "grown from empty space leaves a hole there and walls inside the object behind it "
                         "(train.hull_start=off starts it empty)")


def sightlines_of(scene: Scene, frames: list[Frame]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per photo of `frames` that the scene says which points it observes (not an import's), its camera centre and
    those points (`recon.geometry.visual_hull.free_space`)."""
    lines = []
    for frame in frames:
        seen = scene.observed_points(frame)
        if seen is not None and len(seen):
            lines.append((np.asarray(frame.c2w, np.float64)[:3, 3].copy(), seen))
    return lines


def freed_hull(box: np.ndarray, res: int, views: list[View],
               lines: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(the training photos' visual hull on a res³ grid over box, the part of it that the sightlines `lines` pass
    through: `free_space`, a hollow or an overhang the silhouettes cannot carve), both (res, res, res) bool."""
    inside, _ = carve(box, res, [v.c2w for v in views], [v.intrinsics for v in views], silhouettes(views))
    return inside, (inside & free_space(box, res, lines)) if lines else np.zeros_like(inside)


def surface_start(kwargs: dict[str, Any], scene: Scene, views: list[View]) -> tuple[dict[str, Any], np.ndarray | None, str]:
    """(the surface model's kwargs with its start shape settled, the visual hull's SDF volume or None, why).

    Called once the training views have their alpha (masks or the backdrop key). auto: the visual hull when the
    photos have silhouettes, else the SfM points' convex hull, else a sphere."""
    from recon.geometry.visual_hull import visual_hull_sdf

    surf = kwargs["config"]
    shape = surf.get("init_shape", "auto")
    box = np.asarray(surf["aabb"], np.float64)
    res = int(surf["sdf_res"])
    with_alpha = has_silhouettes(views)
    if shape == "visual_hull" and not with_alpha:
        raise ReconError("train.surface.init_shape=visual_hull needs silhouettes: a masks/ folder beside the photos, or "
                         "a plain backdrop to key (train.backdrop_key). Use train.surface.init_shape=auto.")
    not_visual = ("train.surface.init_shape=" + shape if shape != "auto"
                  else "the photos have no silhouettes (masks or a keyed backdrop) for a visual hull")
    if shape in ("auto", "visual_hull") and with_alpha:
        lines = sightlines_of(scene, scene.split("train"))
        hull, free = freed_hull(box, res, views, lines)
        inside = hull & ~free
        core, freed = inside[1:-1, 1:-1, 1:-1], free[1:-1, 1:-1, 1:-1].mean()
        if core.any():
            why = (f"initial surface: the visual hull of the {len(views)} training photos' silhouettes "
                   f"({hull[1:-1, 1:-1, 1:-1].mean():.1%} of the box; {VISUAL_HULL_WHY})" + (
                       f", less {freed:.1%} of the box that lies on the sightlines from {len(lines)} photos "
                       "to the sparse points they observe (a hollow or an overhang the silhouettes cannot carve)"
                       if freed > 0 else ""))
            settled = {**kwargs, "config": {**surf, "init_shape": "visual_hull", "init_planes": ()}}
            return settled, visual_hull_sdf(inside, box), why
        if shape == "visual_hull":
            raise ReconError("The training photos' silhouettes leave nothing of the scene box: every point of it is "
                             "background in some photo. Check the masks (white = object).")
        not_visual = "the photos' silhouettes leave nothing of the box (every point is background in some photo)"
    points = np.asarray(scene.points, np.float64).reshape(-1, 3)
    n_in = int(((points >= box[0]) & (points <= box[1])).all(axis=1).sum())
    planes = hull_planes(points, box) if shape in ("auto", "hull") else []
    settled = {**kwargs, "config": {**surf, "init_shape": "hull" if planes else "sphere", "init_planes": tuple(planes)}}
    if planes:
        return settled, None, (f"initial surface: the convex hull of the {n_in:,} sparse points in the box ({len(planes)} "
                               f"faces; {not_visual}): {HULL_WHY}")
    if shape == "sphere":
        return settled, None, "initial surface: a sphere (train.surface.init_shape=sphere)"
    return settled, None, (f"initial surface: a sphere ({not_visual}, and only {n_in} sparse points in the box, or they "
                           f"span no volume: no convex hull)")


START_WHY = "what no photo sees keeps the shape the SDF starts from, pulled back to it with train.surface.init_prior_weight"

VISUAL_HULL_WHY = (
    f"{START_WHY}, and the silhouettes bound it down to the lowest edges the photos see; the SfM points' convex hull "
    "passes where the points end, above an object's lowest edges when few points lie on them"
)

HULL_WHY = (
    f"{START_WHY}; from a sphere an unseen underside drifts into a cave, from the hull it stays flat where the points "
    "reach the bottom edges"
)

GRID_LR = 1e-2
"""Default learning rate of the grid models (fast, surface) at GRID_LR_RAYS rays a step: their networks' (their grids
train at multiples of it, grid_lr_scale and sdf_lr_scale)."""
GRID_LR_RAYS = 4096


def grid_lr(cfg: TrainConfig, kind: str) -> tuple[float, str]:
    """Grid model ``kind``'s (fast, surface) learning rate: train.lr where set, else GRID_LR, grown above GRID_LR_RAYS
    rays a step with the cube root of the batch, which scored best or within 0.06 dB of it at 2x, 4x and 8x the rays
    on the half-res Lego and above GRID_LR for the surface model at 8x (benchmarks/results/lego_half_lr_8k.json,
    lego_half_lr_16k.json, lego_half_lr_big_batch.json, sample_surface_lr_big_batch.json); and why, "" where the rate
    is train.lr or GRID_LR."""
    if cfg.lr:
        return cfg.lr, ""
    batch_rays = cfg.batch_rays
    if batch_rays <= GRID_LR_RAYS:
        return GRID_LR, ""
    factor = (batch_rays / GRID_LR_RAYS) ** (1 / 3)
    lr = GRID_LR * factor
    return lr, (f"learning rate {lr:.3g}: the {kind} model's {GRID_LR:g} for {GRID_LR_RAYS:,} rays a step "
                f"× {factor:.2f} (the cube root of {batch_rays:,} / {GRID_LR_RAYS:,}): a larger batch's gradient is "
                "less noisy, so it takes longer steps (train.lr sets the rate)")


def auto_fast_config(base: Any, scene: Scene, footprint: float) -> tuple[Any, list[str]]:
    """Fit the fast model to the scene: box, bounded or not, and grid resolution no finer than the pixels."""
    aabb = np.asarray(scene.aabb, dtype=np.float64)
    unbounded = scene.capture != "object"
    reasons = [
        (f"unbounded scene: space outside the box is contracted (mip-NeRF 360, L∞); occupancy keeps space from "
         f"{base.unbounded_occupancy_alpha:.0%} opacity per step (an object's: {base.occupancy_alpha:.0%}), so the "
         "young fog every ray of a room crosses costs no samples") if unbounded
        else "object capture: a plain box around the object, nothing modelled outside it"
    ]
    extent = float((aabb[1] - aabb[0]).max()) if not unbounded else 4.0
    needed = int(np.ceil(extent / max(footprint, 1e-12) / 16.0) * 16)
    density_res = int(min(base.density_res, max(32, needed)))
    feature_res = int(min(base.feature_res, max(32, needed)))
    hashed = (f" (a hash grid of {base.feature_dim} levels, 2^{base.hash_table_log2} rows each)"
              if base.grid == "hash" else "")
    if density_res < base.density_res or feature_res < base.feature_res:
        reasons.append(
            f"grids {density_res}³/{feature_res}³{hashed} instead of {base.density_res}³/{base.feature_res}³: one "
            f"training pixel covers {footprint:.4g} units at the cameras' distance, so finer voxels could not be seen"
        )
    else:
        reasons.append(f"grids {density_res}³ density / {feature_res}³ features{hashed} (the preset's cap; pixels "
                       f"would allow {needed}³)")
    distortion = base.unbounded_distortion_weight if unbounded else base.distortion_weight
    if distortion > 0:
        key = "unbounded_distortion_weight" if unbounded else "distortion_weight"
        reasons.append(
            f"distortion loss {distortion:g} (mip-NeRF 360, train.fast.{key}): draws each ray's weight into one "
            "interval, so no fog or floaters stand in front of the surface, and fewer samples a ray"
            + ("; on contracted distance, so the far field weighs no more than the object" if unbounded else "")
            + (f"; from {base.distortion_from:.0%} of training on (train.fast.distortion_from), once the field has "
               "found its finer parts" if base.distortion_from > 0 else "")
            + (f"; until {base.distortion_until:.0%} of it (train.fast.distortion_until)"
               if base.distortion_until < 1 else "")
        )
    elif unbounded and base.distortion_weight > 0:
        reasons.append(
            f"no distortion loss (an object's: {base.distortion_weight:g}): in an unbounded capture it cost held-out "
            "PSNR and the mesh's accuracy (docs/presets.md); train.fast.unbounded_distortion_weight turns it on"
        )
    cfg = replace(base, aabb=tuple(tuple(float(x) for x in row) for row in aabb), unbounded=unbounded,
                  density_res=density_res, feature_res=feature_res)
    return cfg, reasons


SURFACE_DEPTH_WHY = (
    "the surface model starts from a closed shape, and the photos' colours alone do not open a concavity it has "
    "closed over (a bowl keeps a lid at its rim); the SfM points' depths say the rays pass through to the floor"
)

EMPTY_START_DEPTH_WHY = (
    "the field starts empty though the photos have silhouettes, as an object on a wall does: its colours place a plain "
    "face, and the corner where it meets the object, at many depths; the SfM points say at which"
)

HOLLOW_SHARE = 0.1
"""`train.depth_prior=auto` turns the prior on for a field started in the visual hull when the photos' sightlines to the
sparse points pass through at least this share of the hull (`hollow_share`): a bowl's hollow, which the silhouettes
fill to the rim, and which a field started there kept as a lid; objects without a hollow stay well under it
(benchmarks/results/object_shapes.json, docs/real_captures.md "Hollows")."""

HOLLOW_RES = 41
"""Vertices a side of the grid `hollow_share` measures the hull and its sightlines on."""

UNBOUNDED_DEPTH_WHY = (
    "an unbounded capture without masks: where the object's colour matches what lies behind it the photos alone leave "
    "the surface soft and holed at any depth; the SfM points say at which depth the surface is"
)


def own_ray_bounds(scene: Scene, views: list[View]) -> dict[str, torch.Tensor]:
    """Where a term's own rays start and stop, as the training rays do: the scene box of an object capture, else each
    photo's near/far (the `aabb` or `near_far` keyword of `DepthPrior` and `PatchSmoothness`)."""
    if scene.capture == "object":
        return {"aabb": torch.tensor(np.asarray(scene.aabb, np.float64), dtype=torch.float32)}
    return {"near_far": torch.tensor([[v.near, v.far] for v in views], dtype=torch.float32)}


def hollow_share(scene: Scene, views: list[View], lines: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """The share of the training photos' visual hull (on a HOLLOW_RES³ grid over the scene box) that their sightlines
    to the sparse points they observe pass through (`free_space`): 0 for a shape the silhouettes bound, most of it for a
    bowl, whose hollow they fill."""
    if not lines or scene.aabb is None:
        return 0.0
    inside, free = freed_hull(np.asarray(scene.aabb, np.float64), HOLLOW_RES, views, lines)
    return float(free.sum() / inside.sum()) if inside.any() else 0.0


def depth_prior_for(cfg: TrainConfig, kind: str, scene: Scene, frames: list[Frame], views: list[View],
                    kwargs: dict[str, Any], cull_slowly: bool = False,
                    hollow: float | None = None) -> tuple[DepthPrior | None, str]:
    """The sparse-depth prior (`recon.nerf.depth_prior.DepthPrior`, on the CPU) or None, and why (printed either way).

    auto: on with few photos (masks or not, for the fast field), for the surface model (`SURFACE_DEPTH_WHY`), for
    unbounded captures (`UNBOUNDED_DEPTH_WHY`), for a fast field that starts empty though its photos have silhouettes
    (`cull_slowly`, `EMPTY_START_DEPTH_WHY`) and for one started in a hull whose `hollow` share (None: not measured)
    is at least HOLLOW_SHARE; otherwise off with masks. Its rays are cut to the scene box of an object capture, else
    to each photo's near/far, as the training rays are."""
    from recon.capture.normalization import FEW_PHOTOS

    if cfg.depth_prior == "off":
        return None, "depth prior: off (train.depth_prior=off)"
    visible = [np.asarray(scene.point_visibility.get(f.name, []), np.int64) for f in frames]
    n_obs = sum(len(v) for v in visible)
    few = len(frames) < FEW_PHOTOS
    hollowed = hollow is not None and hollow >= HOLLOW_SHARE
    if cfg.depth_prior == "auto" and not cull_slowly and not hollowed:  # either takes it whatever follows
        if not few and kind != "surface" and scene.capture != "unbounded":
            shape = ("" if hollow is None else f"; their sightlines to the sparse points pass through {hollow:.0%} of "
                     f"their silhouettes' hull, under {HOLLOW_SHARE:.0%}: no hollow the silhouettes fill")
            return None, (f"depth prior: off ({len(frames)} training photos >= {FEW_PHOTOS} of an object capture: the "
                          f"photos constrain the geometry{shape}; train.depth_prior=on forces it)")
        if scene.has_alpha and (not few or kind == "surface"):
            return None, (f"depth prior: off ({len(frames)} training photos, but masks: their silhouettes already "
                          f"constrain the geometry; train.depth_prior=on forces it)")
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
    prior = DepthPrior(targets, cfg.depth_weight, cfg.depth_rays, seed=cfg.seed, **own_ray_bounds(scene, views))
    if cfg.depth_prior != "auto":
        why = "train.depth_prior=on"
    elif kind == "surface":
        why = SURFACE_DEPTH_WHY
    elif cull_slowly:
        why = EMPTY_START_DEPTH_WHY
    elif hollowed:
        why = (f"the photos' sightlines to the sparse points they observe pass through {hollow:.0%} of their "
               f"silhouettes' visual hull (from {HOLLOW_SHARE:.0%}): a hollow, such as a bowl's, that the silhouettes "
               "fill and the colours alone place at many depths; the SfM points say at which")
    elif not few:
        why = UNBOUNDED_DEPTH_WHY
    else:
        why = (f"{len(frames)} training photos (< {FEW_PHOTOS}): few views leave the geometry ambiguous"
               + (", and few silhouettes carve no concavity" if scene.has_alpha else ""))
    sig = prior.sigma.cpu().numpy() if len(prior) else np.zeros(1)
    return prior, (f"depth prior: on ({why}): {len(prior):,} depth targets from the SfM points the photos observe "
                   f"(DS-NeRF; uncertainty from reprojection error and triangulation angle, median {np.median(sig):.3g} "
                   f"units), {cfg.depth_rays} of them rendered per step, weight {cfg.depth_weight:g}")


def smoothness_for(cfg: TrainConfig, kind: str, scene: Scene, views: list[View], hull_start: bool,
                   cull_slowly: bool) -> tuple[PatchSmoothness | None, str]:
    """The edge-aware depth smoothness (`recon.nerf.smoothness.PatchSmoothness`) or None, and why ("" where there is
    nothing to say: auto for another model than the fast one, or an unbounded one). auto: on for a fast field that
    starts empty though its photos have silhouettes (`cull_slowly`, `hull_start_for`)."""
    if cfg.smoothness == "off" or cfg.smoothness_weight <= 0 or cfg.smoothness_patches <= 0:
        return None, "depth smoothness: off (a zero weight or no patches)" if cfg.smoothness == "on" else ""
    if cfg.smoothness == "auto" and not cull_slowly:
        if hull_start:
            return None, ("depth smoothness: off (the field starts in the photos' visual hull, which carves plain "
                          "faces flat; train.smoothness=on forces it)")
        if kind == "fast" and not has_silhouettes(views):
            return None, ("depth smoothness: off (the photos have no silhouettes to keep it inside the object; "
                          "train.smoothness=on forces it)")
        return None, ""
    why = ("train.smoothness=on" if cfg.smoothness == "on" else
           "the field starts empty though the photos have silhouettes: a plain face, which its colours place at many "
           "depths, would grow lumpy")
    smooth = PatchSmoothness([v.image for v in views], np.stack([v.c2w for v in views]),
                             np.array([v.intrinsics for v in views]), cfg.smoothness_weight, cfg.smoothness_patches,
                             stride=cfg.smoothness_stride, seed=cfg.seed, **own_ray_bounds(scene, views))
    return smooth, (f"depth smoothness: on ({why}; where a photo is plain its surface is taken to be smooth): "
                    f"{cfg.smoothness_patches} patches of {smooth.size}×{smooth.size} rays {smooth.stride} px apart a "
                    f"step from {len(smooth):,} places, weight {cfg.smoothness_weight:g}")


def choose_appearance(cfg: TrainConfig, kind: str, views: list[View], frames: list[Frame]) -> tuple[bool, str]:
    """(model the photos' exposure / white balance per photo?, why) — see recon.nerf.appearance. `frames`: the
    views' frames, in the same order.

    A photo whose alpha is its mask is measured whole: the camera's exposure is the whole photo's, and a plain
    object alone gives SIFT too few matches to measure it by. A photo's own alpha (a render's) is kept: the colours
    under it are not the photo's."""
    if kind == "classic" and cfg.appearance != "off":
        return False, "per-photo appearance off: it is built for the grid models (fast, surface), not the classic MLP"
    if cfg.appearance == "off":
        return False, "per-photo appearance off (train.appearance=off)"
    images = [v.image[..., :3] if f.mask_path else v.image for v, f in zip(views, frames, strict=True)]
    return decide(cfg.appearance, exposure_spread(images, np.stack([v.c2w for v in views])))


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


@dataclass
class TrainPlan:
    """Everything the train stage decides before it builds anything, and why: `build_training` builds from it, so
    the stage, `recon bench --profile` and the benchmarks train the very same step."""

    kind: str
    kwargs: dict[str, Any]
    """The model's constructor arguments, its start shape and sky settled."""
    lr: float
    lr_final: float
    batch_rays: int
    seed: int
    views: list[View]
    """The training photos, keyed to RGBA when the backdrop key applies."""
    aabb: np.ndarray | None
    """The box the rays are cut to (an object capture); None: each photo's near/far (unbounded)."""
    background: np.ndarray
    random_background: bool
    background_why: str
    empty: list[np.ndarray] | None
    """Per training photo, its pixels known to show nothing (its sky, or its transparent pixels), which train as
    empty space at `empty_weight`."""
    empty_weight: float
    start_sdf: np.ndarray | None
    """The surface model's start shape as an SDF volume (the visual hull), or None."""
    hull_start: bool
    """The fast model starts with matter inside the training photos' visual hull (`hull_start_for`)."""
    sightlines: list[tuple[np.ndarray, np.ndarray]]
    """With `hull_start`: per training photo, its camera centre and the sparse points it observes, whose sightlines
    free the hollows the hull fills (`recon.geometry.visual_hull.free_space`); empty otherwise."""
    slow_culling: bool
    """The fast model starts empty though the photos have silhouettes, so its occupancy culls slowly (`hull_start_for`)."""
    appearance: bool
    appearance_why: str
    pose_refine: bool
    pose_why: str
    depth_prior: DepthPrior | None
    """The sparse-depth prior on the CPU (`build_training` puts a copy on the device), or None."""
    smoothness: PatchSmoothness | None
    """The edge-aware depth smoothness on patches of the photos (`smoothness_for`), or None."""
    compile: str | None
    """train.compile when the fast model's colour network is compiled, else None."""
    autocast: torch.dtype | None
    optimizer: str
    """"adam" or "masked_adam" (`choose_optimizer`)."""
    adam_beta2: float
    budget_s: float
    reasons: list[str]
    """Every choice's reason, in the order they are printed."""


def plan_training(cfg: TrainConfig, scene: Scene, views: list[View], device: torch.device) -> TrainPlan:
    """The train stage's choices for `scene` on `device`; `views`: the training photos (`scene.split("train")`)
    as `recon.evaluation.views.load_views` loads them."""
    from recon.config import parse_duration
    from recon.nerf.compiled import compile_wanted

    frames = scene.split("train")
    kind, kwargs, lr, reasons = model_spec(cfg, scene, views)
    if cfg.adjusted:
        reasons.insert(0, cfg.adjusted)
    appearance, appearance_why = choose_appearance(cfg, kind, views, frames)
    reasons.append(appearance_why)
    pose_refine, pose_why = choose_pose_refine(cfg, kind)
    reasons.append(pose_why)
    views, backdrop, key_why = key_backdrop_for(cfg, kind, scene, views)
    reasons.append(key_why)
    start_sdf = None
    if kind == "surface":
        kwargs, start_sdf, start_why = surface_start(kwargs, scene, views)
        reasons.append(start_why)
    hull_start, cull_slowly, hull_why = hull_start_for(cfg, kind, kwargs, scene, views)
    if hull_why:
        reasons.append(hull_why)
    background, random_bg, bg_why = choose_background(cfg, scene, views, backdrop)
    sky, sky_why = sky_for(cfg, kind, scene, frames, views)
    reasons.append(sky_why)
    empty, empty_weight = sky, cfg.sky_weight
    if sky is not None:
        kwargs = with_sky(kwargs)
        bg_why = "the field's sky colour per ray direction (see sky:)"
    else:
        empty, transparent_why = transparent_for(cfg, kind, scene, views)
        empty_weight = cfg.transparent_weight
        if transparent_why:
            reasons.append(transparent_why)
    budget_s = parse_duration(cfg.budget)
    if budget_s:
        reasons.append(f"time budget {cfg.budget}: at most {cfg.steps} steps, stopping when the budget is spent")
    if kind == "fast" and device.type == "cpu":
        from recon.nerf.native import native_status

        reasons.append(f"marcher: {native_status()}")
    if kind == "fast" and (device.type == "cuda" or cfg.fast.kernels == "triton"):  # on a CPU by default: nothing to say
        from recon.nerf.kernels import kernels_choice

        fused, why = kernels_choice(cfg.fast.kernels, device.type)
        reasons.append(why)
        if fused and cfg.fast.grid == "hash":
            from recon.nerf.model_config import HASH_FEATURES
            from recon.nerf.grid import hash_kernel_check

            reasons.append(hash_kernel_check(str(device), cfg.fast.feature_dim, HASH_FEATURES)[1])
    optimizer, optimizer_why = choose_optimizer(cfg, kind, device)
    if optimizer_why:
        reasons.append(optimizer_why)
    sightlines = sightlines_of(scene, frames) if hull_start else []
    hollow = hollow_share(scene, views, sightlines) if sightlines else None  # unknown without them (an import)
    depth_prior, depth_why = depth_prior_for(cfg, kind, scene, frames, views, kwargs, cull_slowly, hollow)
    reasons.append(depth_why)
    smoothness, smooth_why = smoothness_for(cfg, kind, scene, views, hull_start, cull_slowly)
    if smooth_why:
        reasons.append(smooth_why)
    return TrainPlan(
        kind=kind, kwargs=kwargs, lr=lr, lr_final=lr * cfg.lr_decay, batch_rays=cfg.batch_rays, seed=cfg.seed,
        views=views, aabb=np.asarray(scene.aabb) if scene.capture == "object" else None,
        background=background, random_background=random_bg, background_why=bg_why, empty=empty,
        empty_weight=empty_weight,
        start_sdf=start_sdf, hull_start=hull_start, sightlines=sightlines,
        slow_culling=cull_slowly, appearance=appearance,
        appearance_why=appearance_why, pose_refine=pose_refine, pose_why=pose_why, depth_prior=depth_prior,
        smoothness=smoothness,
        compile=cfg.compile if kind == "fast" and compile_wanted(cfg.compile, device)[0] else None,
        autocast=torch.bfloat16 if cfg.precision == "bf16" else None, optimizer=optimizer,
        adam_beta2=cfg.adam_beta2, budget_s=budget_s, reasons=reasons,
    )


def choose_optimizer(cfg: TrainConfig, kind: str, device: torch.device) -> tuple[str, str]:
    """train.optimizer for this model on this device, and why ("" where there is nothing to say: no grid model)."""
    from recon.nerf.native import native_marcher

    if kind != "fast":
        return "adam", ""
    if cfg.optimizer != "auto":
        return cfg.optimizer, f"optimizer: {cfg.optimizer} (train.optimizer={cfg.optimizer})"
    if device.type == "cpu" and native_marcher() is not None:
        return "masked_adam", ("optimizer: masked Adam (train.optimizer=auto on a CPU): a step's rays touch few of the "
                               "grids' values, and updating only those, in C, spares the pass over all of them")
    return "adam", (f"optimizer: Adam on every grid value (train.optimizer=auto: "
                    f"{'a GPU updates them all in one fused pass' if device.type != 'cpu' else 'no native library here'})")


@dataclass
class TrainSetup:
    """What training needs, built from a `TrainPlan` on a device."""

    model: torch.nn.Module
    batcher: RayBatcher
    step_kwargs: dict[str, Any]
    """`recon.nerf.trainer.train`'s (and `TrainStep`'s) arguments besides the model, the batcher and the step count:
    rates, rays per step, autocast and the pieces (empty rays: the sky or the transparent pixels, depth prior,
    depth smoothness, appearance, pose refinement, in that order)."""
    aabb: torch.Tensor | None
    c2w: torch.Tensor
    """The training photos' camera-to-world matrices on the device."""
    appearance: PhotoAppearance | None
    pose_refine: PoseRefinement | None
    notes: list[str]
    """What building said (torch.compile's outcome), printed after the plan's reasons."""


def build_training(plan: TrainPlan, device: torch.device) -> TrainSetup:
    """The model (seeded with the plan's seed, start shape set, colour network compiled when planned), the ray
    batcher and the step's pieces, on `device`."""
    from recon.field import build_model
    from recon.nerf.compiled import compile_color_network
    from recon.nerf.pieces import Appearance, DepthPriorLoss, EmptyRays, PoseRefine, TrainPiece

    torch.manual_seed(plan.seed)
    model = build_model(plan.kind, plan.kwargs)
    if plan.start_sdf is not None:
        model.set_initial_sdf(plan.start_sdf)
    notes = []
    if plan.hull_start:
        hull, free = freed_hull(model.grid_box.numpy().astype(np.float64), model.start_resolution, plan.views,
                                plan.sightlines)
        model.start_inside(hull & ~free)
        notes.append(f"start: the visual hull holds {hull.mean():.1%} of the box ({model.start_resolution}³ vertices)"
                     + (f"; of that, {free.mean():.1%} of the box lies on the sightlines from "
                        f"{len(plan.sightlines)} photos to the sparse points they observe, so it is empty (a hollow "
                        "or an overhang the silhouettes cannot carve) and starts so" if plan.sightlines else ""))
    if plan.slow_culling:
        model.cull_slowly()
    model = model.to(device)
    if plan.compile:
        notes.append(compile_color_network(model, device, plan.compile))
    images, c2w, intr, near_far = view_tensors(plan.views, device)
    aabb = None if plan.aabb is None else torch.tensor(plan.aabb, dtype=torch.float32, device=device)
    batcher = RayBatcher(
        images, c2w, intr, aabb=aabb, near_far=None if aabb is not None else near_far,
        background=torch.tensor(plan.background), random_background=plan.random_background, seed=plan.seed,
        device=device, empty=plan.empty, kernels=model.config.kernels if plan.kind == "fast" else "torch",
    )
    pieces: list[TrainPiece] = []
    if plan.empty is not None:
        pieces.append(EmptyRays(plan.empty_weight))
    if plan.depth_prior is not None:
        pieces.append(DepthPriorLoss(copy.copy(plan.depth_prior).to(device)))
    if plan.smoothness is not None:
        pieces.append(DepthPriorLoss(copy.copy(plan.smoothness).to(device)))
    appearance = None
    if plan.appearance:
        appearance = PhotoAppearance(len(plan.views), include_background=not batcher.has_alpha).to(device)
        pieces.append(Appearance(appearance))
    pose_refine = None
    if plan.pose_refine:
        pose_refine = PoseRefinement(len(plan.views), centres=c2w[:, :3, 3]).to(device)
        pieces.append(PoseRefine(pose_refine, batcher.aabb))
    step_kwargs = {"lr": plan.lr, "lr_final": plan.lr_final, "batch_rays": plan.batch_rays, "autocast": plan.autocast,
                   "pieces": pieces, "optimizer": plan.optimizer, "beta2": plan.adam_beta2}
    return TrainSetup(model=model, batcher=batcher, step_kwargs=step_kwargs, aabb=aabb, c2w=c2w,
                      appearance=appearance, pose_refine=pose_refine, notes=notes)

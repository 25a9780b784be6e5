"""Which model a scene gets, with what settings and background, and why: the train stage's choices, shared with
`recon bench --profile`, which must build the very model the stage builds."""
from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np

from recon.camera import pixel_footprint, project
from recon.config import TrainConfig
from recon.errors import ReconError
from recon.nerf.surface import hull_planes
from recon.scene import Frame, Scene
from recon.sky import SKY_MIN_FRACTION, sky_mask
from recon.views import (
    BACKDROP_TOLERANCE,
    PLAIN_BACKDROP_FRACTION,
    View,
    border_color,
    key_backdrop,
    plain_backdrop,
)

BACKDROP_KEY_WHY = (
    "a surface colored like the backdrop is as bright as the backdrop itself, so the photos' colours cannot tell it "
    "from empty space; keyed, the backdrop's pixels say where the object is not"
)


def key_backdrop_for(cfg: TrainConfig, kind: str, scene: Scene, views: list[View]) -> tuple[list[View], np.ndarray | None, str]:
    """(the training views, keyed to RGBA when the backdrop key applies; the backdrop colour or None; why).

    auto keys the surface model's photos when their borders are a plain backdrop (`recon.views.plain_backdrop`):
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
    """(per training photo, the (H, W) bool mask of its sky pixels, or None; why) — see `recon.sky`.

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


def with_sky(kwargs: dict[str, Any]) -> dict[str, Any]:
    """`model_spec`'s model kwargs with the fast field's background set to its sky colour (`sky_for` said on)."""
    return {**kwargs, "config": {**kwargs["config"], "background": "sky"}}


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
    return kind, {"config": asdict(fast_cfg)}, cfg.lr or FAST_LR, reasons


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
    return "surface", {"config": asdict(surf)}, cfg.lr or FAST_LR, [why]


def surface_start(kwargs: dict[str, Any], scene: Scene, views: list[View]) -> tuple[dict[str, Any], np.ndarray | None, str]:
    """(the surface model's kwargs with its start shape settled, the visual hull's SDF volume or None, why).

    Called once the training views have their alpha (masks or the backdrop key). auto: the visual hull when the
    photos have silhouettes, else the SfM points' convex hull, else a sphere."""
    from recon.geometry.visual_hull import carve, visual_hull_sdf

    surf = kwargs["config"]
    shape = surf.get("init_shape", "auto")
    box = np.asarray(surf["aabb"], np.float64)
    res = int(surf["sdf_res"])
    with_alpha = bool(views) and all(v.image.shape[-1] == 4 for v in views)
    if shape == "visual_hull" and not with_alpha:
        raise ReconError("train.surface.init_shape=visual_hull needs silhouettes: a masks/ folder beside the photos, or "
                         "a plain backdrop to key (train.backdrop_key). Use train.surface.init_shape=auto.")
    not_visual = ("train.surface.init_shape=" + shape if shape != "auto"
                  else "the photos have no silhouettes (masks or a keyed backdrop) for a visual hull")
    if shape in ("auto", "visual_hull") and with_alpha:
        inside, _ = carve(box, res, [v.c2w for v in views], [v.intrinsics for v in views],
                          [v.image[..., 3] >= 128 for v in views])
        core = inside[1:-1, 1:-1, 1:-1]
        if core.any():
            why = (f"initial surface: the visual hull of the {len(views)} training photos' silhouettes ({core.mean():.1%} "
                   f"of the box; {VISUAL_HULL_WHY})")
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

FAST_LR = 1e-2
"""Default learning rate of the fast model's MLP (its grids use lr × grid_lr_scale)."""


def auto_fast_config(base: Any, scene: Scene, footprint: float) -> tuple[Any, list[str]]:
    """Fit the fast model to the scene: box, bounded or not, and grid resolution no finer than the pixels."""
    aabb = np.asarray(scene.aabb, dtype=np.float64)
    unbounded = scene.capture != "object"
    reasons = [
        "unbounded scene: space outside the box is contracted (mip-NeRF 360, L∞)" if unbounded
        else "object capture: a plain box around the object, nothing modelled outside it"
    ]
    extent = float((aabb[1] - aabb[0]).max()) if not unbounded else 4.0
    needed = int(np.ceil(extent / max(footprint, 1e-12) / 16.0) * 16)
    density_res = int(min(base.density_res, max(32, needed)))
    feature_res = int(min(base.feature_res, max(32, needed)))
    if density_res < base.density_res or feature_res < base.feature_res:
        reasons.append(
            f"grids {density_res}³/{feature_res}³ instead of {base.density_res}³/{base.feature_res}³: one training pixel "
            f"covers {footprint:.4g} units at the cameras' distance, so finer voxels could not be seen"
        )
    else:
        reasons.append(f"grids {density_res}³ density / {feature_res}³ features (the preset's cap; pixels would allow {needed}³)")
    cfg = replace(base, aabb=tuple(tuple(float(x) for x in row) for row in aabb), unbounded=unbounded,
                  density_res=density_res, feature_res=feature_res)
    return cfg, reasons

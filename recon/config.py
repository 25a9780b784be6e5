"""Typed configuration: one dataclass per stage, presets from `pipelines/*.toml`, `--set a.b=c` overrides.

A preset is data: a TOML file whose tables mirror the dataclasses below (`[train]`, `[train.fast]`, ...).
Every field has a default and a line of doc; unknown keys and wrong types are refused with a message
naming the key, so a typo never silently falls back to a default.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.capture.sfm import SfmOptions
from recon.errors import ConfigError
from recon.nerf.model_config import (
    HASH_BASE_RES, HASH_FEATURES, FastConfig, GridKind, SurfaceConfig, density_grid_dim, hash_level_layout,
)

PIPELINES_DIR = Path(__file__).resolve().parent.parent / "pipelines"


@dataclass
class PosesConfig(SfmOptions):
    """Structure from motion (pycolmap) on the photos — the SfM options plus how photos are prepared for it.

    Ignored when the input already carries poses (transforms.json, NeRF-synthetic, COLMAP model, .npz).
    """

    max_side: int = 1600
    """Photos are downscaled to this longest side for feature extraction (intrinsics are scaled back)."""
    video_frames: int = 150
    """A video is split into this many windows (shared among the clips of a folder by length) and the sharpest
    frame of each is kept."""
    video_min_change: float = 1.0
    """A video frame whose mean absolute gray difference to the last kept frame (0-255 levels, on a 128-px copy)
    is below this is a near-duplicate and skipped: the camera stood still."""
    turntable: Literal["auto", "off"] = "auto"
    """auto: where most photos show the same background pixel for pixel with the object changing in front of it (a
    camera on a tripod, the object on a turntable), features are taken only where the photos change
    (`recon.capture.turntable`); off: from every pixel."""


@dataclass
class NormalizeConfig:
    """Orient, center and scale the scene into the canonical box; near/far per camera; data split."""

    up: Literal["auto", "z", "y", "none"] = "auto"
    """auto: the mean camera up vector becomes +Z; z/y: the source's own +Z/+Y is up; none: keep rotation."""
    link_spacings: float = 6.0
    """The box is fit to the sparse points less stray ones: points within this many median point spacings
    of each other are linked, and linked groups holding under 2 % of the points are dropped."""
    box_margin: float = 0.05
    """The box is enlarged by this fraction of its size on each side."""
    depth_percentile: float = 1.0
    """Per-camera near/far come from this low/high percentile of the depths of the points it sees."""
    test_every: int = 8
    """Every Nth photo (sorted by name) is held out for testing (when the source gives no split); 0: none."""
    val_every: int = 0
    """Every Nth photo, offset by half of it, is held out for validation (the training's progress, else shown on the
    test photos); 0: none, so that those photos train the field too."""
    masks: Literal["auto", "off"] = "auto"
    """auto: an object capture without masks that shows a lot of table and room gets object masks cut from its
    photos (`recon.capture.auto_masks`, written to 02_scene/masks/) when they agree across photos; off: never."""
    blurred: Literal["auto", "keep"] = "auto"
    """auto: a training photo far blurrier than the photos that share its view (shaken, out of focus) is left out
    of training (`recon.capture.blur`; 20 training photos or more, at most an eighth of them; a video's frames were
    chosen for sharpness already); keep: every photo."""
    beside: Literal["auto", "keep"] = "auto"
    """auto: of the points most photos keep in frame, groups apart that the photos frame off to the side (a cup or a
    book beside the object) are no part of the object region (`recon.capture.region.AIM_MAX`); keep: all are."""


@dataclass
class ClassicConfig:
    """The classic NeRF (Mildenhall et al. 2020): 8×256 MLP, skip at layer 5, coarse + fine networks."""

    n_coarse: int = 64
    """Stratified samples per ray for the coarse network."""
    n_fine: int = 128
    """Extra samples per ray drawn from the coarse weights for the fine network (0: coarse only)."""
    pos_freqs: int = 10
    """Positional-encoding frequencies for positions (L)."""
    dir_freqs: int = 4
    """Positional-encoding frequencies for view directions."""
    depth: int = 8
    """Layers of the density trunk."""
    width: int = 256
    """Units per trunk layer."""


@dataclass
class TrainConfig:
    """Fitting the radiance field to the training photos."""

    model: Literal["auto", "fast", "classic", "surface"] = "auto"
    """auto: the fast grid model (practical on a CPU); classic: the original NeRF MLP; surface: a signed
    distance field (NeuS) whose mesh is closed and smooth (object captures)."""
    steps: int = 2000
    """Optimizer steps (an upper bound when a time budget is set)."""
    budget: str = ""
    """Training time budget, e.g. "90s", "5m", "1h" (evaluation excluded); empty: train for `steps`."""
    batch_rays: int = 4096
    """Rays per step, drawn across all training photos."""
    lr: float = 0.0
    """Initial learning rate; 0 uses the model's own default (the grid models' grows with batch_rays above 4,096:
    `recon.plans.training.grid_lr`)."""
    lr_decay: float = 0.1
    """The learning rate decays exponentially to lr × lr_decay at the last step."""
    adam_beta2: float = 0.999
    """Adam's decay of its running mean of squared gradients (its second beta)."""
    max_side: int = 400
    """Training photos are downscaled to this longest side (intrinsics scaled with them)."""
    background: Literal["auto", "white", "black", "random"] = "auto"
    """Color behind the scene. auto: random for RGBA photos (known alpha), else the photos' border color."""
    eval_every: int = 500
    """Evaluate held-out views every N steps (0: only at the end)."""
    eval_views: int = 3
    """Held-out views rendered at each interval evaluation (spread evenly over the split; 0: all)."""
    final_eval_views: int = 8
    """Test views rendered for the final metrics and preview renders, spread evenly over the split (0: all;
    `recon eval` renders all)."""
    checkpoint_every: int = 250
    """Save a resumable checkpoint every N steps (and on Ctrl-C)."""
    seed: int = 0
    """Seed for initialization, ray shuffling and sampling jitter."""
    device: str = "auto"
    """auto (CUDA when present), cpu, cuda or cuda:K."""
    adjusted: str = ""
    """Set by a preset's [no_gpu] table when no GPU is found, or by `device_sizing` on a GPU: what it changed and
    why (printed first among the train stage's reasons)."""
    device_sizing: Literal["auto", "off"] = "auto"
    """auto: on CUDA, the grid models' rays per step, grid resolutions and (with a budget) step cap grow with the
    GPU's memory (`device_sizing`; a preset's values are sized for a CPU); --set values are kept. off: the preset's
    values on any device."""
    compile: Literal["auto", "on", "off"] = "auto"
    """torch.compile of the fast model's per-sample networks (recon/nerf/compiled.py): auto: on CUDA only (on a
    CPU the C marcher and fused torch kernels are faster than compiled ones, and compiling costs a minute)."""
    optimizer: Literal["auto", "adam", "masked_adam"] = "auto"
    """masked_adam: the fast model's grid values that no ray of a step touched keep their value and Adam moments
    (DVGO's masked Adam; recon/nerf/masked_adam.py); adam: torch's Adam moves every value every step. auto:
    masked_adam on a CPU with the native library (the C update skips the untouched values), adam elsewhere."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """bf16: the networks' matrix math in bfloat16 (autocast; volume rendering stays fp32). For GPUs: on a CPU, even
    one with AMX, the casts around the colour network's small layers cost more than they save (docs/profile.md)."""
    depth_prior: Literal["auto", "on", "off"] = "auto"
    """Sparse-depth supervision from the SfM points (DS-NeRF). auto: on when fewer than 20 photos train the field
    (few views leave the geometry ambiguous; with masks too for the fast field, as few silhouettes carve no
    concavity), the model is `surface` (its SDF starts closed and needs the points' depths to open concavities) or
    the capture is unbounded (the object in front of a background it may match in colour), the scene has sparse
    points and no masks; and for a fast field that starts empty though its photos have silhouettes (an object on a
    wall: its plain faces have no other depth to go by) or in a hull the sightlines show hollow; on / off force it."""
    depth_weight: float = 0.002
    """Weight of the sparse-depth loss (robust, in units of each point's depth uncertainty)."""
    depth_rays: int = 512
    """Sparse-point rays rendered per step for the depth loss (on top of batch_rays)."""
    smoothness: Literal["auto", "on", "off"] = "auto"
    """Edge-aware smoothness of depth on patches of the photos (`recon.nerf.smoothness`): where a photo is plain, its
    surface is taken to be smooth. auto: on for a fast field that starts empty though its photos have silhouettes (an
    object on a wall, `train.hull_start`): its plain faces, which the colours place at many depths, would grow lumpy;
    a field started in the hull carves them flat already. on / off force it."""
    smoothness_weight: float = 0.1
    """Weight of the depth smoothness (a mean of relative second differences of inverse depth)."""
    smoothness_patches: int = 32
    """Patches rendered per step for the smoothness term (each 4 × 4 rays, `train.smoothness_stride` pixels apart)."""
    smoothness_stride: int = 8
    """Training pixels between neighbouring rays of a smoothness patch: the scale at which a plain face is taken to be
    flat."""
    hull_start: Literal["auto", "on", "off"] = "auto"
    """Where the fast field's matter starts (photos with silhouettes: masks or alpha). on: inside their visual hull, at
    `train.fast.hull_start_alpha` opacity a step, so a surface the colours cannot place (a plain or glossy patch)
    forms on the hull rather than leaving a hole with walls behind it; off: empty everywhere. auto: on, except for an
    object that hangs on a wall (normalize's support plane): photos from one side leave a hull that reaches out towards
    them, and a plain face would form on it, in front of the true one."""
    small_object: Literal["auto", "off"] = "auto"
    """auto: where the scene box of an object capture spans under half of max_side in the median training photo (a
    small object in wide photos), the photos train at the larger side where it spans max_side, as it does in photos
    it fills, up to their own size (`recon.plans.training.training_side`): the field's grids and the mesh grid follow
    the finer pixels. off: always max_side."""
    photo_footprint: Literal["auto", "off"] = "auto"
    """auto: a photo that sees the object finer than most (a close-up) trains downscaled to their pixel footprint
    (`recon.plans.training.photo_sides`), so its detail is no finer than the rest and its rays no more; off: every
    photo at max_side."""
    appearance: Literal["auto", "on", "off"] = "auto"
    """Per-photo colour transforms for exposure / white-balance changes (grid models). auto: on when the colours
    of matched points differ between neighbouring photos (recon/nerf/appearance.py); the mesh uses the neutral one."""
    backdrop_key: Literal["auto", "on", "off"] = "auto"
    """Photos on a plain backdrop (a light box, a studio sweep): train the pixels of the backdrop's colour as empty
    space, as masks would (recon.evaluation.views.key_backdrop). auto: on for the surface model of an object capture without
    masks whose photos' borders are plain; the density models keep the photos as they are."""
    sky: Literal["auto", "on", "off"] = "auto"
    """A sky behind an unbounded scene (recon/capture/sky.py): the fast field gets a colour per ray direction behind it,
    and the photos' clear-sky pixels (smooth, blue, no SfM point near) train as empty space. auto: on when at
    least 1% of the training pixels are sky, for an unbounded capture without masks."""
    sky_weight: float = 0.1
    """Weight of the sky pixels' opacity (L1, averaged over each batch's rays) in the loss."""
    transparent_weight: float = 0.1
    """Weight of the opacity of the photos' fully transparent pixels (outside their masks or alpha; L1, averaged over
    each batch's rays) in the fast field's loss: the random backgrounds alone leave a faint haze there, grey on a
    held-out view's backdrop. A strong weight lets one photo's wrong mask carve away what the others see. 0: off."""
    transparent_disputed_share: float = 1.0
    """The share of ``transparent_weight`` that the transparent pixels the hull of all the masks still covers pay
    (`recon.plans.training.transparent_for`). Such a pixel may show a thin part one photo's mask cut away, which the
    other photos keep through their colour; or space under an object's base that only the lowest photos see, which
    the photos above cannot see behind the base: left to the colour loss alone, a blob hangs there in every low
    view. 0: the colour loss alone."""
    pose_refine: Literal["on", "off"] = "off"
    """on: learn a small rotation and shift per training photo with the field (recon.nerf.pose_refine), for poses SfM
    left a few pixels off; held-out photos are then scored with their pose fitted on their left half. Off by default:
    it finds misregistered photos but has not raised the held-out PSNR or the mesh accuracy (docs/real_captures.md)."""
    classic: ClassicConfig = field(default_factory=ClassicConfig)
    fast: FastConfig = field(default_factory=FastConfig)
    """The fast grid model's options (its box and boundedness are set from the scene)."""
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    """The surface (SDF) model's options (its box is set from the scene)."""


@dataclass
class MeshConfig:
    """Density grid → marching cubes → cleaned, colored mesh in glTF/OBJ/PLY."""

    resolution: int = 0
    """Grid vertices per side; 0: from the scene (cell ≈ the pixel footprint), capped by max_resolution."""
    max_resolution: int = 384
    """Upper bound on the automatic resolution (and the memory budget caps it further)."""
    memory_budget_mb: int = 2048
    """The density grid (float32) must fit in this much memory; the resolution is lowered to fit."""
    coarse_to_fine: bool = True
    """Evaluate a coarse grid first and refine only blocks the surface crosses."""
    iso: float = 0.0
    """Density iso-level; 0: automatic (one cell of thickness is `iso_opacity` opaque)."""
    iso_opacity: float = 0.0
    """Opacity of one cell of material at the automatic iso-level; 0: 0.35 (`recon.meshing.extraction.ISO_OPACITY`), or 0.25
    when masks trained the background empty (the masks already carve the object, so the level can be lower and close
    the holes an undertrained field leaves)."""
    min_component_fraction: float = 0.05
    """Drop disconnected pieces with less than this fraction of the largest piece's area (floaters)."""
    smooth_iters: int = 0
    """Taubin smoothing iterations (0: none)."""
    fill_cavities: int = 0
    """Fill the empty space the density field's material encloses before marching cubes, after closing holes up to
    about twice this many cells wide (0: off; the density presets: 4). Not on the whole box of an unbounded scene;
    see `recon.geometry.extract.fill_enclosed` and `recon.plans.mesh.hollow_fill_applies`. Why: a density field is a
    shell whose inner walls show through its pits, and the hidden-face test keeps them; filling removes them."""
    target_faces: int = 300000
    """Decimate to this many faces (0: keep all)."""
    drop_hidden: bool = True
    """Remove faces that no photo sees (depth-tested against the field's rendered depth): the walls and
    islands marching cubes finds inside a soft, unconstrained interior; they cost most of the mesh's precision.
    Off, the mesh is closed where the field is, but full of inner walls."""
    closed: bool = False
    """A closed (watertight) solid, for 3D printing or a physics engine: the field filled down to the ground or wall the
    object stands on and capped flat there, closed at the mesh region's box, and no face dropped for being unseen or
    outside a mask. Off: the surface the photos saw, open where none looked (often the underside)."""
    mask_keep_fraction: float = 0.5
    """With masks, a vertex stays when it falls inside the object's mask in at least this fraction of the photos
    that have it in frame (below 1: room for a pixel of mask edge; lower it when imperfect masks bite into the mesh)."""
    unsure_masks: Literal["auto", "off"] = "auto"
    """auto: where the automatic masks were not sure enough to train the object alone (normalize's masks_unsure/),
    the mesh of the field trained on the whole photos keeps only what at least mesh.mask_keep_fraction of the photos
    framing it call object, as with masks: the table and room that field holds around the object go, while a part
    a few masks miss stays. off: the mesh region alone crops it."""
    color: Literal["photos", "field"] = "photos"
    """Per-vertex color: baked from the photos (depth-tested), or queried from the field."""
    cpu_bake_views: int = 0
    """On the CPU the mesh is checked (hidden faces, masks) and colored against at most this many training photos,
    spread evenly, each costing a render of the field's depth; 0: 24 for the grid models, 6 for the classic NeRF
    (which renders about a hundred times slower)."""
    gpu_bake_views: int = 0
    """The same on a GPU, where each photo costs the CPU's rasterizing and baking more than the depth render;
    0: 48."""
    cpu_depth_side: int = 0
    """On the CPU those depth renders are at most this many pixels on the longest side (upsampled to the photo);
    0: 200 for the grid models, 64 for the classic NeRF. A GPU renders them at training size."""
    frame: Literal["normalized", "source"] = "normalized"
    """Export in our normalized frame (+Z up, box ≈ [-1, 1]³) or back in the source (COLMAP/import) frame."""
    real_size: float = 0.0
    """> 0: scale the mesh so its largest bounding-box side is this many units (e.g. meters)."""
    region: str = "auto"
    """What to mesh. auto: the object the cameras look at (normalize's object region, when it found one);
    all: the whole scene box; or an explicit box "xmin,ymin,zmin,xmax,ymax,zmax" in the source frame."""
    region_margin: float = 0.1
    """mesh.region=auto grows normalize's object region (percentiles of the sparse points) by this fraction of its
    size on each side; raise it when the object is cut off at the region's faces."""
    keep_ground: bool = False
    """Keep the ground plane the object stands on, or the wall it hangs on (normalize finds either by RANSAC); by
    default it is cut away."""
    ground_margin_cells: float = -1.0
    """Faces up to this many surface cells (the mesh cell, or the field's voxel when coarser) above the ground (or in
    front of the wall) are cut with it. -1: automatic (`recon.plans.mesh.capture_ground_margin`): 2 without masks,
    where the field makes a table top a layer about a voxel thick; 0 when masks trained the table empty, so what
    stands on the plane is the object's base. Raise it when a layer of table stays."""
    texture_faces: int = 50000
    """Also write mesh_textured.glb/.obj: the mesh decimated to this many faces, UV-unwrapped, its color
    baked into a texture (0: no textured mesh)."""
    texture_size: int = 0
    """Side of the square texture image of the textured mesh, in texels; 0: the smallest power of two from 512 to
    2048 that gives every photo pixel on the surface a texel (`recon.plans.mesh.texture_side`)."""


@dataclass
class RunConfig:
    """The whole pipeline's configuration: one slice per stage (a stage's fingerprint covers only its slice)."""

    poses: PosesConfig = field(default_factory=PosesConfig)
    normalize: NormalizeConfig = field(default_factory=NormalizeConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)


def available_presets() -> list[str]:
    """Names of the presets in pipelines/ (file stems)."""
    return sorted(p.stem for p in PIPELINES_DIR.glob("*.toml"))


def preset_path(name: str) -> Path:
    """The TOML file of a preset: a name from pipelines/ or a path to a TOML file."""
    candidate = Path(name)
    if candidate.suffix == ".toml" and candidate.is_file():
        return candidate
    path = PIPELINES_DIR / f"{name}.toml"
    if not path.is_file():
        raise ConfigError(
            f"Unknown preset '{name}'. Available presets: {', '.join(available_presets()) or 'none'} "
            f"(files in {PIPELINES_DIR}); or pass a path to a .toml file."
        )
    return path


DEFAULT_PRESET = "fast"
"""The preset a run takes when none is named, for the reason DEFAULT_PRESET_WHY gives (the records behind it:
docs/presets.md#the-default-fast)."""

DEFAULT_PRESET_WHY = "the default: on the captures measured, longer training made no better mesh (docs/presets.md)"
"""What a run says when it takes DEFAULT_PRESET because no preset was named."""


def load_config(preset: str | None = None, overrides: list[str] | None = None) -> RunConfig:
    """Defaults, then the preset's TOML, then each `section.key=value` override, all type-checked."""
    config = RunConfig()
    data: dict[str, Any] = {}
    no_gpu = None
    if preset:
        path = preset_path(preset)
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"Preset file {path} is not valid TOML: {exc}. Fix the file.") from None
        data.pop("description", None)
        no_gpu = data.pop("no_gpu", None)
        _apply_table(config, data, prefix="", source=str(path))
    _apply_overrides(config, overrides)
    _check_values(config)
    if no_gpu is not None and not _gpu_training(config.train.device):
        # the preset's [no_gpu] table: what it does on a CPU; --set still wins
        no_gpu = dict(no_gpu)
        why = str(no_gpu.pop("why", ""))
        device = config.train.device
        config = RunConfig()
        _apply_table(config, data, prefix="", source=str(path))
        _apply_table(config, no_gpu, prefix="", source=f"{path} [no_gpu]")
        changes = ", ".join(f"{k}={v}" for k, v in _flatten(no_gpu))
        config.train.adjusted = (
            f"no GPU (train.device={device}): preset {path.stem} uses its CPU settings {changes} "
            f"({path.name} [no_gpu]{'; ' + why if why else ''}); --set any of them to change it"
        )
        _apply_overrides(config, overrides)
    if config.train.device_sizing == "auto" and _gpu_training(config.train.device):
        from recon.nerf.device import cuda_memory

        found = cuda_memory(config.train.device)
        if found is not None:
            config, why = device_sizing(config, *found, keep=_override_keys(overrides))
            config.train.adjusted = why or config.train.adjusted
    validate(config)
    return config


GPU_TIERS: tuple[tuple[float, int, float, int], ...] = (
    (40.0, 8, 1.5, 8),
    (16.0, 4, 1.25, 4),
    (6.0, 2, 1.0, 2),
)
"""(at least this many GiB of GPU memory, rays per step ×, grid resolution ×, step cap ×) for the grid models.
A preset's 4,096 rays a step leave a GPU launch-bound (an H200 ran the fast preset at 26 ms a step, 157k rays/s):
more rays per step cost little more time per step; finer grids cost memory, which a large card has."""
GPU_DISTORTION_FROM = 0.1
"""With finer grids on a card, the distortion loss starts after this share of training: from the first step, at a
card's grids, it cost the Lego its finer parts; from here it still kept real objects' meshes as clean, which a later
start did not (docs/gpu.md)."""
GPU_SH_DEGREE = 3
"""On a card the fast model's view-dependent colour takes the direction's spherical harmonics to this degree (the
most `recon.nerf.fast.sh_encode` has; the presets' is 2): it fits the glossy highlights degree 2 leaves as error, and
the colour network's wider input costs a card next to nothing. A CPU keeps the presets' value (docs/gpu.md)."""
GPU_FEATURE_LEVELS = 2
"""With finer grids on a card and the colour features kept in dense grids (a --set of a feature key: else they go into
a hash grid, GPU_HASH_FEATURES), the features are a sum of this many dense grids, each half the
resolution of the one before (`recon.nerf.grid.MultiDenseGrid`): at a card's feature resolution a vertex of the
finest grid is reached by few rays early on, and the coarser level learns the colour of every part in the meantime
(docs/gpu.md)."""
MAX_GRID_RES = 1024
"""The finest grid resolution an option may ask for (vertices, or a hash grid's cells, per side)."""
GPU_HASH_FEATURES: dict[str, int | str] = {"grid": "hash", "feature_dim": 16, "hash_table_log2": 19,
                                           "feature_res": MAX_GRID_RES}
"""With finer grids on a card, the fast model's colour features in instant-ngp's multiresolution hash grid (16
levels of 2 features, 2^19 rows a level, the finest as fine as the pixels resolve: `auto_fast_config` caps
feature_res there) instead of dense grids: it reaches the photos' detail with a tenth of the dense grids' values,
and its one Triton kernel reads every level in a pass (docs/gpu.md). A CPU keeps dense grids, which it reads in C."""
GPU_HASH_KEYS = frozenset(f"train.fast.{key}" for key in (*GPU_HASH_FEATURES, "feature_levels"))
"""A --set of any of these keeps the preset's feature grid (then dense grids get GPU_FEATURE_LEVELS)."""
GPU_GRID_MEMORY_FRACTION = 0.25
"""The sized grids' training memory (parameters, gradients, Adam moments) stays below this share of the GPU's."""


def _override_keys(overrides: list[str] | None) -> frozenset[str]:
    """The dotted keys a --set list names."""
    return frozenset(item.partition("=")[0].strip() for item in overrides or [])


def device_sizing(config: RunConfig, memory_bytes: int, name: str,
                  keep: frozenset[str] = frozenset()) -> tuple[RunConfig, str]:
    """(config sized to a CUDA device of `memory_bytes`, what changed and why; "" when nothing did).

    Only the grid models (fast, surface) are sized: the classic preset's values are already the paper's GPU
    values. Rays per step (and depth rays) and grid resolutions grow with the card's memory (`GPU_TIERS`); with a
    time budget the step cap, evaluation and checkpoint periods grow too, so the same minutes run the steps the
    card can take. Keys in `keep` (the user's --set) are left as they are."""
    train = config.train
    tier = next((t for t in GPU_TIERS if memory_bytes >= t[0] * 2**30), None)
    if train.model not in ("auto", "fast", "surface") or tier is None:
        return config, ""
    _, rays_x, grid_x, steps_x = tier
    sized = dataclasses.replace(config, train=dataclasses.replace(
        train, fast=dataclasses.replace(train.fast), surface=dataclasses.replace(train.surface)))
    changes: list[str] = []

    def scale(dotted: str, factor: float, multiple: int = 1, cap: int = 2**31) -> None:
        if dotted in keep or factor == 1:
            return
        *path, key = dotted.split(".")
        target = sized
        for part in path:
            target = getattr(target, part)
        old = getattr(target, key)
        new = min(cap, max(multiple, int(round(old * factor / multiple)) * multiple))
        if new != old:
            setattr(target, key, new)
            changes.append(f"{dotted}={old}→{new}")

    scale("train.batch_rays", rays_x)
    scale("train.depth_rays", rays_x)
    if train.budget:
        for key in ("train.steps", "train.eval_every", "train.checkpoint_every"):
            scale(key, steps_x)
    grids = (("train.fast.density_res", "train.fast.feature_res", "train.fast.occupancy_res")
             if train.model != "surface" else ("train.surface.sdf_res", "train.surface.feature_res"))
    before = list(changes)
    for key in grids:
        scale(key, grid_x, 16, MAX_GRID_RES if "occupancy" not in key else 512)
    levels = ""
    finer = changes != before and train.model != "surface" and sized.train.fast.grid == "dense"
    if finer and not keep & GPU_HASH_KEYS:
        changes = [c for c in changes if not c.startswith("train.fast.feature_res=")]  # the hash grid's instead
        changes += [f"train.fast.{key}={getattr(train.fast, key)}→{value}" for key, value in GPU_HASH_FEATURES.items()
                    if getattr(train.fast, key) != value]
        sized.train.fast = dataclasses.replace(sized.train.fast, feature_levels=1, **GPU_HASH_FEATURES)  # type: ignore[arg-type]
        levels = ("; the colour features in a multiresolution hash grid (instant-ngp's), whose finest levels reach "
                  "the pixels' detail with a tenth of a dense grid's values")
    elif (finer and sized.train.fast.feature_levels < GPU_FEATURE_LEVELS
          and "train.fast.feature_levels" not in keep):
        changes.append(f"train.fast.feature_levels={sized.train.fast.feature_levels}→{GPU_FEATURE_LEVELS}")
        sized.train.fast = dataclasses.replace(sized.train.fast, feature_levels=GPU_FEATURE_LEVELS)
        levels = ("; under the finer feature grid a coarser one learns the colour of the parts few rays have reached "
                  "yet")
    grid_bytes = sum(need for keys, _, need in implied_memory(sized) if keys.startswith("train."))
    late_loss = ""
    if grid_bytes > GPU_GRID_MEMORY_FRACTION * memory_bytes:  # the card cannot hold finer grids: keep the preset's
        sized.train.fast, sized.train.surface = train.fast, train.surface
        changes, levels = before, ""
    elif (changes != before and train.model != "surface" and sized.train.fast.distortion_weight > 0
          and sized.train.fast.distortion_from == 0 and "train.fast.distortion_from" not in keep
          and sized.train.fast.distortion_until > GPU_DISTORTION_FROM):
        sized.train.fast.distortion_from = GPU_DISTORTION_FROM
        changes.append(f"train.fast.distortion_from=0→{GPU_DISTORTION_FROM:g}")
        late_loss = (f"; at the finer grids the distortion loss from the first step costs held-out detail, from "
                     f"{GPU_DISTORTION_FROM:.0%} of training it still clears the fog (docs/gpu.md)")
    glossy = ""
    fast = sized.train.fast
    if (train.model != "surface" and fast.color_model == "mlp_view" and fast.sh_degree < GPU_SH_DEGREE
            and "train.fast.sh_degree" not in keep):
        changes.append(f"train.fast.sh_degree={fast.sh_degree}→{GPU_SH_DEGREE}")
        sized.train.fast = dataclasses.replace(fast, sh_degree=GPU_SH_DEGREE)  # a copy: `fast` may be the caller's
        glossy = ("; the colour's view dependence to the third degree fits glossy highlights, and its wider input "
                  "costs a card next to nothing")
    if not changes:
        return config, ""
    return sized, (f"GPU sizing ({name}, {memory_bytes / 2**30:.0f} GiB; train.device_sizing=off keeps the preset's "
                   f"CPU-sized values): {', '.join(changes)} — 4,096 rays a step leave a GPU waiting on kernel "
                   f"launches, and the same minutes buy more steps there{late_loss}{levels}{glossy}")


def _apply_overrides(config: RunConfig, overrides: list[str] | None) -> None:
    for item in overrides or []:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE (e.g. --set train.steps=2000), got {_shown(item)}.")
        set_value(config, key.strip(), raw.strip(), source="--set")


def _flatten(table: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """A TOML table as (dotted key, value) pairs."""
    out: list[tuple[str, Any]] = []
    for key, value in table.items():
        out += _flatten(value, f"{prefix}{key}.") if isinstance(value, dict) else [(f"{prefix}{key}", value)]
    return out


def _gpu_training(device: str) -> bool:
    """Will training run on a GPU? cuda[:K]: yes; cpu: no; auto: when torch sees CUDA (torch imported only here)."""
    pref = device.strip().lower()
    if pref != "auto":
        return pref.startswith("cuda")
    import torch

    return bool(torch.cuda.is_available())


@dataclass(frozen=True)
class Bound:
    """The allowed range of one numeric option: [low, high] (either end open), plus one special value outside it
    (`off`, e.g. 0 for "automatic") that the option's doc gives a meaning."""

    low: float
    high: float
    low_open: bool = False
    high_open: bool = False
    off: float | None = None
    off_means: str = ""

    def ok(self, value: float) -> bool:
        if self.off is not None and value == self.off:
            return True
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        low = f"greater than {self.low:g}" if self.low_open else f"at least {self.low:g}"
        high = f"below {self.high:g}" if self.high_open else f"at most {self.high:g}"
        text = f"{low} and {high}"
        return f"{self.off:g} ({self.off_means}) or {text}" if self.off is not None else text


def _range(low: float, high: float, off: float | None = None, off_means: str = "") -> Bound:
    return Bound(low, high, off=off, off_means=off_means)


def _above(low: float, high: float) -> Bound:
    return Bound(low, high, low_open=True)


def _fraction() -> Bound:
    """A probability, opacity or transmittance: 1 would mean log(0) or nothing left to render."""
    return Bound(0.0, 1.0, high_open=True)


SEED = _range(0, 2**31 - 1)
"""Seeds go to COLMAP (a C int) and NumPy (which refuses negative seeds)."""
PERIOD = _range(1, 10**7)
"""A period in steps that code takes a remainder by: 0 would divide by zero."""
STEPS = _range(0, 10**8)
WEIGHT = _range(0, 1e4)
LR_SCALE = _above(0, 1e4)
MAX_RAYS_PER_STEP = 2**18
"""Rays rendered per training step (batch plus depth rays): 64 times the presets' largest batch (4096)."""
MAX_HOLDOUT_EVERY = 10**4

BOUNDS: dict[str, Bound] = {
    "poses.max_side": _range(16, 20000),
    "poses.max_features": _range(64, 100000),
    "poses.sequential_overlap": _range(1, 10000),
    "poses.loop_keyframes": _range(0, 10000),
    "poses.video_frames": _range(3, 100000),
    "poses.video_min_change": _range(0, 255),
    "poses.num_threads": _range(1, 1024, off=-1, off_means="every core"),
    "poses.seed": SEED,
    "poses.min_registered": _range(2, 10**6),
    "poses.min_registered_fraction": _range(0, 1),
    "normalize.link_spacings": _above(0, 1e4),
    "normalize.box_margin": _range(0, 10),
    "normalize.depth_percentile": _range(0, 49),
    "normalize.test_every": _range(2, MAX_HOLDOUT_EVERY, off=0, off_means="none"),
    "normalize.val_every": _range(2, MAX_HOLDOUT_EVERY, off=0, off_means="none"),
    "train.steps": _range(1, 10**8),
    "train.batch_rays": _range(1, MAX_RAYS_PER_STEP),
    "train.lr": _range(0, 1),
    "train.lr_decay": _above(0, 1),
    "train.adam_beta2": _fraction(),
    "train.max_side": _range(4, 16384),
    "train.eval_every": STEPS,
    "train.eval_views": _range(0, 10**5),
    "train.final_eval_views": _range(0, 10**5),
    "train.checkpoint_every": STEPS,
    "train.seed": SEED,
    "train.depth_weight": WEIGHT,
    "train.depth_rays": _range(1, MAX_RAYS_PER_STEP),
    "train.smoothness_weight": WEIGHT,
    "train.smoothness_patches": _range(0, MAX_RAYS_PER_STEP // 16),
    "train.smoothness_stride": _range(1, 1024),
    "train.sky_weight": WEIGHT,
    "train.transparent_weight": WEIGHT,
    "train.transparent_disputed_share": _range(0, 1),
    "train.classic.n_coarse": _range(1, 1024),
    "train.classic.n_fine": _range(0, 1024),
    "train.classic.pos_freqs": _range(0, 20),
    "train.classic.dir_freqs": _range(0, 20),
    "train.classic.depth": _range(1, 32),
    "train.classic.width": _range(1, 4096),
    "train.fast.density_res": _range(2, MAX_GRID_RES),
    "train.fast.feature_res": _range(2, MAX_GRID_RES),
    "train.fast.feature_dim": _range(1, 64),
    "train.fast.hash_table_log2": _range(10, 24),
    "train.fast.density_levels": _range(1, 8),
    "train.fast.feature_levels": _range(1, 8),
    "train.fast.sh_degree": _range(0, 3),
    "train.fast.mlp_width": _range(1, 1024),
    "train.fast.mlp_layers": _range(0, 16),
    "train.fast.occupancy_res": _range(2, 512),
    "train.fast.occupancy_alpha": Bound(0, 1, low_open=True, high_open=True),
    "train.fast.occupancy_alpha_start": Bound(0, 1, low_open=True, high_open=True),
    "train.fast.unbounded_occupancy_alpha": Bound(0, 1, low_open=True, high_open=True),
    "train.fast.occupancy_ramp": STEPS,
    "train.fast.slow_occupancy_alpha_start": Bound(0, 1, low_open=True, high_open=True),
    "train.fast.slow_occupancy_ramp": STEPS,
    "train.fast.occupancy_warmup": STEPS,
    "train.fast.occupancy_every": PERIOD,
    "train.fast.warmup_step_scale": _above(0, 100),
    "train.fast.step_ratio": _above(0, 100),
    "train.fast.max_samples": _range(1, 65536),
    "train.fast.cone_angle": _range(0, 1),
    "train.fast.early_stop_transmittance": _fraction(),
    "train.fast.color_min_weight": _fraction(),
    "train.fast.init_alpha": Bound(0, 1, low_open=True, high_open=True),
    "train.fast.tv_weight": WEIGHT,
    "train.fast.distortion_weight": WEIGHT,
    "train.fast.distortion_from": _fraction(),
    "train.fast.hull_start_alpha": _range(0.001, 0.99),
    "train.fast.distortion_until": Bound(0.0, 1.0, low_open=True),
    "train.fast.unbounded_distortion_weight": WEIGHT,
    "train.fast.entropy_weight": WEIGHT,
    "train.fast.grid_lr_scale": LR_SCALE,
    "train.fast.shrink_step": STEPS,
    "train.fast.shrink_margin": _range(0, 1),
    "train.surface.sdf_res": _range(17, MAX_GRID_RES),
    "train.surface.sdf_levels": _range(1, 8),
    "train.surface.sdf_mlp_width": _range(0, 1024),
    "train.surface.level_every": STEPS,
    "train.surface.init_radius": _range(0.01, 1),
    "train.surface.init_sharpness": _above(0, 1e5),
    "train.surface.feature_res": _range(2, MAX_GRID_RES),
    "train.surface.feature_dim": _range(1, 64),
    "train.surface.sh_degree": _range(0, 3),
    "train.surface.mlp_width": _range(1, 1024),
    "train.surface.mlp_layers": _range(0, 16),
    "train.surface.step_ratio": _above(0, 100),
    "train.surface.max_samples": _range(1, 65536),
    "train.surface.occupancy_res": _range(2, 512),
    "train.surface.occupancy_warmup": STEPS,
    "train.surface.occupancy_every": PERIOD,
    "train.surface.warmup_step_scale": _above(0, 100),
    "train.surface.band_width": _above(0, 100),
    "train.surface.early_stop_transmittance": _fraction(),
    "train.surface.color_min_weight": _fraction(),
    "train.surface.eikonal_weight": WEIGHT,
    "train.surface.curvature_weight": WEIGHT,
    "train.surface.boundary_weight": WEIGHT,
    "train.surface.init_prior_weight": WEIGHT,
    "train.surface.boundary_margin_cells": _range(0, 100),
    "train.surface.boundary_points": _range(0, MAX_RAYS_PER_STEP),
    "train.surface.eikonal_samples": _range(1, MAX_RAYS_PER_STEP),  # 0: the mean over no sample is NaN
    "train.surface.eikonal_points": _range(1, MAX_RAYS_PER_STEP),
    "train.surface.sdf_lr_scale": LR_SCALE,
    "train.surface.grid_lr_scale": LR_SCALE,
    "train.surface.sharpness_lr_scale": _range(0, 1e4),
    "mesh.resolution": _range(8, 4096, off=0, off_means="automatic"),
    "mesh.max_resolution": _range(8, 4096),
    "mesh.memory_budget_mb": _range(1, 2**30),
    "mesh.iso": _range(0, 1e12),
    "mesh.iso_opacity": _range(0, 0.99),
    "mesh.min_component_fraction": _range(0, 1),
    "mesh.smooth_iters": _range(0, 10000),
    "mesh.fill_cavities": _range(0, 256),
    "mesh.mask_keep_fraction": _range(0, 1),
    "mesh.cpu_bake_views": _range(1, 10**5, off=0, off_means="automatic"),
    "mesh.gpu_bake_views": _range(1, 10**5, off=0, off_means="automatic"),
    "mesh.cpu_depth_side": _range(8, 16384, off=0, off_means="automatic"),
    "mesh.region_margin": _range(0, 10),
    "mesh.ground_margin_cells": _range(0, 100, off=-1, off_means="automatic"),
    "mesh.target_faces": _range(4, 10**8, off=0, off_means="keep all"),
    "mesh.real_size": _range(0, 1e9),
    "mesh.texture_faces": _range(4, 150000, off=0, off_means="no textured mesh"),
    "mesh.texture_size": _range(16, 8192, off=0, off_means="automatic"),
}
"""Allowed range of every int and float option (tests/test_bad_input.py checks that none is missing): checked once
the preset and every --set are applied. texture_faces stops at 150,000 because xatlas (the UV unwrap) crashed the
process (SIGSEGV) unwrapping 300,000 faces; texture_size at 8192 because its packing time grows with the size
(15 s at 4096 and 54 s at 16384 for a 320-face sphere, over 60 s from 20000)."""

GRID_COPIES_IN_MESH_STAGE = 6.0
"""The mesh stage's peak memory in units of its float32 density grid (which mesh.memory_budget_mb caps): the grid,
plus 4.7 grids more that fill_enclosed allocates (its masks and labels; tracemalloc on 128³ and 256³ grids), plus
marching cubes' 0.2-0.4."""
AUTO_TEXTURE_SIDES = (512, 1024, 2048)
"""mesh.texture_size=0 picks from these (`recon.plans.mesh.texture_side`)."""
TEXTURE_BAKE_BYTES_PER_TEXEL = 180
"""Peak memory of baking a texture, per texel (rasterized face ids and barycentrics, points, colors, the padding's
distance transform): measured 0.75 GB over the process for a 2048² bake."""
TRAINING_BYTES_PER_PARAMETER = 16
"""A trained float32 parameter costs itself, its gradient and Adam's two moments."""


def machine_memory_bytes() -> int:
    """Physical memory of this machine, or the container's memory limit (cgroup v2 / v1) when that is lower."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for limit_file in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        with contextlib.suppress(OSError, ValueError):
            total = min(total, int(Path(limit_file).read_text().strip()))
    return total


def _dense_grid_parameters(res: int, channels: int, levels: int) -> int:
    """Values in a dense grid of `levels` levels, each half the resolution of the previous (at most 8/7 res³)."""
    return sum(max(2, (res - 1) // 2**k + 1) ** 3 for k in range(levels)) * channels


def _grid_parameters(kind: str, res: int, channels: int, levels: int, table_log2: int) -> int:
    """Values in one of the fast model's grids: a "hash" grid's tables (``channels`` levels of HASH_FEATURES), any
    other as dense (a "vm" grid of the same resolution is far smaller)."""
    if kind == "hash":
        return sum(hash_level_layout(channels, HASH_BASE_RES, res, table_log2)[1]) * HASH_FEATURES
    return _dense_grid_parameters(res, channels, levels)


def implied_memory(config: RunConfig) -> list[tuple[str, str, int]]:
    """The memory each memory-hungry group of options implies: (options to lower, what needs it, bytes).

    The mesh grid is what mesh.memory_budget_mb allows of mesh.resolution (or max_resolution) cubed, times the
    copies the stage makes of it; the training grids as `_grid_parameters` counts them; the texture is baked at
    mesh.texture_size² (automatic: at most 2048²).
    """
    mesh, fast, surface = config.mesh, config.train.fast, config.train.surface
    res = mesh.resolution or mesh.max_resolution
    grid = min(4 * res**3, mesh.memory_budget_mb * 2**20)
    out = [("mesh.resolution / mesh.max_resolution / mesh.memory_budget_mb",
            "the mesh stage (its float32 density grid and the grids filling and meshing copy from it)",
            int(grid * GRID_COPIES_IN_MESH_STAGE))]
    if config.mesh.texture_faces:
        side = mesh.texture_size or AUTO_TEXTURE_SIDES[-1]
        out.append(("mesh.texture_size", "baking the texture", TEXTURE_BAKE_BYTES_PER_TEXEL * side**2))
    if config.train.model in ("auto", "fast"):
        params = (_grid_parameters(fast.density_grid, fast.density_res, density_grid_dim(fast.density_grid),
                                   fast.density_levels, fast.hash_table_log2)
                  + _grid_parameters(fast.grid, fast.feature_res, fast.feature_dim, fast.feature_levels,
                                     fast.hash_table_log2))
        out.append(("train.fast.density_res / feature_res / feature_dim / *_levels", "training the fast model's grids",
                    TRAINING_BYTES_PER_PARAMETER * params))
    if config.train.model == "surface":
        params = (_dense_grid_parameters(surface.sdf_res, 1, surface.sdf_levels)
                  + _dense_grid_parameters(surface.feature_res, surface.feature_dim, 1))
        out.append(("train.surface.sdf_res / sdf_levels / feature_res / feature_dim",
                    "training the surface model's grids", TRAINING_BYTES_PER_PARAMETER * params))
    return out


def _check_types(config: Any, prefix: str = "") -> None:
    """Every option holds its declared type (a finite number for numbers): an API caller may set fields directly."""
    hints = _field_types(type(config))
    for f in dataclasses.fields(config):
        value, dotted, ftype = getattr(config, f.name), f"{prefix}{f.name}", hints[f.name]
        if dataclasses.is_dataclass(value):
            _check_types(value, f"{dotted}.")
        elif ftype in (int, float):
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            whole = isinstance(value, int)  # math.isfinite would overflow on a 400-digit int
            if not number or (ftype is int and not whole) or (not whole and not math.isfinite(value)):
                raise ConfigError(f"Option '{dotted}' must be a finite {'whole ' if ftype is int else ''}number; "
                                  f"got {value!r}. Fix it in the preset or the --set override.")


def _check_boxes(config: RunConfig) -> None:
    """The grid models' boxes: finite, each min below its max (the train stage sets them from the scene)."""
    for dotted, box in (("train.fast.aabb", config.train.fast.aabb), ("train.surface.aabb", config.train.surface.aabb)):
        lows, highs = box
        if not all(math.isfinite(v) for v in (*lows, *highs)) or not all(lo < hi for lo, hi in zip(lows, highs)):
            raise ConfigError(f"Option '{dotted}' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with finite values, "
                              f"each min below its max; got {box}.")
    if not all(all(math.isfinite(v) for v in row) for row in config.train.surface.init_planes):
        raise ConfigError("Option 'train.surface.init_planes' must hold finite rows (nx, ny, nz, d).")


def _check_cross(config: RunConfig) -> None:
    """Checks that involve several options: rays per step, the held-out split, the memory the options imply."""
    train = config.train
    if train.batch_rays + train.depth_rays > MAX_RAYS_PER_STEP:
        raise ConfigError(
            f"Options 'train.batch_rays' ({train.batch_rays}) and 'train.depth_rays' ({train.depth_rays}) add up to "
            f"more than {MAX_RAYS_PER_STEP} rays per training step. Lower them (the presets use at most 4096 + 512)."
        )
    fast = train.fast
    if fast.distortion_weight > 0 and fast.distortion_until <= fast.distortion_from:
        raise ConfigError(
            f"Options 'train.fast.distortion_from' ({fast.distortion_from:g}) and 'train.fast.distortion_until' "
            f"({fast.distortion_until:g}) leave the distortion loss no share of training: start it before it stops, "
            "or set train.fast.distortion_weight=0 to train without it."
        )
    test, val = config.normalize.test_every, config.normalize.val_every
    if test and val:
        ranks = np.arange(math.lcm(test, val))
        if ((ranks % test == 0) | (ranks % val == val // 2)).all():
            raise ConfigError(
                f"Options 'normalize.test_every'={test} and 'normalize.val_every'={val} hold out every photo: none "
                f"would be left to train on. Raise one of them (the defaults are 8 and 0) or set it to 0."
            )
    available = machine_memory_bytes()
    for keys, what, need in implied_memory(config):
        if need > available:
            raise ConfigError(
                f"Options {keys} imply about {need / 2**30:.1f} GiB for {what}, more than this machine's "
                f"{available / 2**30:.1f} GiB of memory. Lower them (the presets' values fit in a few GiB)."
            )


def check_batch_against_pixels(config: RunConfig, photos: int) -> None:
    """train.batch_rays above every pixel the training photos can have: each step would repeat pixels."""
    pixels = photos * config.train.max_side**2
    if photos > 0 and config.train.batch_rays > pixels:
        raise ConfigError(
            f"Option 'train.batch_rays'={config.train.batch_rays} is more than all the pixels of the {photos} "
            f"photo(s) at train.max_side={config.train.max_side} (at most {pixels:,}): every step would repeat pixels. "
            f"Lower train.batch_rays to at most {pixels:,}, or raise train.max_side."
        )


DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")
"""train.device values: auto, cpu, cuda or cuda:K (whether CUDA is there is checked when a stage needs it)."""


def validate(config: RunConfig) -> None:
    """Refuse wrong types and out-of-range values (negative steps, zero batch, a zero period, a probability of 1,
    an unreadable budget, an unknown device, more memory than the machine has...) before any stage runs, naming
    the option: a typo must not surface after structure from motion has run."""
    _check_values(config)
    _check_boxes(config)
    _check_cross(config)
    parse_region(config.mesh.region)


def _check_values(config: RunConfig) -> None:
    """Each option on its own: the budget, the device, types and ranges (what a preset's CPU table or the sizing for a
    card cannot make valid, so `load_config` checks it before torch loads to look for a GPU)."""
    try:
        parse_duration(config.train.budget)
    except ConfigError as exc:
        raise ConfigError(f"Option 'train.budget' (or --budget): {exc}") from None
    if not DEVICE_PATTERN.fullmatch(config.train.device.strip().lower()):
        raise ConfigError(
            f"Option 'train.device' must be auto, cpu, cuda or cuda:K (e.g. cuda:0); got {_shown(config.train.device)}."
        )
    _check_types(config)
    for dotted, bound in BOUNDS.items():
        value: Any = config
        for part in dotted.split("."):
            value = getattr(value, part)
        if not bound.ok(value):
            raise ConfigError(
                f"Option '{dotted}' must be {bound.describe()}; got {_shown(value)}. Fix it in the preset or the --set override."
            )


def parse_region(text: str) -> str | tuple[tuple[float, float, float], tuple[float, float, float]]:
    """mesh.region: "auto", "all", or "xmin,ymin,zmin,xmax,ymax,zmax" → ((xmin, ymin, zmin), (xmax, ymax, zmax))."""
    value = str(text).strip().lower()
    if value in ("auto", "all"):
        return value
    try:
        numbers = [float(v) for v in value.strip("[]()").split(",")]
    except ValueError:
        numbers = []
    if len(numbers) != 6 or not all(math.isfinite(v) for v in numbers) or not all(
        numbers[i] < numbers[i + 3] for i in range(3)
    ):
        raise ConfigError(
            f"Option 'mesh.region' must be auto, all, or a box xmin,ymin,zmin,xmax,ymax,zmax (source frame, each min "
            f"below its max); got {_shown(text)}."
        )
    return (numbers[0], numbers[1], numbers[2]), (numbers[3], numbers[4], numbers[5])


def preset_description(name: str) -> str:
    """The one-line `description` a preset gives of what it trades."""
    data = tomllib.loads(preset_path(name).read_text())
    return str(data.get("description", ""))


def set_value(config: Any, dotted: str, raw: Any, source: str) -> None:
    """Set `a.b.c` on nested dataclasses; raw strings are parsed to the field's type."""
    parts = dotted.split(".")
    target = config
    for i, part in enumerate(parts):
        names = [f.name for f in dataclasses.fields(target)]
        if part not in names:
            where = ".".join(parts[:i]) or "the top level"
            raise ConfigError(
                f"Unknown option '{dotted}' ({source}): '{part}' is not a key of {where}. "
                f"Valid keys there: {', '.join(names)}."
            )
        if i == len(parts) - 1:
            if dataclasses.is_dataclass(getattr(target, part)):
                raise ConfigError(
                    f"Option '{dotted}' ({source}) is a section, not a value: set one of its keys, e.g. "
                    f"{dotted}.{dataclasses.fields(getattr(target, part))[0].name}=..."
                )
            ftype = _field_types(type(target))[part]
            setattr(target, part, _coerce(raw, ftype, dotted, source))
        else:
            target = getattr(target, part)
            if not dataclasses.is_dataclass(target):
                raise ConfigError(f"Option '{dotted}' ({source}): '{part}' is a value, not a section.")


def _apply_table(config: Any, table: dict, prefix: str, source: str) -> None:
    for key, value in table.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            names = [f.name for f in dataclasses.fields(config)]
            if key not in names or not dataclasses.is_dataclass(getattr(config, key)):
                raise ConfigError(f"Unknown section [{dotted}] in {source}. Valid sections: {', '.join(names)}.")
            _apply_table(getattr(config, key), value, f"{dotted}.", source)
        else:
            set_value_on(config, key, value, dotted, source)


def set_value_on(target: Any, key: str, value: Any, dotted: str, source: str) -> None:
    names = [f.name for f in dataclasses.fields(target)]
    if key not in names:
        raise ConfigError(f"Unknown option '{dotted}' in {source}. Valid keys there: {', '.join(names)}.")
    setattr(target, key, _coerce(value, _field_types(type(target))[key], dotted, source))


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(raw: Any, ftype: Any, dotted: str, source: str) -> Any:
    """Parse a TOML value or a `--set` string into the field's declared type, or explain why not."""
    origin = typing.get_origin(ftype)
    args = typing.get_args(ftype)
    if origin is Literal:
        value = raw
        if isinstance(raw, str) and all(not isinstance(a, str) for a in args):
            value = _parse_scalar(raw)
        if value not in args:
            raise ConfigError(
                f"Option '{dotted}' ({source}) must be one of {', '.join(map(str, args))}; got {_shown(raw)}."
            )
        return value
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if raw in (None, "none", "None", "") and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(raw, arg, dotted, source)
            except ConfigError:
                continue
        raise ConfigError(f"Option '{dotted}' ({source}) got {_shown(raw)}, which is not a valid {ftype}.")
    if origin in (list, tuple):
        value = _parse_scalar(raw) if isinstance(raw, str) else raw
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"Option '{dotted}' ({source}) expects a list like [1, 2]; got {_shown(raw)}.")
        inner = args[0] if args else Any
        items = [_coerce(v, inner, dotted, source) if inner is not Any and inner is not Ellipsis else v for v in value]
        return tuple(items) if origin is tuple else items
    if ftype is bool:
        if isinstance(raw, bool):
            return raw
        if isinstance(raw, str) and raw.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return raw.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"Option '{dotted}' ({source}) expects true or false; got {_shown(raw)}.")
    if ftype in (int, float):
        value = _parse_scalar(raw) if isinstance(raw, str) else raw
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"Option '{dotted}' ({source}) expects a number; got {_shown(raw)}.")
        if ftype is int:
            if isinstance(value, float) and not value.is_integer():
                raise ConfigError(f"Option '{dotted}' ({source}) expects a whole number; got {_shown(raw)}.")
            return int(value)
        try:
            number = float(value)
        except OverflowError:  # an int beyond float range
            number = float("inf")
        if not math.isfinite(number):
            raise ConfigError(f"Option '{dotted}' ({source}) must be a finite number; got {_shown(raw)}.")
        return number
    if ftype is str:
        return str(raw)
    return raw


def _shown(raw: Any, limit: int = 60) -> str:
    """A value quoted for an error message, cut short when long: the message stays one readable line."""
    text = str(raw)
    return f"'{text}'" if len(text) <= limit else f"'{text[:limit]}…' ({len(text)} characters)"


def _parse_scalar(raw: str) -> Any:
    try:
        return json.loads(raw)
    except (ValueError, RecursionError):  # not JSON, a number over Python's 4300 digits, nested too deeply
        return raw


def parse_duration(text: str) -> float:
    """ "90s", "5m", "1.5h", "300" (seconds) → seconds; "" → 0 (no budget)."""
    text = text.strip().lower()
    if not text:
        return 0.0
    units = {"s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
    for suffix in sorted(units, key=len, reverse=True):
        if text.endswith(suffix):
            number, scale = text[: -len(suffix)], units[suffix]
            break
    else:
        number, scale = text, 1.0
    try:
        value = float(number) * scale
    except ValueError:
        raise ConfigError(f"Cannot read the time budget {_shown(text)}: write it like 90s, 5m or 1h.") from None
    if not value > 0 or value == float("inf"):
        raise ConfigError(f"The time budget must be positive and finite, got {_shown(text)}.")
    return value


def config_slice(config: RunConfig, name: str) -> dict:
    """A stage's slice as plain data: what its fingerprint hashes and what the manifest records."""
    return dataclasses.asdict(getattr(config, name))

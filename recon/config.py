"""Typed configuration: one dataclass per stage, presets from `pipelines/*.toml`, `--set a.b=c` overrides.

A preset is data: a TOML file whose tables mirror the dataclasses below (`[train]`, `[train.fast]`, ...).
Every field has a default and a line of doc; unknown keys and wrong types are refused with a message
naming the key, so a typo never silently falls back to a default.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from recon.errors import ConfigError
from recon.nerf.model_config import FastConfig, GridKind, SurfaceConfig
from recon.sfm import SfmOptions

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
    val_every: int = 8
    """Every Nth photo, offset by half of it, is held out for validation; 0: none."""


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
    """Initial learning rate; 0 uses the model's own default."""
    lr_decay: float = 0.1
    """The learning rate decays exponentially to lr × lr_decay at the last step."""
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
    """Set by a preset's [no_gpu] table when no GPU is found: what it changed and why (printed with the train
    stage's reasons)."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """bf16: the networks' matrix math in bfloat16 (autocast; volume rendering stays fp32). Faster on GPUs and
    CPUs with AMX/AVX512-BF16, slower on older CPUs."""
    depth_prior: Literal["auto", "on", "off"] = "auto"
    """Sparse-depth supervision from the SfM points (DS-NeRF). auto: on when fewer than 20 photos train the field
    (few views leave the geometry ambiguous), the model is `surface` (its SDF starts closed and needs the
    points' depths to open concavities) or the capture is unbounded (the object in front of a background it may
    match in colour), the scene has sparse points and no masks; on / off force it."""
    depth_weight: float = 0.002
    """Weight of the sparse-depth loss (robust, in units of each point's depth uncertainty)."""
    depth_rays: int = 512
    """Sparse-point rays rendered per step for the depth loss (on top of batch_rays)."""
    appearance: Literal["auto", "on", "off"] = "auto"
    """Per-photo colour transforms for exposure / white-balance changes (grid models). auto: on when the colours
    of matched points differ between neighbouring photos (recon/nerf/appearance.py); the mesh uses the neutral one."""
    backdrop_key: Literal["auto", "on", "off"] = "auto"
    """Photos on a plain backdrop (a light box, a studio sweep): train the pixels of the backdrop's colour as empty
    space, as masks would (recon.views.key_backdrop). auto: on for the surface model of an object capture without
    masks whose photos' borders are plain; the density models keep the photos as they are."""
    sky: Literal["auto", "on", "off"] = "auto"
    """A sky behind an unbounded scene (recon/sky.py): the fast field gets a colour per ray direction behind it,
    and the photos' clear-sky pixels (smooth, blue, no SfM point near) train as empty space. auto: on when at
    least 1% of the training pixels are sky, for an unbounded capture without masks."""
    sky_weight: float = 0.1
    """Weight of the sky pixels' opacity (L1, averaged over each batch's rays) in the loss."""
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
    """Opacity of one cell of material at the automatic iso-level; 0: 0.35 (the mesh stage's ISO_OPACITY), or 0.25
    when masks trained the background empty (the masks already carve the object, so the level can be lower and close
    the holes an undertrained field leaves)."""
    min_component_fraction: float = 0.05
    """Drop disconnected pieces with less than this fraction of the largest piece's area (floaters)."""
    smooth_iters: int = 0
    """Taubin smoothing iterations (0: none)."""
    fill_cavities: int = 0
    """Fill the empty space the density field's material encloses before marching cubes, after closing holes up to
    about twice this many cells wide (0: off; the density presets: 4). Not on the whole box of an unbounded scene;
    see `recon.geometry.extract.fill_enclosed` and `recon.stages.mesh.hollow_fill_applies`. Why: a density field is a
    shell whose inner walls show through its pits, and the hidden-face test keeps them; filling removes them."""
    target_faces: int = 300000
    """Decimate to this many faces (0: keep all)."""
    drop_hidden: bool = True
    """Remove faces that no photo sees (depth-tested against the field's rendered depth): the walls and
    islands marching cubes finds inside a soft, unconstrained interior; they cost most of the mesh's precision.
    Off, the mesh is closed where the field is, but full of inner walls."""
    color: Literal["photos", "field"] = "photos"
    """Per-vertex color: baked from the photos (depth-tested), or queried from the field."""
    frame: Literal["normalized", "source"] = "normalized"
    """Export in our normalized frame (+Z up, box ≈ [-1, 1]³) or back in the source (COLMAP/import) frame."""
    real_size: float = 0.0
    """> 0: scale the mesh so its largest bounding-box side is this many units (e.g. meters)."""
    region: str = "auto"
    """What to mesh. auto: the object the cameras look at (normalize's object region, when it found one);
    all: the whole scene box; or an explicit box "xmin,ymin,zmin,xmax,ymax,zmax" in the source frame."""
    keep_ground: bool = False
    """Keep the ground plane the object stands on, or the wall it hangs on (normalize finds either by RANSAC); by
    default it is cut away."""
    texture_faces: int = 50000
    """Also write mesh_textured.glb/.obj: the mesh decimated to this many faces, UV-unwrapped, its color
    baked into a texture (0: no textured mesh)."""
    texture_size: int = 2048
    """Side of the square texture image of the textured mesh, in texels."""


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
    validate(config)
    return config


def _apply_overrides(config: RunConfig, overrides: list[str] | None) -> None:
    for item in overrides or []:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE (e.g. --set train.steps=2000), got '{item}'.")
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


def _at_least(low: float) -> tuple[Any, str]:
    return (lambda v: v >= low), f"at least {low}"


def _positive() -> tuple[Any, str]:
    return (lambda v: v > 0), "greater than 0"


def _between(low: float, high: float) -> tuple[Any, str]:
    return (lambda v: low <= v <= high), f"between {low} and {high}"


BOUNDS: dict[str, tuple[Any, str]] = {
    "poses.max_side": _at_least(16),
    "poses.max_features": _at_least(64),
    "poses.sequential_overlap": _at_least(1),
    "poses.loop_keyframes": _at_least(0),
    "poses.video_frames": _at_least(3),
    "poses.video_min_change": _at_least(0),
    "poses.num_threads": _at_least(-1),
    "poses.min_registered": _at_least(2),
    "poses.min_registered_fraction": _between(0, 1),
    "normalize.link_spacings": _positive(),
    "normalize.box_margin": _between(0, 10),
    "mesh.iso_opacity": _between(0, 0.99),
    "normalize.depth_percentile": _between(0, 49),
    "normalize.test_every": _at_least(0),
    "normalize.val_every": _at_least(0),
    "train.steps": _at_least(1),
    "train.batch_rays": _at_least(1),
    "train.lr": _at_least(0),
    "train.lr_decay": _positive(),
    "train.max_side": _at_least(4),
    "train.eval_every": _at_least(0),
    "train.eval_views": _at_least(0),
    "train.final_eval_views": _at_least(0),
    "train.checkpoint_every": _at_least(0),
    "train.depth_weight": _at_least(0),
    "train.depth_rays": _at_least(1),
    "train.classic.n_coarse": _at_least(1),
    "train.classic.n_fine": _at_least(0),
    "train.classic.pos_freqs": _at_least(0),
    "train.classic.dir_freqs": _at_least(0),
    "train.classic.depth": _at_least(1),
    "train.classic.width": _at_least(1),
    "train.fast.density_res": _at_least(2),
    "train.fast.feature_res": _at_least(2),
    "train.fast.feature_dim": _at_least(1),
    "train.fast.sh_degree": _between(0, 4),
    "train.fast.mlp_width": _at_least(1),
    "train.fast.mlp_layers": _at_least(0),
    "train.fast.occupancy_res": _at_least(2),
    "train.fast.step_ratio": _positive(),
    "train.fast.max_samples": _at_least(1),
    "train.fast.cone_angle": _at_least(0),
    "train.fast.grid_lr_scale": _positive(),
    "train.surface.sdf_res": _at_least(17),
    "train.surface.sdf_levels": _at_least(1),
    "train.surface.feature_res": _at_least(2),
    "train.surface.feature_dim": _at_least(1),
    "train.surface.init_radius": _between(0.01, 1),
    "train.surface.init_sharpness": _positive(),
    "train.surface.step_ratio": _positive(),
    "train.surface.occupancy_res": _at_least(2),
    "train.surface.eikonal_weight": _at_least(0),
    "train.surface.curvature_weight": _at_least(0),
    "train.surface.boundary_weight": _at_least(0),
    "train.surface.boundary_margin_cells": _at_least(0),
    "train.surface.boundary_points": _at_least(0),
    "mesh.resolution": ((lambda v: v == 0 or v >= 8), "0 (automatic) or at least 8"),
    "mesh.max_resolution": _at_least(8),
    "mesh.memory_budget_mb": _at_least(1),
    "mesh.iso": _at_least(0),
    "mesh.min_component_fraction": _between(0, 1),
    "mesh.smooth_iters": _at_least(0),
    "mesh.fill_cavities": _at_least(0),
    "mesh.target_faces": _at_least(0),
    "mesh.real_size": _at_least(0),
    "mesh.texture_faces": ((lambda v: v == 0 or v >= 4), "0 (no textured mesh) or at least 4"),
    "mesh.texture_size": _at_least(16),
}
"""Allowed range of each numeric option: checked once the preset and every --set are applied."""


DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")
"""train.device values: auto, cpu, cuda or cuda:K (whether CUDA is there is checked when a stage needs it)."""


def validate(config: RunConfig) -> None:
    """Refuse out-of-range values (negative steps, zero batch, an unreadable budget, an unknown device...) before
    any stage runs, naming the option: a typo must not surface after structure from motion has run."""
    try:
        parse_duration(config.train.budget)
    except ConfigError as exc:
        raise ConfigError(f"Option 'train.budget' (or --budget): {exc}") from None
    if not DEVICE_PATTERN.fullmatch(config.train.device.strip().lower()):
        raise ConfigError(
            f"Option 'train.device' must be auto, cpu, cuda or cuda:K (e.g. cuda:0); got '{config.train.device}'."
        )
    for dotted, (ok, allowed) in BOUNDS.items():
        value: Any = config
        for part in dotted.split("."):
            value = getattr(value, part, None)
        if value is not None and not ok(value):
            raise ConfigError(
                f"Option '{dotted}' must be {allowed}; got {value}. Fix it in the preset or the --set override."
            )
    parse_region(config.mesh.region)


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
            f"below its max); got '{text}'."
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
                f"Option '{dotted}' ({source}) must be one of {', '.join(map(str, args))}; got '{raw}'."
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
        raise ConfigError(f"Option '{dotted}' ({source}) got '{raw}', which is not a valid {ftype}.")
    if origin in (list, tuple):
        value = _parse_scalar(raw) if isinstance(raw, str) else raw
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"Option '{dotted}' ({source}) expects a list like [1, 2]; got '{raw}'.")
        inner = args[0] if args else Any
        items = [_coerce(v, inner, dotted, source) if inner is not Any and inner is not Ellipsis else v for v in value]
        return tuple(items) if origin is tuple else items
    if ftype is bool:
        if isinstance(raw, bool):
            return raw
        if isinstance(raw, str) and raw.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return raw.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"Option '{dotted}' ({source}) expects true or false; got '{raw}'.")
    if ftype in (int, float):
        value = _parse_scalar(raw) if isinstance(raw, str) else raw
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"Option '{dotted}' ({source}) expects a number; got '{raw}'.")
        if ftype is int:
            if isinstance(value, float) and not value.is_integer():
                raise ConfigError(f"Option '{dotted}' ({source}) expects a whole number; got '{raw}'.")
            return int(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise ConfigError(f"Option '{dotted}' ({source}) must be a finite number; got '{raw}'.")
        return float(value)
    if ftype is str:
        return str(raw)
    return raw


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
        raise ConfigError(f"Cannot read the time budget '{text}': write it like 90s, 5m or 1h.") from None
    if not value > 0 or value == float("inf"):
        raise ConfigError(f"The time budget must be positive and finite, got '{text}'.")
    return value


def config_slice(config: RunConfig, name: str) -> dict:
    """A stage's slice as plain data: what its fingerprint hashes and what the manifest records."""
    return dataclasses.asdict(getattr(config, name))

"""The grid models' settings (fast density field, SDF surface): plain dataclasses, importable without torch.

They live with the models that read them; `recon.config` gathers them into the run's config with the rest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

GridKind = Literal["dense", "vm", "hash"]


@dataclass
class FastConfig:
    """Options of the fast grid model (`recon.nerf.fast.FastModel`) (one named point per preset in pipelines/*.toml)."""

    aabb: tuple[tuple[float, float, float], tuple[float, float, float]] = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
    """Scene box [min_xyz, max_xyz] in the normalized frame (world units); the grids span it when bounded."""
    unbounded: bool = False
    """Contract space outside the unit box into [-2, 2]^3 (mip-NeRF 360) instead of using ``aabb``."""
    unbounded_steps: Literal["contracted", "world"] = "contracted"
    """Unbounded scenes: "contracted" marches ``step_ratio`` voxels of the contracted grid (world steps grow like
    r² outside the unit box; docs/profile_unbounded.md), "world" uniform world steps from near to far (the old,
    ~5-10x more samples per ray)."""
    density_grid: GridKind = "dense"
    """Grid holding density: "dense" voxels (default, cheapest per sample), "vm" (TensoRF) or "hash"."""
    density_res: int = 128
    """Vertices per side of the density grid (levels' finest resolution for "hash")."""
    grid: GridKind = "dense"
    """Grid holding the color features: "dense" (default, fastest per sample here), "vm" (TensoRF) or "hash"."""
    feature_res: int = 128
    """Vertices per side of the feature grid (finest resolution for "hash")."""
    feature_dim: int = 12
    """Feature channels: dense = channels, vm = components per axis (3x channels out), hash = levels (x2)."""
    hash_table_log2: int = 17
    """"hash" grids: rows of each hashed level's table, as a power of two (instant-ngp's T; its NeRF uses 19)."""
    density_levels: int = 3
    """Dense density grid: sum of this many grids, each half the resolution of the previous (coarse-to-fine)."""
    feature_levels: int = 1
    """Dense feature grid: number of resolution levels, as density_levels."""
    color_model: Literal["mlp_view", "mlp", "direct"] = "mlp_view"
    """"mlp_view": MLP(features, SH(direction)); "mlp": view-independent MLP; "direct": sigmoid(features[:3])."""
    sh_degree: int = 2
    """Spherical-harmonics degree of the view direction encoding (0..3; (degree+1)^2 channels)."""
    mlp_width: int = 64
    """Hidden width of the color MLP."""
    mlp_layers: int = 2
    """Hidden layers of the color MLP."""
    occupancy_res: int = 64
    """Occupancy grid cells per side."""
    occupancy_alpha: float = 0.05
    """A vertex is occupied when its density gives at least this opacity over one step. Keep it above
    ``init_alpha``: space no ray has touched yet then gets culled at the first refresh (at ``init_alpha`` itself
    much of the box stays occupied and every step marches through it). Why 0.05, not lower: a young field's faint fog
    keeps every sample of every ray otherwise; culling it trains a sharper field in more steps of the same minutes
    (benchmarks/results/sample_culling.json)."""
    unbounded_occupancy_alpha: float = 0.1
    """``occupancy_alpha`` of an unbounded scene (contracted space). Why higher than an object's: every ray of a room
    ends on something and crosses its young fog on the way; culling that fog harder trains more steps in the same
    minutes and scores higher on held-out photos (benchmarks/results/sample_culling.json, the fox's rows)."""
    occupancy_alpha_start: float = 0.02
    """The occupancy opacity at the end of the warm-up, raised linearly to ``occupancy_alpha`` over
    ``occupancy_ramp`` steps: an object whose density is still rising is not culled before it can pass the final
    threshold (culled space gets no samples, so no gradient brings it back)."""
    occupancy_ramp: int = 200
    """Steps after the warm-up over which the occupancy opacity rises from ``occupancy_alpha_start``."""
    slow_occupancy_alpha_start: float = 0.005
    """``occupancy_alpha_start`` of a field that starts empty though its photos have silhouettes (the train stage
    decides: `FastModel.cull_slowly`). Below ``init_alpha``, so space no ray has touched is not culled straight after
    the warm-up: a plain or glossy patch the colours cannot place yet fades at first, and culled then it can stay a hole
    that the field explains with walls inside the object (benchmarks/results/closeups_occupancy_ramp.json). Photos
    without silhouettes keep the faster pace: on the shipped sample the slow one marched fewer rays a second for no
    better field (benchmarks/results/sample_occupancy_ramp.json)."""
    slow_occupancy_ramp: int = 200
    """``occupancy_ramp`` of a field that culls slowly. As short as the usual one: the low start does the work, and a
    longer ramp marched fewer rays a second for the same field (benchmarks/results/wall_mounted_undercut.json,
    fox_slow_ramp.json, closeups_occupancy_ramp_parts.json)."""
    occupancy_warmup: int = 16
    """Steps during which every cell counts as occupied."""
    occupancy_every: int = 8
    """Refresh the occupancy grid every this many steps (1/4 of the vertices per refresh after warm-up)."""
    warmup_step_scale: float = 4.0
    """Ray-march step multiplier during the occupancy warm-up: few, coarse samples while nothing is culled."""
    step_ratio: float = 0.5
    """Ray-march step in density-grid voxels (world step = step_ratio * voxel size)."""
    max_samples: int = 1024
    """Cap on candidate samples per ray."""
    cone_angle: float = 0.0
    """> 0: steps grow like t * cone_angle beyond the base step (unbounded scenes, e.g. 1/256)."""
    early_stop_transmittance: float = 1e-4
    """Drop samples behind this transmittance (no-grad pre-pass); 0 disables the pre-pass."""
    color_min_weight: float = 1e-3
    """Evaluate color only on samples with at least this weight (0 = everywhere): each colored sample costs a feature
    read and the color MLP forward and backward, and ones below 1e-3 move a pixel by less than 1/1000."""
    init_alpha: float = 0.01
    """Opacity of one step of the initial (empty) density field."""
    density_activation: Literal["softplus", "trunc_exp"] = "softplus"
    """Density activation; both are overflow-safe."""
    tv_weight: float = 0.0
    """Weight of the total-variation loss on the grids (0 = off)."""
    distortion_weight: float = 0.0
    """Weight of the mip-NeRF 360 distortion loss (0 = off) for an object capture, on ray distance."""
    distortion_from: float = 0.0
    """The share of training (0 to 1) done before the distortion loss starts (0: from the first step). Early, the
    loss draws each ray's weight into one interval before the field has found its finer parts, and at fine grids
    they never come back; started later it still clears fog and floaters (docs/gpu.md)."""
    distortion_until: float = 1.0
    """The share of training (0 to 1) after which the distortion loss stops (1: to the last step, the presets'
    value: stopping it earlier has not measured better, docs/gpu.md)."""
    unbounded_distortion_weight: float = 0.0
    """The same for an unbounded capture, on contracted distance (`recon.nerf.contraction.contracted_distance`)."""
    entropy_weight: float = 0.0
    """Weight of the binary entropy of ray opacity (pushes opacity to 0 or 1; 0 = off)."""
    hull_start_alpha: float = 0.1
    """Opacity a step inside the training photos' visual hull where the field starts from it (`FastModel.start_inside`;
    whether it does: train.hull_start). A plain surface gives the colours nothing to place it by, so where matter
    first grows is where it stays."""
    background: Literal["white", "black", "learned", "random", "sky"] = "white"
    """Background used when render_rays gets none; "learned" always uses the model's own color, "sky" its own
    colour per ray direction (`recon.nerf.fast.SkyColor`; the train stage's sky, `recon.capture.sky`)."""
    grid_lr_scale: float = 10.0
    """Grids train at lr * grid_lr_scale (the MLP at lr)."""
    shrink_step: int = 64
    """Bounded scenes with dense grids: at the first occupancy refresh from this step on, re-sample the grids
    onto the box around the occupied cells (same parameter count, finer voxels where the object is;
    CPU_NERF_NOTES lesson 3). 0 = never."""
    shrink_margin: float = 0.05
    """Margin added around the occupied box before shrinking, as a fraction of the scene box's extent."""
    kernels: Literal["auto", "torch", "triton"] = "auto"
    """On CUDA: "triton" marches, composites and reads the grids in fused Triton kernels (`recon.nerf.kernels`,
    where triton imports), "torch" in torch; "auto" takes the kernels where a GPU check measured them faster
    (`recon.nerf.kernels.MEASURED_FASTER`, docs/gpu.md). A CPU always runs the torch code (and the C marcher)."""


@dataclass
class SurfaceConfig:
    """Options of :class:`SurfaceModel` (pipelines/surface.toml names the preset's values)."""

    aabb: tuple[tuple[float, float, float], tuple[float, float, float]] = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    """Scene box [min_xyz, max_xyz] (world units); the grids span it."""
    sdf_res: int = 128
    """Vertices per side of the finest SDF grid level."""
    sdf_levels: int = 4
    """SDF grid levels, each half the resolution of the next finer one (at least 16 vertices)."""
    sdf_mlp_width: int = 32
    """Hidden width of the SDF MLP on the levels' values (0: the SDF is the prior plus the levels' sum)."""
    level_every: int = 150
    """Coarse to fine: level k (0 = coarsest) joins the SDF after k * level_every steps (0: all from the start)."""
    init_radius: float = 0.8
    """Radius of the initial sphere, as a fraction of half the box's shortest side (when no ``init_planes``)."""
    init_shape: Literal["auto", "visual_hull", "hull", "sphere"] = "auto"
    """The surface training starts from. visual_hull: what no training photo's silhouette (masks or a keyed
    backdrop) calls background, set with ``SurfaceModel.set_initial_sdf`` and saved with the weights; hull: the
    convex hull of the scene's sparse points (the train stage fills ``init_planes``); sphere: a sphere at the box
    centre. auto: the train stage picks the first of these the capture allows (`recon.plans.training.surface_start`);
    the model itself reads auto as hull (its ``init_planes``, else a sphere)."""
    init_planes: tuple[tuple[float, float, float, float], ...] = ()
    """Half-spaces n·x <= d (unit n; rows (nx, ny, nz, d)) whose intersection is the initial surface instead of the
    sphere: the train stage passes the SfM points' convex hull (:func:`recon.nerf.surface.hull_planes`)."""
    init_sharpness: float = 40.0
    """Initial NeuS sharpness s (1/world unit): the opacity ramp is ~1/s wide at the start."""
    feature_res: int = 96
    """Vertices per side of the color feature grid."""
    feature_dim: int = 12
    """Color feature channels."""
    color_model: Literal["mlp_view", "mlp", "direct"] = "mlp"
    """As FastConfig.color_model."""
    sh_degree: int = 2
    """Spherical-harmonics degree of the view direction (color_model "mlp_view")."""
    mlp_width: int = 64
    """Hidden width of the color MLP."""
    mlp_layers: int = 2
    """Hidden layers of the color MLP."""
    step_ratio: float = 1.0
    """Ray-march step in finest SDF voxels."""
    max_samples: int = 1024
    """Cap on candidate samples per ray."""
    occupancy_res: int = 64
    """Occupancy grid cells per side."""
    occupancy_warmup: int = 32
    """Steps during which every cell counts as occupied."""
    occupancy_every: int = 8
    """Refresh the occupancy grid every this many steps."""
    warmup_step_scale: float = 4.0
    """Ray-march step multiplier during the occupancy warm-up (nothing is skipped yet)."""
    band_width: float = 4.0
    """Occupied shell: |f| < 2 occupancy-cell diagonals + band_width / s (NeuS weights there are below
    e^-band_width of their peak)."""
    early_stop_transmittance: float = 1e-3
    """Drop samples behind this transmittance (no-grad pre-pass); 0 disables it."""
    color_min_weight: float = 1e-4
    """Evaluate color only on samples with at least this weight."""
    eikonal_weight: float = 0.1
    """Weight of the Eikonal loss mean (|∇f| - 1)²."""
    curvature_weight: float = 5e-4
    """Weight of the curvature loss mean |Δf| (world units; 0: off)."""
    boundary_weight: float = 0.1
    """Weight of the box-boundary term mean relu(boundary_margin - f) on random points of the box's faces:
    the object must close inside its box. Without it the SDF of the shipped sample ran through the box floor
    under the object (f = -0.14 there): NeuS gives no opacity where a ray enters already inside, so nothing
    held the bottom up, and the mesh's underside was the box floor, 1 % of the diagonal too low. 0: off."""
    init_prior_weight: float = 0.1
    """With a visual hull or ``init_planes``: weight of mean (f - f0)² on the random box points, f0 that initial SDF.
    Where no photo holds the surface (an underside no camera sees) it stays on the start shape instead of drifting
    with the coarse levels the seen parts move (without it an unseen base is carved up into a cave). 0: off."""
    boundary_margin_cells: float = 2.0
    """The SDF at the box's faces is pushed to at least this many finest SDF cells (outside)."""
    boundary_points: int = 1024
    """Random points on the box's faces the boundary term is evaluated on per step."""
    eikonal_samples: int = 4096
    """Ray samples (a random subset) the regularizers are evaluated on per step."""
    eikonal_points: int = 2048
    """Uniform random points in the box the regularizers are evaluated on per step."""
    background: Literal["white", "black", "learned", "random"] = "white"
    """Background used when render_rays gets none."""
    sdf_lr_scale: float = 1.0
    """SDF grids train at lr * sdf_lr_scale (world units per Adam step)."""
    grid_lr_scale: float = 10.0
    """The color grid trains at lr * grid_lr_scale."""
    sharpness_lr_scale: float = 1.0
    """log s trains at lr * sharpness_lr_scale."""


def density_grid_dim(kind: GridKind) -> int:
    """The density grid's ``dim`` (as FastConfig.feature_dim counts it): one channel of a dense grid, else 8
    (vm components, hash levels) that a linear map turns into the density."""
    return 1 if kind == "dense" else 8


HASH_BASE_RES = 16
"""Cells per side of a "hash" grid's coarsest level (instant-ngp's N_min)."""
HASH_FEATURES = 2
"""Features per level of a "hash" grid (instant-ngp's F)."""


def hash_level_layout(levels: int, base_res: int, max_res: int, log2_table: int) -> tuple[list[int], list[int], list[bool]]:
    """Per level: vertices per side, table rows, and whether the level is hashed (else dense-indexed).

    Resolutions grow geometrically from base_res to max_res cells per side (instant-ngp eq. 2); a level
    whose (res + 1)**3 vertices fit in 2**log2_table rows is stored densely, without collisions.
    """
    growth = math.exp((math.log(max_res) - math.log(base_res)) / max(levels - 1, 1))
    verts, rows, hashed = [], [], []
    for lv in range(levels):
        n = int(math.floor(base_res * growth**lv)) + 1
        dense = n**3 <= 2**log2_table
        verts.append(n)
        rows.append(n**3 if dense else 2**log2_table)
        hashed.append(not dense)
    return verts, rows, hashed

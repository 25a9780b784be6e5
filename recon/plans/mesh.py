"""What the mesh stage decides, and why: `plan_mesh` makes every choice before any work is done.

From the options (`MeshConfig`), the normalized scene and the trained field's metadata it picks the box to mesh
and the ground to cut, the grid, the iso opacity, the hollow fill, the photos the mesh is checked and coloured
against and the size of their depth renders, the tolerances in scene units and the held-out photos; each with the
reason the stage prints or reports. The stage then only loads, computes and writes. Pure: no field is evaluated and
no photo is read, so a plan can be made (and tested) without either.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from recon.camera import pixel_footprint
from recon.capture.normalization import box_corners
from recon.capture.region import support_kind
from recon.capture.scene import Frame, Scene, spread_evenly
from recon.config import AUTO_TEXTURE_SIDES, MeshConfig, parse_region
from recon.errors import ReconError
from recon.geometry.extract import choose_resolution, surface_cell
from recon.meshing.extraction import ISO_OPACITY

MASKED_ISO_OPACITY = 0.25
"""ISO_OPACITY with masks: the masked-out pixels trained the space around the object empty, so a lower level cannot
grow into the background; it closes the holes a soft, undertrained surface leaves (see MeshConfig.iso_opacity)."""
CPU_BAKE_VIEWS = {"fast": 24, "classic": 6}
"""mesh.cpu_bake_views=0 per model: the classic NeRF renders about a hundred times slower than the grid models."""
GPU_BAKE_VIEWS = 48
"""mesh.gpu_bake_views=0: on a GPU the depth maps are quick, and what grows with the photos is the CPU's work of
rasterizing the mesh into each and baking its pixels: past 48 photos that work doubles for a held-out PSNR that
barely moves (benchmarks/results/bake_views.json)."""
CPU_DEPTH_SIDE = {"fast": 200, "classic": 64}
"""mesh.cpu_depth_side=0 per model."""
HIDDEN_TOL_CELLS = 1.0
"""Depth tolerance of the hidden-face test in `surface_cell` units (the field's voxel for grid models). The
result is insensitive to it near one voxel: the inner walls lie several voxels behind the visible surface."""
POINT_TOL_CELLS = 1.0
"""The mesh passes through an SfM point (coherence's point agreement) when within this many surface cells of it."""
GROUND_LAYER_CELLS = 2.0
"""How thick a table top (or wall) the field makes, in surface cells: about a voxel. Without masks the faces this
close above the ground are cut with it (mesh.ground_margin_cells=-1); with or without, the SfM points and pixels this
close are the ground's, not the object's, in the coherence check (a table's points scatter about its plane)."""
TEXTURE_COVERAGE = 0.5
"""The share of a texture's texels on the surface once xatlas has packed the charts with gaps between them
(`recon.geometry.texture.CHARTS_PER_ATLAS`): about half on a marching-cubes mesh (each mesh's share is its
mesh_report.json → textured → coverage)."""
HELD_OUT_VIEWS = 8
"""The textured and vertex-colored meshes are compared in at most this many held-out views (spread evenly)."""


def training_focal(frame: Frame, max_side: int) -> float:
    """Horizontal focal length (pixels) of a frame at the training resolution (photos downscaled to max_side)."""
    scale = min(1.0, max_side / max(frame.w, frame.h)) if max_side else 1.0
    return float(frame.fl_x * scale)


def scene_footprint(frames: list[Frame], aabb: np.ndarray, max_side: int) -> tuple[float, str]:
    """`pixel_footprint` of the frames at training size, and how it was measured."""
    centres = np.stack([f.c2w[:3, 3] for f in frames])
    focals = np.array([training_focal(f, max_side) for f in frames])
    fp, dist = pixel_footprint(aabb, centres, focals)
    return fp, f" (median camera distance {dist:.3g}, focal {np.median(focals):.1f} px at training size {max_side})"


def texture_side(cfg: MeshConfig, area: float, footprint: float) -> tuple[int, str]:
    """The textured mesh's texture side and why: mesh.texture_size when set, else the smallest of AUTO_TEXTURE_SIDES
    that gives every photo pixel on the surface a texel. area: the mesh's surface (scene units²); footprint: what a
    photo pixel covers there (`MeshPlan.photo_footprint`). A texture finer than the photos it is baked from holds
    nothing they do not show, and each step up costs four times the bake."""
    if cfg.texture_size:
        return int(cfg.texture_size), f"texture {cfg.texture_size}² (mesh.texture_size)"
    pixels = area / max(footprint, 1e-12) ** 2
    needed = math.sqrt(pixels / TEXTURE_COVERAGE)
    side = next((s for s in AUTO_TEXTURE_SIDES if s >= needed), AUTO_TEXTURE_SIDES[-1])
    return side, (f"texture {side}²: the photos put about {pixels:,.0f} pixels on the mesh's {area:.3g} units² "
                  f"({footprint:.3g} units a pixel), and about {TEXTURE_COVERAGE:.0%} of a texture's texels land on the "
                  f"surface, so {side}² gives each pixel a texel" + (
                      "" if side >= needed else f" as near as the largest automatic size allows (wants {needed:.0f}²)")
                  + "; mesh.texture_size sets it")


def mesh_region(scene: Scene, aabb: np.ndarray, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray | None, str]:
    """The box to mesh (scene frame, inside aabb), the ground plane to cut (or None) and why.

    mesh.region auto: normalize's object region (what the cameras look at) grown by mesh.region_margin, down to
    the ground; all: the whole scene box, nothing cut; a source-frame box: its bounding box in the scene frame.
    """
    choice = parse_region(cfg.region)
    aabb = np.asarray(aabb, np.float64)
    if choice == "all":
        return aabb, None, "the whole scene box (mesh.region=all)"
    ground = None if cfg.keep_ground or scene.ground is None else np.asarray(scene.ground, np.float64)
    ground_why = ""
    if scene.ground is not None:
        plane = "ground plane" if support_kind(scene.ground) == "ground" else "wall behind the object"
        ground_why = (f"; the {plane} is cut away (--set mesh.keep_ground=true keeps it)" if ground is not None
                      else f"; the {plane} is kept (mesh.keep_ground)")
    if choice == "auto":
        if scene.region is None:
            return aabb, ground, "the whole scene box (no object region was found)" + ground_why
        region = np.asarray(scene.region, np.float64)
        size = region[1] - region[0]
        box = region + np.stack([-size, size]) * cfg.region_margin
        why = (f"the object the cameras look at (normalize's object region, +{cfg.region_margin:.0%}; "
               "--set mesh.region=all meshes everything)")
    else:
        corners = box_corners(np.asarray(choice, np.float64))
        T = scene.world_from_source
        mapped = corners @ T[:3, :3].T + T[:3, 3]
        box = np.stack([mapped.min(axis=0), mapped.max(axis=0)])
        why = f"the box {cfg.region} given in the source frame (mesh.region)"
    box = np.stack([np.maximum(box[0], aabb[0]), np.minimum(box[1], aabb[1])])
    if np.any(box[1] <= box[0]):
        raise ReconError(
            f"The mesh region ({cfg.region}) does not overlap the scene box {np.round(aabb, 3).tolist()}; give a box "
            f"inside the scene, or --set mesh.region=all."
        )
    return box, ground, why + ground_why


def capture_iso_opacity(cfg: MeshConfig, masked: bool) -> tuple[float, str]:
    """mesh.iso_opacity for this capture and why it differs from the setting ("" when it does not): as set, else
    MASKED_ISO_OPACITY with masks (they trained the background empty), else ISO_OPACITY (`extract_mesh`'s for 0)."""
    if cfg.iso_opacity or cfg.iso or not masked:
        return cfg.iso_opacity, ""
    return MASKED_ISO_OPACITY, (f"iso-level: one cell {MASKED_ISO_OPACITY:.0%} opaque (not {ISO_OPACITY:.0%}): the masks "
                                "trained the background empty, so a lower level closes holes without growing into it "
                                "(mesh.iso_opacity)")


def capture_ground_margin(cfg: MeshConfig, masked: bool, ground: np.ndarray | None) -> tuple[float, str]:
    """mesh.ground_margin_cells for this capture and why it differs from the unmasked default ("" when it does not or
    no ``ground`` is cut): as set, else 0 with masks (they trained the table empty: what the field holds at the plane
    is the object's base, and a margin would cut it off), else GROUND_LAYER_CELLS (the field's table top)."""
    if cfg.ground_margin_cells >= 0:
        return cfg.ground_margin_cells, ""
    if not masked:
        return GROUND_LAYER_CELLS, ""
    if ground is None:
        return 0.0, ""
    plane = "table" if support_kind(ground) == "ground" else "wall"
    return 0.0, (f"{plane} cut at its plane, not {GROUND_LAYER_CELLS:g} cells above it: the masks trained the {plane} "
                 f"empty, so what touches it is the object's (mesh.ground_margin_cells)")


def _whole_unbounded_box(scene: Scene, cfg: MeshConfig, bounded: bool) -> bool:
    """The mesh region is the whole box of an unbounded scene (no object region, none given): no object's inside."""
    choice = parse_region(cfg.region)
    return not bounded and (choice == "all" or (choice == "auto" and scene.region is None))


def hollow_fill_applies(scene: Scene, cfg: MeshConfig, bounded: bool) -> tuple[bool, str]:
    """Whether mesh.fill_cavities applies, and why: it fills what an object's material encloses, so it runs when
    the mesh region is an object's (an object capture, normalize's object region, or a box given) and not on the
    whole box of an unbounded scene, whose walls, sky blobs and gaps enclose no object's inside (filling them
    there joins background into the mesh and splits its largest piece)."""
    if not cfg.fill_cavities:
        return False, ""
    if _whole_unbounded_box(scene, cfg, bounded):
        return False, ("hollow fill off: the mesh region is the whole scene box of an unbounded scene, not an object "
                       "(give mesh.region a box around the object to fill its hollow)")
    return True, ""


def closes_solid(scene: Scene, cfg: MeshConfig, bounded: bool, ground: np.ndarray | None) -> tuple[bool, str]:
    """Whether mesh.closed applies, and why: it closes an object's mesh (an object region or a box given), not the
    whole box of an unbounded scene, which holds no object to close."""
    if not cfg.closed:
        return False, ""
    if _whole_unbounded_box(scene, cfg, bounded):
        return False, ("closed: not done, the mesh region is the whole scene box of an unbounded scene, not an object "
                       "(give mesh.region a box around the object to close it)")
    base = ("filled down to the " + support_kind(ground) + " it stands on and capped flat there"
            if ground is not None else "filled")
    return True, (f"closed: the mesh is a watertight solid (mesh.closed), {base}, closed at the region's box; no face "
                  f"is dropped for being unseen or outside a mask, so the parts no photo saw are guessed flat")


SPLIT_AREA = 0.95
"""A density mesh whose largest piece holds less of its area than this is in pieces a user sees: `pieces_advice`."""


def pieces_advice(largest_area_fraction: float, zero_set: bool, capture: str | None) -> str:
    """What to run for a mesh in one piece when an object's density mesh is in several ("" when it is not): the
    surface preset meshes an object as one closed surface, without the holes a density mesh has where few photos
    agree (a real capture's soft fur, a plain patch)."""
    if zero_set or capture != "object" or largest_area_fraction >= SPLIT_AREA:
        return ""
    return (f"{1 - largest_area_fraction:.0%} of the mesh's area lies outside its largest piece: --preset surface meshes "
            "an object as one closed surface, without the holes a density mesh has where few photos agree "
            "(docs/surface.md)")


@dataclass(frozen=True)
class MeshPlan:
    """Every decision of the mesh stage, in the order it makes them; the ``*_why`` fields say why (printed or
    reported; "" where the setting is used as given)."""

    aabb: np.ndarray
    """The field's scene box (2, 3)."""
    bounded: bool
    """The field is bounded by that box (depth is rendered inside it), not an unbounded scene's."""
    unbounded_why: str
    region: np.ndarray
    """The box to mesh (2, 3), scene frame, inside aabb."""
    ground: np.ndarray | None
    """The plane (nx, ny, nz, d) cut away with what lies below it, or None."""
    region_why: str
    shape: tuple[int, int, int]
    """Grid nodes per axis over the region."""
    footprint: float | None
    """The training pixel's size at the cameras' distance (None with mesh.resolution given)."""
    photo_footprint: float
    """`scene_footprint`: what one pixel of the photos (at training size, as the mesh is colored from them) covers at
    the cameras' median distance, scene units; sets the automatic texture size (`texture_side`)."""
    resolution_why: str
    zero_set: bool
    """A surface field: its signed distance's zero set is the mesh (closed, no iso choice, no hidden faces)."""
    extraction: MeshConfig
    """The options the extraction runs with: mesh.* with the iso opacity and hollow fill below."""
    iso_why: str
    fill_why: str
    closed: bool
    """mesh.closed applies: the extraction closes the solid on its support (`support_plane`) and at the box, and
    no face is dropped afterwards (hidden, masked, ground cut)."""
    closed_why: str
    cell: float
    """`surface_cell`: the unit of the tolerances below (scene units)."""
    hidden_tolerance: float | None
    """Depth tolerance of the hidden-face test; None: hidden faces stay (mesh.drop_hidden off, or a zero set)."""
    ground_margin: float
    """Faces this close above the ground are cut with it (scene units)."""
    ground_margin_why: str
    ground_layer: float
    """SfM points and pixels this close above the ground are the ground's in the coherence check (scene units)."""
    point_tolerance: float
    """The mesh passes through an SfM point this close to it (coherence)."""
    masked: bool
    """Every training photo has a mask: vertices outside them go, and the masks are the coherence check's object."""
    unsure_frames: list[Frame]
    """The training photos whose unsure automatic masks (normalize's masks_unsure/) crop the mesh as masks would
    (mesh.unsure_masks); none when the photos trained masked, the mesh is closed or normalize made no such masks."""
    unsure_why: str
    max_side: int
    """The photos' longest side at training size, as the views are loaded."""
    uses_views: bool
    """Photos are needed: to color from, for the hidden-face test, for the masks or for a closed mesh's inside."""
    view_frames: list[Frame]
    """The training photos the mesh is checked (hidden faces, masks, coherence) and colored against."""
    depth_side: int | None
    """Their depth renders' longest side (None: at training size)."""
    views_why: str
    texture: bool
    """A textured copy is made (mesh.texture_faces > 0)."""
    held_out_frames: list[Frame]
    """The held-out photos the textured and vertex-colored meshes are compared in (none without a textured mesh)."""
    held_out_why: str

    @property
    def notes(self) -> list[str]:
        """The decisions' reasons the stage prints before it starts, in order."""
        return [line for line in (self.unbounded_why, f"mesh region: {self.region_why}",
                                  f"resolution: {self.resolution_why}", self.ground_margin_why, self.iso_why,
                                  self.fill_why, self.closed_why, self.unsure_why) if line]

    @property
    def support_plane(self) -> np.ndarray | None:
        """The plane (4,) a closed mesh is capped on: the ground raised by the margin its faces are cut within."""
        if self.ground is None:
            return None
        return np.append(self.ground[:3], self.ground[3] + self.ground_margin)


def plan_mesh(cfg: MeshConfig, scene: Scene, meta: dict[str, Any], *, on_cpu: bool, voxel: float,
              unsure_masks: bool = False) -> MeshPlan:
    """The mesh stage's decisions for this scene and field. meta: the field's metadata (`load_field`: kind, aabb,
    bounded, max_side); on_cpu: the field runs on the CPU (fewer, smaller depth renders); voxel: the field's own
    voxel (`field_voxel`), the finest layer it can make opaque; unsure_masks: normalize cut the object out of the
    photos but was not sure enough of the cuts to train with them (its masks_unsure/)."""
    aabb = np.asarray(meta.get("aabb", scene.aabb), np.float64)
    bounded = bool(meta.get("bounded", True))
    max_side = int(meta.get("max_side", 400))
    train_frames = scene.split("train") or scene.frames

    region, ground, region_why = mesh_region(scene, aabb, cfg)
    photo_footprint, fp_why = scene_footprint(train_frames, aabb, max_side)
    footprint = None if cfg.resolution > 0 else photo_footprint
    shape, resolution_why = choose_resolution(region, cfg, footprint, fp_why)

    zero_set = meta.get("kind") == "surface"
    masked = bool(train_frames) and all(f.mask_path for f in train_frames)
    margin_cells, margin_why = capture_ground_margin(cfg, masked, ground)
    extraction, iso_why, fill_why = cfg, "", ""
    if not zero_set:
        opacity, iso_why = capture_iso_opacity(cfg, masked)
        fill, fill_why = hollow_fill_applies(scene, cfg, bounded)
        extraction = dataclasses.replace(cfg, iso_opacity=opacity or ISO_OPACITY,
                                         fill_cavities=cfg.fill_cavities if fill else 0)

    cell = surface_cell(region, shape, voxel)[0]
    closed, closed_why = closes_solid(scene, cfg, bounded, ground)
    drop_hidden = cfg.drop_hidden and not zero_set and not closed

    kind = "classic" if meta.get("kind") == "classic" else "fast"
    limit = (cfg.cpu_bake_views or CPU_BAKE_VIEWS[kind]) if on_cpu else (cfg.gpu_bake_views or GPU_BAKE_VIEWS)
    depth_side = (cfg.cpu_depth_side or CPU_DEPTH_SIDE[kind]) if on_cpu else None
    uses_views = cfg.color == "photos" or drop_hidden or masked or closed
    view_frames, views_why = [], ""
    if uses_views:
        view_frames = spread_evenly(train_frames, limit)
        views_why = f"{len(view_frames)} of {len(train_frames)} training views"
        if len(view_frames) < len(train_frames):
            views_why += (f" (spread evenly; at most {limit} on the CPU for the {meta.get('kind', kind)} model, "
                          "each costs a depth render)" if on_cpu else
                          f" (spread evenly; at most {limit} on a GPU: each costs the CPU a rasterization and a bake)")
        if depth_side:
            views_why += f", depth rendered at ≤ {depth_side} px"

    unsure_frames, unsure_why = [], ""
    if unsure_masks and cfg.unsure_masks == "auto" and not masked and not closed:
        unsure_frames = spread_evenly(train_frames, limit)
        unsure_why = (f"unsure masks: the mesh keeps what at least {cfg.mask_keep_fraction:.0%} of "
                      f"{len(unsure_frames)} photos call object in the automatic masks that were not sure enough to "
                      "train the object alone (masks_unsure/): the table and room the field holds around the object "
                      "go, a part a few of them miss stays (mesh.unsure_masks=off keeps all the mesh region holds)")

    texture = cfg.texture_faces > 0
    held_out = scene.split("test") if texture else []
    held_out_frames = spread_evenly(held_out, HELD_OUT_VIEWS)
    held_out_why = (f"{len(held_out_frames)} of {len(held_out)}"
                    + (", spread evenly" if len(held_out_frames) < len(held_out) else "")) if held_out else ""
    return MeshPlan(
        aabb=aabb, bounded=bounded,
        unbounded_why="" if bounded else "unbounded scene: the mesh covers the scene box only (the background is not meshed)",
        region=region, ground=ground, region_why=region_why,
        shape=shape, footprint=footprint, photo_footprint=photo_footprint, resolution_why=resolution_why,
        zero_set=zero_set, extraction=extraction, iso_why=iso_why, fill_why=fill_why,
        closed=closed, closed_why=closed_why,
        cell=cell, hidden_tolerance=HIDDEN_TOL_CELLS * cell if drop_hidden else None,
        ground_margin=margin_cells * cell, ground_margin_why=margin_why, ground_layer=GROUND_LAYER_CELLS * cell,
        point_tolerance=POINT_TOL_CELLS * cell,
        masked=masked, unsure_frames=unsure_frames, unsure_why=unsure_why, max_side=max_side, uses_views=uses_views,
        view_frames=view_frames, depth_side=depth_side,
        views_why=views_why, texture=texture, held_out_frames=held_out_frames, held_out_why=held_out_why,
    )

"""mesh stage: the trained field → a cleaned, colored triangle mesh in glTF/OBJ/PLY, with a report.

`plan_mesh` (recon.plans.mesh) makes every decision first: the box and the ground to cut, the grid, the iso
opacity, the hollow fill, the photos to check and color against. `run` prints its reasons, then does the work
with the library, loading and writing in between:
1. the photos as the field saw them and the field's depth in each (`field_views`, `render_depths`);
2. `extract_mesh` (a density field) or `extract_zero_set` (a surface field): the grid → marching cubes;
3. `clean_mesh`: crop, cut the ground, drop floaters, the faces no photo sees (`see_with_views`) and what the masks
   call background (`inside_masks`), smooth, decimate; then the `coherence` checks;
4. colors baked from the photos against the mesh's own z-buffer (`mesh_depths`, `bake_colors`) or the field's;
5. `export_mesh` in the chosen frame (`export_transform`), two previews, `mesh_report.json`;
6. with mesh.texture_faces > 0, a decimated, UV-unwrapped copy with a baked texture (`texture_mesh`), compared
   with the vertex-colored mesh in the held-out photos (`compare_in_views`). Its decimation and unwrap (xatlas, in a
   process of its own) start as soon as the mesh is cleaned and run beside steps 3–5, which do not need them.
"""
from __future__ import annotations

import resource
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
import trimesh

from recon.atomic import write_json_atomic
from recon.capture.region import support_kind
from recon.capture.scene import UNSURE_MASK_FOLDER, Scene, load_scene
from recon.config import MeshConfig
from recon.errors import ReconError
from recon.evaluation.views import View, load_views
from recon.field import load_field
from recon.geometry.clean import clean_mesh
from recon.geometry.color import colors_from_field
from recon.geometry.export import export_mesh, export_record, export_textured_mesh, export_transform
from recon.geometry.preview import preview_textured, write_mesh_previews
from recon.geometry.texture import UnwrappedMesh, unwrap_mesh
from recon.meshing.extraction import extract_mesh, extract_zero_set, field_voxel
from recon.meshing.photos import (
    bake_colors,
    coherence,
    compare_in_views,
    describe_coherence,
    field_views,
    hidden_from_views,
    inside_masks,
    inside_photo_masks,
    mesh_depths,
    render_depths,
    see_with_views,
    texture_mesh,
)
from recon.plans.mesh import MeshPlan, pieces_advice, plan_mesh, texture_side
from recon.runner.pipeline import StageContext

REPORT_FILE = "mesh_report.json"
MESH_STEM = "mesh"
TEXTURED_STEM = "mesh_textured"
TEXTURED_OUTPUTS = ("preview_textured.png", "texture_compare.png")
"""The textured mesh's previews (besides its TEXTURED_STEM.* files): removed with them when texturing fails."""


def run(ctx: StageContext) -> dict:
    from recon.nerf.device import select_device

    cfg: MeshConfig = ctx.config
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    try:
        device = select_device(ctx.run_config.train.device)  # the device training used, as the user chose it
    except ValueError as exc:
        raise ReconError(f"train.device={ctx.run_config.train.device}: {exc}") from None
    scene = load_scene(ctx.inputs["normalize"], ctx.source)
    model, meta = load_field(ctx.inputs["train"], device)
    unsure_folder = ctx.inputs["normalize"] / UNSURE_MASK_FOLDER
    plan = plan_mesh(cfg, scene, meta, on_cpu=device.type == "cpu", voxel=field_voxel(model),
                     unsure_masks=unsure_folder.is_dir())
    for note in plan.notes:
        ctx.report.info(note)
    background = np.asarray(meta.get("background", [1.0, 1.0, 1.0]), np.float32)

    views: list[View] = []
    depths: list[np.ndarray] = []
    opacities: list[np.ndarray] = []
    if plan.uses_views:
        t = time.perf_counter()
        views = field_views(scene, plan.view_frames, plan.max_side, meta, ctx.report)
        box = torch.tensor(plan.aabb, dtype=torch.float32, device=device) if plan.bounded else None
        depths = render_depths(model, views, box, background, plan.depth_side, ctx.report, opacities)
        timings["depth_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    region_t = torch.tensor(plan.region, dtype=torch.float32, device=device)
    if plan.zero_set:
        vertices, faces, extraction = extract_zero_set(model, region_t, plan.shape, plan.extraction, ctx.report,
                                                       closed=plan.closed, support=plan.support_plane)
    else:
        hidden = hidden_from_views(views, depths, opacities, plan.region, plan.cell) if plan.closed and views else None
        vertices, faces, extraction = extract_mesh(model, region_t, plan.shape, plan.extraction, ctx.report,
                                                   closed=plan.closed, support=plan.support_plane, hidden=hidden,
                                                   keep=inside_masks(views, cfg.mask_keep_fraction)
                                                   if plan.closed and plan.masked else None)
    timings["extract_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    vertices, faces, clean = clean_mesh(
        vertices, faces, plan.region,
        min_component_fraction=cfg.min_component_fraction,
        smooth_iters=cfg.smooth_iters,
        target_faces=cfg.target_faces or None,
        seen_fn=see_with_views(views, depths, plan.hidden_tolerance, device) if plan.hidden_tolerance is not None else None,
        ground=None if plan.closed else plan.ground,  # a closed solid was capped there already
        ground_margin=plan.ground_margin,
        keep_fn=(inside_masks(views, cfg.mask_keep_fraction) if plan.masked and not plan.closed else
                 inside_photo_masks(plan.unsure_frames, unsure_folder, cfg.mask_keep_fraction) if plan.unsure_frames
                 else None),
        closed=plan.closed,
    )
    timings["clean_s"] = round(time.perf_counter() - t, 3)
    if len(faces) == 0:
        raise ReconError("Every piece of the extracted surface was removed while cleaning; lower mesh.min_component_fraction.")
    _say_cleaning(ctx, clean, plan, len(views))
    side, side_why = texture_side(cfg, clean["output"]["area"], plan.photo_footprint)
    unwrapping = None
    if plan.texture:
        ctx.report.info(f"textured mesh: {side_why}")
        unwrapping = _start_unwrap(vertices, faces, cfg.texture_faces, side)

    t = time.perf_counter()
    observed = ([np.zeros((0, 3)) if p is None else p for p in map(scene.observed_points, plan.view_frames)]
                if scene.point_visibility else None)
    coherent = coherence(vertices, faces, views, depths, plan.region, plan.ground, plan.ground_layer, plan.masked,
                         opacities or None, observed, plan.point_tolerance)
    timings["coherence_s"] = round(time.perf_counter() - t, 3)
    ctx.report.info(describe_coherence(coherent))
    advice = pieces_advice(coherent["largest_piece"]["largest_area_fraction"], plan.zero_set, scene.capture)
    if advice:
        ctx.report.info(advice)

    t = time.perf_counter()
    normals = np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, np.float32)
    surface_depths: list[np.ndarray] = []
    if cfg.color == "photos":
        surface_depths = mesh_depths(vertices, faces, views)
        colors, color_info = bake_colors(model, views, surface_depths, vertices, normals)
        color_info["source"] = "photos"
        color_info["note"] = (f"baked from {plan.views_why}, each photo's pixel taken where no other part of the mesh "
                              f"hides the vertex; {color_info['unseen_from_field']:,} unseen vertices colored by the field")
    else:
        colors = colors_from_field(model.radiance, vertices, normals, device=device)
        color_info = {"source": "field", "note": "queried from the field, viewed head-on (d = -normal)"}
    ctx.report.info(f"colors: {color_info['note']}")
    timings["color_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    transform, frame_why = export_transform(vertices, cfg.frame, scene.source_from_world, cfg.real_size)
    paths = export_mesh(vertices, faces, colors, ctx.out, stem=MESH_STEM, transform=transform)
    previews = write_mesh_previews(vertices, faces, colors, ctx.out)
    timings["export_s"] = round(time.perf_counter() - t, 3)

    textured_info: dict[str, Any] | None = None
    if plan.texture:
        try:
            textured_info, texture_previews = _textured(ctx, cfg, plan, scene, model, views, surface_depths,
                                                        (vertices, faces, colors), transform, background, timings,
                                                        side, unwrapping)
            textured_info["texture_size_reason"] = side_why
            previews += texture_previews
        except Exception as exc:  # an optional output: the vertex-colored mesh above is the stage's result
            textured_info = textured_failed(exc, cfg, ctx, side)
    timings["total_s"] = round(time.perf_counter() - t_all, 3)

    out = clean["output"]
    removed = clean["components"]["removed"] + clean.get("crumbs", {}).get("removed", 0)
    write_json_atomic(ctx.out / REPORT_FILE, {
        "vertices": out["vertices"],
        "faces": out["faces"],
        "watertight": out["watertight"],
        "components_removed": removed,
        "component_rule": clean["components"]["rule"],
        "bbox_scene": out["bbox"],
        "resolution": {"grid": list(plan.shape), "reason": plan.resolution_why, "pixel_footprint": plan.footprint,
                       "photo_footprint": plan.photo_footprint},
        "region": {"box": plan.region.tolist(), "reason": plan.region_why,
                   "ground": None if plan.ground is None else plan.ground.tolist()},
        "extraction": extraction,
        "iso": extraction["iso"],
        "iso_reason": extraction["iso_reason"],
        "clean": clean,
        "masks": ("the photos' masks" if plan.masked else
                  f"unsure automatic masks ({UNSURE_MASK_FOLDER}/ of {len(plan.unsure_frames)} photos)"
                  if plan.unsure_frames else None),
        "coherence": coherent,
        "colors": color_info,
        "export": export_record(cfg.frame, frame_why, transform, paths),
        "textured": textured_info,
        "previews": previews,
        "device": str(device),
        "timings_s": timings,
        "peak_rss_mb": round(peak_rss_mb(), 1),
    })
    return {
        "headline": (
            f"{out['vertices']:,} vertices, {out['faces']:,} faces, "
            f"{'watertight' if out['watertight'] else 'not watertight'}, {removed} floating piece(s) removed"
        ),
        "vertices": out["vertices"],
        "faces": out["faces"],
        "watertight": out["watertight"],
        "components_removed": removed,
        "grid": list(plan.shape),
        "iso": round(extraction["iso"], 4),
        "colors": color_info["note"],
        **({"textured": _textured_summary(textured_info)} if textured_info else {}),
    }


def _say_cleaning(ctx: StageContext, clean: dict, plan: MeshPlan, n_views: int) -> None:
    """What cleaning removed, a line per step that ran."""
    components = clean["components"]
    ctx.report.info(f"cleaning: {components['rule']}: {components['removed']} of {components['components']} pieces removed")
    if "masked" in clean and plan.unsure_frames:
        ctx.report.info(f"unsure masks: {clean['masked']['faces_removed']:,} faces that under "
                        f"{ctx.config.mask_keep_fraction:.0%} of {len(plan.unsure_frames)} photos' automatic masks "
                        "call object removed")
    elif "masked" in clean:
        ctx.report.info(f"masks: {clean['masked']['faces_removed']:,} faces outside the object masks removed ({n_views} photos)")
    if "ground_cut" in clean:
        kind = support_kind(plan.ground)
        where = "on or below the ground plane" if kind == "ground" else "on or behind the wall"
        ctx.report.info(f"{kind}: {clean['ground_cut']['faces_removed']:,} faces {where} cut away")
    if "hidden" in clean:
        ctx.report.info(f"hidden faces: {clean['hidden']['removed_faces']:,} faces that no photo sees removed (inner walls "
                        f"of the field; {n_views} views, depth tolerance {plan.hidden_tolerance:.3g} units)")
    if clean.get("crumbs", {}).get("removed"):
        ctx.report.info(f"crumbs: {clean['crumbs']['removed']} of {clean['crumbs']['components']} pieces left by the "
                        "hidden faces' removal or the decimation removed, by the same rule")
    if clean.get("decimated", {}).get("closed_tries") == 0:
        decimated = clean["decimated"]
        ctx.report.warn(f"decimation: every try pinched the closed mesh (two sheets on one edge), so it is kept at "
                        f"{decimated['faces']:,} faces, watertight (mesh.target_faces={decimated['target_faces']:,} "
                        "not reached)")


def _start_unwrap(vertices: np.ndarray, faces: np.ndarray, target_faces: int, side: int) -> Future[UnwrappedMesh]:
    """The textured copy's `unwrap_mesh`, started in a thread: xatlas runs in a process of its own (seconds on a
    150k-face mesh), so the stage's next steps go on beside it; its error, if any, comes with the result."""
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="recon-unwrap")
    try:
        # copies: the steps beside it must stay free to work on the mesh's arrays
        return pool.submit(unwrap_mesh, vertices.copy(), faces.copy(), target_faces, side)
    finally:
        pool.shutdown(wait=False)  # the thread ends with its one task


def _textured(
    ctx: StageContext, cfg: MeshConfig, plan: MeshPlan, scene: Scene, model: torch.nn.Module, views: list[View],
    depths: list[np.ndarray], mesh: tuple[np.ndarray, np.ndarray, np.ndarray], transform: np.ndarray | None,
    background: np.ndarray, timings: dict[str, float], side: int, unwrapping: Future[UnwrappedMesh] | None = None,
) -> tuple[dict, list[str]]:
    """`texture_mesh`, its files, preview, and `compare_in_views` in the held-out views: the report's "textured"."""
    from PIL import Image

    t = time.perf_counter()
    unwrapped = None
    if unwrapping is not None:
        with ctx.report.task("texture: decimate, unwrap (started after cleaning)", total=None):
            unwrapped = unwrapping.result()
    waited = round(time.perf_counter() - t, 3)
    textured = texture_mesh(model, cfg, views, depths, mesh[0], mesh[1], ctx.report, side, unwrapped)
    if unwrapped is not None:
        textured.info["timings_s"]["unwrap_wait_s"] = waited  # what the unwrap beside steps 3-5 still cost the stage
    paths = export_textured_mesh(textured.vertices, textured.faces, textured.uv, textured.texture, ctx.out,
                                 stem=TEXTURED_STEM, normals=textured.normals, transform=transform)
    Image.fromarray(np.round(preview_textured(textured) * 255).astype(np.uint8)).save(ctx.out / "preview_textured.png")
    timings["texture_s"] = round(time.perf_counter() - t, 3)
    info: dict[str, Any] = {**textured.info, "files": {k: p.name for k, p in paths.items()}}
    previews = ["preview_textured.png"]
    ctx.report.info(
        f"textured mesh: {info['faces']:,} faces ("
        + (f"decimated from {info['faces_in']:,}" if info["faces"] < info["faces_in"] else
           f"the mesh's own, under mesh.texture_faces={ctx.config.texture_faces:,}") + f"), {side}² texture, "
        f"{info['coverage']:.0%} of its texels on the surface, baked like the vertex colors"
        + (f" ({info['unseen_from_field']:,} texels no photo sees colored by the field)" if "unseen_from_field" in info else "")
    )
    if not plan.held_out_frames:
        info["held_out"] = None
        ctx.report.info("textured mesh: no held-out photos in the scene's split, so no PSNR against photos")
        return info, previews
    t = time.perf_counter()
    test_views = load_views(scene, plan.held_out_frames, plan.max_side, ctx.report, "held-out photos")
    light_colors = None
    if cfg.color == "photos":  # the same light mesh with vertex colors: what the texture adds at its face count
        light_colors = bake_colors(model, views, depths, textured.vertices, textured.normals)[0]
    info["held_out"], strips = compare_in_views(test_views, background, mesh, textured, ctx.report, light_colors)
    Image.fromarray(np.round(np.clip(strips[0], 0, 1) * 255).astype(np.uint8)).save(ctx.out / "texture_compare.png")
    previews.append("texture_compare.png")
    timings["held_out_s"] = round(time.perf_counter() - t, 3)
    h = info["held_out"]
    ctx.report.info(
        f"held-out photos ({plan.held_out_why}): "
        f"PSNR vertex colors {h['psnr_vertex_colors']:.2f} dB, textured {h['psnr_textured']:.2f} dB "
        f"(where both cover: {h['psnr_vertex_colors_covered']:.2f} / {h['psnr_textured_covered']:.2f} dB)"
        + (f"; the light mesh with vertex colors instead: {h['psnr_light_vertex_colors']:.2f} dB "
           f"({h['psnr_light_vertex_colors_covered']:.2f} dB where both cover)" if "psnr_light_vertex_colors" in h else "")
    )
    return info, previews


def textured_failed(exc: Exception, cfg: MeshConfig, ctx: StageContext, side: int) -> dict[str, Any]:
    """The report's "textured" when unwrapping, baking or exporting the textured mesh failed: the error and what
    to do, said in one warning line; its partial files are removed so no half-written textured mesh is left.

    Why: the textured mesh is optional; the vertex-colored mesh (mesh.glb) is already written and is delivered."""
    for path in [*ctx.out.glob(f"{TEXTURED_STEM}.*"), *(ctx.out / name for name in TEXTURED_OUTPUTS)]:
        path.unlink(missing_ok=True)
    error = f"{type(exc).__name__}: {exc}"
    todo = (f"the vertex-colored {MESH_STEM}.glb is complete; for a textured mesh rerun the mesh stage with a larger "
            f"--set mesh.texture_size (now {side}) or fewer --set mesh.texture_faces (now {cfg.texture_faces}), "
            f"or --set mesh.texture_faces=0 to skip it")
    ctx.report.warn(f"textured mesh not written ({error}); {todo}")
    return {"failed": True, "error": error, "what_to_do": todo, "texture_size": side,
            "texture_faces": cfg.texture_faces}


def _textured_summary(info: dict) -> str:
    if info.get("failed"):
        return f"failed ({info['error']}), see mesh_report.json"
    text = f"{info['faces']:,} faces, {info['texture_size']}² texture"
    if info.get("held_out"):
        h = info["held_out"]
        text += f"; held-out PSNR {h['psnr_textured']:.2f} dB (vertex colors {h['psnr_vertex_colors']:.2f} dB)"
    return text


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (ru_maxrss is KiB on Linux, bytes on macOS)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 1024


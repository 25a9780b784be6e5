"""poses stage: camera poses for every photo — by SfM (pycolmap) or imported from poses the user has.

Writes `scene.json` + `points.npz` in the source frame (COLMAP's or the import's), and for SfM also
`colmap/database.db`, `colmap/sparse/` and the downscaled `colmap/images/` that COLMAP saw.
"""
from __future__ import annotations

import dataclasses
import hashlib
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from recon.atomic import sha256_file
from recon.capture.colmap import find_colmap_model
from recon.capture.images import (MIN_PHOTOS, READABLE_FORMATS, camera_exif, check_photo_set, list_photos, no_photos,
                                  oriented_size, read_image, save_image)
from recon.capture.scene import (
    MASK_FOLDER,
    Scene,
    check_cameras,
    detect_source,
    find_masks,
    frame_from_sfm,
    import_colmap,
    import_nerf_synthetic,
    import_npz,
    import_transforms,
    stored_path,
    video_mask_homes,
)
from recon.config import PosesConfig
from recon.errors import InputError
from recon.runner.pipeline import StageContext

LOG_DIR = "logs"
"""COLMAP's own log files go to SCENE/logs/ (outside the stage folder: glog may still append after it is sealed);
what it prints while SfM runs goes to SCENE/logs/01_poses.log."""


SFM_PHASES = {"extract": "extracting SIFT features", "match": "matching", "map": "incremental mapping"}


def sfm_bar_position(phase: str, fraction: float) -> float | None:
    """Where the 3-step structure-from-motion bar stands: a retry with other feature settings runs the three
    phases again, so the bar goes back to the phase it is in instead of counting past 3/3."""
    if phase not in SFM_PHASES:
        return None
    return list(SFM_PHASES).index(phase) + min(max(fraction, 0.0), 1.0)


def drop_copies(photos: list[Path]) -> tuple[list[Path], dict[Path, Path]]:
    """The photos (in their order) without byte-identical copies (a photo copied twice into the folder: 'IMG_1 (1).jpg',
    'IMG_1 copy.jpg'), and each copy left out with the photo kept for it: the shortest name, the original's."""
    sizes = Counter(path.stat().st_size for path in photos)
    by_digest: dict[str, list[Path]] = {}
    for path in photos:  # only a photo whose size another shares is read: source_digest read them all already
        by_digest.setdefault(sha256_file(path) if sizes[path.stat().st_size] > 1 else str(path), []).append(path)
    original = {p: min(same, key=lambda q: (len(q.name), q.name)) for same in by_digest.values() for p in same}
    return [p for p in photos if original[p] == p], {p: o for p, o in original.items() if o != p}


def source_digest(source: Path, cfg: PosesConfig | None) -> str:
    """Digest of the files the poses come from (names + bytes): adding, removing or editing one re-runs poses.

    Exactly the files recon reads: the photos directly in a photos folder (never other files or subfolders), or a
    poses file with every image it refers to (an edited image re-runs poses too), or a COLMAP model with its images.
    Paths are hashed as the scene stores them (`stored_path`: by their place in the input's folder), so the same
    photos moved elsewhere, their masks beside them, keep the poses and every later stage.
    """
    return _files_digest(source, sha256_file)


def source_stat(source: Path) -> str:
    """Digest of the same files' names, sizes and modification times: reads no photo, so `recon status` can tell
    at once that the photos are as they were (and hashes them only where this differs)."""
    return _files_digest(source, _size_and_time)


def _size_and_time(path: Path) -> str:
    stat = path.stat()
    return f"{stat.st_size}:{stat.st_mtime_ns}"


def _files_digest(source: Path, of_file: Callable[[Path], str]) -> str:
    """Digest of `source_files`: each label, and `of_file` of each file."""
    h = hashlib.sha256()
    for label, path in source_files(source):
        h.update(label.encode())
        if path is not None:
            h.update(of_file(path).encode())
    return h.hexdigest()


def source_files(source: Path) -> list[tuple[str, Path | None]]:
    """What the poses come from, as (label, file): the source's kind (no file), then its files by their stored
    path, then the masks beside a photos folder or a video (labelled by name: the folder may move with the photos)."""
    kind = detect_source(source)
    files: list[tuple[str, Path | None]] = [(kind, None)]
    files += [(stored_path(path, source), path) for path in sorted(set(input_files(source, kind)))]
    homes = {"photos": [source.parent / MASK_FOLDER], "video": video_mask_homes(source)}.get(kind, [])
    home = next((c for c in homes if c.is_dir()), None)  # masks beside the photos folder or the video are inputs too
    if home is not None:
        files += [(f"masks/{path.name}", path) for path in sorted(p for p in home.iterdir() if p.is_file())]
    return files


def input_files(source: Path, kind: str) -> list[Path]:
    """The files a source of this kind consists of, as `run` reads them."""
    if kind == "photos":
        photos = list_photos(source)[0]
        return photos + sorted(find_masks(photos)[1].values())  # their masks are inputs too
    if kind == "npz":
        return [source]
    if kind == "video":
        from recon.capture.video import list_videos

        return [source] if source.is_file() else list_videos(source)
    if kind == "colmap":
        model = find_colmap_model(source)
        assert model is not None  # detect_source found it
        roots = (source / "images", model / "images", model.parent / "images", model.parent.parent / "images")
        images = [p for root in roots if root.is_dir() for p in list_photos(root)[0]]
        return [p for p in sorted(model.iterdir()) if p.is_file() and p.suffix in (".bin", ".txt")] + images
    if kind == "nerf_synthetic":
        jsons = [source / f"transforms_{s}.json" for s in ("train", "val", "test") if (source / f"transforms_{s}.json").is_file()]
        return jsons + [Path(f.file_path) for f in import_nerf_synthetic(source).frames]
    json_path = source / "transforms.json" if source.is_dir() else source
    return [json_path] + [Path(f.file_path) for f in import_transforms(source).frames]


def run(ctx: StageContext) -> dict:
    assert ctx.source is not None
    kind = detect_source(ctx.source)
    if kind == "photos":
        scene, summary = _structure_from_motion(ctx)
    elif kind == "video":
        scene, summary = _video(ctx)
    else:
        ctx.report.info(f"Poses given ({kind}): importing {ctx.source}, structure from motion is skipped.")
        if kind == "npz":
            scene = import_npz(ctx.source, ctx.out / "images")
            for frame in scene.frames:  # images we wrote live inside the scene folder: store them relative to it
                frame.file_path = str(Path(ctx.folder) / Path(frame.file_path).relative_to(ctx.out))
        elif kind == "nerf_synthetic":
            scene = import_nerf_synthetic(ctx.source)
        elif kind == "colmap":
            scene = import_colmap(ctx.source, log_dir=ctx.scene_dir / LOG_DIR)
        else:
            scene = import_transforms(ctx.source)
        check_cameras(scene, _poses_file(ctx.source, kind))  # here, naming the input, not later blaming recon's own files
        for frame in scene.frames:  # the input's own files by their place in its folder (images recon wrote stay)
            frame.file_path = _stored(frame.file_path, ctx.source)
            frame.mask_path = _stored(frame.mask_path, ctx.source)
        splits = {s: sum(f.split == s for f in scene.frames) for s in ("train", "val", "test") if any(f.split == s for f in scene.frames)}
        summary = {
            "headline": f"imported {len(scene.frames)} cameras from {kind}" + (f" (splits {splits})" if splits else ""),
            "source_kind": kind,
            "cameras": len(scene.frames),
        }
    scene.save(ctx.out)
    return summary


def _stored(path: str | None, source: Path) -> str | None:
    """An absolute path as the scene stores it (`stored_path`); relative ones are the scene folder's own."""
    return stored_path(path, source) if path and Path(path).is_absolute() else path


def _poses_file(source: Path, kind: str) -> Path:
    """The file (or COLMAP model folder) the imported cameras were read from, for messages."""
    if kind == "colmap":
        return find_colmap_model(source) or source
    if kind == "nerf_synthetic":
        return source / "transforms_{train,val,test}.json"
    if kind == "transforms" and source.is_dir():
        return source / "transforms.json"
    return source


def prepare_photo(path: Path, image_dir: Path, max_side: int, turn: bool = False) -> tuple[str, tuple[int, int],
                                                                                      tuple[int, int]]:
    """The copy of one photo COLMAP reads: upright (with `turn`, then turned a quarter counterclockwise:
    `recon.capture.sfm.turned_to_share`), downscaled to max_side, 8-bit, with the photo's device and focal-length EXIF
    (Orientation 1). Returns its file name, the photo's and the copy's (width, height), both upright."""
    original = oriented_size(path)
    small = read_image(path, max_side=max_side)
    name = path.stem + (".png" if small.shape[-1] == 4 or path.suffix.lower() == ".png" else ".jpg")
    pixels = np.ascontiguousarray(np.rot90(small[..., :3])) if turn else small[..., :3]
    save_image(image_dir / name, pixels, exif=camera_exif(path))
    return name, original, (small.shape[1], small.shape[0])


def _turned_photos(ctx: StageContext, photos: list[Path]) -> set[Path]:
    """The photos taken the other way up from most (`turned_to_share`), said with why: SfM sees them turned, so one
    camera's intrinsics hold every photo instead of one camera each way up (or one a photo, without EXIF)."""
    from recon.capture.sfm import turned_to_share

    sizes = [oriented_size(path) for path in photos]
    turns = turned_to_share(sizes)
    turned = {path for path, turn in zip(photos, turns, strict=True) if turn}
    if turned:
        w, h = sizes[turns.index(True)]
        ctx.report.info(
            f"{len(turned)} of {len(photos)} photos are {w}x{h} where most are {h}x{w} (taken the other way up): "
            f"SfM sees them turned a quarter, so that one camera's intrinsics hold them all; their poses are turned "
            f"back"
        )
    return turned


def _turntable_masks(ctx: StageContext, image_dir: Path, names: list[str], mask_dir: Path) -> tuple[Path | None, str]:
    """With `poses.turntable` auto, COLMAP's feature masks (in ``mask_dir``) for a turntable capture
    (`recon.capture.turntable`) and the reason, said; (None, "") for any other capture."""
    from recon.capture.turntable import SIDE, STILL_FOLDER, feature_mask, turntable_verdict

    cfg: PosesConfig = ctx.config
    if cfg.turntable == "off":
        return None, ""
    images = []
    with ctx.report.task("comparing the photos' backgrounds", total=len(names), unit="photos") as bar:
        for name in names:
            images.append(read_image(image_dir / name, max_side=2 * SIDE))
            bar.advance()
        found, reason = turntable_verdict(images)
    ctx.report.info(reason)
    if found is None:
        return None, ""
    mask_dir.mkdir(parents=True)
    (ctx.out / STILL_FOLDER).mkdir()
    for i, name in enumerate(names):
        save_image(mask_dir / f"{name}.png", feature_mask(found, i, oriented_size(image_dir / name)).astype(np.float32))
        if i in found.background:
            save_image(ctx.out / STILL_FOLDER / f"{Path(name).stem}.png", found.background[i].astype(np.float32))
    return mask_dir, reason


def _video(ctx: StageContext) -> tuple[Scene, dict]:
    """Decode the clip(s) into the kept frames (01_poses/frames/, with time stamps), then SfM on them in order."""
    from recon.capture.video import SelectOptions, frame_name, list_videos, probe, select_frames, share_frames

    cfg: PosesConfig = ctx.config
    videos = [ctx.source] if ctx.source.is_file() else list_videos(ctx.source)
    infos = [probe(v) for v in videos]
    total = sum(info.frame_count for info in infos)
    frames_dir = ctx.out / "frames"
    frames_dir.mkdir()
    kept: list[tuple[Path, float]] = []
    selections = []
    with ctx.report.task("decoding video", total=total, unit="frames") as bar:
        done = 0
        for video, info, target in zip(videos, infos, share_frames(cfg.video_frames, [i.frame_count for i in infos])):
            options = SelectOptions(target, cfg.video_min_change)

            def keep(frame, image: np.ndarray, stem: str = video.stem) -> None:
                path = frames_dir / frame_name(stem, frame.index)
                save_image(path, image.astype(np.float32) / 255.0)
                kept.append((path, frame.time_s))

            selection = select_frames(video, options, keep, lambda n, base=done: bar.update(completed=base + n), info)
            done += info.frame_count
            selections.append(selection)
            ctx.report.info(selection.describe())
    if len(kept) < MIN_PHOTOS:
        raise InputError(
            f"Only {len(kept)} distinct frame(s) came out of {ctx.source}: the camera barely moved. Film a slow walk "
            f"all around the object (or lower poses.video_min_change, now {cfg.video_min_change})."
        )
    scene, summary = _structure_from_motion(ctx, photos=[p for p, _ in kept], mask_homes=video_mask_homes(ctx.source))
    times = {p.name: t for p, t in kept}
    for frame in scene.frames:
        frame.time_s = round(times[frame.name], 6)
    scene.source_kind = "video"
    scene.notes["video"] = [s.describe() for s in selections]
    summary["headline"] = f"{len(kept)} of {sum(s.read for s in selections)} video frames kept; " + summary["headline"]
    summary["video"] = [
        {"file": s.info.path.name, "read": s.read, "kept": len(s.kept), "dropped": s.dropped, "seconds": round(s.seconds, 2)}
        for s in selections
    ]
    return scene, summary


def _structure_from_motion(ctx: StageContext, photos: list[Path] | None = None,
                           mask_homes: list[Path] | None = None) -> tuple[Scene, dict]:
    """SfM on the photos of ctx.source, or on `photos` given in order (video frames: matched sequentially, their
    masks looked for in `mask_homes`)."""
    from recon.capture.sfm import SfmOptions, dropped_message, run_sfm

    cfg: PosesConfig = ctx.config
    ordered = photos is not None
    skipped: list[Path] = []
    if photos is None:
        photos, skipped = list_photos(ctx.source)
        for path in skipped:
            ctx.report.warn(f"Skipping {path.name}: not an image file recon reads ({READABLE_FORMATS}).")
        photos, copies = drop_copies(photos)
        for copy, original in copies.items():
            ctx.report.warn(f"Skipping {copy.name}: the same file as {original.name} (a copy adds no view; it would "
                            f"count twice in training).")
    if not photos:
        raise no_photos(ctx.source, skipped)
    check_photo_set(ctx.source, photos)  # `recon run` told it before the scene folder; here for what copies left
    mask_dir, masks = find_masks(photos, mask_homes)
    if mask_dir is not None:
        ctx.report.info(
            f"masks: {len(masks)} masks in {mask_dir} (white = object): masked-out pixels train as background and "
            f"the mesh keeps only what the masks call object"
        )
    sfm_dir = ctx.out / "colmap"
    image_dir = sfm_dir / "images"
    image_dir.mkdir(parents=True)
    original_size: dict[str, tuple[int, int]] = {}
    sfm_size: dict[str, tuple[int, int]] = {}
    names = []
    turned = _turned_photos(ctx, photos)
    with ctx.report.task("reading photos", total=len(photos)) as bar:
        for path in photos:
            name, original_size[path.name], sfm_size[path.name] = prepare_photo(path, image_dir, cfg.max_side,
                                                                                path in turned)
            names.append((path, name))
            bar.advance()
    by_sfm_name = {name: path for path, name in names}
    feature_masks, turntable_reason = _turntable_masks(ctx, image_dir, [n for _, n in names], sfm_dir / "feature_masks")
    options = SfmOptions(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(SfmOptions)})
    if ordered and options.matcher == "auto":
        options.matcher = "sequential"
        loop = f", loop closure over {options.loop_keyframes} keyframes" if options.loop_keyframes > 1 else ""
        ctx.report.info(
            f"Matching: sequential (each frame with the next {options.sequential_overlap}{loop}): video frames come "
            f"in order, so exhaustive matching would mostly pair views that cannot overlap."
        )
    with ctx.report.task("structure from motion", total=3) as bar:
        def progress(phase: str, fraction: float) -> None:
            bar.update(completed=sfm_bar_position(phase, fraction),
                       info=SFM_PHASES.get(phase, phase) if fraction < 1.0 else None)

        log_file = ctx.scene_dir / LOG_DIR / f"{ctx.folder}.log"
        result = run_sfm(image_dir, [n for _, n in names], sfm_dir, options, progress=progress, log_file=log_file,
                         mask_dir=feature_masks)
    ctx.report.info(f"Camera model: {result.camera_model} — {result.choice_reason}")
    if len(result.attempts) > 1:
        first, last = result.attempts[0], result.attempts[-1]
        helped = "helped" if last["registered"] > first["registered"] else "did not help"
        ctx.report.info(
            f"registration retry: the first pass ({first['settings']}) registered "
            f"{first['registered']}/{len(names)} photos; "
            f"retried with {last['settings']}: {last['registered']}/{len(names)} ({helped})"
        )
    ref = result.refinement
    if ref and ref.get("undone"):
        ctx.report.warn(
            f"the final robust bundle adjustment ran away (mean reprojection error {ref['error_before_px']:.3f} -> "
            f"{ref['error_after_px']:.3g} px, focal {ref['focal_before']:.1f} -> {ref['focal_after']:.3g} px): it is "
            f"undone and the model before it kept. Such a run-away comes from a model with little to hold it, e.g. "
            f"every camera in one place; check the cameras in 01_poses"
        )
    elif ref:
        ctx.report.info(
            f"final bundle adjustment with a robust (Cauchy, {ref['scale_px']} px) loss, so a few off matches do not "
            f"pull the focal length: focal {ref['focal_before']:.1f} -> {ref['focal_after']:.1f} px, mean "
            f"reprojection error {ref['error_before_px']:.3f} -> {ref['error_after_px']:.3f} px"
        )
    if result.dropped:
        ctx.report.warn(f"{len(result.dropped)} of {len(names)} photos could not be registered and are left out: "
                        + dropped_message(result, len(result.registered), lambda n: by_sfm_name[n].name))
    for sfm_name, reason in result.excluded.items():
        ctx.report.warn(f"{by_sfm_name[sfm_name].name} is left out of training: {reason}.")
    frames = []
    for sfm_name, fd in result.frames.items():
        path = by_sfm_name[sfm_name]
        (ow, oh), (sw, sh) = original_size[path.name], sfm_size[path.name]
        # frames recon wrote live in the scene folder: stored relative to it, like the .npz import's images
        inside = path.is_relative_to(ctx.out)
        file_path = str(Path(ctx.folder) / path.relative_to(ctx.out)) if inside else stored_path(path, ctx.source)
        frame = frame_from_sfm(file_path, fd, ow / sw, oh / sh, turned=path in turned)
        frame.mask_path = stored_path(masks[path.name], ctx.source) if path.name in masks else None
        frames.append(frame)
    visibility = {by_sfm_name[n].name: np.asarray(v, dtype=np.int64) for n, v in result.points_visible.items()}
    sfm_scale = float(np.median([original_size[by_sfm_name[n].name][0] / sfm_size[by_sfm_name[n].name][0] for n in result.frames]))
    scene = Scene(
        frames=frames,
        points=result.points_xyz,
        point_colors=result.points_rgb,
        point_visibility=visibility,
        point_errors=np.asarray(result.points_error, np.float64) * sfm_scale,  # SfM pixels -> original photo pixels
        source_kind="photos",
        has_alpha=mask_dir is not None,
        notes={"camera_model": result.camera_model, "camera_choice": result.choice_reason,
               **({"masks": stored_path(mask_dir, ctx.source)} if mask_dir is not None else {}),
               **({"turntable": turntable_reason} if turntable_reason else {})},
    )
    summary = {
        "headline": (
            f"{len(result.registered)}/{len(names)} photos registered"
            + (f" ({len(result.excluded)} more left out: pose disagrees)" if result.excluded else "")
            + f", {result.num_points} points, reprojection error {result.mean_reprojection_error:.2f} px"
            + (", a turntable capture" if turntable_reason else "")
        ),
        "turntable": bool(turntable_reason),
        "registered": len(result.registered),
        "total": len(names),
        "dropped": [by_sfm_name[n].name for n in result.dropped],
        "groups_apart": [[by_sfm_name[n].name for n in group] for group in result.groups_apart],
        "excluded": {by_sfm_name[n].name: reason for n, reason in result.excluded.items()},
        "points": result.num_points,
        "reprojection_error_px": round(result.mean_reprojection_error, 4),
        "camera_model": result.camera_model,
        "shared_intrinsics": result.shared_intrinsics,
        "cameras": result.num_cameras,
        "attempts": result.attempts,
        "refinement": result.refinement,
        "timings_s": {k: round(v, 2) for k, v in result.timings.items()},
    }
    return scene, summary


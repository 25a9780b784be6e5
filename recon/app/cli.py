"""The `recon` command line: `recon run PHOTOS --out SCENE`, single stages, status, and tools.

Every command goes through `_guard`, which turns user-fixable errors into one paragraph and an exit
code (2), Ctrl-C into a note on how to resume (130), and anything unexpected into a short message with
the traceback saved to a log file instead of the screen.
"""
from __future__ import annotations

import contextlib
import os
import sys
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from recon.app.api import require_scene
from recon.app.progress import Reporter, format_seconds, format_summary, local_minute
from recon.config import (DEFAULT_PRESET, DEFAULT_PRESET_WHY, RunConfig, available_presets, check_batch_against_pixels,
                          load_config, preset_description)
from recon.errors import ConfigError, ReconError
from recon.runner.pipeline import RUN_LOG, install_sigterm_as_interrupt, is_disk_full, recorded_source

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Photos → camera poses → neural radiance field → colored mesh you can open in Blender.",
)
console = Console(stderr=True, highlight=False)
out_console = Console(highlight=False)


def version_line() -> str:
    """recon's version and those of the packages its results depend on, for a bug report (read from the installed
    packages' metadata, so torch is not loaded to say it)."""
    from importlib.metadata import PackageNotFoundError, version

    from recon import __version__

    def of(package: str) -> str:
        try:
            return version(package)
        except PackageNotFoundError:
            return "not installed"

    python = ".".join(str(v) for v in sys.version_info[:3])
    return (f"recon {__version__} (Python {python}; torch {of('torch')}, pycolmap {of('pycolmap')}, "
            f"opencv {of('opencv-contrib-python-headless')}, trimesh {of('trimesh')})")


def _show_version(shown: bool) -> None:
    if shown:
        out_console.print(version_line(), markup=False, soft_wrap=True)
        raise typer.Exit()


@app.callback()
def _options(version: Annotated[bool, typer.Option("--version", callback=_show_version, is_eager=True,
                                                   help="Print recon's version and its main packages' and exit.")]
             = False) -> None:
    """The options that come before a command."""

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130

PresetOpt = Annotated[Optional[str], typer.Option("--preset", "-p", help=f"Preset from pipelines/ (or a .toml path); default {DEFAULT_PRESET}.")]
SetOpt = Annotated[Optional[list[str]], typer.Option("--set", help="Override an option: section.key=value (repeatable).")]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="Only warnings and errors.")]


@contextlib.contextmanager
def _guard(scene_dir: Path | None = None) -> Iterator[None]:
    """User errors → one paragraph + exit 2; Ctrl-C → how to resume; bugs → message + traceback in a log file."""
    try:
        yield
    except ReconError as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}")  # escaped: '[train]' in a message is text, not markup
        raise typer.Exit(EXIT_USER_ERROR) from None
    except KeyboardInterrupt:
        console.print(
            "\n[yellow]Interrupted.[/] Finished stages (and the last training checkpoint) are kept; "
            "run the same command again (with a longer --budget too) to resume where it stopped."
        )
        raise typer.Exit(EXIT_INTERRUPTED) from None
    except OSError as exc:
        if is_disk_full(exc):
            console.print(
                f"[bold red]error:[/] the disk is full ({escape(str(exc.filename or 'writing output'))}). Nothing finished was lost; "
                f"free some space and run the same command again to resume."
            )
            raise typer.Exit(EXIT_USER_ERROR) from None
        _report_bug(exc, scene_dir)
    except typer.Exit:
        raise
    except Exception as exc:  # a bug: keep the screen readable, keep the details
        _report_bug(exc, scene_dir)


def _crash_log_path(scene_dir: Path | None) -> Path:
    """Where a crash's traceback goes: the scene folder when it is a recon scene, else the per-user cache folder
    (never a fixed name in a shared /tmp, where anyone could plant a link)."""
    if scene_dir is not None and (scene_dir / "manifest.json").is_file():
        return scene_dir / "recon-error.log"
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "recon"
    cache.mkdir(mode=0o700, parents=True, exist_ok=True)
    return cache / "recon-error.log"


def _report_bug(exc: BaseException, scene_dir: Path | None) -> None:
    from recon.atomic import write_bytes_atomic

    log: Path | None = None
    with contextlib.suppress(OSError):
        # written exclusively next to it and renamed over it: a link planted at the log's name is replaced, not followed
        log = write_bytes_atomic(_crash_log_path(scene_dir), "".join(traceback.format_exception(exc)))
    where = f"The details are in {escape(str(log))}; please include that file in a report." if log else (
        "The details could not be saved (the log folder is not writable).")
    console.print(
        f"[bold red]internal error:[/] {type(exc).__name__}: {escape(str(exc))}\n"
        f"This is a bug in recon, not in your input. {where}"
    )
    raise typer.Exit(1) from None


def preset_line(preset: str | None) -> str:
    """The line a run starts with: the preset, why when it is the default one (an automatic choice), what it trades."""
    why = "" if preset else f" ({DEFAULT_PRESET_WHY}; --preset NAME picks another)"
    name = preset or DEFAULT_PRESET
    return f"preset [bold]{escape(name)}[/]{escape(why)}: {escape(preset_description(name))}"


def _config(preset: str | None, overrides: list[str] | None) -> RunConfig:
    """The named preset (DEFAULT_PRESET when none is given) with the `--set` overrides."""
    return load_config(preset or DEFAULT_PRESET, overrides)


def _check_device(config: RunConfig) -> None:
    """A CUDA device that is not there is refused before any stage runs (not after structure from motion)."""
    if config.train.device.strip().lower().startswith("cuda"):
        from recon.nerf.device import select_device

        try:
            select_device(config.train.device)
        except ValueError as exc:
            raise ConfigError(f"Option 'train.device': {exc}.") from None


def _recorded_preset(scene_dir: Path) -> str | None:
    """The preset the scene was last run with (so `recon mesh SCENE` keeps the run's settings)."""
    from recon.runner.pipeline import Manifest

    return Manifest(scene_dir).data.get("preset")  # a damaged manifest records none (the runner warns)


def _pipeline():
    from recon.stages import default_pipeline

    return default_pipeline()


def _summary_table(outcomes: list[Any], scene_dir: Path) -> None:
    table = Table(title=f"recon — {escape(str(scene_dir))}", show_lines=False)
    table.add_column("stage")
    table.add_column("")
    table.add_column("time", justify="right")
    table.add_column("result")
    for o in outcomes:
        table.add_row(o.name, "ran" if o.action == "ran" else "cached", format_seconds(o.wall_s) if o.action == "ran" else "—", escape(format_summary(o.summary)))
    out_console.print(table)


def mesh_deliverables(scene_dir: Path) -> list[str]:
    """Lines that tell the user where the mesh stage's files are and how to open them (only those that exist): a run
    ends with a table of stages, which says what was made but not where."""
    from recon.app.api import mesh_files
    from recon.stages.mesh import TEXTURED_STEM

    files = mesh_files(scene_dir)
    if "glb" not in files:
        return []
    folder = files["glb"].parent
    lines = [f"your mesh: {files['glb']} (colours per vertex; in Blender: File → Import → glTF 2.0)"]
    textured = folder / f"{TEXTURED_STEM}.glb"
    if textured.is_file():
        lines.append(f"           {textured} (its colours in a texture image, for tools that show no vertex colours)")
    others = [files[ext].name for ext in ("obj", "ply") if ext in files]
    if others:
        lines.append(f"           {' and '.join(others)} beside them, for other tools")
    previews = [p.name for p in (folder / "preview_front.png", folder / "preview_side.png") if p.is_file()]
    look = f"{', '.join(previews)} in {folder}, or " if previews else ""
    lines.append(f"look at it: {look}`recon view {scene_dir}` (a viewer in your browser, on this machine only)")
    return lines


def _run(
    scene_dir: Path,
    source: Path | None,
    preset: str | None,
    overrides: list[str] | None,
    quiet: bool,
    from_stage: str | None = None,
    until_stage: str | None = None,
    force: bool = False,
    observers: list[Callable[[str, dict], None]] | None = None,
) -> None:
    install_sigterm_as_interrupt()
    with _guard(scene_dir):
        if source is not None:
            from recon.capture.scene import check_source
            from recon.runner.ownership import resolve_path

            source = resolve_path(source, "The photos folder")  # a link loop is the user's to fix, not a crash
            check_source(source)  # a wrong input (see check_source) is said before the scene folder is made
        preset = preset or _recorded_preset(scene_dir)
        config = _config(preset, overrides)
        _check_device(config)
        if source is not None:
            from recon.capture.video import count_photos

            check_batch_against_pixels(config, count_photos(source, config.poses.video_frames))
        report = Reporter(console, quiet=quiet)
        report.observers = list(observers or [])
        if not quiet:
            report.info(preset_line(preset), markup=True)
        outcomes = _pipeline().run(
            scene_dir,
            config,
            report,
            source=source,
            from_stage=from_stage,
            until_stage=until_stage,
            force=force,
            preset=preset or DEFAULT_PRESET,
        )
        if not quiet:
            _summary_table(outcomes, scene_dir)
            if report.warnings:  # said as they came, above a screenful of reasons: said again where the run ends
                out_console.print(f"{len(report.warnings)} warning{'s' if len(report.warnings) > 1 else ''} in this run "
                                  f"(also in {scene_dir / RUN_LOG}):", markup=False)
                for message in report.warnings:
                    out_console.print(f"- {message}", markup=False)
            if any(o.name == "mesh" for o in outcomes):
                for line in mesh_deliverables(scene_dir):
                    out_console.print(escape(line), soft_wrap=True)


@app.command()
def run(
    photos: Annotated[Path, typer.Argument(help="Folder of photos, a video (MP4/MOV/M4V) or folder of videos, or poses you have: transforms.json folder, NeRF-synthetic folder, COLMAP model, .npz.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Scene folder for every stage's output.")],
    preset: PresetOpt = None,
    set_: SetOpt = None,
    from_stage: Annotated[Optional[str], typer.Option("--from", help="Re-run from this stage on.")] = None,
    until_stage: Annotated[Optional[str], typer.Option("--until", help="Stop after this stage.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Re-run every selected stage even if cached.")] = False,
    budget: Annotated[Optional[str], typer.Option("--budget", help="Training time budget, e.g. 5m (same as --set train.budget=5m).")] = None,
    quiet: QuietOpt = False,
    view: Annotated[bool, typer.Option("--view", help="Show training live in a web viewer (loss, PSNR, current render), then the result.")] = False,
    port: Annotated[int, typer.Option("--port", help="Viewer port (with --view).")] = 8080,
) -> None:
    """Run every stage in order, reusing what is already done."""
    overrides = list(set_ or []) + ([f"train.budget={budget}"] if budget else [])
    if not view:
        _run(out, photos, preset, overrides, quiet, from_stage, until_stage, force)
        return
    from recon.app.viewer import SceneViewer, TrainingView

    with _guard(out):
        live = TrainingView(out, port=port)
    console.print(f"[bold]viewer:[/] {live.url} (training shows there live)")
    _run(out, photos, preset, overrides, quiet, from_stage, until_stage, force, observers=[live])
    if live.render_s:
        console.print(f"viewer: {len(live.render_s)} live renders during training, {sum(live.render_s) / len(live.render_s):.2f} s each")
    _serve(lambda: SceneViewer(out, server=live.server, log=lambda m: console.print(f"viewer: {m}")), out)


def _single_stage(name: str) -> Callable[..., None]:
    def command(
        scene: Annotated[Path, typer.Argument(help="Scene folder (made by `recon run`).")],
        photos: Annotated[Optional[Path], typer.Option("--photos", help="Photos folder (defaults to the one recorded in the scene).")] = None,
        preset: PresetOpt = None,
        set_: SetOpt = None,
        quiet: QuietOpt = False,
    ) -> None:
        _run(scene, photos, preset, set_, quiet, from_stage=name, until_stage=name, force=True)

    command.__doc__ = f"Run the {name} stage alone (again), with its upstream stages already done."
    return command


for _name in ("poses", "normalize", "train", "mesh"):
    app.command(name=_name)(_single_stage(_name))


@app.command()
def status(
    scene: Annotated[Path, typer.Argument(help="Scene folder.")],
    preset: PresetOpt = None,
    set_: SetOpt = None,
) -> None:
    """Each stage's state (done / stale / missing / failed / corrupt), wall time and what it produced."""
    with _guard(scene):
        require_scene(scene)
        # without options, "stale" means an upstream stage changed; with them, also "differs from these options",
        # the --set ones on the preset the scene was run with, as `recon run` would take them
        asked = (preset or _recorded_preset(scene) or DEFAULT_PRESET) if (preset or set_) else None
        config = _config(asked, set_) if asked else None
        from recon.runner.pipeline import Manifest, running_pid

        manifest = Manifest(scene)
        if manifest.warning:
            console.print(f"[yellow]warning:[/] {escape(manifest.warning)}")
        if (photos := manifest.source) and not photos.exists():
            console.print(f"[yellow]warning:[/] the photos {escape(str(photos))} are not there (moved or deleted): "
                          "training or meshing again reads them. Give `recon run` the folder where they are now (the "
                          "same photos keep what was made from them).")
        if pid := running_pid(scene):
            console.print(f"a recon run (pid {escape(pid)}) is writing this scene now: below are the stages it has "
                          "finished so far (a training's row: its last checkpoint)")
        rows = _pipeline().state(scene, config, preset=asked)
        table = Table(title=f"recon status — {escape(str(scene))}")
        for col in ("stage", "state", "time", "finished", "result"):
            table.add_column(col)
        colors = {"done": "green", "stale": "yellow", "missing": "dim", "failed": "red", "corrupt": "red"}
        for row in rows:
            state = row["state"]
            result = format_summary(row["summary"]) if state != "failed" else row.get("error", "")
            if row.get("why"):  # what a run with these options would run again for
                result = f"{result}; runs again: {row['why']}" if result else f"runs again: {row['why']}"
            if row.get("scratch"):
                result = f"{result}; {row['scratch']}" if result else row["scratch"]
            table.add_row(row["stage"], f"[{colors[state]}]{state}[/]", format_seconds(row["wall_s"]),
                          local_minute(row.get("finished")), escape(str(result)))
        out_console.print(table)


@app.command()
def render(
    scene: Annotated[Path, typer.Argument(help="Scene folder with a trained field.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the frames and the GIF/MP4.")],
    path: Annotated[str, typer.Option("--path", help="orbit | spiral | train | test")] = "orbit",
    frames: Annotated[int, typer.Option("--frames", help="Frames on an orbit/spiral path.")] = 60,
    max_side: Annotated[Optional[int], typer.Option("--size", help="Longest image side (default: training size).")] = None,
    depth: Annotated[bool, typer.Option("--depth", help="Also write colored depth maps and a depth video.")] = False,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
) -> None:
    """Render a novel-view camera path (or the train/test cameras) to PNG frames and a GIF/MP4."""
    from recon.app.novel_views import render_path

    with _guard(scene):
        if path not in ("orbit", "spiral", "train", "test"):
            raise ReconError(f"--path must be orbit, spiral, train or test; got '{path}'.")
        if frames < 1:
            raise ReconError(f"--frames must be at least 1; got {frames}.")
        require_scene(scene, "train")
        written = render_path(scene, path, out, frames=frames, max_side=max_side, depth=depth, device=device, report=Reporter(console))  # type: ignore[arg-type]
        out_console.print("wrote " + ", ".join(str(p) for p in written) + f" and the frames in {out}", markup=False)


@app.command(name="eval")
def eval_(
    scene: Annotated[Path, typer.Argument(help="Scene folder with a trained field.")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Report folder (default SCENE/eval).")] = None,
    split: Annotated[str, typer.Option("--split", help="test | val | train")] = "test",
    max_side: Annotated[Optional[int], typer.Option("--size", help="Longest image side (default: training size).")] = None,
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda")] = "auto",
    limit: Annotated[int, typer.Option("--limit", help="Evaluate at most N views of the split (0: all).")] = 0,
    gt_mesh: Annotated[Optional[Path], typer.Option("--gt-mesh", help="Ground-truth mesh: report Chamfer-L1 and F-score of our mesh.")] = None,
    gt_masks: Annotated[Optional[Path], typer.Option("--gt-masks", help="Folder of true object masks (white = object, named like the photos): IoU of the mesh's silhouette and of the automatic masks.")] = None,
) -> None:
    """Render every held-out view: per-view and mean PSNR/SSIM, and image grids (and mesh accuracy with --gt-mesh)."""
    from recon.app.novel_views import claim_eval_folder, evaluate_scene

    with _guard(scene):
        require_scene(scene, "mesh" if gt_mesh is not None else "normalize" if gt_masks is not None else "train")
        target = out or scene / "eval"
        if gt_mesh is not None and not gt_mesh.is_file():
            raise ReconError(f"The ground-truth mesh {gt_mesh} does not exist.")
        if gt_masks is not None and not gt_masks.is_dir():
            raise ReconError(f"The masks folder {gt_masks} does not exist: give --gt-masks a folder of object masks.")
        if gt_masks is not None or gt_mesh is not None:
            claim_eval_folder(target, [*(["silhouette_iou.json"] if gt_masks is not None else []),
                                       *(["mesh_accuracy.json"] if gt_mesh is not None else [])])
        if gt_masks is not None:
            from recon.atomic import write_json_atomic
            from recon.evaluation.mesh_eval import silhouette_iou

            result = silhouette_iou(scene, gt_masks, recorded_source(scene))
            write_json_atomic(target / "silhouette_iou.json", result)
            parts = [f"{what} IoU {result[f'mean_{key}iou']:.3f} (least {result[f'min_{key}iou']:.3f}), precision "
                     f"{result[f'mean_{key}precision']:.3f}, recall {result[f'mean_{key}recall']:.3f}"
                     for what, key in (("mesh silhouette", ""), ("the scene's masks", "masks_"),
                                       ("the unsure automatic masks", "unsure_masks_")) if f"mean_{key}iou" in result]
            out_console.print(f"against {gt_masks} over {len(result['views'])} photos: " + "; ".join(parts)
                              + f" — {target / 'silhouette_iou.json'}", markup=False)
        if gt_mesh is not None:
            from recon.atomic import write_json_atomic
            from recon.evaluation.mesh_eval import compare_to_gt, format_comparison

            comparison = compare_to_gt(scene, gt_mesh)
            write_json_atomic(target / "mesh_accuracy.json", comparison)
            out_console.print(format_comparison(comparison), markup=False)
        if gt_mesh is not None or gt_masks is not None:
            return
        result = evaluate_scene(scene, target, split=split, max_side=max_side, device=device, report=Reporter(console), limit=limit)
        out_console.print(
            f"{split}: mean PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.3f} over {len(result['views'])} views "
            f"— {target / 'metrics.json'}, {target / 'grid.png'}",
            markup=False,
        )


FIT_IMAGE_FILES = ("fitted.png", "curve.json", "curve.png")
"""What `recon fit-image` writes into its --out folder."""


@app.command(name="fit-image")
def fit_image_cmd(
    image: Annotated[Path, typer.Argument(help="An image to fit with a 2D neural field.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the fitted image and PSNR curve.")] = Path("fit-image"),
    steps: Annotated[int, typer.Option("--steps")] = 1000,
    freqs: Annotated[int, typer.Option("--freqs", help="Positional-encoding frequencies (0: none).")] = 10,
    max_side: Annotated[int, typer.Option("--size", help="Downscale the image to this longest side.")] = 256,
) -> None:
    """Fit an MLP with positional encoding to one image and plot its PSNR curve (a check of the encoding)."""
    import json

    import torch

    from recon.capture.images import read_image, save_image
    from recon.nerf.image_fit import fit_image, render_field
    from recon.plots import training_curves
    from recon.runner.ownership import claim_folder
    from recon.stages import scene_parts

    with _guard():
        if steps < 1 or freqs < 0:
            raise ReconError("--steps must be ≥ 1 and --freqs ≥ 0.")
        # a new or empty folder or an earlier fit's (recon.runner.ownership): a file of the user's is never replaced
        owned = claim_folder(out, "fit-image", scene_parts, [image])
        owned.check_free(FIT_IMAGE_FILES)
        img = torch.from_numpy(read_image(image, max_side=max_side)[..., :3].copy())
        report = Reporter(console)
        with report.task("fitting", total=steps) as bar:
            model, curve = fit_image(img, steps=steps, n_freqs=freqs, on_step=lambda s, loss: bar.advance())
        with owned.staging() as staged:
            save_image(staged / "fitted.png", render_field(model, *img.shape[:2]).numpy())
            (staged / "curve.json").write_text(json.dumps(curve, indent=1))
            training_curves([], curve, staged / "curve.png", title=f"2D field, L={freqs}")
            owned.replace_with(staged)
        out_console.print(f"PSNR {curve[-1]['psnr']:.2f} dB after {steps} steps — {out / 'fitted.png'}, {out / 'curve.png'}", markup=False)


@app.command()
def bench(
    data: Annotated[str, typer.Option("--data", help="sample | lego-half | fox | tabletop_realistic | tabletop_turntable | tabletop_sweep | tabletop_closeups | wall_mounted | tabletop_painted | tabletop_far | tabletop_video (NAME@SEED: another draw of it) | a path to photos or poses.")] = "sample",
    presets_: Annotated[str, typer.Option("--presets", help="Comma-separated presets to compare.")] = "fast,balanced,quality,surface",
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the scenes, bench.md, bench.json, bench.png.")] = Path("bench"),
    set_: SetOpt = None,
    until: Annotated[str, typer.Option("--until", help="train (PSNR only) or mesh (also mesh accuracy when a GT mesh exists).")] = "mesh",
    profile: Annotated[bool, typer.Option("--profile", help="Instead: profile training steps and a test render of each preset (profile.md).")] = False,
    profile_warmup: Annotated[int, typer.Option("--profile-warmup", help="Steps trained before the profiled ones.")] = 200,
    profile_steps: Annotated[int, typer.Option("--profile-steps", help="Training steps profiled.")] = 8,
) -> None:
    """Measure the speed/accuracy trade: each preset's time, held-out PSNR and mesh error, as a table and a plot."""
    from recon.app.bench import run_bench

    install_sigterm_as_interrupt()
    with _guard():
        names = [p.strip() for p in presets_.split(",") if p.strip()]
        if profile:
            from recon.app.profiling import run_profile

            path = run_profile(data, names, out, list(set_ or []), Reporter(console), warmup=profile_warmup, steps=profile_steps)
            out_console.print(path.read_text(), markup=False)
            return
        rows = run_bench(data, names, out, list(set_ or []), Reporter(console), until=until)
        out_console.print((out / "bench.md").read_text(), markup=False)
        out_console.print(f"{len(rows)} presets measured — {out / 'bench.md'}, {out / 'bench.png'}", markup=False)


@app.command()
def export(
    scene: Annotated[Path, typer.Argument(help="Scene folder (made by `recon run`).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the export (new, empty, or an earlier recon export).")],
    format_: Annotated[str, typer.Option("--format", "-f", help="nerfstudio (transforms.json + images) | colmap (text model + images) | points (PLY).")] = "nerfstudio",
    frame: Annotated[str, typer.Option("--frame", help="normalized (recon's box, +Z up, like the mesh) | source (the SfM / imported poses).")] = "normalized",
) -> None:
    """Export cameras, undistorted images and sparse points for other tools (nerfstudio, instant-ngp, Gaussian splatting)."""
    from recon.app.exports import export_scene

    with _guard():
        written = export_scene(scene, format_, out, frame, report=Reporter(console))  # type: ignore[arg-type]
        out_console.print(f"{format_} export ({frame} frame): " + ", ".join(str(p) for p in written))


def _serve(make: Callable[[], Any], scene: Path) -> None:
    """Build a viewer and keep serving until Ctrl-C (which here simply closes it)."""
    import time

    with _guard(scene):
        viewer = make()
        console.print(f"[bold]viewer:[/] {viewer.url} — Ctrl-C to stop")
    try:
        with contextlib.suppress(KeyboardInterrupt):
            while True:
                time.sleep(1.0)
    finally:
        viewer.stop()


@app.command()
def view(
    scene: Annotated[Path, typer.Argument(help="Scene folder (made by `recon run`).")],
    port: Annotated[int, typer.Option("--port", help="Port to serve on (the next free one if taken).")] = 8080,
    host: Annotated[str, typer.Option("--host", help="Address to bind; 0.0.0.0 shares the viewer on your network.")] = "127.0.0.1",
    device: Annotated[str, typer.Option("--device", help="auto | cpu | cuda (for the live field render)")] = "auto",
) -> None:
    """A local web viewer: cameras with their photos, sparse points, the mesh, and the field rendered live."""
    from recon.app.viewer import SceneViewer

    _serve(lambda: SceneViewer(scene, host=host, port=port, device=device, log=lambda m: console.print(f"viewer: {m}")), scene)


@app.command()
def batch(
    inputs: Annotated[list[Path], typer.Argument(help="Capture folders (photos or poses), videos, or one text file listing them (one per line, # comments).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for every capture's scene (OUT/<capture name>/), batch.md and batch.json.")],
    address: Annotated[Optional[str], typer.Option("--address", help="Ray cluster to join: auto or HOST:PORT (default: start Ray on this machine).")] = None,
    preset: PresetOpt = None,
    set_: SetOpt = None,
    cpus_per_capture: Annotated[Optional[float], typer.Option("--cpus-per-capture", help="CPUs each capture asks Ray for (default: from the config).")] = None,
    retries: Annotated[int, typer.Option("--retries", help="Times Ray re-runs a capture whose worker died (it resumes from its cache).")] = 2,
    quiet: QuietOpt = False,
) -> None:
    """Run many captures as Ray tasks (one per capture), locally or on a cluster; exit 1 if any failed."""
    from recon.app.batch import run_batch

    install_sigterm_as_interrupt()
    with _guard():
        if retries < 0 or (cpus_per_capture is not None and cpus_per_capture <= 0):
            raise ReconError("--retries must be ≥ 0 and --cpus-per-capture > 0.")
        report = Reporter(console, quiet=quiet)
        report.info(preset_line(preset), markup=True)
        result = run_batch(inputs, out, preset or DEFAULT_PRESET, list(set_ or []), report,
                           address=address, retries=retries, cpus_per_capture=cpus_per_capture)
        out_console.print((out / "batch.md").read_text())
    if result["failed"]:
        console.print(f"[bold red]{result['failed']} of {len(result['captures'])} captures failed[/] (errors above and in {out / 'batch.md'}); "
                      f"fix them and run the same command again: finished captures are reused.")
        raise typer.Exit(1)


@app.command()
def presets() -> None:
    """List the presets in pipelines/ and what each trades."""
    with _guard():
        for name in available_presets():
            default = " (default)" if name == DEFAULT_PRESET else ""
            out_console.print(f"[bold]{escape(name)}[/]{default}: {escape(preset_description(name))}")


def main() -> None:
    app(prog_name="recon")


if __name__ == "__main__":
    sys.exit(main())

"""Issue 17: recon never loses a user's files, refuses hostile input early, and keeps its I/O in one place.

Each test reproduces one case of the issue through the CLI (in-process) or the function at fault.
"""
from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from recon.app.cli import app
from tests import faults

runner = CliRunner()
QUICK = ["--until", "poses"]


def recon(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


def assert_refused(code: int, output: str, *needles: str) -> None:
    assert code == 2, output
    assert "Traceback" not in output and "internal error" not in output, output
    flat = " ".join(output.split())
    for needle in needles:
        assert needle in flat, output


def snapshot(folder: Path) -> dict[str, bytes | str]:
    """Every entry below `folder` (links as their target) with its bytes: to show nothing was touched."""
    out: dict[str, bytes | str] = {}
    for p in sorted(folder.rglob("*")):
        key = p.relative_to(folder).as_posix()
        out[key] = f"link:{os.readlink(p)}" if p.is_symlink() else p.read_bytes() if p.is_file() else "dir"
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return faults.make_capture(tmp_path_factory.mktemp("safety") / "capture", views=6, size=64)


@pytest.fixture
def capture(tiny: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(tiny, tmp_path / "capture"))


# ---------------------------------------------------------------------------------------- data safety
def test_capture_named_like_a_stage_folder_inside_out_is_not_replaced(tiny: Path, tmp_path: Path) -> None:
    """Case 1: `recon run X/01_poses --out X` used to replace the capture folder X/01_poses by its output."""
    x = tmp_path / "X"
    shutil.copytree(tiny, x / "01_poses")
    before = snapshot(x)
    assert_refused(*recon("run", x / "01_poses", "--out", x, *QUICK), "contains the input")
    assert snapshot(x) == before


def test_non_empty_folder_that_is_not_a_scene_is_refused(capture: Path, tmp_path: Path) -> None:
    """Case 2: temporary-looking files, files in 01_poses/ and a foreign manifest.json used to be deleted or replaced."""
    out = tmp_path / "mine"
    (out / ".tmp-notes").mkdir(parents=True)
    (out / ".tmp-notes" / "draft.txt").write_text("keep")
    (out / ".draft.tmp").write_text("keep")
    (out / "01_poses").mkdir()
    (out / "01_poses" / "photo.jpg").write_bytes(b"my photo")
    (out / "manifest.json").write_text('{"shipping": "list"}')
    before = snapshot(out)
    assert_refused(*recon("run", capture, "--out", out, *QUICK), "not a manifest recon can read", "choose another --out")
    assert snapshot(out) == before
    (out / "manifest.json").unlink()
    before = snapshot(out)
    assert_refused(*recon("run", capture, "--out", out, *QUICK), "is not a recon scene")
    assert snapshot(out) == before


def test_leftover_cleanup_removes_only_names_recon_makes(capture: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    assert recon("run", capture, "--out", scene, *QUICK)[0] == 0
    ours = [scene / f".tmp-01_poses-{os.getpid() + 1}", scene / ".old-02_scene-77"]
    for p in ours:
        p.mkdir()
    (scene / ".manifest.json.123.tmp").write_text("half")
    theirs = [scene / ".tmp-holiday", scene / ".old-photos", scene / ".notes.tmp", scene / ".tmp-01_poses-abc"]
    for p in theirs:
        p.mkdir()
    code, output = recon("run", capture, "--out", scene, *QUICK)
    assert code == 0, output
    assert not any(p.exists() for p in ours) and not (scene / ".manifest.json.123.tmp").exists()
    assert all(p.is_dir() for p in theirs)


@pytest.mark.parametrize("where", ["root", "home", "photos", "inside photos"])
def test_out_may_not_be_root_home_or_the_photos(capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    """Case 3: `--out /`, the home folder, the photos folder or a folder inside it used to be accepted."""
    home = tmp_path / "home"
    (home / "Documents").mkdir(parents=True)
    monkeypatch.setenv("HOME", str(home))
    out = {"root": Path("/"), "home": home, "photos": capture, "inside photos": capture / "images" / "scene"}[where]
    needle = {"root": "root of the file system", "home": "your home folder", "photos": "is the input",
              "inside photos": "is inside the input"}[where]
    before = snapshot(capture)
    assert_refused(*recon("run", capture, "--out", out, *QUICK), needle)
    assert snapshot(capture) == before and snapshot(home) == {"Documents": "dir"}


def test_crash_log_goes_to_the_scene_or_user_cache_never_through_a_link(
    capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Case 4: the crash log was /tmp/recon-error.log, written through a symlink planted there."""
    import recon.app.cli as cli

    def boom() -> None:
        raise RuntimeError("a bug")

    cache = tmp_path / "cache"
    (cache / "recon").mkdir(parents=True)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (cache / "recon" / "recon-error.log").symlink_to(victim)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(cli, "_pipeline", boom)
    code, output = recon("run", capture, "--out", tmp_path / "new")
    assert code == 1 and "internal error" in output, output
    log = cache / "recon" / "recon-error.log"
    assert victim.read_text() == "precious"
    assert not log.is_symlink() and "RuntimeError: a bug" in log.read_text()
    monkeypatch.undo()
    scene = tmp_path / "scene"
    assert recon("run", capture, "--out", scene, *QUICK)[0] == 0
    monkeypatch.setattr(cli, "_pipeline", boom)
    code, output = recon("run", capture, "--out", scene)
    assert code == 1 and "RuntimeError: a bug" in (scene / "recon-error.log").read_text()


def test_failed_run_keeps_the_finished_scenes_source_and_preset(capture: Path, tmp_path: Path) -> None:
    """Case 5: a failed run with other photos and another preset rewrote the recorded source and preset."""
    scene = tmp_path / "scene"
    assert recon("run", capture, "--out", scene, "--preset", "fast", *QUICK)[0] == 0
    before = json.loads((scene / "manifest.json").read_text())
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_refused(*recon("run", empty, "--out", scene, "--preset", "quality", *QUICK), "No photos found")
    after = json.loads((scene / "manifest.json").read_text())
    assert (after["source"], after["preset"]) == (before["source"], before["preset"]) == (str(capture.resolve()), "fast")


# ---------------------------------------------------------------------------------------- input checks
def _edit_transforms(capture: Path, edit) -> None:
    path = capture / "transforms.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("case, needle", [
    ("angle_y", "camera_angle_y = 3.5"),
    ("focal", "field of view of 180°"),
    ("size_mismatch", "another shape"),
    ("too_small", "at least 32 px"),
    ("nan_distortion", "'k1' must be a finite number"),
    ("principal_point", "principal point"),
])
def test_imported_intrinsics_are_checked_before_poses_is_done(capture: Path, tmp_path: Path, case: str, needle: str) -> None:
    """`camera_angle_y=3.5` and friends passed poses; normalize then blamed recon's own scene.json."""
    def edit(doc: dict) -> None:
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            doc.pop(key, None)
        doc["camera_angle_x"] = 0.8
        if case == "angle_y":
            doc["camera_angle_y"] = 3.5
        elif case == "focal":
            doc.pop("camera_angle_x")
            doc["fl_x"] = 1e-320  # positive, but a field of view of 180°
        elif case == "size_mismatch":
            doc["w"], doc["h"] = 64, 100
        elif case == "too_small":
            doc["w"], doc["h"] = 16, 16
        elif case == "nan_distortion":
            doc["k1"] = float("nan")
        else:
            doc["cx"] = -40.0
    _edit_transforms(capture, edit)
    scene = tmp_path / "scene"
    assert_refused(*recon("run", capture, "--out", scene, *QUICK), needle, str(capture / "transforms.json"))
    assert not (scene / "01_poses").exists()  # poses is not done


def _colmap_model(folder: Path, camera_params: tuple[float, ...] = (50.0, 32.0, 32.0)) -> Path:
    """A one-image COLMAP binary model (SIMPLE_PINHOLE camera) with its image, written with struct."""
    (folder / "images").mkdir(parents=True)
    Image.fromarray(np.full((64, 64, 3), 128, np.uint8)).save(folder / "images" / "a.png")
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.bin").write_bytes(struct.pack("<QiiQQ", 1, 1, 0, 64, 64) + struct.pack("<3d", *camera_params))
    image = struct.pack("<I4d3dI", 1, 1, 0, 0, 0, 0, 0, 4, 1) + b"a.png\x00" + struct.pack("<Q", 0)
    (model / "images.bin").write_bytes(struct.pack("<Q", 1) + image)
    (model / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    return folder


def test_colmap_binaries_are_size_checked_before_pycolmap_reads_them(tmp_path: Path) -> None:
    """A 4-byte points3D.bin made pycolmap's memory grow without bound (> 8 GB in 27 s)."""
    from recon.capture.colmap import check_colmap_binaries

    project = _colmap_model(tmp_path / "project")
    model = project / "sparse" / "0"
    check_colmap_binaries(model)  # a sound model passes
    (model / "points3D.bin").write_bytes(b"\x01\x02\x03\x04")
    assert_refused(*recon("run", project, "--out", tmp_path / "s", *QUICK), "points3D.bin is damaged", "shorter than")
    (model / "points3D.bin").write_bytes(struct.pack("<Q", 10**9) + b"\x00" * 100)
    assert_refused(*recon("run", project, "--out", tmp_path / "s2", *QUICK), "1,000,000,000 records")


def test_colmap_camera_with_a_bad_focal_is_refused_naming_the_model(tmp_path: Path) -> None:
    project = _colmap_model(tmp_path / "project", camera_params=(-50.0, 32.0, 32.0))
    assert_refused(*recon("run", project, "--out", tmp_path / "s", *QUICK), "focal length", "sparse/0")


@pytest.mark.parametrize("content, needle", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"fl_x": ' + "9" * 4400 + "}", "more than 4300 digits"),
])
def test_hostile_json_is_a_clear_error(capture: Path, tmp_path: Path, content: str, needle: str) -> None:
    (capture / "transforms.json").write_text(content)
    assert_refused(*recon("run", capture, "--out", tmp_path / "s", *QUICK), needle, "transforms.json")


def test_utf8_bom_is_accepted(capture: Path, tmp_path: Path) -> None:
    path = capture / "transforms.json"
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    code, output = recon("run", capture, "--out", tmp_path / "s", *QUICK)
    assert code == 0, output


def test_manifest_with_wrong_types_is_not_an_internal_error(capture: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    assert recon("run", capture, "--out", scene, *QUICK)[0] == 0
    doc = json.loads((scene / "manifest.json").read_text())
    doc["stages"]["poses"]["files"] = 5
    doc["preset"] = ["fast"]
    (scene / "manifest.json").write_text(json.dumps(doc))
    code, output = recon("status", scene)
    assert code == 0 and "poses" in output and "manifest.json was unreadable" in " ".join(output.split()), output
    code, output = recon("run", capture, "--out", scene, *QUICK)
    assert code == 0 and "manifest.json was unreadable" in " ".join(output.split()), output
    assert json.loads((scene / "manifest.json").read_text())["stages"]["poses"]["status"] == "done"


@pytest.mark.parametrize("args, needle", [
    (["--set", "train.budget=abc"], "Cannot read the time budget 'abc'"),
    (["--budget", "-5m"], "must be positive"),
    (["--set", "train.device=tpu"], "'train.device' must be auto, cpu, cuda or cuda:K"),
    (["--set", "train.device=cuda:99"], "train.device"),
    (["--set", "train.steps=" + "9" * 5000], "expects a number"),
    (["--set", "train.fast.aabb=" + "[" * 100_000], "expects a list"),
])
def test_bad_training_options_fail_before_any_stage_runs(capture: Path, tmp_path: Path, args: list[str], needle: str) -> None:
    scene = tmp_path / "scene"
    assert_refused(*recon("run", capture, "--out", scene, *args), needle)
    assert not scene.exists()


def test_uint16_npz_images_keep_their_values(tmp_path: Path) -> None:
    from recon.capture.images import read_image
    from recon.capture.scene import import_npz

    images = np.zeros((2, 40, 40, 3), np.uint16)
    images[..., 0] = 65535
    images[..., 1] = 32768
    poses = np.tile(np.eye(4), (2, 1, 1))
    np.savez(tmp_path / "tiny.npz", images=images, poses=poses, focal=np.array(50.0))
    scene = import_npz(tmp_path / "tiny.npz", tmp_path / "out")
    pixels = read_image(Path(scene.frames[0].file_path))
    assert pixels[..., 0].min() == pytest.approx(1.0) and pixels[..., 1].max() == pytest.approx(128 / 255, abs=1 / 255)
    assert pixels[..., 2].max() == 0.0


def test_paths_with_brackets_print_as_they_are(tiny: Path, tmp_path: Path) -> None:
    """'[/b]' in a path used to be read as rich markup: a MarkupError (internal error) or a mangled path."""
    capture = Path(shutil.copytree(tiny, tmp_path / "x[" / "b]" / "cap[red]"))
    scene = tmp_path / "y[bold]" / "scene"
    code, output = recon("run", capture, "--out", scene, *QUICK)
    assert code == 0, output
    flat = "".join(output.split())
    assert "".join(str(capture).split()) in flat and "y[bold]" in flat


def test_photo_fingerprint_covers_only_the_photos_recon_uses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """It used to hash everything below PHOTOS, unrelated subfolders and symlinks out of it included."""
    import recon.stages.poses as poses

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.fromarray(np.full((40, 40, 3), 40 * i, np.uint8)).save(photos / f"p{i}.jpg")
    (photos / "raw").mkdir()
    (photos / "raw" / "huge.bin").write_bytes(b"x" * 1000)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.jpg").write_bytes(b"not mine")
    (photos / "link").symlink_to(outside, target_is_directory=True)
    read: list[Path] = []
    real = poses.sha256_file
    monkeypatch.setattr(poses, "sha256_file", lambda p: read.append(Path(p)) or real(p))
    first = poses.source_digest(photos, None)
    assert sorted(p.name for p in read) == ["p0.jpg", "p1.jpg", "p2.jpg"]
    (photos / "raw" / "huge.bin").write_bytes(b"y")
    assert poses.source_digest(photos, None) == first
    Image.fromarray(np.full((40, 40, 3), 200, np.uint8)).save(photos / "p1.jpg")
    assert poses.source_digest(photos, None) != first


def test_photo_fingerprint_follows_the_photos_when_they_move(tmp_path: Path) -> None:
    """The poses name the photos (and masks beside them) by their place in the photos folder, so the fingerprint does
    too: the same capture moved elsewhere keeps its poses; moved without its masks, or with a photo renamed, it does
    not."""
    from recon.stages.poses import source_digest

    capture = tmp_path / "capture"
    for folder in ("photos", "masks"):
        (capture / folder).mkdir(parents=True)
    for i in range(3):
        Image.fromarray(np.full((40, 40, 3), 40 * i, np.uint8)).save(capture / "photos" / f"p{i}.jpg")
        Image.fromarray(np.full((40, 40), 255, np.uint8)).save(capture / "masks" / f"p{i}.png")
    first = source_digest(capture / "photos", None)
    moved = tmp_path / "elsewhere" / "the fox"
    moved.parent.mkdir()
    capture.rename(moved)
    assert source_digest(moved / "photos", None) == first
    (moved / "masks").rename(tmp_path / "masks")  # the masks left behind: other poses (no silhouettes)
    assert source_digest(moved / "photos", None) != first
    (tmp_path / "masks").rename(moved / "masks")
    for folder, suffix in (("photos", ".jpg"), ("masks", ".png")):  # a photo renamed, with its mask
        (moved / folder / f"p2{suffix}").rename(moved / folder / f"p3{suffix}")
    assert source_digest(moved / "photos", None) != first


def test_transforms_file_fingerprint_covers_its_images(capture: Path) -> None:
    """Given the transforms.json file itself, an edited image did not re-run poses."""
    from recon.stages.poses import source_digest

    first = source_digest(capture / "transforms.json", None)
    image = sorted((capture / "images").iterdir())[2] if (capture / "images").is_dir() else None
    assert image is not None
    Image.fromarray(np.zeros((64, 64, 3), np.uint8)).save(image)
    assert source_digest(capture / "transforms.json", None) != first
    assert source_digest(capture, None) != first


def test_pycolmap_logs_land_in_the_given_folder(tmp_path: Path) -> None:
    import pycolmap

    from recon.capture.colmap import pycolmap_logging_to

    pycolmap_logging_to(tmp_path / "logs")
    pycolmap.logging.error("recon test line")
    logs = list((tmp_path / "logs").glob("colmap.ERROR.*"))
    assert logs and "recon test line" in logs[0].read_text()


# ---------------------------------------------------------------------------------------- also fix
def test_same_photo_name_with_two_extensions_is_a_clear_error(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, name in enumerate(("a.jpg", "a.jpeg", "b.jpg", "c.jpg")):  # four different photos (copies are left out)
        Image.fromarray(np.full((40, 40, 3), 50 * i, np.uint8)).save(photos / name, format="JPEG")
    assert_refused(*recon("run", photos, "--out", tmp_path / "s", *QUICK), "a.jpeg and a.jpg")


def test_eval_limit_picks_the_views_training_picks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.app.novel_views as nv
    from recon.capture.scene import Frame, Scene, spread_evenly

    frames = [Frame(f"v{i}.png", np.eye(4), 10, 10, 5, 5, 10, 10, split="test") for i in range(10)]
    picked: list[str] = []

    class Stop(Exception):
        pass

    def fake_load(scene, chosen, *a, **k):
        picked.extend(f.name for f in chosen)
        raise Stop

    monkeypatch.setattr(nv, "_trained", lambda *a: (Scene(frames=frames), None, {"background": [1, 1, 1], "max_side": 10}, None))
    monkeypatch.setattr(nv, "load_views", fake_load)
    with pytest.raises(Stop):
        nv.evaluate_scene(tmp_path, tmp_path / "eval", limit=4)
    assert picked == [f.name for f in spread_evenly(frames, 4)] == ["v0.png", "v3.png", "v6.png", "v9.png"]


def test_mesh_stage_uses_train_device(tmp_path: Path) -> None:
    from recon.app.progress import Reporter
    from recon.config import RunConfig
    from recon.errors import ReconError
    from recon.runner.pipeline import StageContext
    from recon.stages import mesh

    config = RunConfig()
    config.train.device = "cuda:99"
    ctx = StageContext("mesh", "04_mesh", tmp_path, tmp_path, {"normalize": tmp_path, "train": tmp_path},
                       config.mesh, config, None, tmp_path, Reporter(quiet=True))
    with pytest.raises(ReconError, match="train.device=cuda:99"):
        mesh.run(ctx)


def test_library_modules_import_no_runner_and_config_no_torch() -> None:
    """scene.py, field.py and geometry/export.py imported the runner for its atomic writes; config.py loaded torch
    (through FastConfig), pycolmap and scipy (through SfmOptions), so reading a scene paid for them."""
    import ast

    code = ("import sys, recon.capture.scene, recon.config; "
            "print(sorted(m for m in ('torch', 'pycolmap', 'scipy', 'recon.runner.pipeline') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=faults.REPO,
                          env=faults.env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
    library = ["capture/scene.py", "field.py", "evaluation/views.py", "atomic.py", "geometry/export.py", "geometry/preview.py", "geometry/extract.py"]
    for name in library:
        tree = ast.parse((faults.REPO / "recon" / name).read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        assert not {m for m in imported if m.startswith(("recon.runner.pipeline", "recon.app.cli", "recon.stages"))}, name


def test_bench_reruns_poses_and_normalize_only_when_a_preset_changes_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """bench ran every preset `--from train`: a preset that changes normalize kept the shared normalize output."""
    import recon.config
    import recon.stages
    from recon.app.bench import run_bench
    from recon.app.progress import Reporter
    from recon.runner.pipeline import Pipeline, Stage

    ran: list[tuple[str, str]] = []
    metrics = {"model": "fast", "steps": 1, "train_time_s": 1.0, "rays_per_s": 1.0, "evals": [],
               "test": {"psnr": 20.0, "ssim": 0.5, "views": []}}

    def stage(name: str, folder: str, inputs: tuple[str, ...]) -> Stage:
        def run(ctx) -> dict:
            ran.append((ctx.scene_dir.name, name))
            (ctx.out / "metrics.json").write_text(json.dumps(metrics))
            return {}
        return Stage(name, folder, inputs, 1, run, needs_source=name == "poses",
                     source_digest=(lambda s, c: "photos") if name == "poses" else None)

    pipe = Pipeline([stage("poses", "01_poses", ()), stage("normalize", "02_scene", ("poses",)),
                     stage("train", "03_field", ("normalize",)), stage("mesh", "04_mesh", ("normalize", "train"))])
    monkeypatch.setattr(recon.stages, "default_pipeline", lambda: pipe)
    presets = tmp_path / "presets"
    presets.mkdir()
    (presets / "plain.toml").write_text('description = "defaults"\n')
    (presets / "wide.toml").write_text('description = "a wider box"\n[normalize]\nbox_margin = 0.3\n')
    monkeypatch.setattr(recon.config, "PIPELINES_DIR", presets)
    photos = tmp_path / "photos"
    photos.mkdir()
    run_bench(str(photos), ["plain", "wide"], tmp_path / "bench", [], Reporter(quiet=True), until="train")
    assert ran == [("photos-poses", "poses"), ("photos-poses", "normalize"),
                   ("photos-plain", "train"), ("photos-wide", "normalize"), ("photos-wide", "train")]


# ---------------------------------------------------------------------------------------- issue 35: who owns a folder
@pytest.fixture(scope="module")
def trained(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = tmp_path_factory.mktemp("owned") / "scene"
    proc = faults.run(tiny, scene, "--until", "train")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return scene


@pytest.mark.parametrize("where", ["photos", "home", "user's batch.md"])
def test_batch_out_may_not_be_the_photos_home_or_a_users_folder(capture: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                where: str) -> None:
    """`recon batch --out` took the capture's own photos folder and $HOME, and overwrote a batch.md the user had there."""
    pytest.importorskip("ray")
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    out = {"photos": capture, "home": home, "user's batch.md": tmp_path / "reports"}[where]
    out.mkdir(exist_ok=True)
    (out / "batch.md").write_text("my notes")
    before = snapshot(out)
    needle = {"photos": "is the input", "home": "your home folder", "user's batch.md": "files that recon did not write (batch.md)"}[where]
    assert_refused(*recon("batch", capture, "--out", out), needle)
    assert snapshot(out) == before


def test_export_and_render_never_write_into_a_stage_folder(tiny: Path, trained: Path) -> None:
    """`recon export --out SCENE/03_field/x` or `recon render --out SCENE/04_mesh` corrupted the stage, which then re-ran."""
    before = snapshot(trained)
    assert_refused(*recon("run", tiny, "--out", trained / "03_field" / "nested", *QUICK), f"inside {trained / '03_field'}")
    assert_refused(*recon("export", trained, "--out", trained / "03_field" / "x"), f"inside {trained / '03_field'}, a part of the scene")
    assert_refused(*recon("render", trained, "--out", trained / "02_scene", "--frames", "1"), f"inside {trained / '02_scene'}, a part")
    assert_refused(*recon("render", trained, "--out", trained, "--frames", "1"), "it holds a recon scene, not a recon render")
    assert snapshot(trained) == before


def test_reexport_keeps_the_files_the_user_added(trained: Path, tmp_path: Path) -> None:
    """Re-exporting over an export deleted what the user had added there."""
    out = tmp_path / "ns"
    assert recon("export", trained, "--out", out)[0] == 0
    (out / "notes.txt").write_text("mine")
    (out / "images" / "sketch.txt").write_text("mine too")
    code, output = recon("export", trained, "--out", out, "--format", "colmap")
    assert code == 0, output
    assert (out / "notes.txt").read_text() == "mine" and (out / "images" / "sketch.txt").read_text() == "mine too"
    assert (out / "sparse" / "0" / "images.txt").is_file() and not (out / "transforms.json").exists()
    (out / "transforms.json").write_text("{}")  # the user's file where the nerfstudio export would write its own
    before = snapshot(out)
    assert_refused(*recon("export", trained, "--out", out), "transforms.json, which recon did not write there")
    assert snapshot(out) == before


def test_rerender_keeps_the_users_files_and_never_overwrites_them(trained: Path, tmp_path: Path) -> None:
    """`recon render --out DIR` overwrote a user's orbit.gif and frames without asking."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "orbit.gif").write_bytes(b"my gif")
    assert_refused(*recon("render", trained, "--out", mine, "--frames", "2"), "files that recon did not render (orbit.gif)")
    assert (mine / "orbit.gif").read_bytes() == b"my gif" and len(list(mine.iterdir())) == 1
    out = tmp_path / "renders"
    assert recon("render", trained, "--out", out, "--frames", "2")[0] == 0
    (out / "notes.txt").write_text("mine")
    (out / "spiral.gif").write_bytes(b"my spiral")
    assert_refused(*recon("render", trained, "--out", out, "--path", "spiral", "--frames", "2"), "spiral.gif")
    (out / "spiral.gif").unlink()
    code, output = recon("render", trained, "--out", out, "--path", "spiral", "--frames", "2")
    assert code == 0, output
    assert (out / "notes.txt").read_text() == "mine" and (out / "spiral_001.png").is_file()
    assert not (out / "orbit.gif").exists()  # recon's earlier render is replaced, not mixed with this one
    assert not [p for p in out.iterdir() if p.name.startswith(".recon-staging")]


def test_eval_never_replaces_the_users_files(trained: Path, tmp_path: Path) -> None:
    """`recon eval SCENE --out DIR` overwrote a metrics.json (or grid.png, or views/*.png) the user had in DIR."""
    mine = tmp_path / "mine"
    (mine / "views").mkdir(parents=True)
    (mine / "metrics.json").write_text("my metrics")
    assert_refused(*recon("eval", trained, "--out", mine, "--limit", "1", "--split", "train"), "files that recon did not write (metrics.json, views)")
    assert snapshot(mine) == {"metrics.json": b"my metrics", "views": "dir"}
    out = tmp_path / "ev"
    code, output = recon("eval", trained, "--out", out, "--limit", "1", "--split", "train")
    assert code == 0, output
    (out / "notes.txt").write_text("mine")
    (out / "grid.png").unlink()
    (out / "grid.png").write_bytes(b"my grid")  # recon's name, recorded as recon's: replaced on the next run
    code, output = recon("eval", trained, "--out", out, "--limit", "1", "--split", "train")
    assert code == 0, output
    assert (out / "notes.txt").read_text() == "mine" and (out / "grid.png").read_bytes()[:4] == b"\x89PNG"
    # SCENE/eval from before evaluations kept a record: recon's, as its files say
    (out / "notes.txt").unlink()
    own = Path(shutil.copytree(out, trained / "eval", dirs_exist_ok=True))
    (own / ".recon-eval.json").unlink()
    code, output = recon("eval", trained, "--limit", "1", "--split", "train")
    assert code == 0 and (own / ".recon-eval.json").is_file(), output
    shutil.rmtree(own)


def test_fit_image_never_replaces_the_users_files(tiny: Path, tmp_path: Path) -> None:
    """`recon fit-image --out DIR` overwrote a curve.json (or fitted.png) the user had in DIR."""
    image = min((tiny / "images").iterdir())
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "curve.json").write_text("my curve")
    assert_refused(*recon("fit-image", image, "--out", mine, "--steps", "2", "--size", "32"),
                   "files that recon did not write (curve.json)")
    assert snapshot(mine) == {"curve.json": b"my curve"}
    out = tmp_path / "fit"
    code, output = recon("fit-image", image, "--out", out, "--steps", "2", "--size", "32")
    assert code == 0, output
    assert json.loads((out / "curve.json").read_text())[-1]["step"] == 2
    (out / "notes.txt").write_text("mine")
    code, output = recon("fit-image", image, "--out", out, "--steps", "3", "--size", "32")
    assert code == 0, output
    assert json.loads((out / "curve.json").read_text())[-1]["step"] == 3  # its own files are replaced
    assert (out / "notes.txt").read_text() == "mine" and (out / "fitted.png").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".recon-staging")]


def _fake_bench(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """A photos folder and a stand-in pipeline (each stage writes metrics.json) for `run_bench`; the stages it ran."""
    import recon.stages
    from recon.runner.pipeline import Pipeline, Stage

    ran: list[str] = []
    metrics = {"model": "fast", "steps": 1, "train_time_s": 1.0, "rays_per_s": 1.0, "evals": [],
               "test": {"psnr": 20.0, "ssim": 0.5, "views": []}}

    def stage(name: str, folder: str, inputs: tuple[str, ...]) -> Stage:
        def run(ctx) -> dict:
            ran.append(name)
            (ctx.out / "metrics.json").write_text(json.dumps(metrics))
            return {}
        return Stage(name, folder, inputs, 1, run, needs_source=name == "poses",
                     source_digest=(lambda s, c: "photos") if name == "poses" else None)

    pipe = Pipeline([stage("poses", "01_poses", ()), stage("normalize", "02_scene", ("poses",)),
                     stage("train", "03_field", ("normalize",))])
    monkeypatch.setattr(recon.stages, "default_pipeline", lambda: pipe)
    photos = tmp_path / "photos"
    photos.mkdir()
    return photos, ran


def test_bench_never_replaces_the_users_reports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`recon bench --out DIR` (and --profile) overwrote a bench.md or profile.md the user had in DIR."""
    from recon.app.bench import run_bench
    from recon.app.profiling import run_profile
    from recon.app.progress import Reporter
    from recon.errors import InputError

    photos, ran = _fake_bench(tmp_path, monkeypatch)
    for name in ("bench.md", "profile.md"):
        mine = tmp_path / f"mine-{name}"
        mine.mkdir()
        (mine / name).write_text("my notes")
        with pytest.raises(InputError, match=f"files that recon did not write \\({name}\\)"):
            if name == "bench.md":
                run_bench(str(photos), ["fast"], mine, [], Reporter(quiet=True), until="train")
            else:
                run_profile(str(photos), ["fast"], mine, [], Reporter(quiet=True))
        assert snapshot(mine) == {name: b"my notes"} and ran == []
    out = tmp_path / "bench"
    run_bench(str(photos), ["fast"], out, [], Reporter(quiet=True), until="train")
    assert ran == ["poses", "normalize", "train"] and (out / ".recon-bench.json").is_file()
    (out / "notes.txt").write_text("mine")
    run_bench(str(photos), ["fast"], out, [], Reporter(quiet=True), until="train")  # its own folder: reused
    assert (out / "notes.txt").read_text() == "mine" and json.loads((out / "bench.json").read_text())[0]["name"] == "fast"


def test_a_benchmark_folder_from_before_records_is_adopted_only_when_it_holds_only_recons(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from recon.app.bench import run_bench
    from recon.app.progress import Reporter
    from recon.errors import InputError

    photos, _ = _fake_bench(tmp_path, monkeypatch)
    old = tmp_path / "old"
    run_bench(str(photos), ["fast"], old, [], Reporter(quiet=True), until="train")
    (old / ".recon-bench.json").unlink()  # as recon left a benchmark before it kept a record
    alike = Path(shutil.copytree(old, tmp_path / "alike"))
    (alike / "draft.txt").write_text("mine")  # ... with a file of the user's beside it: not recon's folder
    run_bench(str(photos), ["fast"], old, [], Reporter(quiet=True), until="train")
    assert (old / ".recon-bench.json").is_file()
    with pytest.raises(InputError, match="draft.txt"):
        run_bench(str(photos), ["fast"], alike, [], Reporter(quiet=True), until="train")
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "bench.md").write_text("my notes")  # a report's name alone is no sign of recon
    with pytest.raises(InputError, match="bench.md"):
        run_bench(str(photos), ["fast"], lone, [], Reporter(quiet=True), until="train")
    assert (lone / "bench.md").read_text() == "my notes"


def test_photos_folder_named_masks_is_not_its_own_masks_folder(tmp_path: Path) -> None:
    from recon.capture.scene import find_masks

    photos = tmp_path / "masks"
    photos.mkdir()
    for i in range(3):
        Image.fromarray(np.full((40, 40, 3), 60 * i, np.uint8)).save(photos / f"p{i}.png")
    assert find_masks(sorted(photos.iterdir())) == (None, {})


@pytest.mark.parametrize("kind", ["loop", "dangling"])
def test_broken_links_are_a_clear_error_and_leave_nothing_behind(capture: Path, trained: Path, tmp_path: Path, kind: str) -> None:
    """Symlink loops as --out, a batch entry or an export target were internal errors; an export to a dangling link
    left its temporary folder behind."""
    pytest.importorskip("ray")
    links = tmp_path / "links"
    links.mkdir()
    bad = links / "out"
    if kind == "loop":
        bad.symlink_to(links / "out")
    else:
        bad.symlink_to(tmp_path / "nowhere" / "folder")
    needle = "loops or points to nothing"
    assert_refused(*recon("export", trained, "--out", bad), str(bad), needle)
    assert_refused(*recon("render", trained, "--out", bad, "--frames", "1"), str(bad), needle)
    assert_refused(*recon("batch", capture, "--out", bad), str(bad), needle)
    assert_refused(*recon("batch", bad, "--out", tmp_path / "batch"), str(bad), needle)
    assert_refused(*recon("run", capture, "--out", bad, *QUICK), str(bad), needle)
    assert sorted(p.name for p in links.iterdir()) == ["out"] and not (tmp_path / "batch").exists()
    assert not (tmp_path / "nowhere").exists()


def test_a_bench_row_reads_what_the_normalize_stage_reported_and_nothing_when_it_is_missing(tmp_path: Path) -> None:
    """The automatic masks' count and in-hull share come from the scene's manifest; a scene without one (or a stage
    that did not report them) gives nothing rather than an error."""
    import json

    from recon.app.bench import _stage_summary

    assert _stage_summary(tmp_path, "normalize") == {}
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"stages": {"normalize": {"summary": {"auto_masks": 67, "auto_masks_in_hull": 0.95}}, "poses": {}}}))
    assert _stage_summary(tmp_path, "normalize") == {"auto_masks": 67, "auto_masks_in_hull": 0.95}
    assert _stage_summary(tmp_path, "poses") == {} and _stage_summary(tmp_path, "train") == {}
    (tmp_path / "manifest.json").write_text("{not json")
    assert _stage_summary(tmp_path, "normalize") == {}


@pytest.mark.parametrize("profile", [
    [{"name": "fast", "limits": {}, "profiled_steps": 4, "commit": "abc"}],  # profile.json's rows
    {"limits": {}, "results": []},  # an earlier recon's profile.json
    [{"name": "fast", "psnr": 30.0}],  # not a profile
])
def test_a_profile_folder_from_before_records_is_recognised_by_its_profile_json(tmp_path: Path, profile: Any) -> None:
    from recon.app.bench import _unrecorded_bench

    (tmp_path / "profile.json").write_text(json.dumps(profile))
    (tmp_path / "profile.md").write_text("# recon bench --profile")
    found = _unrecorded_bench(tmp_path)
    assert found == ({"profile.json", "profile.md"} if "profiled_steps" in json.dumps(profile)
                     or isinstance(profile, dict) else None)

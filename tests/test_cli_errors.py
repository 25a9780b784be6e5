"""Bad input through the real CLI: one clear paragraph, a non-zero exit, no traceback, nothing lost; and what it says
before torch loads (a typo, `--version`)."""
from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from recon.app.cli import app
from tests import faults

REPO = Path(__file__).resolve().parents[1]

runner = CliRunner()


def recon(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.output


def assert_clean_error(code: int, output: str, *needles: str) -> None:
    assert code == 2, output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in output, output


def _noise_photos(folder: Path, n: int, size: int = 160, seed: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (size, size, 3), dtype=np.uint8)).save(folder / f"p{i}.jpg")


def test_missing_and_empty_folder(tmp_path: Path) -> None:
    assert_clean_error(*recon("run", str(tmp_path / "nope"), "--out", str(tmp_path / "s")), "does not exist")
    assert not (tmp_path / "s").exists()  # a mistyped input leaves no scene folder behind
    (tmp_path / "empty").mkdir()
    assert_clean_error(*recon("run", str(tmp_path / "empty"), "--out", str(tmp_path / "s")), "No photos found")


def test_too_few_photos(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "two", 2)
    assert_clean_error(*recon("run", str(tmp_path / "two"), "--out", str(tmp_path / "s")), "Only 2 photo(s)", "at least 3")
    assert not (tmp_path / "s").exists()  # told before the scene folder is made


def test_photos_named_alike_but_for_the_extension(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "p", 3)
    (tmp_path / "p" / "p1.png").write_bytes((tmp_path / "p" / "p1.jpg").read_bytes())
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", str(tmp_path / "s")), "p1.jpg and p1.png",
                       "Rename or remove one")
    assert not (tmp_path / "s").exists()


def test_corrupt_jpeg_names_the_file(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "p", 3)
    (tmp_path / "p" / "bad.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    code, out = recon("run", str(tmp_path / "p"), "--out", str(tmp_path / "s"))
    assert_clean_error(code, out, "bad.jpg", "Remove it from the folder")


def test_photos_that_do_not_overlap(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "p", 4)
    (tmp_path / "p" / "notes.txt").write_text("not a photo")
    code, out = recon("run", str(tmp_path / "p"), "--out", str(tmp_path / "s"), "--set", "poses.max_side=160")
    assert_clean_error(code, out, "overlap")
    assert "Skipping notes.txt" in out


def test_output_is_a_file(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "p", 3)
    (tmp_path / "out").write_text("x")
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", str(tmp_path / "out")), "is a file")


def test_bad_options(tmp_path: Path) -> None:
    _noise_photos(tmp_path / "p", 3)
    out = str(tmp_path / "s")
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", out, "--preset", "nonexistent"), "Unknown preset")
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", out, "--set", "poses.bogus=1"), "Unknown option")
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", out, "--set", "poses.max_side=big"), "expects a number")
    assert_clean_error(*recon("run", str(tmp_path / "p"), "--out", out, "--from", "nostage"), "Unknown stage")


def test_commands_that_read_a_scene_say_what_it_lacks(tmp_path: Path) -> None:
    """A mistyped scene folder, a folder of the user's and a scene whose run stopped early each get their own
    sentence (what to run), before any command writes its output."""
    missing, foreign, posed = tmp_path / "missing", tmp_path / "foreign", tmp_path / "posed"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    posed.mkdir()
    (posed / "manifest.json").write_text("{}")
    (posed / "01_poses").mkdir()
    outputs = {"render": ["--out", str(tmp_path / "frames")], "export": ["--out", str(tmp_path / "export")]}
    for command in ("status", "eval", "render", "export"):
        options = outputs.get(command, [])
        assert_clean_error(*recon(command, str(missing), *options), "does not exist", f"--out {missing}")
        assert_clean_error(*recon(command, str(foreign), *options), "not a recon scene folder")
    for command in ("eval", "render"):
        assert_clean_error(*recon(command, str(posed), *outputs.get(command, [])), "no trained field yet",
                           f"recon run PHOTOS --out {posed}")
    assert_clean_error(*recon("eval", str(posed), "--gt-mesh", str(foreign / "notes.txt")), "no mesh yet")
    assert not (tmp_path / "frames").exists() and not (tmp_path / "export").exists() and not missing.exists()
    assert sorted(p.name for p in posed.iterdir()) == ["01_poses", "manifest.json"]


def test_failed_stage_keeps_earlier_complete_stages(tmp_path: Path, shared_data: Path) -> None:
    scene = tmp_path / "s"
    code, out = recon("run", str(shared_data / "nerf_synthetic_lego_half"), "--out", str(scene), "-q", "--until", "normalize")
    assert code == 0, out
    before = (scene / "02_scene" / "scene.json").read_bytes()
    code, out = recon("normalize", str(scene), "--set", "normalize.up=sideways")
    assert_clean_error(code, out, "must be one of")
    assert (scene / "02_scene" / "scene.json").read_bytes() == before
    code, out = recon("status", str(scene))
    assert code == 0 and "done" in out


def test_real_process_exit_code_and_no_traceback(tmp_path: Path) -> None:
    """`python -m recon` (a checkout without an install) is the same command line as `recon`."""
    proc = subprocess.run(
        [sys.executable, "-m", "recon", "run", str(tmp_path / "missing"), "--out", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr + proc.stdout
    assert "does not exist" in proc.stderr


@pytest.mark.parametrize("photos, setting, said", [
    ("missing", "train.steps=100", "does not exist"),
    ("images", "mesh.resolution=5", "'mesh.resolution' must be"),
    ("images/IMG_1.JPG", "train.steps=100", "is one photo; recon needs many photos of the object"),
    ("photos.zip", "train.steps=100", "is an archive; recon reads the photos themselves. Unpack it"),
])
def test_a_missing_input_or_a_value_out_of_range_is_refused_before_torch_loads(
    tmp_path: Path, photos: str, setting: str, said: str
) -> None:
    """A typo costs a second, not the seconds torch takes to load (to look for a GPU), and makes no scene folder; nor
    does one photo or an archive of them given for a folder (they made one and were refused in the poses stage)."""
    (tmp_path / "images").mkdir()
    for i in (1, 2, 3):  # enough photos: the option is what is wrong
        Image.fromarray(np.full((40, 40, 3), i, np.uint8)).save(tmp_path / "images" / f"IMG_{i}.JPG")
    with zipfile.ZipFile(tmp_path / "photos.zip", "w") as archive:
        archive.write(tmp_path / "images" / "IMG_1.JPG", "IMG_1.JPG")
    proc = faults.recon_noting_torch("run", str(tmp_path / photos), "--out", str(tmp_path / "s"), "--set", setting)
    assert said in " ".join(proc.stderr.split())
    assert proc.stdout.split()[-5:] == ["exit", "2", "torch", "loaded", "False"], proc.stdout + proc.stderr
    assert not (tmp_path / "s").exists()


def test_version_names_recon_and_its_packages_without_loading_torch() -> None:
    proc = faults.recon_noting_torch("--version")
    version = re.search(r'^version = "(.+)"$', (REPO / "pyproject.toml").read_text(), re.M).group(1)
    import torch

    assert proc.stdout.startswith(f"recon {version} (Python ") and f"torch {torch.__version__}," in proc.stdout
    assert proc.stdout.split()[-5:] == ["exit", "0", "torch", "loaded", "False"], proc.stdout + proc.stderr


"""Every option × hostile values through the real `recon run` entry: exit 0 or one clear line with exit 2, nothing else.

A value validation lets through runs the import of a tiny transforms.json capture (no structure from motion), so
an accepted value is exercised past validation too; a refused one must be refused before any stage folder exists.
Hypothesis is derandomized (the same examples every run) and bounded; the `slow` version draws many more and runs
through normalize.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from typer.testing import CliRunner

from recon.app.cli import app
from recon.camera import look_at
from recon.config import RunConfig

runner = CliRunner()


def option_keys(config: object, prefix: str = "") -> list[str]:
    """Dotted names of every option (nested sections included)."""
    keys: list[str] = []
    for f in dataclasses.fields(config):  # type: ignore[arg-type]
        value = getattr(config, f.name)
        keys += option_keys(value, f"{prefix}{f.name}.") if dataclasses.is_dataclass(value) else [f"{prefix}{f.name}"]
    return keys


KEYS = option_keys(RunConfig())
HOSTILE = ["0", "-1", "-0.5", "1e300", "9" * 400, "2147483648", "nan", "inf", "-inf", "", "abc", "[1]", "{}",
           "true", "[[0, 0, 0], [0, 0, 0]]", "0.999999", "1"]
"""0, negative, huge, NaN, inf, empty, the wrong type (text, a list, an object, a bool), a box of zero size, and the
edges of a probability."""


def _capture(folder: Path, n: int = 4) -> None:
    """A tiny posed capture: images/ + transforms.json, cameras on a circle looking at the origin."""
    (folder / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        Image.fromarray(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)).save(folder / "images" / f"v{i}.png")
        angle = 2 * math.pi * i / n
        eye = np.array([3 * math.cos(angle), 3 * math.sin(angle), 0.5])
        frames.append({"file_path": f"images/v{i}.png", "transform_matrix": look_at(eye, np.zeros(3)).tolist()})
    doc = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 16.0, "w": 32, "h": 32, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-options") / "cap"
    _capture(folder)
    return folder


_scene_ids = itertools.count()


def assert_exit_0_or_one_clear_line(capture: Path, overrides: list[tuple[str, str]], until: str) -> None:
    scene = capture.parent / f"scene{next(_scene_ids)}"
    args = ["run", str(capture), "--out", str(scene), "--until", until, "-q"]
    for key, value in overrides:
        args += ["--set", f"{key}={value}"]
    result = runner.invoke(app, args)
    shown = f"{overrides}: exit {result.exit_code}\n{result.output}"
    assert result.exception is None or isinstance(result.exception, SystemExit), shown
    assert result.exit_code in (0, 2), shown
    assert "Traceback" not in result.output and "internal error" not in result.output, shown
    if result.exit_code == 2:
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: "), shown
        assert not (scene / "01_poses").exists(), shown  # refused before any stage ran


_value = st.one_of(st.sampled_from(HOSTILE), st.integers(-(2**70), 2**70).map(str),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr))
_override = st.tuples(st.sampled_from(KEYS), _value)


@settings(max_examples=40, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(overrides=st.lists(_override, min_size=1, max_size=2))
def test_hostile_option_values_exit_0_or_one_clear_line(capture: Path, overrides: list[tuple[str, str]]) -> None:
    assert_exit_0_or_one_clear_line(capture, overrides, until="poses")


@pytest.mark.parametrize("key", KEYS)
def test_every_option_refuses_nan_and_text_or_takes_them(capture: Path, key: str) -> None:
    """Each key once with the two values every parser must survive (NaN for numbers, text for everything)."""
    assert_exit_0_or_one_clear_line(capture, [(key, "nan")], until="poses")
    assert_exit_0_or_one_clear_line(capture, [(key, "9" * 400)], until="poses")


@pytest.mark.slow
@settings(max_examples=400, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(overrides=st.lists(_override, min_size=1, max_size=4))
def test_hostile_option_values_long(capture: Path, overrides: list[tuple[str, str]]) -> None:
    assert_exit_0_or_one_clear_line(capture, overrides, until="normalize")

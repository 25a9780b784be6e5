"""`recon view` without the optional viser package: exit 2 and the install command, no traceback."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from recon.app.cli import app


def test_view_without_viser_says_how_to_install_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now raises ImportError
    result = CliRunner().invoke(app, ["view", str(tmp_path)])
    assert result.exit_code == 2
    assert 'pip install -c constraints.txt -e ".[view]"' in result.output and "Traceback" not in result.output


def test_view_of_a_folder_without_a_scene_is_a_clear_error(tmp_path: Path) -> None:
    pytest.importorskip("viser")
    result = CliRunner().invoke(app, ["view", str(tmp_path), "--port", "0"])
    assert result.exit_code == 2 and "not a recon scene folder" in result.output

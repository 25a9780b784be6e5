"""Shared test fixtures: paths to the shipped sample and to the optional ../shared data sets."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("COLUMNS", "400")  # rich must not wrap the error messages tests look for

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or skip the test cleanly when it is absent (e.g. on a contributor's machine)."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: long runs kept out of the default suite (pytest -m slow)")

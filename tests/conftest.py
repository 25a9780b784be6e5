"""Shared test fixtures: paths to the shipped sample and to the optional ../shared data sets."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hypothesis import settings

os.environ.setdefault("COLUMNS", "400")  # rich must not wrap the error messages tests look for

# hypothesis: "ci" (few examples, no deadline: 2 shared cores make timings noisy) by default; "long" for
# `pytest -m slow` or HYPOTHESIS_PROFILE=long
settings.register_profile("ci", max_examples=15, deadline=None, print_blob=True)
settings.register_profile("long", max_examples=300, deadline=None, print_blob=True)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
"""What device-parametrized tests run on: the CPU always, CUDA where present (a GPU machine runs the same checks)."""


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    """Each of `DEVICES` in turn: a test taking `device` runs once per device."""
    return torch.device(request.param)


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or skip the test cleanly when it is absent (e.g. on a contributor's machine)."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: long runs kept out of the default suite (pytest -m slow)")
    markexpr = config.getoption("markexpr", "") or ""
    default = "long" if "slow" in markexpr and "not slow" not in markexpr else "ci"
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", default))

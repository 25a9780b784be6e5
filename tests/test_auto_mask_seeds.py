"""benchmarks/auto_mask_seeds.py's outline measure: how many pixels a mask's outline lies outside and inside the
true one, which says whether the automatic masks are fat or thin rather than only how much they overlap."""
from __future__ import annotations

import numpy as np
import pytest

from tests.scripts import load_script


def _tool():
    return load_script("benchmarks/auto_mask_seeds.py", "auto_mask_seeds")


def _disc(radius: float, size: int = 200) -> np.ndarray:
    y, x = np.mgrid[:size, :size] + 0.5
    return np.hypot(x - size / 2, y - size / 2) <= radius


@pytest.mark.parametrize("grow", [2.0, -3.0])
def test_a_mask_grown_or_shrunk_all_round_is_off_by_that_many_pixels(grow: float) -> None:
    truth = _disc(50.0)
    extra, missed = _tool().outline_offset_px(_disc(50.0 + grow), truth)
    assert extra == pytest.approx(max(grow, 0.0), abs=0.25)
    assert missed == pytest.approx(max(-grow, 0.0), abs=0.25)


def test_a_mask_shifted_sideways_is_off_both_ways_by_the_same_amount() -> None:
    truth = _disc(50.0)
    extra, missed = _tool().outline_offset_px(np.roll(truth, 4, axis=1), truth)
    assert extra == pytest.approx(missed, rel=0.05)
    assert extra == pytest.approx(4 / np.pi, abs=0.2)  # a disc shifted by d ≪ r adds a crescent of 2·r·d


@pytest.mark.parametrize("text, share", [("0.2", True), ("0", True), ("1", False), ("-0.1", False), ("most", False)])
def test_a_hull_tolerance_variant_takes_a_share_of_the_photos(text: str, share: bool) -> None:
    assert _tool()._is_share(text) is share

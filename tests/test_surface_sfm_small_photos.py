"""Small photos get COLMAP's default 2x-resolution SIFT from the first SfM attempt (the pose ceiling of the
surface model's accuracy on the shipped sample); large ones keep native resolution."""
from __future__ import annotations

from recon.capture.sfm import ATTEMPTS, SMALL_PHOTO_SIDE, attempts_for


def test_small_photos_extract_at_twice_the_resolution_from_the_first_attempt() -> None:
    small = attempts_for([(400, 400), (SMALL_PHOTO_SIDE, 300)])
    assert small[0].first_octave == -1 and "2× resolution" in small[0].settings(_Opts())
    assert small[0].feature_factor == ATTEMPTS[0].feature_factor
    assert small[1:] == ATTEMPTS  # native resolution next when the 2x attempt leaves photos out


def test_large_photos_keep_native_resolution_first() -> None:
    large = attempts_for([(400, 400), (SMALL_PHOTO_SIDE + 1, 600)])
    assert all(a.first_octave == 0 for a in large)  # every attempt, the retry too (tests/test_sfm.py: which ones)


class _Opts:
    max_features = 8192

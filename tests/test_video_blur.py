"""Video frame selection when windows hold a frame or two: a blurred frame is never kept where a sharp neighbour
exists (a rendered orbit from fixtures/gen_video.py whose blurred frames are known)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from recon.capture import video

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fixtures"))
import gen_video  # noqa: E402

BLURRED = [8, 36, 45, 54, 63]
"""Five blurred frames of 70 (the pause is frames 20-29)."""
CLIP = dict(size=(160, 120), fps=10.0, seconds=6.0, pause_s=1.0, blurred=BLURRED, supersample=1, mesh_res=64,
            mesh_faces=None)


@pytest.fixture(scope="module")
def dense_clip(pytestconfig: pytest.Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 70-frame clip, rendered once per generator version into pytest's cache (else a temporary folder)."""
    name = f"recon-video-dense-v{gen_video.FORMAT_VERSION}"
    cache = getattr(pytestconfig, "cache", None)
    folder = Path(cache.mkdir(name)) if cache is not None else tmp_path_factory.mktemp(name)
    if not (folder / "video_info.json").is_file():
        gen_video.generate_video(folder, **CLIP)
    return folder / "clip.mp4"


def test_no_blurred_frame_is_kept_where_a_sharp_neighbour_exists(dense_clip: Path) -> None:
    info = json.loads((dense_clip.parent / "video_info.json").read_text())
    assert info["frames"] == 70 and info["blurred"] == BLURRED
    sel = video.select_frames(dense_clip, video.SelectOptions(target_frames=50), lambda frame, image: None)
    kept = [f.index for f in sel.kept]
    assert not set(kept) & set(BLURRED), kept
    assert len(kept) + sum(sel.dropped.values()) == sel.read == 70  # every frame kept or counted under a reason
    # a blurred window is merged into the next, not left empty: the orbit keeps a frame close to each blurred one
    for b in BLURRED:
        assert min(abs(k - b) for k in kept) <= 2, (b, kept)
    moving = [k for k in kept if not 20 <= k <= 29]
    assert len(moving) >= 40 - len(BLURRED)  # 50 windows of 1.4 frames, less the pause's and the blurred ones


def test_one_frame_windows_skip_blurred_frames_without_gaps(dense_clip: Path) -> None:
    """One window per frame: a blurred frame's window is merged into the next, whose sharp frame is kept."""
    sel = video.select_frames(dense_clip, video.SelectOptions(target_frames=70), lambda frame, image: None)
    kept = [f.index for f in sel.kept]
    assert not set(kept) & set(BLURRED), kept
    gaps = [b - a for a, b in zip(kept, kept[1:]) if not (a <= 29 and b >= 20)]
    assert max(gaps) == 2 and len(kept) >= 70 - 10 - len(BLURRED) - 1  # the pause keeps at most one of its views

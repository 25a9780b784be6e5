"""Frames from a video for structure from motion: the sharpest frame of each stretch of the clip, no repeats.

A phone clip of a walk around an object has far more frames than SfM needs, some blurred by the
walk and long runs of nearly identical ones where the camera stood still. `select_frames` decodes the
clip once (OpenCV's bundled FFmpeg, rotation metadata applied so portrait clips come out upright),
splits it into `target_frames` equal windows and keeps the sharpest frame of each (variance of the
Laplacian of a downscaled gray copy), unless it barely differs from the last kept frame (camera
standing still). Frames are handed to a callback as they are chosen, so a 4K clip never sits in
memory, and every dropped frame is counted under its reason.
"""
from __future__ import annotations

import contextlib
import os
import struct
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.capture.images import MAX_PIXELS, list_photos, too_large
from recon.errors import InputError

VIDEO_SUFFIXES = frozenset({".mp4", ".mov", ".m4v"})
ANALYSIS_SIDE = 640
"""Sharpness is measured on a gray copy downscaled to this longest side (cost independent of 4K/1080p)."""
CHANGE_SIDE = 128
"""Frames are compared (camera standing still?) on gray copies this small: codec and sensor noise average out."""
BLURRED_FRACTION = 0.7
"""A window's sharpest frame below this fraction of the median sharpness of the last TYPICAL_FRAMES frames is
blurred, and its window is merged into the next: when windows hold a frame or two, a jerk of the hand can blur
a whole window while its neighbours are sharp (a rendered orbit's blurred frames measure 0.25-0.62 of it, its
other frames 0.81 and up)."""
TYPICAL_FRAMES = 31
MAX_MERGED_WINDOWS = 2
"""A blurred stretch longer than this many windows keeps its sharpest frame all the same: a view, however
blurred, is better than a gap in the orbit."""
TRUNCATED_TOLERANCE = 0.02
"""Decoding may end this fraction of the announced frame count early (rounded container durations)."""

REASON_BLURRIER = "blurrier than the sharpest frame of its window"
REASON_STILL = "near-duplicate of the last kept frame (camera standing still)"

KeepFn = Callable[["KeptFrame", np.ndarray], None]
ProgressFn = Callable[[int], None]

# FFmpeg's own log lines ("moov atom not found") would bypass our error messages; OpenCV reads this lazily
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


@dataclass
class VideoInfo:
    """What the container says about a clip; width and height are as displayed (rotation applied)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int
    rotation: int
    """Degrees of the rotation metadata (counter-clockwise, as FFmpeg reports it); 0 for none."""

    @property
    def duration_s(self) -> float:
        return self.frame_count / self.fps if self.fps > 0 else 0.0


@dataclass
class SelectOptions:
    """How many frames to keep and when two frames count as the same view."""

    target_frames: int = 150
    """Windows the clip is split into; at most one frame is kept from each."""
    min_change: float = 1.0
    """Mean absolute gray difference (0-255 levels, on a CHANGE_SIDE-px copy) to the last kept frame below
    which a frame is a near-duplicate: the camera stood still."""


@dataclass
class KeptFrame:
    """One chosen frame: its position in the clip and why it is a good one."""

    index: int
    """0-based index among the decoded frames."""
    time_s: float
    """Presentation time stamp, seconds from the start of the clip."""
    sharpness: float
    """Variance of the Laplacian of the ANALYSIS_SIDE gray copy (higher is sharper)."""
    change: float | None
    """Mean absolute gray difference to the previously kept frame; None for the first."""


@dataclass
class Selection:
    """The outcome of `select_frames`: what was read, what was kept, and why the rest was not."""

    info: VideoInfo
    read: int = 0
    kept: list[KeptFrame] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    """reason -> number of frames dropped for it."""
    windows: int = 0
    seconds: float = 0.0
    """Wall time of decoding and selection."""

    def describe(self) -> str:
        """One sentence: frames read, kept and the count per reason (what the poses stage prints)."""
        clip = self.info
        text = (
            f"{clip.path.name}: read {self.read} frames ({clip.width}x{clip.height}, {clip.fps:.4g} fps, "
            f"{self.read / clip.fps if clip.fps > 0 else 0:.1f} s"
            + (f", rotated {clip.rotation}°" if clip.rotation else "")
            + f") in {self.seconds:.1f} s, kept {len(self.kept)} (the sharpest of each of {self.windows} windows)"
        )
        if self.dropped:
            text += "; dropped " + ", ".join(f"{n} {reason}" for reason, n in self.dropped.items())
        return text + "."


def frame_name(video_stem: str, index: int) -> str:
    """File name of a kept frame: the clip's name and the frame's index, so names sort in time order."""
    return f"{video_stem}_f{index:06d}.jpg"


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_SUFFIXES


def list_videos(folder: Path) -> list[Path]:
    """Video files directly in `folder`, sorted by name (hidden files skipped)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".") and is_video(p))


def share_frames(target: int, frame_counts: list[int]) -> list[int]:
    """Split a frame budget among clips by length (each clip gets at least one window)."""
    total = max(sum(frame_counts), 1)
    return [max(1, round(target * n / total)) for n in frame_counts]


def _unreadable(path: Path, what: str) -> InputError:
    return InputError(
        f"Cannot read the video {path}: {what}. It is damaged, truncated (an interrupted copy or recording), not "
        f"a video at all, or in a codec OpenCV's FFmpeg cannot decode. Check that it plays in a video player: if "
        f"it does not, copy it again from the phone; if it does, re-encode it "
        f"(ffmpeg -i {path.name} -c:v libx264 -crf 18 fixed.mp4) and pass the new file."
    )


FIRST_BOXES = frozenset({b"ftyp", b"wide", b"free", b"skip", b"mdat", b"moov", b"pnot", b"uuid"})
"""What an MP4 or QuickTime file begins with (ISO/IEC 14496-12 and Apple's QuickTime file format)."""
TOP_BOXES = FIRST_BOXES | {b"moof", b"mfra", b"sidx", b"ssix", b"styp", b"emsg", b"prft", b"pdin", b"meta", b"udta",
                           b"meco"}
"""The boxes such a file holds at its top level: only these are told cut short (a maker's own box that fits is passed
over; one that does not is taken for a trailer or padding)."""


def check_container(path: Path) -> None:
    """Refuse an MP4/MOV file that cannot be a whole clip, from its top-level boxes' headers alone (a few bytes read,
    no frame decoded, so a cached run still decodes nothing): not such a file, a box that runs past the end (a copy
    or a recording cut short), or no index (the 'moov' box a phone writes when the recording stops)."""
    size, offset, kinds = path.stat().st_size, 0, []
    if size == 0:
        raise _unreadable(path, "it is empty (0 bytes)")
    with path.open("rb") as f:
        while offset + 8 <= size and len(kinds) < 10_000:
            f.seek(offset)
            length, kind = struct.unpack(">I4s", f.read(8))
            if length == 1:  # a 64-bit size follows
                extended = f.read(8)
                length = struct.unpack(">Q", extended)[0] if len(extended) == 8 else 0
            elif length == 0:  # the box runs to the end of the file
                length = size - offset
            box = kind.decode("latin-1")
            if not kinds and kind not in FIRST_BOXES:
                raise _unreadable(path, "it is not an MP4 or MOV file (it does not start as one)")
            if length < 8 or not all(32 <= c < 127 for c in kind):
                break  # bytes after the last box (padding): not a box
            if offset + length > size:
                if kind not in TOP_BOXES:
                    break  # a trailer some cameras append, or padding that reads as a name
                raise _unreadable(path, f"it is cut short (its '{box}' box needs {offset + length:,} bytes, the file "
                                        f"holds {size:,})")
            kinds.append(kind)
            offset += length
    if b"moov" not in kinds:
        raise _unreadable(path, "it has no index (no 'moov' box: the recording or the copy stopped before the end)")


@contextlib.contextmanager
def _open(path: Path) -> Iterator[object]:
    """A cv2.VideoCapture with rotation metadata applied (set explicitly: never trust a default), closed after."""
    import cv2

    if not path.is_file():
        raise InputError(f"The video {path} does not exist. Check the path.")
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # its "can't capture by name" warning
    try:
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    finally:
        cv2.utils.logging.setLogLevel(previous)
    try:
        if not cap.isOpened():
            raise _unreadable(path, "FFmpeg cannot open it as a video")
        cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        yield cap
    finally:
        cap.release()


def probe(path: Path) -> VideoInfo:
    """Size (as displayed), frame rate, frame count and rotation of a clip, decoding one frame to be sure; frames
    over the photos' pixel limit (recon.capture.images.MAX_PIXELS) are refused from the header, before that decode."""
    import cv2

    path = Path(path)
    with _open(path) as cap:
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if width * height > MAX_PIXELS:  # from the container's header: refused before a frame is decoded
            raise too_large(path, width, height, "video")
        ok, frame = cap.read()
        if not ok or frame is None:
            raise _unreadable(path, "it holds no frame that can be decoded")
        if frame.shape[0] * frame.shape[1] > MAX_PIXELS:  # a header that gave no size (or a wrong one)
            raise too_large(path, frame.shape[1], frame.shape[0], "video")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        rotation = int(round(cap.get(cv2.CAP_PROP_ORIENTATION_META))) % 360
    if count <= 0:  # some containers do not say: count by decoding headers only
        with _open(path) as cap:
            count = 0
            while cap.grab():
                count += 1
    return VideoInfo(path, int(frame.shape[1]), int(frame.shape[0]), fps if np.isfinite(fps) else 0.0, count, rotation)


def _small_gray(frame_bgr: np.ndarray, side: int) -> np.ndarray:
    import cv2

    gray = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    scale = side / max(h, w)
    if scale < 1.0:
        gray = cv2.resize(gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    return gray


def sharpness(frame_bgr: np.ndarray) -> float:
    """Variance of the Laplacian of the gray frame at ANALYSIS_SIDE: blur removes the high frequencies it sums."""
    import cv2

    return float(cv2.Laplacian(_small_gray(frame_bgr, ANALYSIS_SIDE), cv2.CV_32F).var())


def change(a_small: np.ndarray, b_small: np.ndarray) -> float:
    """Mean absolute difference of two CHANGE_SIDE gray copies, in gray levels (0-255)."""
    return float(np.abs(a_small.astype(np.float32) - b_small.astype(np.float32)).mean())


def select_frames(
    path: Path, options: SelectOptions, on_keep: KeepFn, progress: ProgressFn | None = None, info: VideoInfo | None = None
) -> Selection:
    """Decode `path` once and keep the sharpest frame of each of `options.target_frames` windows.

    on_keep(frame, image) gets each kept frame as soon as its window ends, image an RGB uint8 (H, W, 3)
    array as displayed. progress(frames_read) is called every few frames. A window whose sharpest frame
    barely differs from the last kept one (options.min_change) keeps nothing: the camera stood still. A window
    whose sharpest frame is blurred (BLURRED_FRACTION) is merged into the next, whose frames compete with it.
    Raises InputError when the clip cannot be decoded or ends well before the frames it announced.
    """
    import cv2

    if options.target_frames < 1:
        raise ValueError("target_frames must be at least 1")
    path = Path(path)
    info = info or probe(path)
    start = time.perf_counter()
    total = max(info.frame_count, 1)
    per_window = max(1.0, total / options.target_frames)
    result = Selection(info=info)
    last_small: np.ndarray | None = None
    best: tuple[float, int, float, np.ndarray] | None = None  # sharpness, index, time, BGR image of the window
    window = 0
    recent: deque[float] = deque(maxlen=TYPICAL_FRAMES)
    merged = 0

    def close_window(last: bool = False) -> None:
        nonlocal best, last_small, merged
        if best is None:
            return
        sharp, index, t, image = best
        if not last and merged < MAX_MERGED_WINDOWS and sharp < BLURRED_FRACTION * float(np.median(recent)):
            merged += 1  # blurred: left pending, so that a sharp frame of the next window replaces it
            return
        merged = 0
        small = _small_gray(image, CHANGE_SIDE)
        diff = None if last_small is None else change(small, last_small)
        if diff is not None and diff < options.min_change:
            result.dropped[REASON_STILL] = result.dropped.get(REASON_STILL, 0) + 1
        else:
            last_small = small
            kept = KeptFrame(index=index, time_s=t, sharpness=sharp, change=diff)
            result.kept.append(kept)
            on_keep(kept, cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        best = None

    with _open(path) as cap:
        index = 0
        while True:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            t = float(cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
            frame_window = int(index / per_window)
            if frame_window != window:
                close_window()
                window = frame_window
            sharp = sharpness(frame)
            recent.append(sharp)
            if best is None or sharp > best[0]:
                if best is not None:
                    result.dropped[REASON_BLURRIER] = result.dropped.get(REASON_BLURRIER, 0) + 1
                best = (sharp, index, t, frame)
            else:
                result.dropped[REASON_BLURRIER] = result.dropped.get(REASON_BLURRIER, 0) + 1
            index += 1
            if progress is not None and index % 8 == 0:
                progress(index)
        close_window(last=True)
    result.read = index
    result.windows = window + 1 if index else 0
    if progress is not None:
        progress(index)
    if index == 0:
        raise _unreadable(path, "no frame could be decoded")
    if index < info.frame_count * (1.0 - TRUNCATED_TOLERANCE) - 1:
        raise _unreadable(path, f"decoding stopped after {index} of the {info.frame_count} frames it announces")
    result.seconds = time.perf_counter() - start
    return result


def count_photos(source: Path, video_frames: int) -> int:
    """How many photos the poses stage would read from `source` at most: the image files directly in the folder,
    plus `video_frames` when it is a video or holds any; 0 when that cannot be told (a poses file, a missing path)."""
    try:
        if source.is_file():
            return video_frames if is_video(source) else 0
        if not source.is_dir():
            return 0
        return len(list_photos(source)[0]) + (video_frames if list_videos(source) else 0)
    except OSError:
        return 0

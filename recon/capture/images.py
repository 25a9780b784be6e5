"""Reading photos the way a user means them: EXIF orientation applied, any bit depth, clear errors.

Every stage reads images through here, so orientation, 16-bit, grayscale and RGBA are handled once.
Arrays are float32 in [0, 1], shape (H, W, 3) or (H, W, 4) when the file has alpha.
"""
from __future__ import annotations

import warnings
from collections import deque
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from recon.camera import intrinsic_matrix
from recon.errors import InputError

HEIF_SUFFIXES = {".heic", ".heif"}
"""iPhones save HEIC by default; pillow-heif decodes it (upright, HDR to 8 bit), no other tool recon hands
photos to (COLMAP, nerfstudio) reads it, so a copy for them is re-encoded."""
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"} | HEIF_SUFFIXES
READABLE_FORMATS = "JPEG, PNG, TIFF, HEIC, WebP or BMP"
"""IMAGE_SUFFIXES as the messages name them."""
MIN_SIDE = 32
MAX_PIXELS = 400_000_000
"""Refuse decompression bombs; huge photos below this are downscaled on read."""

Image.MAX_IMAGE_PIXELS = MAX_PIXELS

try:  # PIL opens .heic/.heif from here on: libheif applies the file's rotation and its EXIF then says Orientation 1
    from pillow_heif import register_heif_opener

    register_heif_opener()
    HEIF_READER: str | None = None
except ImportError:  # a dependency; an install without it still reads every other format
    HEIF_READER = "pillow-heif is not installed: `pip install pillow-heif`, or convert the photos to JPEG"


def list_photos(folder: Path) -> tuple[list[Path], list[Path]]:
    """Image files directly in `folder` (sorted by name) and the other files that were skipped."""
    if not folder.exists():
        raise InputError(f"The photos folder {folder} does not exist. Check the path.")
    if not folder.is_dir():
        raise InputError(f"{folder} is a file, not a folder of photos. Pass the folder that holds the photos.")
    photos, skipped = [], []
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):
            continue
        if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
            photos.append(path)
        elif path.is_file():
            skipped.append(path)
    return photos, skipped


RAW_SUFFIXES = {".cr2", ".cr3", ".nef", ".arw", ".dng", ".raf", ".orf", ".rw2", ".pef", ".srw"}
NESTED_DEPTH = 3
"""How deep `no_photos` looks for folders of photos below the one given (a phone's DCIM/100APPLE is two down)."""
NESTED_MAX_FOLDERS = 2000
"""How many folders it looks into at most (given a home folder, it must not walk the disk)."""


def photo_folders_below(folder: Path, depth: int = NESTED_DEPTH) -> list[tuple[Path, int]]:
    """Folders up to `depth` levels below `folder` that hold photos directly, with how many, most photos first
    (unreadable folders and links are passed over)."""
    found, queue, looked = [], deque([(folder, 0)]), 0
    while queue and looked < NESTED_MAX_FOLDERS:
        parent, level = queue.popleft()
        looked += 1
        try:
            if level and (count := len(list_photos(parent)[0])):
                found.append((parent, count))
            if level < depth:
                queue.extend((d, level + 1) for d in sorted(parent.iterdir())
                             if d.is_dir() and not d.is_symlink() and not d.name.startswith("."))
        except OSError:
            continue
    return sorted(found, key=lambda item: -item[1])


def no_photos(source: Path, skipped: list[Path]) -> InputError:
    """The error for a folder without a photo recon reads, saying what it holds instead: camera RAW files, or
    folders of photos below it."""
    raw = sorted({p.suffix.upper() for p in skipped if p.suffix.lower() in RAW_SUFFIXES})
    nested = photo_folders_below(source)
    if raw:
        why = (f" It holds camera RAW files ({', '.join(raw)}), which recon does not develop: export them as JPEG (or "
               f"16-bit TIFF) from your RAW developer, with the same settings for every photo, into a folder of their "
               f"own.")
    elif nested:
        listed = ", ".join(f"{d.relative_to(source)}/ ({n})" for d, n in nested[:5])
        why = (f" Folders below it hold photos: {listed}. recon reads the photos directly in the folder it is given, "
               f"not its subfolders, so pass one of them (e.g. {nested[0][0]}) or move the photos of one object into "
               f"a folder of their own.")
    else:
        why = f" Put the photos ({READABLE_FORMATS}) directly in that folder and run again."
    return InputError(f"No photos found in {source}.{why}")


MIN_PHOTOS = 3
"""Structure from motion needs at least this many photos (or a video's distinct frames)."""


def check_photo_set(source: Path, photos: list[Path]) -> None:
    """Refuse a folder's photos that recon cannot pose as they are: too few, or two named alike but for the
    extension (views, renders and COLMAP's images go by the name without it). Reads no photo."""
    if len(photos) < MIN_PHOTOS:
        raise InputError(
            f"Only {len(photos)} photo(s) in {source}; structure from motion needs at least {MIN_PHOTOS}, and a "
            f"good reconstruction 20 or more taken all around the subject with about 60% overlap between neighbours."
        )
    by_stem: dict[str, list[str]] = {}
    for path in photos:
        by_stem.setdefault(path.stem, []).append(path.name)
    clashes = [names for names in by_stem.values() if len(names) > 1]
    if clashes:
        named = "; ".join(" and ".join(c) for c in clashes[:5])
        raise InputError(
            f"Photos in {source} share a name apart from the extension ({named}); recon names views, renders and "
            f"COLMAP's images by the name without extension. Rename or remove one of each."
        )


def check_photo_headers(source: Path, photos: list[Path], most: int = 5) -> None:
    """Refuse, naming every one, the photos whose header says they cannot be used: empty, not an image, under
    MIN_SIDE (a photo over MAX_PIXELS is refused alone, by `oriented_size`). Reads headers only, so `recon run` tells
    a bad copy before it makes the scene folder, even of a capture whose stages are cached; a file cut short is told
    when it is read."""
    bad = []
    for path in photos:
        if path.stat().st_size == 0:
            bad.append(f"{path.name} (an empty file)")
            continue
        try:
            w, h = oriented_size(path)
        except UnreadableImage as exc:
            bad.append(f"{path.name} ({exc.reason})")
            continue
        if min(w, h) < MIN_SIDE:
            bad.append(f"{path.name} ({w}×{h} px, under {MIN_SIDE} px a side: a thumbnail?)")
    if bad:
        one = len(bad) == 1
        more = f"; and {len(bad) - most} more" if len(bad) > most else ""
        raise InputError(
            f"{len(bad)} of the {len(photos)} photos in {source} cannot be used: {'; '.join(bad[:most])}{more}. "
            f"Remove {'it' if one else 'them'} from the folder or replace {'it' if one else 'them'} with "
            f"{'a good copy' if one else 'good copies'} (the photo{'' if one else 's'} as the camera saved "
            f"{'it' if one else 'them'})."
        )


def too_large(path: Path | str, width: int, height: int, what: str = "image") -> InputError:
    """The error for a photo (or a video's frames) over MAX_PIXELS, told from the header before any decoding."""
    return InputError(
        f"The {what} {path} is {width}×{height} px ({width * height / 1e6:,.0f} Mpx), over the "
        f"{MAX_PIXELS // 1_000_000} Mpx recon decodes safely. Downscale it (e.g. to 8000 px on the long side) before "
        f"running recon."
    )


class UnreadableImage(InputError):
    """A photo PIL cannot open; `reason` says what it is in a few words, for a message naming several."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


def unreadable(path: Path, exc: BaseException) -> UnreadableImage:
    if HEIF_READER and Path(path).suffix.lower() in HEIF_SUFFIXES:
        return UnreadableImage(f"Cannot read the HEIC photo {path}: {HEIF_READER}.", HEIF_READER)
    return UnreadableImage(
        f"Cannot read the image {path}: {exc}. The file is corrupt or not an image; "
        f"remove it from the folder or replace it with a good copy.",
        f"not an image: no {READABLE_FORMATS} inside" if isinstance(exc, UnidentifiedImageError) else
        f"unreadable: {exc}",
    )


def _open(path: Path, max_side: int | None = None) -> Image.Image:
    """Decode (EXIF-oriented). With max_side, a JPEG is decoded at a reduced scale (1/2…1/8) that still
    has at least max_side pixels on its long side, so a huge photo never occupies memory at full size."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(path)
            if max_side and img.format == "JPEG" and max(img.size) > 2 * max_side:
                img.draft(img.mode, (max_side, max_side))  # keeps both sides >= the requested size
            img.load()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise unreadable(path, exc) from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise InputError(
            f"The image {path} is too large to decode safely (over {MAX_PIXELS // 1_000_000} Mpx). "
            f"Downscale it before running recon."
        ) from None
    return ImageOps.exif_transpose(img)


def oriented_size(path: Path) -> tuple[int, int]:
    """(width, height) after EXIF orientation, from the header alone (PIL's open reads no pixels); a size over
    MAX_PIXELS is refused here, before anything decodes it."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as img:
                w, h = img.size
                if w * h > MAX_PIXELS:  # before getexif: for a PNG it decodes the whole image
                    raise too_large(path, w, h)
                orientation = img.getexif().get(0x0112, 1)
    except Image.DecompressionBombError as exc:  # PIL's own refusal at twice MAX_IMAGE_PIXELS (it says the size)
        raise InputError(
            f"The image {path} is too large to decode safely ({exc}). Downscale it (e.g. to 8000 px on the long "
            f"side) before running recon."
        ) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise unreadable(path, exc) from None
    return (h, w) if orientation in (5, 6, 7, 8) else (w, h)


CAMERA_EXIF_TAGS = {0x010F: "Make", 0x0110: "Model"}
"""IFD0 tags that say which device took a photo."""
CAMERA_EXIF_SUBTAGS = {0x920A: "FocalLength", 0xA405: "FocalLengthIn35mmFilm"}
"""Exif sub-IFD tags COLMAP turns into a focal-length prior; both are independent of the pixel count, so
they stay true for a downscaled copy (sensor-resolution tags such as FocalPlaneXResolution would not)."""
_EXIF_IFD = 0x8769
_ORIENTATION = 0x0112


def camera_exif(path: Path) -> Image.Exif | None:
    """The photo's device and focal-length EXIF (make, model, focal length, 35 mm equivalent), Orientation 1.

    The copy COLMAP reads is re-saved with its pixels already turned upright, so its EXIF must say
    Orientation 1; without these tags COLMAP guesses the focal length and cannot tell two phones apart.
    None when the photo carries none of them.
    """
    try:
        with Image.open(path) as img:
            source = img.getexif()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise unreadable(path, exc) from None
    out = Image.Exif()
    for tag in CAMERA_EXIF_TAGS:
        if source.get(tag):
            out[tag] = source[tag]
    sub_in = source.get_ifd(_EXIF_IFD)
    sub = {tag: sub_in[tag] for tag in CAMERA_EXIF_SUBTAGS if sub_in.get(tag)}
    if not out and not sub:
        return None
    if sub:
        out.get_ifd(_EXIF_IFD).update(sub)
    out[_ORIENTATION] = 1
    return out


def device_of(path: Path) -> str | None:
    """Which camera took a photo, from its EXIF: 'Make Model', and the lens's focal length where the EXIF gives
    one ('Apple iPhone 15 at 6.8 mm (26 mm equiv.)'); None without make and model.

    A phone's lenses (ultra-wide, main, tele) and its digital zoom share make, model and resolution but not
    intrinsics: photos of one camera at two focal lengths must not share a COLMAP camera."""
    try:
        with Image.open(path) as img:
            exif = img.getexif()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise unreadable(path, exc) from None
    parts = [str(exif.get(tag, "")).strip("\x00 ") for tag in CAMERA_EXIF_TAGS]
    text = " ".join(p for p in parts if p)
    if not text:
        return None
    sub = exif.get_ifd(_EXIF_IFD)
    focal, focal35 = (_positive(sub.get(tag)) for tag in CAMERA_EXIF_SUBTAGS)
    if focal:
        text += f" at {focal:.3g} mm" + (f" ({focal35:.3g} mm equiv.)" if focal35 else "")
    elif focal35:
        text += f" at {focal35:.3g} mm equiv."
    return text


def _positive(value: object) -> float | None:
    """An EXIF number (a rational possibly 0/0) as a float, or None when missing, zero or unreadable."""
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if np.isfinite(number) and number > 0 else None


def to_array(img: Image.Image) -> np.ndarray:
    """PIL image of any mode → float32 (H, W, 3|4) in [0, 1]."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float32)
        # 16-bit files span [0, 65535] whatever their content (a dark 16-bit photo must stay dark); only 32-bit
        # "I" has no stated range: 8-bit data promoted to it (max <= 255) is told apart by its values
        arr = arr / (255.0 if img.mode == "I" and arr.max() <= 255 else 65535.0)
        return np.repeat(arr[..., None], 3, axis=-1)
    if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
        return np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0
    if img.mode == "F":
        arr = np.clip(np.asarray(img, dtype=np.float32), 0.0, 1.0)
        return np.repeat(arr[..., None], 3, axis=-1)
    arr = np.asarray(img)
    if arr.dtype == np.uint16:
        return arr.astype(np.float32) / 65535.0
    return np.asarray(img.convert("RGB"), dtype=np.float32) / 255.0


def read_image(path: Path, max_side: int | None = None) -> np.ndarray:
    """Read a photo as float32 (H, W, C) in [0, 1], EXIF-oriented, area-downscaled to `max_side` if larger."""
    full_w, full_h = oriented_size(path)
    if min(full_w, full_h) < MIN_SIDE:
        raise InputError(
            f"The image {path} is only {full_w}×{full_h} px; recon needs at least {MIN_SIDE} px on each side. "
            f"Use the original photo, not a thumbnail."
        )
    img = _open(path, max_side)
    w, h = img.size
    if min(w, h) < MIN_SIDE:
        raise InputError(
            f"The image {path} is only {w}×{h} px; recon needs at least {MIN_SIDE} px on each side. "
            f"Use the original photo, not a thumbnail."
        )
    if max_side and max(w, h) > max_side:
        scale = max_side / max(w, h)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        if img.mode not in ("RGB", "RGBA", "L", "LA"):
            arr = to_array(img)
            return resize(arr, size)
        img = img.resize(size, Image.Resampling.BOX if scale < 0.5 else Image.Resampling.LANCZOS)
    return to_array(img)


def read_mask(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A mask (white = object) as float32 (H, W) in [0, 1] at `size` (width, height), EXIF-oriented."""
    mask = read_image(path, max_side=max(size))
    gray = mask[..., :3].mean(axis=-1) * (mask[..., 3] if mask.shape[-1] == 4 else 1.0)
    if gray.shape[::-1] != tuple(size):
        gray = resize(gray, size)
    return np.clip(gray, 0.0, 1.0).astype(np.float32)


def resize(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-resize a float image to (width, height)."""
    import cv2

    interp = cv2.INTER_AREA if size[0] < arr.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(arr, size, interpolation=interp)


def composite(image: np.ndarray, background: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """RGBA → RGB over a constant background; RGB passes through."""
    if image.shape[-1] == 3:
        return image
    alpha = image[..., 3:4]
    return image[..., :3] * alpha + np.asarray(background, dtype=np.float32) * (1.0 - alpha)


def save_image(path: Path, image: np.ndarray, quality: int = 95, exif: Image.Exif | None = None) -> None:
    """Save a float [0, 1] image (RGB/RGBA/gray) as 8-bit PNG or JPEG, by suffix (with `exif` if given)."""
    arr = np.clip(np.asarray(image) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    img = Image.fromarray(arr)
    extra = {"exif": exif} if exif is not None else {}
    if path.suffix.lower() in (".jpg", ".jpeg"):
        img.convert("RGB").save(path, quality=quality, **extra)
    else:
        img.save(path, **extra)


def undistort(
    image: np.ndarray, fl_x: float, fl_y: float, cx: float, cy: float, dist: tuple[float, ...], model: str = "OPENCV"
) -> np.ndarray:
    """The pinhole image with the same intrinsics: lens distortion removed.

    model OPENCV: radial-tangential `dist` = (k1, k2, p1, p2[, k3]); OPENCV_FISHEYE: equidistant `dist` =
    (k1, k2, k3, k4) (cv2.fisheye). Keeping fl, cx, cy keeps the image centre's resolution; a fisheye's
    periphery beyond the pinhole's field of view is cut.
    """
    if not any(abs(d) > 0 for d in dist) and model != "OPENCV_FISHEYE":
        return image
    import cv2

    K = intrinsic_matrix(fl_x, fl_y, cx, cy)
    h, w = image.shape[:2]
    coeffs = np.asarray(dist, dtype=np.float64)
    if model == "OPENCV_FISHEYE":
        if coeffs.shape != (4,):
            raise ValueError(f"a fisheye lens takes 4 coefficients (k1..k4), got {len(coeffs)}")
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, coeffs, np.eye(3), K, (w, h), cv2.CV_32FC1)
    elif model == "OPENCV":
        map_x, map_y = cv2.initUndistortRectifyMap(K, coeffs, None, K, (w, h), cv2.CV_32FC1)
    else:
        raise ValueError(f"unknown lens model {model!r}; expected OPENCV or OPENCV_FISHEYE")
    # replicate edge pixels where the corrected image reaches outside the photo (never black borders to learn)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

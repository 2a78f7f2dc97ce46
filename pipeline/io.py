"""The only module in :mod:`pipeline` that touches disk: decode originals safely, write artifacts.

Array convention everywhere in the pipeline: ``uint8``, shape ``(H, W)`` for grey or
``(H, W, 3)`` in **RGB** order, row 0 at the top, x to the right.
"""

from __future__ import annotations

import io
import json
import os
import stat
import tempfile
import time
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import ImageReadError, ImageTooLargeError, InvalidInputError

# A 1200 dpi scan of a 7 x 3.5 inch card is ~35 MP; 150 MP leaves room for any real scan
# while refusing decompression bombs (a 100 KB PNG can claim 50,000 x 50,000 pixels).
DEFAULT_MAX_PIXELS = 150_000_000

# Pillow's own guard refuses images over 2 x 89 MP at open time with a message that cannot
# say which cap applies; every decode here goes through _open_checked, which enforces the
# configurable cap from the header before any pixel is decoded, so Pillow's is switched off.
Image.MAX_IMAGE_PIXELS = None

# .mpo: multi-picture JPEG from stereo cameras (catalogue.stereo_ingest makes a card of its two frames).
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".jps", ".mpo"})


@dataclass(frozen=True)
class ImageInfo:
    width: int
    height: int
    format: str  # PIL's name for the decoded format: JPEG, PNG, TIFF, ...
    mode: str  # PIL mode of the file: L, RGB, I;16, ...
    byte_size: int


def _open_checked(path: Path, max_pixels: int) -> Image.Image:
    try:
        size = path.stat().st_size
    except FileNotFoundError as exc:
        raise ImageReadError(f"no such file: {path}") from exc
    except OSError as exc:
        raise ImageReadError(f"cannot stat {path}: {exc.strerror or exc}") from exc
    if size == 0:
        raise ImageReadError("empty file (0 bytes)")
    try:
        image = Image.open(path)
    except PermissionError as exc:
        raise ImageReadError(f"permission denied: {path}") from exc
    except UnidentifiedImageError as exc:
        raise ImageReadError("not an image (no decoder recognises its contents)") from exc
    except OSError as exc:
        raise ImageReadError(f"cannot open: {exc}") from exc
    except Exception as exc:
        # Pillow's header parsers raise what they meet: ValueError for a zTXt or iCCP chunk that
        # inflates past its limit (a 2 KB PNG), SyntaxError, struct.error, EOFError, its
        # DecompressionBombError. Whatever it is, the file is refused with a reason, not a crash.
        raise ImageReadError(f"cannot open: {type(exc).__name__}: {exc}") from exc
    width, height = image.size
    if width < 1 or height < 1:
        image.close()
        raise ImageReadError(f"image has no pixels ({width}x{height})")
    if width * height > max_pixels:
        image.close()
        raise ImageTooLargeError(
            f"{width}x{height} = {width * height:,} pixels exceeds the cap of {max_pixels:,} "
            "(possible decompression bomb; raise KEYSTONE_MAX_PIXELS if the scan is real)"
        )
    return image


def _decode(image: Image.Image) -> None:
    try:
        image.load()
    except Exception as exc:
        # PIL reports truncated JPEGs/PNGs as OSError("image file is truncated ..."); its decoders
        # also raise ValueError, SyntaxError, struct.error, EOFError or worse on hostile data.
        raise ImageReadError(f"corrupt or truncated image data: {type(exc).__name__}: {exc}") from exc


def probe_image(path: str | os.PathLike[str], max_pixels: int = DEFAULT_MAX_PIXELS) -> ImageInfo:
    """Check that ``path`` is a complete, decodable image within the pixel cap.

    Decodes every pixel (a header-only check misses truncated files). Raises
    :class:`ImageReadError` (or :class:`ImageTooLargeError`) with a reason for people.
    """
    path = Path(path)
    image = _open_checked(path, max_pixels)
    with image:
        fmt, mode, (width, height) = image.format or "unknown", image.mode, image.size
        _decode(image)
        if mode == "F" and not np.isfinite(np.asarray(image)).any():
            # the reader would refuse it on first use (_to_uint8): refuse it at the door instead
            raise ImageReadError("image holds no finite pixel values")
    return ImageInfo(width=width, height=height, format=fmt, mode=mode, byte_size=path.stat().st_size)


def _to_uint8(image: Image.Image) -> np.ndarray:
    mode = image.mode
    if mode in ("RGB", "L"):
        # Already the pipeline's layout: no conversion copy (0.015 s of a 3000 px scan's 0.055 s decode).
        return np.asarray(image)
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I", "F"):
        # 16/32-bit and float scans: stretch the used range to 0..255 rather than truncate.
        array = np.asarray(image, dtype=np.float64)
        finite = np.isfinite(array)
        if not finite.any():
            raise ImageReadError("image holds no finite pixel values")
        lo, hi = float(array[finite].min()), float(array[finite].max())
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        array = np.where(finite, (array - lo) * scale, 0.0)
        return np.clip(np.rint(array), 0, 255).astype(np.uint8)
    if mode in ("L", "1", "LA", "P") and not (mode == "P" and "transparency" in image.info):
        if mode == "P" and image.getpalette() is not None:
            rgb = np.asarray(image.convert("RGB"))
            if np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2]):
                return np.ascontiguousarray(rgb[..., 0])
            return rgb
        return np.asarray(image.convert("L"))
    return np.asarray(image.convert("RGB"))


def read_image(path: str | os.PathLike[str], max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Decode an original into a ``uint8`` array: ``(H, W)`` grey or ``(H, W, 3)`` RGB.

    16-bit and float images are stretched to their used range. EXIF orientation is not
    applied: originals are analysed as scanned, and orientation fixes are the judge stage's.
    Inside :func:`shared_decodes` a file decoded (or written by :func:`write_png`) earlier in the
    block comes back as that decode, without decoding it again.
    """
    path = Path(path)
    identity = _file_identity(path)
    shared = _shared_decode(identity, 1, max_pixels)
    if shared is not None:
        return shared.pixels
    image = _open_checked(path, max_pixels)
    with image:
        _decode(image)
        pixels = np.ascontiguousarray(_to_uint8(image))
    _keep_decode(identity, ReducedImage(pixels, 1, (pixels.shape[1], pixels.shape[0])))
    return pixels


# libjpeg decodes at 1/2, 1/4 or 1/8 of the size directly (scaled inverse DCT), for less than the
# full decode costs; other formats are decoded at full size.
JPEG_REDUCTIONS = (8, 4, 2)


@dataclass(frozen=True)
class ReducedImage:
    """An original decoded at ``1 / factor`` of its size (:func:`read_image_reduced`)."""

    pixels: np.ndarray  # uint8 (h, w) or (h, w, 3) RGB, h = ceil(H / factor), w = ceil(W / factor)
    factor: int  # 1, 2, 4 or 8: original px per decoded px along each axis
    full_size: tuple[int, int]  # (W, H) of the original

    def to_full(self, points: np.ndarray) -> np.ndarray:
        """``(N, 2)`` points in decoded px to original px (origin at the top-left pixel centre:
        a decoded pixel covers ``factor x factor`` original pixels)."""
        return (np.asarray(points, np.float64) + 0.5) * self.factor - 0.5


def jpeg_reduction(size: tuple[int, int], min_size: tuple[int, int]) -> int:
    """The largest of :data:`JPEG_REDUCTIONS` (else 1) that keeps an image of ``size`` = (W, H)
    at least ``min_size`` px: decoded at 1/s it is ceil(W / s) x ceil(H / s)."""
    width, height = size
    return next(
        (s for s in JPEG_REDUCTIONS if -(-width // s) >= min_size[0] and -(-height // s) >= min_size[1]),
        1,
    )


def read_image_reduced(
    path: str | os.PathLike[str], min_size: tuple[int, int], max_pixels: int = DEFAULT_MAX_PIXELS
) -> ReducedImage:
    """Decode an original at the largest JPEG reduction (1/8, 1/4, 1/2) that keeps it at least
    ``min_size`` = (width, height) px, or at full size (other formats, CMYK JPEGs, small images).

    For stages that only analyse a downscaled copy: measured on a 3000 x 1581 px JPEG scan,
    0.055 s at full size, 0.043 s at 1/2 and 0.039 s at 1/4 (one core), and the copy to
    downscale is 4x smaller. The pixel cap and the typed errors are those of :func:`read_image`.
    """
    path = Path(path)
    identity = _file_identity(path)
    image = _open_checked(path, max_pixels)
    with image:
        width, height = image.size
        factor = 1
        if image.format == "JPEG" and image.mode in ("RGB", "L"):
            factor = jpeg_reduction((width, height), min_size)
        shared = _shared_decode(identity, factor, max_pixels)
        if shared is not None:
            return shared
        if factor > 1:
            image.draft(image.mode, (width // factor, height // factor))
        _decode(image)
        expected = (-(-width // factor), -(-height // factor))
        if image.size != expected:  # the decoder chose another scale: say what it did, not what was asked
            factor = next((f for f in (1, *JPEG_REDUCTIONS) if image.size == (-(-width // f), -(-height // f))), 0)
            if factor == 0:
                raise ImageReadError(f"decoded {image.size} from a {width}x{height} image: not a JPEG reduction")
        decoded = ReducedImage(np.ascontiguousarray(_to_uint8(image)), factor, (width, height))
    _keep_decode(identity, decoded)
    return decoded


# ----------------------------------------------------------------------------- shared decodes

# A file as it is on disk now: (resolved path, device, inode, size in bytes, modification time in
# ns). A file replaced or rewritten (atomic_write renames a new inode into place) gets another.
FileIdentity = tuple[str, int, int, int, int]


class _Kept(OrderedDict[tuple[FileIdentity, int], tuple[ReducedImage, bool]]):
    """The decodes a :func:`shared_decodes` block keeps, oldest first, at most ``limit``: each
    read-only, with whether a decode of the file gives a writable array."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit = limit


_shared_decodes: ContextVar[_Kept | None] = ContextVar("shared_decodes", default=None)


@contextmanager
def shared_decodes(max_entries: int = 4) -> Iterator[None]:
    """Within the block, keep the last ``max_entries`` decodes (and PNGs written with
    :func:`write_png`) in memory, keyed by the file's identity and the JPEG reduction, so that
    reading the same file again at the same reduction gets that decode instead of a second one.

    For a card taken through several stages in one go (``runs.loop``' chained stages): the
    filter and the orientation step decode the same scan at the same reduction, and the
    disparity, grade and views stages read the rectified views the rectify stage just wrote
    (measured on a ~3000 px JPEG card: ~34 ms a reduced decode, ~12 ms a view). The pixels are
    those a decode gives (PNG is lossless, and a write keeps a copy of the array it encoded), and
    so is their mutability: an 8-bit grey or RGB decode is a read-only view of Pillow's buffer,
    and every reader gets that same read-only array; a converted one (16-bit, palette) is
    writable, and every reader gets its own copy. Nothing shared can be changed in place. A
    file changed on disk since has another identity and is decoded afresh. Memory: at most
    ``max_entries`` images (a 3000 px RGB scan at 1/2 is ~3.3 MB, a view ~2 MB); nothing is
    kept outside the block."""
    if max_entries < 1:
        raise InvalidInputError(f"Expected max_entries >= 1, got {max_entries}")
    token = _shared_decodes.set(_Kept(max_entries))
    try:
        yield
    finally:
        _shared_decodes.reset(token)


def _file_identity(path: Path) -> FileIdentity | None:
    """The file's identity for :func:`shared_decodes` (None outside the block or when it cannot
    be read: the decode then says why)."""
    if _shared_decodes.get() is None:
        return None
    try:
        st = path.stat()
    except OSError:
        return None
    return (os.fspath(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def _shared_decode(identity: FileIdentity | None, factor: int, max_pixels: int) -> ReducedImage | None:
    kept = _shared_decodes.get()
    if identity is None or kept is None:
        return None
    entry = kept.get((identity, factor))
    if entry is None:
        return None
    found, writable = entry
    width, height = found.full_size
    if width * height > max_pixels:  # a tighter cap than the first read's: let the decode refuse it
        return None
    kept.move_to_end((identity, factor))
    return ReducedImage(found.pixels.copy(), found.factor, found.full_size) if writable else found


def _keep_decode(identity: FileIdentity | None, decoded: ReducedImage, written: bool = False) -> None:
    """Keep ``decoded`` for later reads of the file in a :func:`shared_decodes` block:
    read-only as it came (a decode's view of Pillow's buffer), else a read-only copy.
    ``written``: the pixels are an array just written to the file, which a decode would give
    back read-only."""
    kept = _shared_decodes.get()
    if identity is None or kept is None:
        return
    pixels = decoded.pixels
    writable = bool(pixels.flags.writeable) and not written
    if pixels.flags.writeable:
        pixels = pixels.copy()
        pixels.flags.writeable = False
    kept[(identity, decoded.factor)] = (ReducedImage(pixels, decoded.factor, decoded.full_size), writable)
    while len(kept) > kept.limit:
        kept.popitem(last=False)


def to_grey(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 luminance of a grey or RGB array (ITU-R 601 weights, as OpenCV)."""
    if image.ndim == 2:
        return image
    import cv2

    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


@contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` and rename it into place only when the block ends
    without error: a crash never leaves half a file under the final name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_png(path: str | os.PathLike[str], image: np.ndarray, fast: bool = False) -> None:
    """Write ``image`` (grey or RGB uint8) as PNG atomically.

    ``fast``: encode with OpenCV at zlib level 1 and the "average" row filter for every row
    instead of Pillow's level 3 with a filter chosen per row; the pixels are the same. Measured
    on an 800 x 843 px rectified view (one core): 29 ms and 1.18 MB instead of 69 ms and 1.18 MB
    (Pillow at level 1: 47 ms, 1.20 MB); decoding costs ~20 ms either way. For files written on
    every card's hot path (the rectified views). Inside :func:`shared_decodes` the written
    pixels are kept for a later :func:`read_image` of the file."""
    if fast:
        import cv2

        pixels = np.ascontiguousarray(image)
        if pixels.ndim == 3:
            pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
        options = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_AVG]
        ok, payload = cv2.imencode(".png", pixels, options)
        if not ok:
            raise InvalidInputError(f"OpenCV could not encode a {pixels.shape} {pixels.dtype} array as PNG")
        with atomic_write(path) as handle:
            handle.write(payload.tobytes())
    else:
        with atomic_write(path) as handle:
            Image.fromarray(np.ascontiguousarray(image)).save(handle, format="PNG", compress_level=3)
    if image.dtype == np.uint8 and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        # What read_image gives back for this file (PNG is lossless), for a later stage in a
        # shared_decodes block.
        _keep_decode(_file_identity(Path(path)), ReducedImage(image, 1, (image.shape[1], image.shape[0])), written=True)


def encode_jpeg(image: np.ndarray, max_side: int | None = None, quality: int = 90) -> bytes:
    """A display JPEG in memory, downscaled (area filter) so its longer side <= ``max_side``."""
    picture = Image.fromarray(np.ascontiguousarray(image))
    if max_side is not None and max(picture.size) > max_side:
        picture.thumbnail((max_side, max_side), Image.Resampling.BOX)
    buffer = io.BytesIO()
    picture.save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


def write_jpeg(path: str | os.PathLike[str], image: np.ndarray, max_side: int | None = None, quality: int = 90) -> None:
    """Write :func:`encode_jpeg`'s JPEG atomically."""
    payload = encode_jpeg(image, max_side, quality)
    with atomic_write(path) as handle:
        handle.write(payload)


def write_json(path: str | os.PathLike[str], document: object) -> None:
    """Write a JSON document atomically (sorted keys, no NaN: ``allow_nan=False`` raises)."""
    with atomic_write(path, "w") as handle:
        json.dump(document, handle, indent=2, sort_keys=True, allow_nan=False)


def write_npy(path: str | os.PathLike[str], array: np.ndarray) -> None:
    """Write a float map as ``.npy`` atomically (dtype and shape kept; loads with ``np.load``)."""
    with atomic_write(path) as handle:
        np.save(handle, array, allow_pickle=False)


TEMP_SUFFIX = ".tmp"
STALE_TEMP_SECONDS = 10 * 60  # a temporary file lives seconds; ten minutes untouched is a dead writer


def remove_stale_temp_files(
    root: str | os.PathLike[str], older_than_s: float, now: float | None = None
) -> list[tuple[Path, int]]:
    """Remove the hidden ``.<name>.XXXX.tmp`` files :func:`atomic_write` (and ingest's store)
    leave when their process is killed, if unchanged for ``older_than_s`` seconds; returns each
    removed path with its size in bytes.

    Age, not the writer's pid, decides: a temporary file is written in one go and renamed at
    once (seconds), and a pid says nothing when dask workers on other hosts share the data dir.
    Links are never followed."""
    now = time.time() if now is None else now
    removed: list[tuple[Path, int]] = []
    for folder, _, filenames in os.walk(root):
        for name in filenames:
            if not (name.startswith(".") and name.endswith(TEMP_SUFFIX)):
                continue
            path = Path(folder) / name
            try:
                info = path.lstat()
                if not stat.S_ISREG(info.st_mode) or now - info.st_mtime < older_than_s:
                    continue
                path.unlink()
            except OSError:
                continue  # gone meanwhile, or not ours to remove
            removed.append((path, info.st_size))
    return removed

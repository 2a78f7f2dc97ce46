"""The picture of one card in a confirm grid: the card as the pipeline would use it, small.

The orientation flags it is shown with (the card as scanned, :mod:`pipeline.orientation`) are applied to the
scan's two photos, as rectification would: turned 180 deg when ``upside_down`` (which also
moves each photo to the other side: the photo on the right of the scan becomes the left one),
negated when ``inverted``, exchanged when ``swapped``. The picture is the fixed left photo
with, under it, a strip of the depth read from the fixed pair in colours (near warm, far cool;
:func:`annotation.pictures.signed_disparity` and :func:`~annotation.pictures.depth_colours`), so
a person sees at a glance a card upside down, a negative, or depth inside out (the near
ground cool, the sky warm: the photos are in the wrong eye order).

Made at request time from the card's display preview (a JPEG of at most 1600 px that the
catalogue keeps on disk, so the original is not decoded again) and kept in memory, so a grid
page shown again, or a gold card shown to the next worker, costs nothing.
"""

from __future__ import annotations

import hashlib
import io
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from .pictures import depth_colours, signed_disparity

PHOTO_WIDTH = 240  # px: a grid cell is 160-260 CSS px wide; this stays sharp on most screens
DEPTH_MATCH_WIDTH = 160  # px: the disparity is read this wide (coarser is faster; the strip is small)
STRIP_FRACTION = 0.4  # the depth strip's height, as a fraction of the photo's
GAP = 3  # px of white between the photo and its strip
_CACHE = 1024

_pictures: OrderedDict[tuple[Any, ...], bytes] = OrderedDict()
_lock = threading.Lock()


def _rgb(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)


def _cut(image: np.ndarray, box: Sequence[float], scale: float) -> np.ndarray:
    height, width = image.shape[:2]
    x0, y0, x1, y1 = (float(v) * scale for v in box)
    x0, x1 = max(0, round(x0)), min(width, round(x1))
    y0, y1 = max(0, round(y0)), min(height, round(y1))
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError(f"Expected photo boxes of at least 2 x 2 px inside the card, got {list(box)}")
    return image[y0:y1, x0:x1]


def oriented_photos(
    card: np.ndarray, left_box: Sequence[float], right_box: Sequence[float], shown: Mapping[str, bool], scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """The left and right photos ``(h, w, 3)`` uint8 after the fixes ``shown`` asks for (the
    forward direction of :func:`pipeline.orientation.orient_variant`), cut to the size they share.

    ``card``: the scan ``(H, W[, 3])`` uint8, possibly reduced; boxes ``[x0, y0, x1, y1]`` in the
    original scan's pixels and ``scale`` = this image's width / the original's.
    """
    left, right = _cut(card, left_box, scale), _cut(card, right_box, scale)
    if shown.get("upside_down"):
        # Turning the whole card turns each photo and trades their places.
        left, right = right[::-1, ::-1], left[::-1, ::-1]
    if shown.get("inverted"):
        left, right = 255 - left, 255 - right
    if shown.get("swapped"):
        left, right = right, left
    height, width = min(left.shape[0], right.shape[0]), min(left.shape[1], right.shape[1])
    return np.ascontiguousarray(_rgb(left[:height, :width])), np.ascontiguousarray(_rgb(right[:height, :width]))


def _resize(image: np.ndarray, width: int, height: int | None = None) -> np.ndarray:
    import cv2

    height = height or max(1, round(image.shape[0] * width / image.shape[1]))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def grid_picture_array(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``(h + gap + strip, PHOTO_WIDTH, 3)``: the left photo over its depth strip (turbo colours,
    near warm; the depth map squeezed in height, so its top is still the scene's top)."""
    photo = _resize(left, PHOTO_WIDTH)
    depth = depth_colours(signed_disparity(_resize(left, DEPTH_MATCH_WIDTH), _resize(right, DEPTH_MATCH_WIDTH)))
    strip = _resize(depth, PHOTO_WIDTH, max(8, round(photo.shape[0] * STRIP_FRACTION)))
    gap = np.full((GAP, PHOTO_WIDTH, 3), 255, np.uint8)
    return np.concatenate([photo, gap, strip], axis=0)


def _jpeg(image: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=80, optimize=True)
    return buffer.getvalue()


def picture_key(content_hash: str, left_box: Sequence[float], right_box: Sequence[float], shown: Mapping[str, bool]) -> str:
    """A short stable name for one grid picture (cache key and ETag): it changes with the boxes
    or the flags, so a card shown two ways (a gold card's wrong turn) never gets the other's."""
    flags = "".join("1" if shown.get(f) else "0" for f in ("upside_down", "inverted", "swapped"))
    text = f"{content_hash}|{list(map(float, left_box))}|{list(map(float, right_box))}|{flags}|{PHOTO_WIDTH}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def grid_picture(
    key: str,
    load: Callable[[], np.ndarray],
    card_width: int,
    left_box: Sequence[float],
    right_box: Sequence[float],
    shown: Mapping[str, bool],
) -> bytes:
    """The JPEG of :func:`grid_picture_array` for the card ``load`` returns (the scan, or a
    reduced copy of it; called only when ``key``, a :func:`picture_key`, is not cached) whose
    original is ``card_width`` px wide (the frame of the boxes)."""
    with _lock:
        if key in _pictures:
            _pictures.move_to_end(key)
            return _pictures[key]
    image = load()
    scale = image.shape[1] / card_width
    data = _jpeg(grid_picture_array(*oriented_photos(image, left_box, right_box, shown, scale)))
    with _lock:
        _pictures[key] = data
        while len(_pictures) > _CACHE:
            _pictures.popitem(last=False)
    return data

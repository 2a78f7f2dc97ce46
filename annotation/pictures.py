"""Pictures the crowd pages show besides the card itself, made at request time and cached in memory.

* Instruction examples (:func:`example_picture`): a good crop, a bad crop that takes in the
  mount, an upside-down card and a negative, drawn on a synthetic demo card
  (:func:`simulation.cards.make_stereo_card`: built from scikit-image's Motorcycle pair,
  so any install has it; nothing is read from a collection and nothing is stored in the repo).
* Eye-order pictures (:func:`eye_order_picture`), for the judge task's ``swapped`` question: the
  depth read from the card's two photos in colour (near warm, far cool) laid over its first photo
  in grey, once with the photos as scanned and once exchanged, shown side by side. Two photos
  simply flicked one after the other look the same in either order (a loop has no first frame),
  so a person cannot tell the order from them; the depth read with the photos in the wrong order
  comes out inside out (the near ground cool, the sky warm), which anybody sees at a glance. The
  pictures are still JPEGs (4:4:4, no palette): an animated GIF's one palette came from the photo
  frame and turned the depth frame sepia, with no blue left in it.
"""

from __future__ import annotations

import functools
import io
import threading
from collections import OrderedDict
from typing import Any

import numpy as np

EXAMPLES: dict[str, str] = {
    "good-crop": "A good crop: each box holds only the photograph.",
    "bad-crop": "A bad crop: the boxes take in the card's mount, its printed title and the gap between the photos.",
    "upside-down": "An upside-down card: the sky is at the bottom and the writing reads upside-down.",
    "negative": "A negative: dark skies, white shadows.",
    "eye-order": "The two colour pictures of a card: as scanned (left) the motorcycle in front is warm and the "
    "shelves behind it cool, the right order; with the photos exchanged (right) it is inside out.",
}
EXAMPLE_WIDTH = 480  # px: the help dialog shows them at most this wide
# px: two sit side by side on a 390 px phone at about 175 CSS px each, so this gives two device
# pixels a CSS pixel there and the full size on a laptop.
EYE_ORDER_WIDTH = 360
EYE_ORDERS: tuple[str, ...] = ("as-is", "swapped")
# The share of the depth colour where the depth is known; the grey photo shows through the rest,
# enough to recognise the scene without washing the colours out.
DEPTH_OPACITY = 0.65
# Turbo's ends are near black (dark purple, dark red): start and stop inside them so that far reads
# clearly blue and near clearly red.
_TURBO_RANGE = (30, 230)
GOOD = (40, 170, 60)
BAD = (220, 40, 40)


def _resize(image: np.ndarray, width: int) -> np.ndarray:
    import cv2

    height = max(1, round(image.shape[0] * width / image.shape[1]))
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def _jpeg(image: np.ndarray, quality: int = 82, full_colour: bool = False) -> bytes:
    """JPEG bytes; ``full_colour`` keeps the colour at full resolution (4:4:4) instead of halving it."""
    from PIL import Image

    buffer = io.BytesIO()
    extra = {"subsampling": 0} if full_colour else {}
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality, optimize=True, **extra)
    return buffer.getvalue()


def _draw_box(image: np.ndarray, box: list[int], colour: tuple[int, int, int], thickness: int) -> None:
    import cv2

    x0, y0, x1, y1 = box
    cv2.rectangle(image, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), colour, thickness)


@functools.lru_cache(maxsize=1)
def _example_card() -> Any:
    from simulation.cards import make_stereo_card

    return make_stereo_card(0, 0)


@functools.lru_cache(maxsize=len(EXAMPLES))
def example_picture(name: str) -> bytes:
    """The JPEG of one instruction example (a key of :data:`EXAMPLES`); KeyError for any other name."""
    if name not in EXAMPLES:
        raise KeyError(name)
    card = _example_card()
    image = card.image.copy()
    thickness = max(3, image.shape[1] // 160)
    if name == "good-crop":
        for x0, y0, x1, y1 in card.truth["photo_boxes"]:
            inset = round(0.04 * (x1 - x0))
            _draw_box(image, [x0 + inset, y0 + inset, x1 - inset, y1 - inset], GOOD, thickness)
    elif name == "bad-crop":
        cx0, cy0, cx1, cy1 = card.truth["card_box"]
        middle = (cx0 + cx1) // 2
        margin = round(0.02 * (cx1 - cx0))
        _draw_box(image, [cx0 + margin, cy0 + margin, middle + margin, cy1 - margin], BAD, thickness)
        _draw_box(image, [middle + 2 * margin, cy0 + margin, cx1 - margin, cy1 - margin], BAD, thickness)
    elif name == "eye-order":
        left_box, right_box = card.truth["photo_boxes"]
        gap = 8
        width = (EXAMPLE_WIDTH - gap) // 2
        as_is, swapped = (eye_order_depth(image, left_box, right_box, order, width) for order in EYE_ORDERS)
        blank = np.full((as_is.shape[0], gap, 3), 255, np.uint8)
        return _jpeg(np.hstack([as_is, blank, swapped]), quality=90, full_colour=True)
    elif name == "upside-down":
        image = np.ascontiguousarray(image[::-1, ::-1])
    else:
        image = 255 - image
    return _jpeg(_resize(image, EXAMPLE_WIDTH))


_eye_order_pictures: OrderedDict[tuple[Any, ...], bytes] = OrderedDict()
_eye_order_lock = threading.Lock()
_EYE_ORDER_CACHE = 256


def eye_order_photos(
    card: np.ndarray, left_box: list[float], right_box: list[float], order: str, width: int = EYE_ORDER_WIDTH
) -> tuple[np.ndarray, np.ndarray]:
    """The two photos in the order asked for: the left, then the right (``as-is``), or the other way round.

    ``card``: ``(H, W, 3)`` or ``(H, W)`` uint8 as scanned; boxes ``[x0, y0, x1, y1]`` in its
    pixels, clipped to the card. Both photos are cut to the size they share (top-left aligned in
    their boxes) and scaled to ``width`` px, ``(h, width, 3)`` uint8 each. ValueError for an
    unknown order or a box that keeps less than 2 x 2 px of the card.
    """
    if order not in EYE_ORDERS:
        raise ValueError(f"Expected an eye order of {' or '.join(EYE_ORDERS)}, got {order!r}")
    rgb = card if card.ndim == 3 else np.repeat(card[:, :, None], 3, axis=2)
    height, full_width = rgb.shape[:2]

    def clipped(box: list[float]) -> tuple[int, int, int, int]:
        x0, y0, x1, y1 = (round(float(v)) for v in box)
        return max(x0, 0), max(y0, 0), min(x1, full_width), min(y1, height)

    lx0, ly0, lx1, ly1 = clipped(left_box)
    rx0, ry0, rx1, ry1 = clipped(right_box)
    w, h = min(lx1 - lx0, rx1 - rx0), min(ly1 - ly0, ry1 - ry0)
    if w < 2 or h < 2:
        raise ValueError(
            f"Expected photo boxes that keep at least 2 x 2 px of the {full_width} x {height} px card, "
            f"got {left_box} and {right_box}"
        )
    first, second = rgb[ly0 : ly0 + h, lx0 : lx0 + w], rgb[ry0 : ry0 + h, rx0 : rx0 + w]
    if order == "swapped":
        first, second = second, first
    return _resize(np.ascontiguousarray(first), width), _resize(np.ascontiguousarray(second), width)


def eye_order_depth(
    card: np.ndarray, left_box: list[float], right_box: list[float], order: str, width: int = EYE_ORDER_WIDTH
) -> np.ndarray:
    """The eye-order picture as an array, ``(h, width, 3)`` uint8 RGB: the depth read from the photos in
    ``order`` (:func:`eye_order_photos`) in colour over the first of them (:func:`depth_over_photo`).
    With the photos in the right order near things come out warm and far ones cool."""
    first, second = eye_order_photos(card, left_box, right_box, order, width)
    return depth_over_photo(first, signed_disparity(first, second))


def signed_disparity(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 disparity of ``first`` against ``second`` (``x_second = x_first - d``; with
    the photos in the right order nearer is larger), searched on both sides of zero (the offset
    between a card's photos is arbitrary, and exchanged photos flip the sign) by the pipeline's
    own estimator, NaN where it has no confidence (a blank photo: nothing matched)."""
    from pipeline.disparity import DEFAULT_BACKEND, DisparityParams, estimate_disparity

    # +-25 % of the width: the demo's close-up cards reach 18 % (66 px at 360); searched to 15 % they
    # were clipped there and kept a half or a third of their matched pixels (05: 18 % -> 53 % matched).
    reach = 0.25 * first.shape[1]
    result = estimate_disparity(first, second, DEFAULT_BACKEND, DisparityParams(disparity_range=(-reach, reach)))
    return np.where(result.confidence > 0, result.disp_left, np.nan).astype(np.float32)


def depth_colours(disparity: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB: the disparity's 5th..95th percentile spread over turbo colours from
    blue to red (:data:`_TURBO_RANGE`), larger (nearer in the right eye order) warm, unmatched
    pixels mid grey; all grey when nothing matched (a blank photo: no colours to mislead)."""
    import cv2

    picture = np.full((*disparity.shape, 3), 128, np.uint8)
    known = np.isfinite(disparity)
    if known.sum() < 16:
        return picture
    low, high = np.percentile(disparity[known], [5, 95])
    scaled = np.clip((np.nan_to_num(disparity) - low) / max(float(high - low), 1e-3), 0.0, 1.0)
    start, stop = _TURBO_RANGE
    coloured = cv2.applyColorMap((start + scaled * (stop - start)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    picture[known] = coloured[known]
    return picture


def depth_over_photo(photo: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB: :func:`depth_colours` at :data:`DEPTH_OPACITY` over ``photo`` (``(H, W, 3)``
    uint8, the view ``disparity`` is aligned to) in grey; the grey photo alone where nothing matched."""
    import cv2

    grey = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY).astype(np.float32)[..., None]
    colours = depth_colours(disparity).astype(np.float32)
    known = np.isfinite(disparity)[..., None]
    blended = np.where(known, DEPTH_OPACITY * colours + (1.0 - DEPTH_OPACITY) * grey, grey)
    return np.clip(np.rint(blended), 0, 255).astype(np.uint8)


def eye_order_picture(key: tuple[Any, ...], card: Any, left_box: list[float], right_box: list[float], order: str) -> bytes:
    """The JPEG of :func:`eye_order_depth`, cached under ``key``, the boxes and ``order`` (a card
    whose photo boxes change, say by a new orientation step, gets a new picture).

    ``card`` is the image or a callable returning it (so a cached picture never decodes the original).
    """
    cache_key = (*key, tuple(float(v) for v in left_box), tuple(float(v) for v in right_box), order)
    with _eye_order_lock:
        if cache_key in _eye_order_pictures:
            _eye_order_pictures.move_to_end(cache_key)
            return _eye_order_pictures[cache_key]
    image = card() if callable(card) else card
    data = _jpeg(eye_order_depth(image, left_box, right_box, order), quality=90, full_colour=True)
    with _eye_order_lock:
        _eye_order_pictures[cache_key] = data
        while len(_eye_order_pictures) > _EYE_ORDER_CACHE:
            _eye_order_pictures.popitem(last=False)
    return data


@functools.lru_cache(maxsize=1)
def sample_card_picture() -> bytes:
    """The synthetic example card as it is (a JPEG), for previews when no collection card is at hand."""
    return _jpeg(_resize(_example_card().image, 2 * EXAMPLE_WIDTH))

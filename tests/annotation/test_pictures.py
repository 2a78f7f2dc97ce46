"""The crowd's eye-order pictures: depth read with the photos in the wrong order comes out inside out,
in colours a person sees (near warm, far cool) on a still JPEG."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from annotation.pictures import (
    EYE_ORDER_WIDTH,
    depth_colours,
    eye_order_depth,
    eye_order_photos,
    eye_order_picture,
    signed_disparity,
)


def _square_card(shift: int = 8) -> tuple[np.ndarray, list[int], list[int]]:
    """A card of two photos: a textured background at disparity 0 and a textured square in
    front (``x_right = x_left - shift`` on it), side by side; boxes in card pixels."""
    rng = np.random.default_rng(3)
    background = rng.integers(0, 255, (96, 128, 1), dtype=np.uint8).repeat(3, axis=2)
    square = rng.integers(0, 255, (40, 40, 1), dtype=np.uint8).repeat(3, axis=2)
    left, right = background.copy(), background.copy()
    left[28:68, 50:90] = square
    right[28:68, 50 - shift : 90 - shift] = square
    return np.hstack([left, right]), [0, 0, 128, 96], [128, 0, 256, 96]


def _warmth(picture: np.ndarray) -> np.ndarray:
    return picture[..., 0].astype(np.float32) - picture[..., 2].astype(np.float32)  # red minus blue


def _decoded(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as picture:
        assert picture.format == "JPEG"
        return np.asarray(picture.convert("RGB"))


def warm_and_cool_shares(picture: np.ndarray) -> tuple[float, float]:
    """The shares of a picture's pixels that are clearly warm (red 60 over blue) and clearly cool (blue 60 over red)."""
    warmth = _warmth(picture)
    return float((warmth > 60).mean()), float((warmth < -60).mean())


def test_the_near_square_is_warm_as_scanned_and_cool_exchanged():
    card, left_box, right_box = _square_card()
    inside, outside = (slice(34, 62), slice(58, 82)), (slice(0, 20), slice(10, 118))
    for order, sign in (("as-is", 1), ("swapped", -1)):
        picture = eye_order_depth(card, left_box, right_box, order, width=128)
        assert picture.shape == (96, 128, 3) and picture.dtype == np.uint8
        warmth = _warmth(picture)
        assert sign * (np.median(warmth[inside]) - np.median(warmth[outside])) > 150, order


@pytest.fixture(scope="module")
def motorcycle_card():  # type: ignore[no-untyped-def]
    from simulation.cards import make_stereo_card

    return make_stereo_card(0, 0)


def _true_disparity_on_the_scan(card) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Middlebury's ground-truth disparity (scan px, 0 = unknown) on both prints of the card: the
    truth's affines take source pixels to scan pixels; the right print's values are the left
    view's carried across (``x_right = x_left - d``), nearer points written last so they hide
    what they occlude."""
    from skimage import data

    _, _, disparity = data.stereo_motorcycle()
    disparity = np.where(np.isfinite(disparity), disparity, 0).astype(np.float32)
    height, width = card.image.shape[:2]
    scale = card.truth["scale"]
    left = cv2.warpAffine(disparity, np.array(card.truth["left_affine"]), (width, height), flags=cv2.INTER_NEAREST) * scale
    ys, xs = np.nonzero(disparity > 0)
    d = disparity[ys, xs]
    order = np.argsort(d, kind="stable")
    ys, xs, d = ys[order], xs[order], d[order]
    points = np.array(card.truth["right_affine"]) @ np.stack([xs - d, ys, np.ones_like(d)])
    px, py = np.rint(points[0]).astype(int), np.rint(points[1]).astype(int)
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    right = np.zeros((height, width), np.float32)
    right[py[inside], px[inside]] = d[inside] * scale
    right = cv2.morphologyEx(right, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))  # the splat's pinholes
    scan = np.zeros((height, width), np.float32)
    for key, values in (("left_box", left), ("right_box", right)):  # each view inside its own print
        x0, y0, x1, y1 = card.truth[key]
        scan[y0:y1, x0:x1] = values[y0:y1, x0:x1]
    return scan


def _on_the_picture(scan: np.ndarray, box: list[int], shared: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """The part of ``scan`` a picture shows: ``shared`` (w, h) px from ``box``'s corner, scaled to ``size`` (w, h)."""
    x0, y0 = box[:2]
    crop = scan[y0 : y0 + shared[1], x0 : x0 + shared[0]]
    return cv2.resize(crop, size, interpolation=cv2.INTER_NEAREST)


def test_a_real_stereo_card_shows_near_warm_as_scanned_and_inside_out_exchanged(motorcycle_card):
    """The synthetic card from Middlebury's Motorcycle pair: the served JPEG holds clearly warm and
    clearly cool pixels in both orders (the old GIF had no blue pixel at all), and the quarter of the
    scene with the largest true disparity (the motorcycle) is warm as scanned and cool exchanged."""
    left_box, right_box = motorcycle_card.truth["photo_boxes"]
    pictures = {
        order: _decoded(eye_order_picture(("motorcycle-test",), motorcycle_card.image, left_box, right_box, order))
        for order in ("as-is", "swapped")
    }
    height, width = pictures["as-is"].shape[:2]
    assert width == EYE_ORDER_WIDTH and height == round(EYE_ORDER_WIDTH * 552 / 605)
    for order, picture in pictures.items():
        warm, cool = warm_and_cool_shares(picture)
        assert warm > 0.15 and cool > 0.15, (order, warm, cool)  # measured 0.52 / 0.23 and 0.23 / 0.49

    scan = _true_disparity_on_the_scan(motorcycle_card)
    shared = (
        min(left_box[2] - left_box[0], right_box[2] - right_box[0]),
        min(left_box[3] - left_box[1], right_box[3] - right_box[1]),
    )
    warmth, near, far = {}, {}, {}
    for order, first_box in (("as-is", left_box), ("swapped", right_box)):
        truth = _on_the_picture(scan, first_box, shared, (width, height))
        known = truth > 0
        near[order] = known & (truth >= np.percentile(truth[known], 75))
        far[order] = known & (truth <= np.percentile(truth[known], 25))
        warmth[order] = _warmth(pictures[order])
    as_is = {"near": warmth["as-is"][near["as-is"]].mean(), "far": warmth["as-is"][far["as-is"]].mean()}
    swapped = {"near": warmth["swapped"][near["swapped"]].mean(), "far": warmth["swapped"][far["swapped"]].mean()}
    # Measured (red minus blue): near +109, far -75 as scanned; near -89, far +96 exchanged.
    assert as_is["near"] > 60 and as_is["far"] < -30, as_is
    assert swapped["near"] < -60 and swapped["far"] > 30, swapped
    assert as_is["near"] - swapped["near"] > 120


def test_signed_disparity_finds_the_offset_on_both_sides_of_zero():
    card, _, _ = _square_card()
    left, right = card[:, :128], card[:, 128:]
    assert abs(np.nanmedian(signed_disparity(left, right)[34:62, 58:82]) - 8) <= 1
    assert abs(np.nanmedian(signed_disparity(right, left)[34:62, 50:74]) + 8) <= 1


def test_a_blank_pair_gives_grey_not_colours_or_nan():
    blank = np.full((60, 80, 3), 128, np.uint8)
    picture = depth_colours(signed_disparity(blank, blank))
    assert picture.dtype == np.uint8 and (picture == 128).all()
    card = np.hstack([blank, blank])
    over_photo = eye_order_depth(card, [0, 0, 80, 60], [80, 0, 160, 60], "as-is", width=80)
    assert (over_photo == 128).all()  # the grey photo, no colour


def test_tiny_or_outside_boxes_and_unknown_orders_say_what_is_wrong():
    card, left_box, _ = _square_card()
    with pytest.raises(ValueError, match=r"at least 2 x 2 px of the 256 x 96 px card, got \[0, 0, 128, 96\] and \[5, 5, 6, 6\]"):
        eye_order_photos(card, left_box, [5, 5, 6, 6], "as-is")
    with pytest.raises(ValueError, match="at least 2 x 2 px"):
        eye_order_photos(card, left_box, [300, 0, 400, 96], "as-is")  # right of the card
    with pytest.raises(ValueError, match="Expected an eye order of as-is or swapped, got 'sideways'"):
        eye_order_photos(card, left_box, [128, 0, 256, 96], "sideways")
    with pytest.raises(ValueError, match="at least 2 x 2 px"):
        eye_order_picture(("tiny-boxes",), card, left_box, [5, 5, 6, 6], "as-is")


def test_boxes_reaching_past_the_card_are_clipped_to_it():
    card, _, _ = _square_card()
    first, second = eye_order_photos(card, [-20, -5, 128, 96], [128, 0, 300, 120], "swapped", width=64)
    assert first.shape == second.shape == (48, 64, 3)


def test_pictures_are_cached_per_card_and_order_without_decoding_again():
    card, left_box, right_box = _square_card()
    decodes = []

    def read() -> np.ndarray:
        decodes.append(1)
        return card

    key = ("cache-test", "content-hash")
    first = eye_order_picture(key, read, left_box, right_box, "as-is")
    assert eye_order_picture(key, read, left_box, right_box, "as-is") is first and len(decodes) == 1
    exchanged = eye_order_picture(key, read, left_box, right_box, "swapped")
    assert exchanged != first and len(decodes) == 2

"""The crowd's eye-order pictures: depth read with the photos in the wrong order comes out inside out."""

from __future__ import annotations

import numpy as np

from annotation.pictures import depth_colours, signed_disparity, wiggle_frames


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


def test_the_near_square_is_warm_as_scanned_and_cool_exchanged():
    card, left_box, right_box = _square_card()
    inside, outside = (slice(34, 62), slice(58, 82)), (slice(0, 20), slice(10, 118))
    for order, sign in (("as-is", 1), ("swapped", -1)):
        frames = wiggle_frames(card, left_box, right_box, order, width=128)
        assert len(frames) == 4 and frames[0].shape == (96, 128, 3)
        warmth = _warmth(frames[2])
        assert sign * (np.median(warmth[inside]) - np.median(warmth[outside])) > 100, order


def test_signed_disparity_finds_the_offset_on_both_sides_of_zero():
    card, _, _ = _square_card()
    left, right = card[:, :128], card[:, 128:]
    assert abs(np.nanmedian(signed_disparity(left, right)[34:62, 58:82]) - 8) <= 1
    assert abs(np.nanmedian(signed_disparity(right, left)[34:62, 50:74]) + 8) <= 1


def test_a_blank_pair_gives_grey_not_colours_or_nan():
    blank = np.full((60, 80, 3), 128, np.uint8)
    picture = depth_colours(signed_disparity(blank, blank))
    assert picture.dtype == np.uint8 and (picture == 128).all()

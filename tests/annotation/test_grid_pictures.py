"""A grid card's picture: the card as the pipeline will use it, and its depth strip."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from annotation.grid_pictures import PHOTO_WIDTH, grid_picture, grid_picture_array, oriented_photos, picture_key
from pipeline.orientation import orient_variant

FLAGS = ("upside_down", "inverted", "swapped")


def _card(card_image):  # type: ignore[no-untyped-def]
    card = card_image()
    half = (card.shape[1] - 12) // 2
    return card, (0, 0, half, card.shape[0]), (half + 12, 0, 2 * half + 12, card.shape[0])


@pytest.mark.parametrize("values", list(itertools.product((False, True), repeat=3)))
def test_the_shown_flags_undo_a_scan_made_with_them(card_image, values):  # type: ignore[no-untyped-def]
    card, left_box, right_box = _card(card_image)
    flags = dict(zip(FLAGS, values, strict=True))
    scanned, scanned_left, scanned_right = orient_variant(card, left_box, right_box, **flags)
    left, right = oriented_photos(scanned, scanned_left, scanned_right, flags)
    x0, y0, x1, y1 = left_box
    assert np.array_equal(left, card[y0:y1, x0:x1])
    x0, y0, x1, y1 = right_box
    assert np.array_equal(right, card[y0:y1, x0:x1])


def test_boxes_scale_with_a_reduced_copy_and_must_cut_a_photo(card_image):  # type: ignore[no-untyped-def]
    card, left_box, right_box = _card(card_image)
    left, _ = oriented_photos(card[::2, ::2], left_box, right_box, dict.fromkeys(FLAGS, False), scale=0.5)
    assert left.shape == (card.shape[0] // 2, left_box[2] // 2, 3)
    with pytest.raises(ValueError, match="2 x 2"):
        oriented_photos(card, [0, 0, 1, 1], right_box, {})


def test_exchanged_photos_turn_the_depth_strip_inside_out(card_image):  # type: ignore[no-untyped-def]
    # Motorcycle: the machine is near, the wall behind it far. The strip's middle band must be
    # warmer (more red than blue) with the photos in the right order and cooler when exchanged.
    card, left_box, right_box = _card(card_image)
    left, right = oriented_photos(card, left_box, right_box, {})
    right_way, inside_out = grid_picture_array(left, right), grid_picture_array(right, left)
    assert right_way.shape[1] == PHOTO_WIDTH and right_way.shape[0] > right_way.shape[1] * left.shape[0] / left.shape[1]
    photo_height = round(left.shape[0] * PHOTO_WIDTH / left.shape[1])
    strip = slice(photo_height + 3, None)

    def warmth(picture: np.ndarray) -> float:
        band = picture[strip].astype(float)
        return float((band[..., 0] - band[..., 2]).mean())

    assert warmth(right_way) > warmth(inside_out)


def test_pictures_are_cached_by_key_and_the_key_names_the_flags(card_image):  # type: ignore[no-untyped-def]
    card, left_box, right_box = _card(card_image)
    loads = []

    def load() -> np.ndarray:
        loads.append(1)
        return card

    shown = {"upside_down": True}
    key = picture_key("c" * 64, left_box, right_box, shown)
    first = grid_picture(key, load, card.shape[1], left_box, right_box, shown)
    assert grid_picture(key, load, card.shape[1], left_box, right_box, shown) == first and len(loads) == 1
    assert first[:2] == b"\xff\xd8"
    assert picture_key("c" * 64, left_box, right_box, {}) != key

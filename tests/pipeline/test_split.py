"""pipeline.split: the gutter between the two photos, and a box on each photo."""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
import pytest
from skimage import data

from pipeline.errors import InvalidInputError
from pipeline.records import param_hash
from pipeline.split import CardSplit, SplitParams, crop_halves, split_card

MOUNT = (214, 201, 170)


def mounted(left: np.ndarray, right: np.ndarray, margin: tuple[int, int, int, int], gutter: int) -> np.ndarray:
    """Two views on a plain buff mount; margin = (left, top, right, bottom) px."""
    h, w = left.shape[:2]
    ml, mt, mr, mb = margin
    card = np.empty((mt + h + mb, ml + 2 * w + gutter + mr, 3), np.uint8)
    card[:] = MOUNT
    card[mt : mt + h, ml : ml + w] = left
    card[mt : mt + h, ml + w + gutter : ml + 2 * w + gutter] = right
    return card


def area(box) -> int:
    return (box[2] - box[0]) * (box[3] - box[1])


def overlap(a, b) -> int:
    return max(0, min(a[2], b[2]) - max(a[0], b[0])) * max(0, min(a[3], b[3]) - max(a[1], b[1]))


@pytest.fixture(scope="module")
def motorcycle():
    left, right, _ = data.stereo_motorcycle()  # Middlebury 2014, (500, 741, 3) each
    return left, right


# ------------------------------------------------------------------------------ synthetic cards


def test_split_lands_in_the_gutter_of_an_off_centre_mount(motorcycle):
    left, right = motorcycle
    # Wide right margin: the card's middle (x = 803) is 30 px right of the gutter (761..785).
    card = mounted(left, right, margin=(20, 30, 80, 50), gutter=24)
    split = split_card(card)
    assert abs(split.gutter_x - 773) <= 3
    assert split.method == "gutter" and split.confidence > 0.8
    left_photo, right_photo = (20, 30, 761, 530), (785, 30, 1526, 530)
    for box, photo in ((split.left_box, left_photo), (split.right_box, right_photo)):
        assert overlap(box, photo) / area(photo) > 0.97  # covers its photo
        assert overlap(box, photo) / area(box) > 0.8  # and is mostly photo
    assert split.left_box[2] <= split.gutter_x <= split.right_box[0]


def test_abutting_photos_split_at_the_join_without_any_gutter(motorcycle):
    left, right = motorcycle
    card = np.hstack([left, right])  # a cropped pair: nothing between the views
    split = split_card(card)
    assert abs(split.gutter_x - 741) <= 6
    assert split.confidence > 0.5


def test_abutting_grey_pair_off_centre(motorcycle):
    """A raw-scan-like grey pair with a wide film edge on the left only: not cut at the middle."""
    grey = [cv2.cvtColor(view, cv2.COLOR_RGB2GRAY) for view in motorcycle]
    card = np.hstack([np.full((500, 90), 250, np.uint8), grey[0], grey[1]])
    split = split_card(card)
    assert abs(split.gutter_x - (90 + 741)) <= 6  # the middle would be 786
    x0, _, x1, _ = split.left_box
    assert x0 >= 70  # the plain film edge is trimmed
    assert card.ndim == 2 and crop_halves(card, split)[0].ndim == 2


def test_boxes_are_equal_and_inside_the_card(motorcycle):
    left, right = motorcycle
    card = mounted(left, right, margin=(35, 12, 15, 60), gutter=10)
    split = split_card(card)
    h, w = card.shape[:2]
    (lx0, ly0, lx1, ly1), (rx0, ry0, rx1, ry1) = split.left_box, split.right_box
    assert (lx1 - lx0, ly1 - ly0) == (rx1 - rx0, ry1 - ry0)
    assert 0 <= lx0 < lx1 <= split.gutter_x <= rx0 < rx1 <= w
    assert 0 <= ly0 < ly1 <= h and 0 <= ry0 < ry1 <= h
    halves = crop_halves(card, split)
    assert halves[0].shape == halves[1].shape == (ly1 - ly0, lx1 - lx0, 3)
    assert np.shares_memory(halves[0], card)  # views, no copy


def test_blank_card_falls_back_to_the_middle_with_no_confidence():
    card = np.full((300, 640, 3), 200, np.uint8)
    split = split_card(card)
    assert split.method == "centre" and split.confidence == 0.0
    assert abs(split.gutter_x - 320) <= 1
    assert np.isfinite(split.confidence)


def test_noise_card_gives_a_valid_split():
    card = np.random.default_rng(7).integers(0, 256, (200, 420), dtype=np.uint8)
    split = split_card(card)
    assert 0.35 * 420 <= split.gutter_x <= 0.65 * 420
    crop_halves(card, split)


@pytest.mark.parametrize("shape", [(16, 32), (16, 32, 3), (17, 40), (300, 33, 3)])
def test_smallest_cards_are_accepted(shape):
    card = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    split = split_card(card)
    left, right = crop_halves(card, split)
    assert left.shape == right.shape and left.size > 0


@pytest.mark.parametrize(
    "card, message",
    [
        (np.zeros((15, 64), np.uint8), "Expected a card of at least 32x16 px (W x H), got 64x15"),
        (np.zeros((64, 31, 3), np.uint8), "Expected a card of at least 32x16 px (W x H), got 31x64"),
        (np.zeros((100, 200), np.float32), "Expected a card with dtype uint8, got float32"),
        (np.zeros((100, 200), np.uint16), "Expected a card with dtype uint8, got uint16"),
        (np.zeros((100, 200, 4), np.uint8), "Expected a card with shape (H, W) or (H, W, 3), got (100, 200, 4)"),
        (np.zeros((2, 100, 200), np.uint8)[None], "Expected a card with shape (H, W) or (H, W, 3), got (1, 2, 100, 200)"),
        ([[0] * 64] * 64, "Expected a card as a numpy array, got list"),
    ],
)
def test_bad_cards_are_refused_at_the_door(card, message):
    with pytest.raises(InvalidInputError) as error:
        split_card(card)
    assert str(error.value) == message
    assert error.value.reason().startswith("invalid_input: Expected")


def test_crop_halves_refuses_boxes_outside_the_card():
    card = np.zeros((100, 200), np.uint8)
    split = CardSplit(left_box=(0, 0, 100, 100), right_box=(100, 0, 201, 100), gutter_x=100, method="gutter", confidence=1.0)
    with pytest.raises(InvalidInputError, match=r"Expected right_box inside the 200x100 card"):
        crop_halves(card, split)


def test_split_is_deterministic(motorcycle):
    card = mounted(*motorcycle, margin=(20, 30, 80, 50), gutter=24)
    assert split_card(card) == split_card(card.copy())


def test_search_band_is_respected(motorcycle):
    card = mounted(*motorcycle, margin=(20, 30, 80, 50), gutter=24)  # gutter at 0.48 of the width
    split = split_card(card, SplitParams(search_band=(0.55, 0.65)))
    assert 0.55 * card.shape[1] - 1 <= split.gutter_x <= 0.65 * card.shape[1] + 1


@pytest.mark.parametrize(
    "kwargs",
    [{"search_band": (0.6, 0.4)}, {"search_band": (0.0, 0.5)}, {"analysis_width": 16}, {"margin": -0.1}, {"plateau": 2.0}],
)
def test_bad_params_fail_when_built(kwargs):
    with pytest.raises(InvalidInputError, match="Expected"):
        SplitParams(**kwargs)


def test_params_change_the_param_hash():
    base = param_hash(SplitParams())
    assert base == param_hash(SplitParams())
    assert base != param_hash(SplitParams(search_band=(0.3, 0.7)))
    assert base != param_hash(SplitParams(analysis_width=640))
    assert base != param_hash(SplitParams(margin=0.02))


# ------------------------------------------------------------------------------------ real cards

# Gutter position (fraction of the width) and photo rectangles (x0, y0, x1, y1 as fractions),
# read by eye off each scan at 2 % grid resolution.
REAL_CARDS = {
    "full_cards/nypl_000206_pima_indians_of_arizona.jpg": (0.515, (0.115, 0.085, 0.513, 0.915), (0.517, 0.075, 0.910, 0.915)),
    "full_cards/nypl_c7980740_birds-eye_view_columbian_exposition_front.jpg": (
        0.494,
        (0.075, 0.07, 0.49, 0.86),
        (0.497, 0.07, 0.915, 0.86),
    ),
    "full_cards/nypl_f0bf5ba0_ostrich_farm_columbian_exposition_front.jpg": (
        0.504,
        (0.09, 0.055, 0.50, 0.85),
        (0.507, 0.06, 0.92, 0.85),
    ),
    "full_cards/nypl_stereogranimator_demo1.jpg": (0.498, (0.085, 0.06, 0.497, 0.945), (0.50, 0.06, 0.915, 0.945)),
    "full_cards/nypl_stereogranimator_demo2.jpg": (0.499, (0.10, 0.065, 0.495, 0.89), (0.505, 0.065, 0.90, 0.89)),
    "full_cards/nypl_stereogranimator_demo3.jpg": (0.490, (0.075, 0.05, 0.49, 0.905), (0.49, 0.05, 0.905, 0.915)),
    "full_cards/nypl_stereogranimator_demo4.jpg": (0.512, (0.10, 0.03, 0.512, 0.965), (0.513, 0.03, 0.925, 0.965)),
    "full_cards/nypl_stereogranimator_demo5.jpg": (0.501, (0.097, 0.04, 0.50, 0.945), (0.503, 0.04, 0.905, 0.945)),
    "full_cards/nypl_stereogranimator_sample-stereo.jpg": (0.498, (0.075, 0.04, 0.495, 0.885), (0.50, 0.04, 0.925, 0.885)),
    "keystone_mast_raw_scans/09995.jpg": (0.507, (0.045, 0.04, 0.505, 1.0), (0.51, 0.04, 0.98, 1.0)),
    "keystone_mast_raw_scans/09997.jpg": (0.501, (0.035, 0.0, 0.497, 1.0), (0.505, 0.0, 0.972, 1.0)),
    "cropped_pairs/jps/8618s.jps": (0.501, (0.0, 0.0, 0.5, 1.0), (0.5, 0.0, 1.0, 1.0)),
    "cropped_pairs/jps/Daibutsu.jps": (0.500, (0.0, 0.0, 0.497, 1.0), (0.502, 0.0, 1.0, 1.0)),
    "cropped_pairs/jps/sports.jps": (0.495, (0.0, 0.0, 0.491, 1.0), (0.499, 0.0, 1.0, 1.0)),
    "cropped_pairs/depthy_7995": (0.500, (0.0, 0.0, 0.5, 1.0), (0.5, 0.0, 1.0, 1.0)),
}


@pytest.mark.parametrize("name", sorted(REAL_CARDS))
def test_real_card_split(load_card, name):
    card = load_card(name)
    height, width = card.shape[:2]
    gutter, *photos = REAL_CARDS[name]
    split = split_card(card)

    assert 0.35 * width <= split.gutter_x <= 0.65 * width
    assert abs(split.gutter_x / width - gutter) <= 0.015, (split.gutter_x / width, gutter)
    (lx0, ly0, lx1, ly1), (rx0, ry0, rx1, ry1) = split.left_box, split.right_box
    assert 0 <= lx0 < lx1 <= split.gutter_x <= rx0 < rx1 <= width
    assert 0 <= ly0 < ly1 <= height and 0 <= ry0 < ry1 <= height
    assert (lx1 - lx0, ly1 - ly0) == (rx1 - rx0, ry1 - ry0)
    for box, (px0, py0, px1, py1) in zip((split.left_box, split.right_box), photos):
        photo = (px0 * width, py0 * height, px1 * width, py1 * height)
        assert overlap(box, photo) / area(photo) >= 0.95, "the box cuts its photo"
        assert overlap(box, photo) / area(box) >= 0.75, "the box is not mostly photo"
    assert split.confidence >= 0.7


@pytest.mark.bench
def test_split_takes_under_20_ms_for_a_1400_px_scan(load_card):
    card = load_card("keystone_mast_raw_scans/09995.jpg")
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        split_card(card)
        times = []
        for _ in range(7):
            start = time.perf_counter()
            split_card(card)
            times.append(time.perf_counter() - start)
    finally:
        cv2.setNumThreads(previous)
    assert statistics.median(times) < 0.020


def test_a_split_found_at_half_size_scales_to_the_full_card():
    from pipeline.split import scale_split

    found = CardSplit(left_box=(3, 2, 48, 40), right_box=(52, 2, 97, 40), gutter_x=50, method="gutter", confidence=0.8)
    scaled = scale_split(found, 2, (199, 80))  # the decoded card was ceil(199 / 2) = 100 px wide
    assert scaled.left_box == (6, 4, 96, 80) and scaled.gutter_x == 100
    # 97 x 2 = 194 <= 199 stays; a box ending past the card moves back inside, keeping its size.
    assert scaled.right_box == (104, 4, 194, 80)
    # At the card's edge there is nothing to move back into: the box is cut to the card.
    edge = scale_split(CardSplit((0, 0, 40, 30), (60, 0, 100, 30), 50, "gutter", 1.0), 2, (199, 59))
    assert edge.right_box == (119, 0, 199, 59) and edge.left_box == (0, 0, 80, 59)

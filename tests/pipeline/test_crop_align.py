"""pipeline.crop_align: SIFT translation between crowd crop boxes, crops cut to their intersection.

The card is scikit-image's Motorcycle pair (Middlebury 2014, GT disparity +7..+60 px) side by side
on a grey mount with a gutter; the right photo is pasted ``SHIFT`` px lower than the left, so the
true vertical offset between any two boxes is known exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
from skimage import data

from pipeline.crop_align import (
    CropAlignment,
    CropAlignParams,
    EmptyIntersectionError,
    TooFewCropMatchesError,
    align_crops,
)
from pipeline.errors import InvalidInputError, PipelineError

MARGIN, GUTTER, SHIFT = 20, 30, 7
W, H = 741, 500


@pytest.fixture(scope="module")
def card() -> tuple[np.ndarray, np.ndarray]:
    left, right, disp = data.stereo_motorcycle()
    out = np.full((H + 2 * MARGIN + SHIFT, 2 * W + GUTTER + 2 * MARGIN, 3), 190, np.uint8)
    out[MARGIN : MARGIN + H, MARGIN : MARGIN + W] = left
    rx = MARGIN + W + GUTTER
    out[MARGIN + SHIFT : MARGIN + SHIFT + H, rx : rx + W] = right
    return out, disp


RX = MARGIN + W + GUTTER
# Crowd-like boxes: different sizes, different margins, partly on the mount.
CASES = [
    ((MARGIN + 5, MARGIN + 12, MARGIN + 700, MARGIN + 480), (RX - 8, MARGIN + 3, RX + 720, MARGIN + 470)),
    ((MARGIN + 40, MARGIN + 30, MARGIN + 650, MARGIN + 430), (RX + 10, MARGIN + 25, RX + 741, MARGIN + 500)),
    ((MARGIN - 10, MARGIN - 5, MARGIN + 741, MARGIN + 505), (RX + 30, MARGIN + 40, RX + 690, MARGIN + 450)),
]


@pytest.mark.parametrize("boxes", CASES)
def test_aligned_boxes_equal_inside_and_recover_the_shift(card, boxes) -> None:
    image, disp = card
    lb, rb = boxes
    res = align_crops(image, lb, rb)
    assert isinstance(res, CropAlignment)
    h, w = image.shape[:2]
    (a0, b0, a1, b1), (c0, d0, c1, d1) = res.left_box, res.right_box
    assert (a1 - a0, b1 - b0) == (c1 - c0, d1 - d0) == res.size
    for box, before in ((res.left_box, lb), (res.right_box, rb)):
        assert 0 <= box[0] < box[2] <= w and 0 <= box[1] < box[3] <= h
        assert before[0] <= box[0] and before[1] <= box[1] and box[2] <= before[2] and box[3] <= before[3]
    # Box-relative vertical offset known exactly: SHIFT + (left y0 - right y0).
    assert abs(res.dy - (SHIFT + lb[1] - rb[1])) < 1.0
    # After alignment the same card-row offset as the pasted photos (within rounding).
    assert abs((d0 - b0) - SHIFT) <= 1
    # Far content lines up: the implied far disparity lies in the low part of the GT range.
    far = (a0 - MARGIN) - (c0 - RX)  # disparity of a point whose crops share a column
    valid = disp[np.isfinite(disp)]
    assert np.percentile(valid, 0) - 2 <= far <= np.percentile(valid, 30)
    assert res.inliers >= 50 and res.matches >= res.inliers
    m = res.metrics()
    assert m["left_box_before"] == list(lb) and m["size"] == list(res.size)


def test_median_convention(card) -> None:
    image, _ = card
    lb, rb = CASES[0]
    far = align_crops(image, lb, rb)
    mid = align_crops(image, lb, rb, CropAlignParams(far_percentile=50))
    assert abs(far.dy - mid.dy) < 1e-9
    assert mid.dx < far.dx  # the median aligns nearer content: the right box moves left


def test_bad_boxes_are_invalid_input(card) -> None:
    image, _ = card
    w = image.shape[1]
    good = CASES[0][1]
    for bad in ((-1, 0, 100, 100), (0, 0, w + 1, 100), (100, 100, 50, 200), (0, 0, 10, 10), (0, 0, float("nan"), 9), "box"):
        with pytest.raises(InvalidInputError):
            align_crops(image, bad, good)
    with pytest.raises(InvalidInputError):
        align_crops(image.astype(np.float32), CASES[0][0], good)


def test_too_few_matches_and_no_overlap(card) -> None:
    image, _ = card
    blank = np.full_like(image, 128)
    with pytest.raises(TooFewCropMatchesError):
        align_crops(blank, CASES[0][0], CASES[0][1])
    # The mount strip vs a photo: nothing in common.
    with pytest.raises(PipelineError):
        align_crops(image, (0, 0, MARGIN, H), CASES[0][1])
    # Boxes whose content overlaps by only a few rows.
    lb = (MARGIN, MARGIN, MARGIN + 300, MARGIN + 200)
    rb = (RX, MARGIN + SHIFT + 190, RX + 300, MARGIN + SHIFT + 400)
    with pytest.raises((EmptyIntersectionError, TooFewCropMatchesError)):
        align_crops(image, lb, rb)


def test_real_cards_align_and_realign_to_zero(shared_data) -> None:
    """Every NYPL full card and Keystone-Mast raw scan, boxes from the automatic split: aligned
    boxes are equal and inside the card; aligning the aligned boxes again finds (0, 0) within a
    pixel. Measured: offsets up to (-54, +6) px (raw scan 09995), 100-1200 consensus matches."""
    from pipeline.io import read_image
    from pipeline.split import split_card

    root = shared_data / "stereocards"
    paths = sorted((root / "full_cards").glob("*.jpg")) + sorted((root / "keystone_mast_raw_scans").glob("*.jpg"))
    assert len(paths) >= 10
    for path in paths:
        card = read_image(path)
        split = split_card(card)
        res = align_crops(card, split.left_box, split.right_box)
        assert res.size == (res.right_box[2] - res.right_box[0], res.right_box[3] - res.right_box[1])
        h, w = card.shape[:2]
        for box in (res.left_box, res.right_box):
            assert 0 <= box[0] < box[2] <= w and 0 <= box[1] < box[3] <= h
        assert res.dy_spread < 1.5, path.name
        again = align_crops(card, res.left_box, res.right_box)
        assert abs(again.dy) <= 1.0 and abs(again.dx) <= 1.0, (path.name, again.dx, again.dy)
        assert all(0 <= a - b <= 1 for a, b in zip(res.size, again.size))  # at most a rounding pixel lost

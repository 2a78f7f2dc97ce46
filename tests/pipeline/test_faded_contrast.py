"""Contrast stretch before features: faded prints keep their keypoints, blank halves stay blank."""

from __future__ import annotations

import glob
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.contrast import MIN_BAND, TARGET_BAND, stretch_contrast
from pipeline.errors import InvalidInputError
from pipeline.filter import filter_card
from pipeline.rectify import RectifyParams, rectify_matches
from pipeline.split import crop_halves

SHARED_CARDS = Path(__file__).resolve().parents[3] / "shared" / "data" / "stereocards" / "full_cards"


def fade(image: np.ndarray, floor: float = 185.0, kept: float = 0.22, seed: int = 0) -> np.ndarray:
    """A faded, yellowed print: the range squeezed to ``kept`` of itself above ``floor``, less
    blue, a little grain (grey levels)."""
    rng = np.random.default_rng(seed)
    faded = floor + image.astype(np.float32) * kept
    if faded.ndim == 3:
        faded[..., 2] *= 0.93
    faded += rng.normal(0.0, 1.5, faded.shape).astype(np.float32)
    return np.clip(np.round(faded), 0, 255).astype(np.uint8)


def test_a_narrow_band_is_widened_to_the_target_about_mid_grey():
    grey = np.tile(np.linspace(190, 240, 200).astype(np.uint8), (50, 1))
    stretched = stretch_contrast(grey)
    assert stretched.dtype == np.uint8 and stretched.shape == grey.shape
    low, high = np.percentile(stretched, (1, 99))
    assert high - low == pytest.approx(TARGET_BAND, abs=4) and (low + high) / 2 == pytest.approx(127.5, abs=3)
    # monotone: the order of grey levels is kept
    assert np.all(np.diff(stretched[0].astype(int)) >= 0)


def test_blank_full_range_and_empty_images_come_back_unchanged():
    rng = np.random.default_rng(0)
    paper = np.clip(200 + rng.normal(0, 2, (64, 64)), 0, 255).astype(np.uint8)  # band ~10 levels
    assert np.percentile(paper, 99) - np.percentile(paper, 1) < MIN_BAND
    assert stretch_contrast(paper) is paper
    full = np.tile(np.arange(256, dtype=np.uint8), (4, 1))
    assert stretch_contrast(full) is full
    normal = np.tile(np.arange(40, 40 + TARGET_BAND + 10, dtype=np.uint8), (4, 1))  # a scan with normal contrast
    assert stretch_contrast(normal) is normal
    constant = np.full((8, 8), 255, np.uint8)
    assert stretch_contrast(constant) is constant
    empty = np.zeros((0, 5), np.uint8)
    assert stretch_contrast(empty) is empty


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8), [[1, 2]]])
def test_anything_but_a_grey_uint8_image_is_a_typed_error(bad):
    with pytest.raises(InvalidInputError):
        stretch_contrast(bad)


@pytest.mark.skipif(not SHARED_CARDS.is_dir(), reason="the shared NYPL cards (../shared/data) are not on this machine")
@pytest.mark.parametrize("path", sorted(glob.glob(str(SHARED_CARDS / "*.jpg")))[:4], ids=lambda p: Path(p).stem[:24])
def test_faded_variants_of_the_shared_cards_pass_the_filter_and_rectify(path):
    card = cv2.cvtColor(cv2.imread(path), cv2.COLOR_BGR2RGB)
    faded = fade(card)
    assert np.percentile(faded, 99) - np.percentile(faded, 1) < 70  # a quarter of the range, or less
    split, result = filter_card(faded)
    assert result.outcome == "pass", result.reason
    left, right = crop_halves(faded, split)
    pts_l, pts_r = result.points
    rect = rectify_matches(pts_l, pts_r, left.shape[1::-1], right.shape[1::-1], RectifyParams(), match_scale=result.match_scale)
    assert rect.dy_p95 < 2.0 * max(1.0, result.match_scale)  # thresholds never under a scan pixel

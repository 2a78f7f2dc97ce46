"""The per-card hot paths rewritten for CPU time (issue 18) give exactly the values of their plain
definitions, on real images: Motorcycle (scikit-image) warped with a black fill, its SGBM
disparity with holes, and grey-level differences between its two views."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from skimage import data

from pipeline.disparity import _fill_background, _sgbm_pair
from pipeline.grading.measurements import _grey_difference_median
from pipeline.rectify import photograph_mask
from pipeline.stages.disparity import colour_disparity


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    left, right, _ = data.stereo_motorcycle()
    size = (left.shape[1] // 4, left.shape[0] // 4)
    return (
        cv2.resize(left, size, interpolation=cv2.INTER_AREA),
        cv2.resize(right, size, interpolation=cv2.INTER_AREA),
    )


def _warped(view: np.ndarray) -> np.ndarray:
    """The view rotated 7 deg about its centre, black outside, as warp_pair fills."""
    height, width = view.shape[:2]
    turn = cv2.getRotationMatrix2D((width / 2, height / 2), 7.0, 0.9)
    return cv2.warpAffine(view, turn, (width, height), flags=cv2.INTER_LINEAR, borderValue=0)


def test_photograph_mask_is_any_channel_above_zero(pair: tuple[np.ndarray, np.ndarray]) -> None:
    rgb = _warped(pair[0])
    rgb[5, 5] = (0, 0, 9)  # one channel alone is still photograph
    mask = photograph_mask(rgb)
    assert mask.shape == rgb.shape[:2] and mask.dtype == bool
    np.testing.assert_array_equal(mask, rgb.max(axis=2) > 0)
    assert mask[5, 5] and not mask[0, 0]
    assert 0.5 < mask.mean() < 0.99  # the fill is there, and most of the view is not fill
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    np.testing.assert_array_equal(photograph_mask(grey), grey > 0)


@pytest.mark.parametrize("size", [1, 2, 17, 4000, 4001])
def test_grey_difference_median_is_numpys(pair: tuple[np.ndarray, np.ndarray], size: int) -> None:
    grey_l = cv2.cvtColor(pair[0], cv2.COLOR_RGB2GRAY).ravel()[:size].astype(np.float64)
    grey_r = cv2.cvtColor(pair[1], cv2.COLOR_RGB2GRAY).ravel()[-size:].astype(np.float64)
    difference = grey_l - grey_r
    assert _grey_difference_median(difference) == np.median(difference)


def test_grey_difference_median_at_the_extremes() -> None:
    difference = np.array([-255.0, -255.0, 255.0, 255.0, 0.0, 3.0])
    assert _grey_difference_median(difference) == np.median(difference) == 1.5


def _fill_background_plain(d: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The definition as first written (take_along_axis on int64 column indices)."""
    w = d.shape[1]
    cols = np.arange(w)[None, :]
    vals = np.where(valid, d, np.nan)
    idx_l = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    left = np.take_along_axis(vals, np.clip(idx_l, 0, w - 1), axis=1)
    left[idx_l < 0] = np.nan
    idx_r = np.minimum.accumulate(np.where(valid, cols, w)[:, ::-1], axis=1)[:, ::-1]
    right = np.take_along_axis(vals, np.clip(idx_r, 0, w - 1), axis=1)
    right[idx_r >= w] = np.nan
    out = np.fmin(left, right)
    out[valid] = d[valid]
    return out


def test_fill_background_keeps_its_values(pair: tuple[np.ndarray, np.ndarray]) -> None:
    grey_l, grey_r = (cv2.cvtColor(view, cv2.COLOR_RGB2GRAY) for view in pair)
    d_left, _ = _sgbm_pair(grey_l, grey_r, 0, 32, 5)
    valid = np.isfinite(d_left)
    valid[7] = False  # a row with nothing kept stays NaN
    assert 0.05 < 1 - valid.mean() < 0.9  # holes to fill
    filled = _fill_background(d_left, valid)
    np.testing.assert_array_equal(filled, _fill_background_plain(d_left, valid))
    assert filled.dtype == d_left.dtype and np.isnan(filled[7]).all()


def test_colour_disparity_keeps_its_picture(pair: tuple[np.ndarray, np.ndarray]) -> None:
    grey_l, grey_r = (cv2.cvtColor(view, cv2.COLOR_RGB2GRAY) for view in pair)
    d_left, _ = _sgbm_pair(grey_l, grey_r, 0, 32, 5)
    valid = np.isfinite(d_left)
    disp = np.nan_to_num(d_left, nan=0.0)
    lo, hi = np.percentile(disp[valid], [1, 99])
    scaled = np.clip((disp - lo) / max(hi - lo, 1e-6), 0, 1)
    plain = np.zeros((*disp.shape, 3), np.uint8)
    plain[valid] = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1][valid]
    picture = colour_disparity(disp, valid)
    assert picture.dtype == np.uint8 and picture.shape == (*disp.shape, 3)
    np.testing.assert_array_equal(picture, plain)
    assert (picture[~valid] == 0).all() and picture[valid].any()

"""The per-card hot paths rewritten for CPU time (issue 18) give exactly the values of their plain
definitions, on real images: Motorcycle (scikit-image) warped with a black fill, its SGBM
disparity with holes, grey-level differences between its two views, and its SIFT descriptors
matched as cv2.BFMatcher matches them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from skimage import data

import pipeline.filter
from pipeline.disparity import _fill_background, _sgbm_pair
from pipeline.filter import ratio_test_matches
from pipeline.grading.measurements import _grey_difference_median
from pipeline.rectify import _cost_at, _costs_at, photograph_mask
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
    # the stage passes the limits it took with its other percentiles, in one partition
    p1, _p5, _p50, _p95, p99 = np.percentile(disp[valid], [1, 5, 50, 95, 99])
    np.testing.assert_array_equal(colour_disparity(disp, valid, (p1, p99)), plain)


def _bf_pairs(a: np.ndarray, b: np.ndarray, ratio: float) -> list[tuple[int, int]]:
    """cv2.BFMatcher's exact two nearest neighbours and Lowe's test, as the filter first did."""
    pairs = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False).knnMatch(a, b, k=2)
    return [(p[0].queryIdx, p[0].trainIdx) for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]


@pytest.mark.parametrize("block", [8_000_000, 100_000])  # one block; queries in blocks of ~50
def test_ratio_test_matches_are_bfmatchers_on_real_sift(block: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pipeline.filter, "_DISTANCE_BLOCK", block)
    sift = cv2.SIFT_create(nfeatures=2000)
    views = data.stereo_motorcycle()[:2]  # 741 x 500 px, as the filter's halves
    _, left = sift.detectAndCompute(cv2.cvtColor(views[0], cv2.COLOR_RGB2GRAY), None)
    _, right = sift.detectAndCompute(cv2.cvtColor(views[1], cv2.COLOR_RGB2GRAY), None)
    assert len(left) > 1000 and len(right) > 1000
    for ratio in (0.6, 0.7, 0.8):
        expected = _bf_pairs(left, right, ratio)
        assert ratio_test_matches(left, right, ratio) == expected
        assert len(expected) > 50


def test_ratio_test_matches_on_ties_and_the_threshold() -> None:
    rng = np.random.default_rng(3)
    right = rng.uniform(0, 255, (40, 128)).astype(np.float32)
    right[1] = right[0]  # a tie for the nearest: never a good match
    query = right[[0, 5]].copy()
    query[1, 0] += 7.0  # 7 from right[5]; right[6] placed 10 away: a ratio of exactly 0.7
    right[6] = right[5]
    right[6, 1] += 10.0
    expected = _bf_pairs(query, right, 0.7)
    assert ratio_test_matches(query, right, 0.7) == expected
    assert [q for q, _ in expected] == [1]  # BFMatcher's own float verdict at the threshold


def test_ratio_test_matches_with_few_descriptors() -> None:
    rng = np.random.default_rng(4)
    left, right = rng.uniform(0, 255, (6, 128)).astype(np.float32), rng.uniform(0, 255, (3, 128)).astype(np.float32)
    right[2] = left[0] + 1.0
    assert ratio_test_matches(left, right, 0.7) == _bf_pairs(left, right, 0.7) == [(0, 2)]
    assert ratio_test_matches(left, right[:1], 0.7) == []
    assert ratio_test_matches(left[:0], right, 0.7) == []


@pytest.mark.parametrize("seed", range(4))
def test_projective_costs_at_every_starting_angle_are_the_scalar_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    thetas = np.linspace(0.0, math.pi, 721)[:-1]
    for _ in range(50):
        views = []
        for _view in range(2):
            m = rng.normal(size=(2, 2))
            views.append((m @ m.T * rng.uniform(0.1, 1e4), rng.normal(size=2) * rng.uniform(1e-3, 10)))
        # one view's v along an axis: its cost is infinite where z is orthogonal to it
        views[1] = (views[1][0], np.array([0.0, 1.0]))
        expected = np.array([_cost_at(t, tuple(views)) for t in thetas])
        got = _costs_at(thetas, tuple(views))
        finite = np.isfinite(expected)
        assert (np.isfinite(got) == finite).all() and not finite[0]
        np.testing.assert_allclose(got[finite], expected[finite], rtol=1e-8)
        assert int(np.argmin(got)) == int(np.argmin(expected))

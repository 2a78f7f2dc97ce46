"""pipeline.rectify: Loop-Zhang rectification, its gates and the stability suite.

Pairs are built from scikit-image's Middlebury Motorcycle (741x500, a real rectified pair with
ground-truth disparity +7..+60 px, +inf invalid). Every case must give a right answer or a typed
:class:`PipelineError`: never another exception, a NaN homography or an unbounded warp.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

from pipeline.errors import InvalidInputError, PipelineError
from pipeline.records import param_hash
from pipeline.rectify import (
    FOCAL_PER_HEIGHT,
    EpipoleInImageError,
    MirroredPairError,
    PlanarSceneError,
    Rectification,
    RectificationError,
    RectifyParams,
    TooFewMatchesError,
    UnboundedWarpError,
    UpsideDownError,
    distortion_metrics,
    epipoles,
    estimate_fundamental,
    loop_zhang,
    match_features,
    rectify_matches,
    rectify_pair,
    warp_pair,
)

F0 = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # rectified: y_l = y_r


@pytest.fixture(scope="module")
def moto() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    left, right, disparity = data.stereo_motorcycle()
    return left, right, disparity


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    xh = np.c_[pts, np.ones(len(pts))] @ H.T
    return xh[:, :2] / xh[:, 2:3]


def _keystoned(image: np.ndarray, degrees: float, dy: float, keystone: float) -> np.ndarray:
    """Rotate about the centre, add a keystone (projective x) term, then shift down by ``dy`` px."""
    h, w = image.shape[:2]
    c = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1.0]])
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    ks = np.array([[1, 0, 0], [0, 1, 0], [keystone, 0, 1.0]])
    M = np.array([[1, 0, 0], [0, 1, dy], [0, 0, 1.0]]) @ np.linalg.inv(c) @ ks @ rot @ c
    return cv2.warpPerspective(image, M, (w, h))


def _assert_sane(rect: Rectification) -> None:
    for H in (rect.H_l, rect.H_r, rect.K):
        assert H.shape == (3, 3) and np.all(np.isfinite(H))
    w, h = rect.size
    assert 0 < w <= 20_000 and 0 < h <= 20_000
    assert rect.disparity_range[0] <= rect.disparity_range[1]
    assert math.isfinite(rect.dy_p95) and math.isfinite(rect.midline_angle)


# ----------------------------------------------------------------------------- loop_zhang


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_loop_zhang_rectified_f_gives_identity(sign: float) -> None:
    H_l, H_r = loop_zhang(sign * F0, 741, 500)
    np.testing.assert_allclose(H_l, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(H_r, np.eye(3), atol=1e-6)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_loop_zhang_nearly_rectified_epipole_far_away_either_sign(sign: float) -> None:
    # Right view rotated by 1e-5 rad: the epipole is ~1e5 px away, its sign arbitrary.
    a = 1e-5
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    F = sign * (np.linalg.inv(Rz).T @ F0)
    e_l, _ = epipoles(F)
    assert abs(np.linalg.norm(e_l) - 1) < 1e-12 and abs(e_l[2]) < 1e-3
    H_l, H_r = loop_zhang(F, 741, 500)
    # A common translation and a hair of rotation at most: pixels move < 0.05 px relative to each other.
    pts = np.array([[0, 0], [740, 0], [740, 499], [0, 499], [370, 250]], float)
    moved_l, moved_r = _apply(H_l, pts) - pts, _apply(H_r, pts) - pts
    assert np.abs(moved_l - moved_l[-1]).max() < 0.05
    assert np.abs(moved_r[:, 1] - moved_l[:, 1]).max() < 0.05  # rows stay together
    assert np.abs(H_r[2, :2]).max() < 1e-6
    assert distortion_metrics(H_l, 741, 500)["midline_angle"] == pytest.approx(90, abs=1e-3)


def test_loop_zhang_rectifies_a_synthetic_f_exactly() -> None:
    # Right camera = left camera rotated by small angles, shifted mostly along x.
    f, cx, cy = 600.0, 370.0, 250.0
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    ry, rx = math.radians(3), math.radians(2)
    R = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]]) @ np.array(
        [[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]]
    )
    t = np.array([-1.0, 0.05, 0.02])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(K).T @ tx @ R @ np.linalg.inv(K)
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-2, 2, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(4, 12, 200)]
    xl = (X @ K.T)[:, :2] / (X @ K.T)[:, 2:]
    Xr = X @ R.T + t
    xr = (Xr @ K.T)[:, :2] / (Xr @ K.T)[:, 2:]
    H_l, H_r = loop_zhang(F, 741, 500)
    dy = _apply(H_l, xl)[:, 1] - _apply(H_r, xr)[:, 1]
    assert np.abs(dy).max() < 1e-6
    for H in (H_l, H_r):
        m = distortion_metrics(H, 741, 500)
        assert m["midline_angle"] == pytest.approx(90, abs=1e-6)
        assert m["aspect_change"] == pytest.approx(1.0, abs=1e-6)
    # Hartley's (OpenCV) on the same F and points shears the left view (measured 89.07 deg).
    ok, H1, _ = cv2.stereoRectifyUncalibrated(xl, xr, F, (741, 500))
    assert ok
    assert abs(distortion_metrics(H1, 741, 500)["midline_angle"] - 90) > 0.5


def test_loop_zhang_refuses_bad_f() -> None:
    with pytest.raises(InvalidInputError):
        loop_zhang(np.full((3, 3), np.nan), 100, 100)
    with pytest.raises(InvalidInputError):
        loop_zhang(np.zeros((3, 3)), 100, 100)
    # Epipole at the image centre (pure forward motion): typed, never NaN.
    c = np.array([49.5, 49.5, 1.0])
    F = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
    with pytest.raises(RectificationError):
        loop_zhang(F, 100, 100)


# ------------------------------------------------------------------------------- real pairs


def test_params_are_hashable_and_validated() -> None:
    assert param_hash(RectifyParams()) == param_hash(RectifyParams())
    assert param_hash(RectifyParams()) != param_hash(RectifyParams(max_dy_p95=3.0))
    with pytest.raises(InvalidInputError):
        RectifyParams(min_inliers=5)
    with pytest.raises(InvalidInputError):
        RectifyParams(ratio=1.5)


def test_estimate_fundamental(moto) -> None:
    left, right, _ = moto
    pts_l, pts_r = match_features(left, _keystoned(right, 2.0, 10.0, 2e-4))
    F, mask, n_h = estimate_fundamental(pts_l, pts_r)
    assert F.shape == (3, 3) and np.linalg.norm(F) == pytest.approx(1.0) and mask.dtype == bool
    assert mask.sum() > 0.8 * len(mask) and n_h < 0.9 * mask.sum()
    xl, xr = np.c_[pts_l[mask], np.ones(mask.sum())], np.c_[pts_r[mask], np.ones(mask.sum())]
    line = xl @ F.T  # epipolar lines in the right view
    dist = np.abs(np.sum(xr * line, axis=1)) / np.hypot(line[:, 0], line[:, 1])
    assert np.median(dist) < 0.5
    with pytest.raises(TooFewMatchesError):
        estimate_fundamental(pts_l[:5], pts_r[:5])
    with pytest.raises(PlanarSceneError):
        estimate_fundamental(pts_l, _apply(np.array([[1, 0.01, 5], [0, 1, 3], [1e-5, 0, 1]]), pts_l))


def test_match_features_deterministic(moto) -> None:
    left, right, _ = moto
    a = match_features(left, right)
    b = match_features(left, right)
    assert a[0].dtype == np.float64 and a[0].shape[1] == 2 and len(a[0]) > 500
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_as_given_is_already_rectified(moto) -> None:
    left, right, disparity = moto
    rect = rectify_pair(left, right)
    _assert_sane(rect)
    assert not rect.warp_needed and not rect.swapped
    assert "already rectified" in rect.reason
    np.testing.assert_array_equal(rect.H_l, np.eye(3))
    np.testing.assert_array_equal(rect.H_r, np.eye(3))
    assert rect.dy_median < 0.3 and rect.dy_p95 < 1.0
    # Matched disparities agree with Middlebury's ground truth range (+7..+60 px).
    gt = disparity[np.isfinite(disparity)]
    assert rect.disparity_range[0] >= gt.min() - 2 and rect.disparity_range[1] <= gt.max() + 2
    assert rect.K[0, 0] == pytest.approx(FOCAL_PER_HEIGHT * 500) and rect.K[0, 0] == pytest.approx(603.55, abs=0.01)
    left_out, right_out = warp_pair(left, right, rect)
    assert np.array_equal(left_out, left) and np.array_equal(right_out, right)


def test_already_rectified_without_the_skip_is_near_identity(moto) -> None:
    left, right, _ = moto
    rect = rectify_pair(left, right, RectifyParams(skip_dy_tolerance=1e-6, planar_ratio=1.0))
    assert rect.warp_needed
    # Loop-Zhang on an estimated F: a common hair of rotation/scale at most, no shear.
    assert rect.midline_angle == pytest.approx(90, abs=0.05)
    relative = rect.H_r @ np.linalg.inv(rect.H_l)
    relative /= relative[2, 2]
    np.testing.assert_allclose(relative[:2, :2], np.eye(2), atol=0.01)
    assert abs(relative[1, 2]) < 1.0 and np.abs(relative[2, :2]).max() < 1e-4


@pytest.fixture(scope="module")
def keystoned_cases(moto):
    left, right, _ = moto
    cases = []
    for degrees, dy, keystone in ((2.0, 10.0, 2e-4), (-3.0, 20.0, -3e-4), (1.0, 5.0, 1e-4)):
        warped = _keystoned(right, degrees, dy, keystone)
        cases.append((left, warped, rectify_pair(left, warped)))
    return cases


def test_keystoned_pairs_are_rectified(keystoned_cases) -> None:
    for _, _, rect in keystoned_cases:
        _assert_sane(rect)
        assert rect.warp_needed and not rect.swapped
        assert rect.dy_median < 0.5 and rect.dy_p95 < 1.5, rect.reason
        assert abs(rect.midline_angle - 90) < 3
        assert rect.aspect_change < 1.05 and rect.kept_fraction > 0.95
        assert rect.disparity_range[0] >= 0.0
        # Ground truth disparity spans ~53 px; rectification keeps the span within 20 %.
        span = rect.disparity_range[1] - rect.disparity_range[0]
        assert 40 < span < 65
        assert rect.inliers >= 500


def test_warped_views_are_rectified_when_matched_again(keystoned_cases) -> None:
    left, warped, rect = keystoned_cases[1]
    left_rect, right_rect = warp_pair(left, warped, rect)
    assert left_rect.shape == (rect.size[1], rect.size[0], 3) and left_rect.dtype == np.uint8
    pts_l, pts_r = match_features(left_rect, right_rect)
    dy = pts_l[:, 1] - pts_r[:, 1]
    on_rows = np.abs(dy) < 3  # matched again; ratio-test outliers are off-row
    assert on_rows.mean() > 0.9
    assert np.percentile(np.abs(dy[on_rows]), 95) < 1.5
    assert np.median(pts_l[on_rows, 0] - pts_r[on_rows, 0]) > 0


def test_loop_zhang_beats_hartley_on_distortion_with_equal_dy(keystoned_cases) -> None:
    w, h = 741, 500
    for _, _, rect in keystoned_cases:
        il, ir = rect.inlier_points
        ok, H1, H2 = cv2.stereoRectifyUncalibrated(il, ir, rect.F, (w, h))
        assert ok
        dy_h = np.abs(_apply(H1, il)[:, 1] - _apply(H2, ir)[:, 1])
        angle_h = max((distortion_metrics(H, w, h)["midline_angle"] for H in (H1, H2)), key=lambda a: abs(a - 90))
        assert abs(rect.midline_angle - 90) < abs(angle_h - 90)
        assert abs(angle_h - 90) > 3  # Hartley shears one view by ~6 deg here
        assert rect.dy_p95 <= np.percentile(dy_h, 95) + 0.05
        assert rect.dy_median <= np.median(dy_h) + 0.05


def test_swapped_halves_are_detected_only_when_asked(moto) -> None:
    left, right, _ = moto
    # Off by default: the eye order is decided before rectification (pipeline.decided_orientation); the
    # pair goes through as given and is translated so that no disparity is negative.
    given = rectify_pair(right, left)
    assert not given.swapped and given.disparity_range[0] >= 0
    rect = rectify_pair(right, left, RectifyParams(detect_swapped=True))
    assert rect.swapped and not rect.warp_needed
    assert rect.disparity_range[0] > 0
    out_l, out_r = warp_pair(right, left, rect)
    assert np.array_equal(out_l, left) and np.array_equal(out_r, right)
    warped = _keystoned(right, 2.0, 10.0, 2e-4)
    rect = rectify_pair(warped, left, RectifyParams(detect_swapped=True))
    assert rect.swapped and rect.warp_needed and rect.dy_p95 < 1.5 and rect.disparity_range[0] >= 0


# --------------------------------------------------------------------------- stability suite


DEFAULT = RectifyParams()


def _outcome(left: np.ndarray, right: np.ndarray, params: RectifyParams = DEFAULT) -> Rectification | PipelineError:
    """Rectification or the typed error; anything else fails the test. Warps when it succeeds."""
    try:
        rect = rectify_pair(left, right, params)
    except PipelineError as exc:
        assert exc.code and exc.reason().startswith(exc.code)
        return exc
    _assert_sane(rect)
    out_l, out_r = warp_pair(left, right, rect)
    assert out_l.shape[:2] == out_r.shape[:2] == (rect.size[1], rect.size[0])
    return rect


def test_identical_halves(moto) -> None:
    left, _, _ = moto
    rect = _outcome(left, left.copy())
    assert isinstance(rect, Rectification) and not rect.warp_needed
    assert rect.dy_p95 == 0 and rect.disparity_range == (0.0, 0.0)


def test_pure_horizontal_shift(moto) -> None:
    left, _, _ = moto
    rect = _outcome(left[:, :-20], left[:, 20:])  # right sees the scene 20 px further left: d = +20
    assert isinstance(rect, Rectification) and not rect.warp_needed and not rect.swapped
    assert rect.dy_p95 < 0.5 and 15 <= rect.disparity_range[0] <= rect.disparity_range[1] <= 21


def test_right_view_upside_down(moto) -> None:
    left, right, _ = moto
    result = _outcome(left, np.ascontiguousarray(right[::-1, ::-1]))
    assert isinstance(result, UpsideDownError)
    result = _outcome(left, np.ascontiguousarray(left[::-1, ::-1]))  # the same photo turned: a homography
    assert isinstance(result, PlanarSceneError)


def test_mirrored(moto) -> None:
    left, right, _ = moto
    assert isinstance(_outcome(left, np.ascontiguousarray(right[:, ::-1])), MirroredPairError)
    assert isinstance(_outcome(left, np.ascontiguousarray(left[:, ::-1])), MirroredPairError)


def test_textureless_blank_tiny_and_few_matches(moto) -> None:
    left, right, _ = moto
    grey = np.full((200, 300), 128, np.uint8)
    assert isinstance(_outcome(grey, grey.copy()), TooFewMatchesError)
    assert isinstance(_outcome(left, np.zeros_like(right)), TooFewMatchesError)
    tiny_l, tiny_r = (
        cv2.resize(left, (32, 22), interpolation=cv2.INTER_AREA),
        cv2.resize(right, (32, 22), interpolation=cv2.INTER_AREA),
    )
    assert isinstance(_outcome(tiny_l, tiny_r), TooFewMatchesError)
    few_l, few_r = np.ascontiguousarray(left[200:260, 300:360]), np.ascontiguousarray(right[200:260, 290:350])
    assert len(match_features(few_l, few_r)[0]) < 10
    assert isinstance(_outcome(few_l, few_r), TooFewMatchesError)
    with pytest.raises(InvalidInputError):
        rectify_pair(left[:10, :10].copy(), right[:10, :10].copy())


def test_planar_and_far_scenes(moto) -> None:
    left, _, _ = moto
    h, w = left.shape[:2]
    M = np.array([[1.0, 0.05, -20], [0.02, 0.95, 10], [1e-4, 5e-5, 1]])
    assert isinstance(_outcome(left, cv2.warpPerspective(left, M, (w, h))), PlanarSceneError)
    # A far scene: every point at ~zero disparity, views differ by a rotation of the camera only.
    assert isinstance(_outcome(left, _keystoned(left, 2.0, 10.0, 0.0)), PlanarSceneError)


def test_nan_and_bad_arrays(moto) -> None:
    left, right, _ = moto
    nan = left.astype(np.float64)
    nan[10, 10] = np.nan
    for bad in (nan, left.astype(np.float32), left[..., :2], "not an image"):
        with pytest.raises(InvalidInputError):
            rectify_pair(bad, right)  # type: ignore[arg-type]


def test_extreme_aspect_ratios(moto) -> None:
    left, right, _ = moto
    for sl in ((slice(230, 262), slice(None)), (slice(None), slice(350, 380))):
        result = _outcome(np.ascontiguousarray(left[sl]), np.ascontiguousarray(right[sl]))
        assert isinstance(result, (Rectification, PipelineError))
        if isinstance(result, Rectification):
            assert result.dy_p95 < 1.5


def test_huge_card_and_matches_on_a_line(moto) -> None:
    left, right, _ = moto
    big_l = cv2.resize(left, (6000, 4048), interpolation=cv2.INTER_LINEAR)
    big_r = cv2.resize(right, (6000, 4048), interpolation=cv2.INTER_LINEAR)
    rect = rectify_pair(big_l, big_r)  # SIFT at 800 px; tolerances scale with it (7.5x here)
    _assert_sane(rect)
    assert not rect.warp_needed and rect.size == (6000, 4048)
    # Texture only in a 20-row band: every match lies near one line.
    band_l, band_r = np.zeros_like(left), np.zeros_like(right)
    band_l[240:260], band_r[240:260] = left[240:260], right[240:260]
    result = _outcome(band_l, band_r)
    assert isinstance(result, (Rectification, PipelineError))
    if isinstance(result, Rectification):
        assert result.dy_p95 < 1.5


def test_epipole_near_the_image_is_refused(moto) -> None:
    left, _, _ = moto
    # A zoom (forward motion) puts the epipole at the centre; mild parallax from the real scene is
    # absent, so this is refused one way or another, always typed.
    h, w = left.shape[:2]
    zoom = cv2.warpAffine(left, cv2.getRotationMatrix2D((w / 2, h / 2), 0.0, 1.08), (w, h))
    result = _outcome(left, zoom)
    assert isinstance(result, (PlanarSceneError, EpipoleInImageError))


def test_warp_refuses_unbounded(moto) -> None:
    left, right, _ = moto
    rect = rectify_pair(left, right)
    huge = Rectification(**{**rect.__dict__, "size": (10**6, 500)})
    with pytest.raises(UnboundedWarpError):
        warp_pair(left, right, huge)
    nan_h = Rectification(**{**rect.__dict__, "H_l": np.full((3, 3), np.nan)})
    with pytest.raises(UnboundedWarpError):
        warp_pair(left, right, nan_h)


def test_metrics_are_json_safe(keystoned_cases) -> None:
    import json

    metrics = keystoned_cases[0][2].metrics()
    text = json.dumps(metrics)
    assert "H_l" in text and metrics["warp_needed"] is True and len(metrics["K"]) == 3


# -------------------------------------------------------------------------------- real card


def test_real_cards(shared_data: Path) -> None:
    """Every NYPL full card in the shared data (9): rectified with |dy| p95 < 2 px, or a typed
    refusal. Measured: 7 rectified (|dy| p95 0.64-0.86 px), 2 refused (epipole_in_image)."""
    from pipeline.filter import filter_card
    from pipeline.io import read_image
    from pipeline.split import crop_halves

    paths = sorted((shared_data / "stereocards" / "full_cards").glob("*.jpg"))
    assert paths
    done = 0
    for path in paths:
        done += _check_real_card(read_image(path), filter_card, crop_halves)
    assert done >= len(paths) // 2  # most real cards rectify


def _check_real_card(card: np.ndarray, filter_card, crop_halves) -> int:
    split, _ = filter_card(card)
    left, right = crop_halves(card, split)
    result = _outcome(np.ascontiguousarray(left), np.ascontiguousarray(right))
    if isinstance(result, Rectification):
        assert result.dy_p95 < 2.0
        assert abs(result.midline_angle - 90) < 3 and result.disparity_range[0] >= 0
        return 1
    assert isinstance(result, RectificationError)
    return 0


def test_already_rectified_pair_with_negative_disparity_is_only_translated():
    """Halves cropped with different margins: no projective warp, but no negative disparity either."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    width = left.shape[1]
    # The left crop starts 30 px later: x_l' = x_l - 30, so every d drops by 30 (truth 7..60 px).
    rect = rectify_pair(np.ascontiguousarray(left[:, 30:]), np.ascontiguousarray(right[:, : width - 30]))
    assert rect.warp_needed and "translated" in rect.reason
    assert np.allclose(rect.H_l, np.eye(3)) and rect.H_r[0, 2] < 0
    assert np.allclose(rect.H_r[:, :2], np.eye(3)[:, :2])
    assert rect.disparity_range[0] == 0.0 and rect.disparity_range[1] > 20


@pytest.mark.parametrize(
    "name", ["full_cards/nypl_stereogranimator_demo1.jpg", "full_cards/nypl_stereogranimator_sample-stereo.jpg"]
)
def test_nearly_rectified_real_cards_are_row_aligned_not_rotated(shared_data, name):
    """On these small NYPL scans F is ill-conditioned: Loop-Zhang turned demo1's views 15.7 deg
    and sample-stereo's epipole fell inside the image. The least warp that aligns the rows fits."""
    from pipeline.filter import filter_card
    from pipeline.io import read_image
    from pipeline.split import crop_halves

    card = read_image(shared_data / "stereocards" / name)
    split, _ = filter_card(card)
    left, right = (np.ascontiguousarray(half) for half in crop_halves(card, split))
    rect = rectify_pair(left, right)
    assert rect.reason.startswith("row-aligned (nearly rectified pair)")
    assert rect.rotation < 2.0 and rect.dy_p95 < 1.0
    assert np.allclose(rect.H_l, np.eye(3)) and rect.H_r[2, :2].tolist() == [0.0, 0.0]
    assert rect.disparity_range[0] == 0.0


def test_implied_pose_recovers_a_pure_rotation():
    """H = K R K^-1 for a known 2 deg rotation of the right camera gives R back."""
    from pipeline.rectify import implied_pose

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    angle = math.radians(2.0)
    R_r = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    pose = implied_pose(np.eye(3), K @ R_r @ np.linalg.inv(K), K)
    assert np.allclose(pose["R_right"], R_r, atol=1e-9)
    assert pose["relative_rotation_deg"] == pytest.approx(2.0, abs=1e-6)
    assert np.allclose(pose["t"], R_r.T @ np.array([-1.0, 0, 0]))
    identity = implied_pose(np.eye(3), np.eye(3), K)
    assert identity["relative_rotation_deg"] == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------- stability from given matches
# rectify_matches takes the matches directly, so the same matches can be perturbed, polluted or
# made degenerate; every outcome must be the same answer or a typed failure, never NaN.


def _row_angles(rect: Rectification, size: tuple[int, int]) -> list[float]:
    """deg: direction, in each input view's pixels, of the rectified row through its centre."""
    w, h = size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    out = []
    for H in (rect.H_l, rect.H_r):
        mapped = H @ centre
        line = H.T @ np.array([0.0, mapped[2], -mapped[1]])
        out.append(math.degrees(math.atan2(-line[0], line[1])) % 180.0)
    return out


def _same_rectification(a: Rectification, b: Rectification, size, clean, angle_tol: float, dy_tol: float) -> None:
    _assert_sane(a)
    _assert_sane(b)
    assert a.method == b.method and a.swapped == b.swapped
    for x, y in zip(_row_angles(a, size), _row_angles(b, size)):
        assert min(abs(x - y), 180 - abs(x - y)) < angle_tol
    pts_l, pts_r = clean
    for rect in (a, b):
        assert rect.dy_p95 < 1.5
    dy_b = np.abs(_apply(b.H_l, pts_l)[:, 1] - _apply(b.H_r, pts_r)[:, 1])
    dy_a = np.abs(_apply(a.H_l, pts_l)[:, 1] - _apply(a.H_r, pts_r)[:, 1])
    on_rows = dy_a < 3
    assert on_rows.mean() > 0.9
    assert np.percentile(dy_b[on_rows], 95) <= np.percentile(dy_a[on_rows], 95) + dy_tol


@pytest.fixture(scope="module")
def match_cases(moto):
    """(name, pts_l, pts_r, params): a keystoned pair (Loop-Zhang's case) and the Motorcycle as
    given with the already-rectified skip off (epipole at infinity: a row alignment's case)."""
    left, right, _ = moto
    nearly = RectifyParams(skip_dy_tolerance=1e-6, planar_ratio=1.0)
    cases = []
    for name, r, params in (("keystoned", _keystoned(right, 2.0, 10.0, 2e-4), DEFAULT), ("rectified", right, nearly)):
        pts_l, pts_r = match_features(left, r)
        cases.append((name, pts_l, pts_r, params))
    return cases


SIZE = (741, 500)


def test_rectify_matches_is_rectify_pair(moto, match_cases) -> None:
    left, right, _ = moto
    _, pts_l, pts_r, params = match_cases[1]
    a, b = rectify_pair(left, right, params), rectify_matches(pts_l, pts_r, SIZE, SIZE, params)
    np.testing.assert_allclose(a.H_r, b.H_r)
    assert a.method == b.method
    for bad in (np.full_like(pts_l, np.nan), pts_l[:, :1]):
        with pytest.raises(InvalidInputError):
            rectify_matches(bad, pts_r, SIZE, SIZE)


def test_the_methods_chosen(match_cases) -> None:
    """Keystoned: Loop-Zhang (a row alignment would leave the view turned); as given: the left
    view kept (a row alignment, not a turn of both views by a loose epipole direction)."""
    by_name = {name: rectify_matches(pl, pr, SIZE, SIZE, params) for name, pl, pr, params in match_cases}
    assert by_name["keystoned"].method == "loop_zhang"
    assert by_name["rectified"].method.startswith("row_")
    assert np.allclose(by_name["rectified"].H_l, np.eye(3)) and by_name["rectified"].rotation < 0.2
    assert "chosen over" in by_name["rectified"].reason


@pytest.mark.parametrize("count", [1, 4, 12])
def test_gross_outliers_do_not_move_the_rectification(match_cases, count) -> None:
    """1-12 matches |dy| 160-390 px off (what wrecked the plain least-squares row fit on real
    cards) give the same rectification to 0.05 deg."""
    rng = np.random.default_rng(count)
    for _, pts_l, pts_r, params in match_cases:
        clean = rectify_matches(pts_l, pts_r, SIZE, SIZE, params)
        bad_l = np.c_[rng.uniform(0, 740, count), rng.uniform(0, 100, count)]
        bad_r = bad_l + np.c_[rng.uniform(-20, 20, count), rng.uniform(160, 390, count)]
        polluted = rectify_matches(np.r_[pts_l, bad_l], np.r_[pts_r, bad_r], SIZE, SIZE, params)
        _same_rectification(clean, polluted, SIZE, (pts_l, pts_r), angle_tol=0.05, dy_tol=0.05)


def test_tiny_perturbations_of_the_matches(match_cases) -> None:
    """0.05 px of noise on every match, or 2 % of the matches dropped: the same method, rows
    within 0.2 deg."""
    rng = np.random.default_rng(7)
    for _, pts_l, pts_r, params in match_cases:
        clean = rectify_matches(pts_l, pts_r, SIZE, SIZE, params)
        noisy = rectify_matches(pts_l + rng.normal(0, 0.05, pts_l.shape), pts_r, SIZE, SIZE, params)
        _same_rectification(clean, noisy, SIZE, (pts_l, pts_r), angle_tol=0.2, dy_tol=0.1)
        keep = rng.random(len(pts_l)) > 0.02
        fewer = rectify_matches(pts_l[keep], pts_r[keep], SIZE, SIZE, params)
        _same_rectification(clean, fewer, SIZE, (pts_l, pts_r), angle_tol=0.2, dy_tol=0.1)


def _scene(n: int, rng: np.random.Generator, depth_spread: float) -> tuple[np.ndarray, np.ndarray]:
    """Matches of a rectified camera pair (baseline along x): disparity 10 px +- depth_spread."""
    pts_l = np.c_[rng.uniform(20, 720, n), rng.uniform(20, 480, n)]
    pts_r = pts_l - np.c_[10 + depth_spread * rng.random(n), np.zeros(n)]
    return pts_l, pts_r


def test_epipole_at_infinity_and_far_and_planar_scenes_from_matches() -> None:
    rng = np.random.default_rng(3)
    # Exactly rectified matches: already rectified, identity homographies.
    pts_l, pts_r = _scene(300, rng, 40.0)
    rect = rectify_matches(pts_l, pts_r, SIZE, SIZE)
    assert rect.method == "identity" and np.allclose(rect.H_l, np.eye(3))
    # The same with the skip off: the epipole is exactly at infinity, no division by e3 anywhere.
    rect = rectify_matches(pts_l, pts_r, SIZE, SIZE, RectifyParams(skip_dy_tolerance=1e-6, planar_ratio=1.0))
    _assert_sane(rect)
    assert rect.dy_p95 < 1e-6 and rect.rotation < 1e-6 and abs(rect.midline_angle - 90) < 1e-6
    # A far scene (one disparity) turned by 2 deg, and a planar scene (a homography): degenerate F
    # (a far scene turned by less than PLANAR_MAX_TURN would be row-aligned).
    far_l, far_r = _scene(300, rng, 0.0)
    a = math.radians(2.0)
    turned = far_r @ np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    with pytest.raises(PlanarSceneError):
        rectify_matches(far_l, turned, SIZE, SIZE)
    M = np.array([[1.0, 0.05, -20], [0.02, 0.95, 10], [1e-4, 5e-5, 1]])
    with pytest.raises(PlanarSceneError):
        rectify_matches(pts_l, _apply(M, pts_l), SIZE, SIZE)
    # A far scene of a nearly rectified pair (turned 0.3 deg, 4 px lower): rows are well defined
    # without F, so it is row-aligned, not refused.
    a = math.radians(0.3)
    nearly = far_r @ np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]]) + [0.0, 4.0]
    rect = rectify_matches(far_l, nearly, SIZE, SIZE)
    assert rect.method.startswith("row_") and "far or planar scene" in rect.reason
    assert rect.dy_p95 < 0.01 and abs(rect.rotation - 0.3) < 0.01 and rect.disparity_range[1] < 0.01


def test_near_degenerate_f_gives_finite_homographies_or_a_typed_error() -> None:
    """F0 plus perturbations from 1e-12 to 1e-2 (pixel units: the epipole from very far away to
    near the image, either sign), and rank-1 / rank-0-like F: loop_zhang returns finite homographies or raises typed."""
    rng = np.random.default_rng(11)
    for scale in (1e-12, 1e-9, 1e-6, 1e-4, 1e-2):
        for _ in range(5):
            F = F0 + scale * rng.normal(size=(3, 3))
            try:
                H_l, H_r = loop_zhang(F, 741, 500)
            except PipelineError as exc:
                assert isinstance(exc, RectificationError)
                continue
            assert np.all(np.isfinite(H_l)) and np.all(np.isfinite(H_r))
            if scale <= 1e-9:  # relative to F0 in pixel units (x y terms ~ 1e5): still nearly rectified
                assert abs(distortion_metrics(H_l, 741, 500)["rotation"]) < 0.1
    for F in (np.outer([0.0, 1.0, 0.0], [0.0, 0.0, 1.0]), np.full((3, 3), 1e-300)):
        try:
            H_l, H_r = loop_zhang(F, 741, 500)
            assert np.all(np.isfinite(H_l)) and np.all(np.isfinite(H_r))
        except PipelineError as exc:
            assert isinstance(exc, (RectificationError, InvalidInputError))


def test_random_matches_are_a_typed_failure() -> None:
    rng = np.random.default_rng(5)
    for n in (5, 40, 400):
        pts_l, pts_r = rng.uniform(0, 500, (n, 2)), rng.uniform(0, 500, (n, 2))
        with pytest.raises(PipelineError) as info:
            rectify_matches(pts_l, pts_r, SIZE, SIZE)
        assert info.value.code


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 7])
def test_a_pair_that_is_only_shifted_is_already_rectified_whatever_the_seed(seed: int) -> None:
    """A textured pair whose right view is the left shifted 4 px (the kind issue 35.2 reports
    failing with every seed): every match lies on its row, and any seed gives the identity."""
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur((rng.random((260, 420)) * 255).astype(np.uint8), (3, 3), 0)
    left, right = np.ascontiguousarray(texture[:, 0:400]), np.ascontiguousarray(texture[:, 4:404])  # x_r = x_l - 4
    rect = rectify_pair(left, right, RectifyParams(random_seed=seed))
    assert rect.method == "identity" and not rect.warp_needed
    assert rect.reason.startswith("already rectified within tolerance: |dy| p95 0.")
    assert rect.matches >= 100 and rect.disparity_range[0] == pytest.approx(4.0, abs=0.5)


def test_a_real_card_with_its_right_photo_moved_down_rectifies_with_any_seed(shared_data) -> None:
    """A real card whose right photo was moved 25 px down (the kind issue 35.2 reports failing
    with seed 0): any seed gives the same rectification, its rows within a pixel."""
    from pipeline.filter import filter_card
    from pipeline.io import read_image
    from pipeline.split import crop_halves

    card = read_image(shared_data / "stereocards" / "full_cards" / "nypl_stereogranimator_demo1.jpg")
    split, _ = filter_card(card)
    left, right = (np.ascontiguousarray(half) for half in crop_halves(card, split))
    moved = np.zeros_like(right)
    moved[25:] = right[:-25]
    found = [rectify_pair(left, moved, RectifyParams(random_seed=seed)) for seed in range(5)]
    assert {rect.method for rect in found} == {"row_affine"}
    p95 = [rect.dy_p95 for rect in found]
    assert max(p95) < 1.0 and max(p95) - min(p95) < 0.05, p95  # the robust row fit samples: hundredths apart


def test_when_opencv_finds_no_f_the_pair_is_still_tested_for_aligned_rows(monkeypatch) -> None:
    """Issue 35.2: OpenCV's USAC can find no F model (``!model.empty()``) for matches that fix no
    epipolar geometry. The pair then still goes through the already-aligned test and the row
    alignments, and a refusal says what happened (planar_or_far_scene), never "too few matches"."""
    import pipeline.rectify as rectify_module

    def no_model(*_args, **_kwargs):
        raise rectify_module.TooFewMatchesError("no fundamental matrix: (-215:Assertion failed) !model.empty()")

    monkeypatch.setattr(rectify_module, "_fit_f", no_model)
    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur((rng.random((260, 420)) * 255).astype(np.uint8), (3, 3), 0)
    left, right = np.ascontiguousarray(texture[:, 0:400]), np.ascontiguousarray(texture[:, 4:404])
    aligned = rectify_pair(left, right)
    assert aligned.method == "identity" and aligned.reason.startswith("already rectified within tolerance")
    # Moved 3 px down: the rows need aligning, which the row models do without F.
    down = np.zeros_like(right)
    down[3:] = right[:-3]
    rows = rectify_pair(left, down)
    assert rows.method.startswith("row_") and rows.dy_p95 < 1.0
    assert "far or planar scene: F undetermined" in rows.reason
    # Random matches: no F, no rows; refused as such.
    pts_l = rng.uniform(0, 399, (60, 2))
    pts_r = rng.uniform(0, 399, (60, 2))
    with pytest.raises(PipelineError) as info:
        rectify_matches(pts_l, pts_r, (400, 260), (400, 260))
    assert info.value.code != "too_few_matches"

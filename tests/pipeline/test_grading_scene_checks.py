"""The grade's scene checks on the real Motorcycle pair and on maps made wrong in known ways:
depth ordering, row streaks, sky taken as near, reflections, mount inside the crop, and the
nearest threshold every grade names.

Measured here (Motorcycle at 741 x 500, its ground truth and the default backend alike): depth
order +0.65 (upside down or reversed -0.66), streaks 0 % (38 % with a 3-row streak every 12
rows), reflection symmetry 0.30 (0.90 with the lower half mirrored), border line 0.12 (0.79
with a plain 40 px mount strip on top).
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from pipeline.cross_validation import stratified_folds
from pipeline.disparity import estimate_disparity
from pipeline.grading import (
    GradeMeasurements,
    GradeThresholds,
    grade,
    measure_card,
    scene_checks,
)


@pytest.fixture(scope="module")
def motorcycle() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    result = estimate_disparity(left, right)
    truth = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    return left, right, result.disp_left, truth


def _grey(view: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(view, cv2.COLOR_RGB2GRAY)


def _all(shape: tuple[int, ...]) -> np.ndarray:
    return np.ones(shape[:2], bool)


def test_depth_order_is_positive_on_a_real_scene_and_negative_upside_down_or_reversed(motorcycle):
    left, _, disp, truth = motorcycle
    inside = _all(left.shape)
    assert scene_checks.depth_order(truth, np.isfinite(truth)) > 0.5
    assert scene_checks.depth_order(disp, inside) > 0.5
    assert scene_checks.depth_order(disp[::-1].copy(), inside) < -0.5
    assert scene_checks.depth_order(np.nanmax(disp) - disp, inside) < -0.5  # swapped eyes reverse depth
    assert scene_checks.depth_order(np.full(disp.shape, 7.0, np.float32), inside) is None  # nothing to order


def test_an_upside_down_depth_map_gets_the_ordering_reason(motorcycle):
    result = grade(GradeMeasurements(depth_order=scene_checks.depth_order(motorcycle[2][::-1].copy(), _all(motorcycle[0].shape))))
    assert result.grade == "failure" and result.deciding == ["depth_order"]
    assert "top of the picture comes out nearer than the bottom" in result.reasons[0]


def test_a_streaky_disparity_gets_the_streak_reason(motorcycle):
    left, _, disp, _ = motorcycle
    inside = _all(left.shape)
    assert scene_checks.streak_fraction(disp, inside) < 0.01
    streaky = disp.copy()
    rng = np.random.default_rng(0)
    for y in range(0, disp.shape[0], 12):  # a 3-row run every 12 rows, off by up to 8 px
        streaky[y : y + 3] += rng.choice([-1, 1]) * rng.uniform(3, 8)
    fraction = scene_checks.streak_fraction(streaky, inside)
    assert 0.2 < fraction < 0.45  # 3 of 12 rows, and a row either side where the scene has vertical structure
    result = grade(GradeMeasurements(streak_fraction=fraction))
    assert result.grade == "failure" and "row streaks" in result.reasons[0]
    # A real depth edge (one step down, flat on both sides) is not a streak.
    step = np.where(np.arange(200)[:, None] < 100, 10.0, 30.0) * np.ones((1, 300))
    assert scene_checks.streak_fraction(step.astype(np.float32), np.ones((200, 300), bool)) == 0.0


def test_a_flat_sky_read_as_near_is_named(motorcycle):
    left, _, disp, _ = motorcycle
    grey, sky_disp = _grey(left), disp.copy()
    assert scene_checks.sky_near_fraction(grey, disp, _all(left.shape)) < 0.05
    grey[:150] = 180
    sky_disp[:150] = np.nanpercentile(disp, 90)
    fraction = scene_checks.sky_near_fraction(grey, sky_disp, _all(left.shape))
    assert fraction > 0.4
    assert "textureless" in grade(GradeMeasurements(sky_near_fraction=fraction)).reasons[0]
    sky_disp[:150] = np.nanpercentile(disp, 2)  # the same sky, far: fine
    assert scene_checks.sky_near_fraction(grey, sky_disp, _all(left.shape)) < 0.05


def test_a_mirrored_lower_half_reads_as_a_reflection(motorcycle):
    left, _, disp, _ = motorcycle
    grey = _grey(left)
    plain = scene_checks.reflection_symmetry(grey, disp, _all(left.shape))
    assert plain is not None and plain.symmetry < 0.5
    h = grey.shape[0]
    mirrored, mirrored_disp = grey.copy(), disp.copy()
    mirrored[h // 2 :] = grey[: h // 2][::-1][: h - h // 2]
    mirrored_disp[h // 2 :] = disp[: h // 2][::-1][: h - h // 2]
    found = scene_checks.reflection_symmetry(mirrored, mirrored_disp, _all(left.shape))
    assert found.symmetry > 0.8 and abs(found.row_px - h // 2) <= 6
    result = grade(GradeMeasurements(reflection_symmetry=found.symmetry, reflection_row_px=found.row_px))
    assert result.grade == "some" and f"about row {found.row_px}" in result.reasons[0]


def test_mount_strip_and_caption_inside_the_crop(motorcycle):
    left = motorcycle[0]
    grey = _grey(left)
    clean = scene_checks.border_intrusion(grey, _all(left.shape))
    assert clean.line < 0.5 and clean.strokes < 0.005
    mounted = grey.copy()
    mounted[:40] = 200
    cv2.putText(mounted, "KEYSTONE VIEW CO. 1905", (30, 28), cv2.FONT_HERSHEY_COMPLEX, 0.8, 30, 2)
    found = scene_checks.border_intrusion(mounted, _all(left.shape))
    assert found.side == "top" and found.line > 0.7 and found.strokes > 0.02
    measured = GradeMeasurements(border_line=found.line, border_strokes=found.strokes, border_side=found.side)
    # Off by default (the bench's true error does not follow it); a curator's thresholds turn it on.
    assert grade(measured).grade == "few"
    flagged = GradeThresholds.from_dict(
        {
            "border_line": {"direction": "above", "some": 0.6, "failure": None},
            "border_strokes": {"direction": "above", "some": 0.02, "failure": None},
        }
    )
    result = grade(measured, flagged)
    assert result.grade == "some" and set(result.deciding) == {"border_line", "border_strokes"}
    assert any("top border" in reason for reason in result.reasons)
    # The warp's black fill has a straight edge too, but it is not the card's.
    filled = grey.copy()
    filled[:, :60] = 0
    assert scene_checks.border_intrusion(filled, filled > 0).line < 0.5


def test_nearest_names_the_measurement_closest_to_a_threshold_that_matters():
    result = grade(GradeMeasurements(coverage=0.83, streak_fraction=0.01, row_misalignment_px=0.3))
    assert result.grade == "few"
    assert result.nearest["measurement"] == "coverage" and result.nearest["threshold"] == 0.8
    assert result.nearest["level"] == "some" and result.nearest["margin"] == pytest.approx(0.03)
    assert "coverage 83 % is 3 points from its some threshold (< 80 %)" in result.reasons[0]
    # A some card: its nearest is the threshold that would change it (the failure line of the
    # streaks at 20 %, 0.15 away in log ratio, not coverage's some line it already passed).
    some = grade(GradeMeasurements(coverage=0.95, streak_fraction=0.17))
    assert some.grade == "some" and some.nearest["measurement"] == "streak_fraction"
    assert some.nearest["level"] == "failure" and some.nearest["grade_if_crossed"] == "failure"
    assert some.uncertainty_reason.startswith(f"uncertainty {some.uncertainty:.2f}: streak_fraction 17 %")
    table = {row["measurement"]: row for row in some.checks}
    assert table["streak_fraction"]["level"] == "some" and table["coverage"]["level"] == "few"
    assert table["depth_order"]["value"] is None


def test_maps_at_a_working_size_are_measured_in_view_pixels(motorcycle):
    left, right, disp, _ = motorcycle
    full = measure_card(left, right, disp, None, None, {})
    half = cv2.resize(disp, (disp.shape[1] // 2, disp.shape[0] // 2), interpolation=cv2.INTER_NEAREST) / 2
    small = measure_card(left, right, half, None, None, {})
    assert small.disparity_range_px == pytest.approx(full.disparity_range_px, rel=0.05)
    assert small.coverage == pytest.approx(full.coverage, abs=0.01)


def test_the_grade_is_cheap_at_a_700_px_working_view(motorcycle):
    left, right, disp, _ = motorcycle
    cv2.setNumThreads(1)
    measure_card(left, right, disp, disp, None, {})  # warm up
    clock = time.process_time()
    for _ in range(3):
        grade(measure_card(left, right, disp, disp, None, {}))
    assert (time.process_time() - clock) / 3 < 0.1 * 2  # 0.1 s a card, x2 for a shared noisy machine


def test_one_fold_splitter_is_stratified_and_covers_every_item():
    labels = np.array([0] * 7 + [1] * 5 + [2] * 3)
    folds = stratified_folds(labels, 3, np.random.default_rng(0))
    assert sorted(np.concatenate(folds).tolist()) == list(range(15))
    for fold in folds:
        assert fold.dtype == np.int64
        counts = np.bincount(labels[fold], minlength=3)
        assert (np.abs(counts - np.array([7, 5, 3]) / 3) <= 1).all()

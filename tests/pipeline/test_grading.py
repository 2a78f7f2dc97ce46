"""The automatic grade on real pairs: measurements, reasons, uncertainty, fitting, the stage task.

Measured here (Motorcycle at 300 px wide, keystone backend): coverage 100 %, left-right
consistency 0.90, rows misaligned 0.08 px, photometric error 0.10 of unrelated images'; with the
right view 6 px down the rows read 6.0 px and the grade is failure.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.disparity import ImageTooSmallError, estimate_disparity
from pipeline.errors import InvalidInputError
from pipeline.grading import (
    GRADES,
    GradeMeasurements,
    GradeParams,
    GradeThresholds,
    NotEnoughLabelsError,
    Threshold,
    fit_thresholds,
    grade,
    measure_card,
    paper_distribution,
)
from pipeline.grading.measurements import REFERENCE_SIDE
from pipeline.io import write_npy, write_png
from pipeline.records import CardTask, param_hash
from pipeline.stages.grade import grade_task

# Metrics of a clean card as the filter and rectify stages record them.
CLEAN_STAGES = {
    "filter": {"good_match_fraction": 0.25},
    "rectify": {
        "dy_p95": 0.4,
        "midline_angle": 89.9,
        "aspect_change": 1.01,
        "rotation": -0.3,
        "kept_fraction": 0.97,
        "swapped": False,
    },
    "disparity": {"coverage": 1.0},
}


def _downscale(image: np.ndarray, width: int = 300) -> np.ndarray:
    scale = width / image.shape[1]
    return cv2.resize(image, (width, round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    cv2.setNumThreads(1)
    return _downscale(left), _downscale(right)


def _measure(left: np.ndarray, right: np.ndarray, stages: dict | None = None) -> GradeMeasurements:
    result = estimate_disparity(left, right, "keystone")
    return measure_card(left, right, result.disp_left, result.disp_right, result.confidence, stages or CLEAN_STAGES)


@pytest.fixture(scope="module")
def good(pair) -> tuple[GradeMeasurements, np.ndarray, np.ndarray, np.ndarray]:
    left, right = pair
    result = estimate_disparity(left, right, "keystone")
    m = measure_card(left, right, result.disp_left, result.disp_right, result.confidence, CLEAN_STAGES)
    return m, result.disp_left, result.disp_right, result.confidence


# ---------------------------------------------------------------------------- measure and grade


def test_a_good_real_pair_grades_few_with_every_measurement(good):
    m = good[0]
    assert m.coverage == 1.0
    assert 0.85 <= m.lr_consistency <= 1.0
    assert m.row_misalignment_px < 0.5
    assert m.photometric_error_rel < 0.2 and 2.0 < m.photometric_error < 12.0
    assert 0.04 < m.disparity_range_rel < 0.08  # Motorcycle spans about 6 % of its width
    assert m.textured_fraction > 0.5
    assert m.shear_deg == pytest.approx(0.1) and m.rotation_deg == pytest.approx(0.3)
    result = grade(m, GradeThresholds())
    assert result.grade == "few" and result.deciding == [] and result.notes == []
    assert result.reasons[0].startswith("few: every measurement within thresholds (20 of 20 measured); nearest: ")
    # A clean card's reason names the measurement nearest its threshold, with value and threshold.
    nearest = result.nearest
    assert nearest is not None and nearest["changes_grade"] and nearest["grade_if_crossed"] == "some"
    assert nearest["measurement"] in result.reasons[0] and nearest["level"] == "some"
    assert nearest["margin"] == pytest.approx(nearest["value"] - nearest["threshold"], abs=1e-6)
    assert result.uncertainty_reason.startswith(f"uncertainty {result.uncertainty:.2f}: {nearest['measurement']} ")
    # The scene checks on a real pair: ground near, top far, no streaks, no mount in the crop.
    assert m.depth_order > 0.4 and m.streak_fraction < 0.01 and m.sky_near_fraction < 0.05
    assert m.reflection_symmetry < 0.5 and m.border_line < 0.5 and m.border_strokes < 0.01
    assert 0.0 <= result.uncertainty < 0.8
    json.dumps(m.as_dict(), allow_nan=False)


def test_right_view_six_px_down_is_a_failure_that_names_the_value(pair):
    left, right = pair
    down = cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, 6]]), right.shape[1::-1], borderMode=cv2.BORDER_REFLECT)
    m = _measure(left, down)
    # px at a 600 px view (REFERENCE_SIDE): 6 px of this 300 px view read 12
    assert m.row_misalignment_px == pytest.approx(6.0 * REFERENCE_SIDE / left.shape[1], abs=1.0)
    result = grade(m)
    assert result.grade == "failure" and result.deciding == ["row_misalignment_px"]
    assert result.reasons[0] == f"failure: rows of the two views are misaligned by {m.row_misalignment_px:.1f} px (> 4 px)"
    # The warped view no longer reproduces the left one: about half-way to unrelated images.
    assert m.photometric_error_rel > 0.4


def test_right_view_sheared_vertically_is_a_failure(pair):
    left, right = pair
    w = right.shape[1]
    slope = 8.0 / (w - 1)  # rows drift from 0 px at the left edge to 8 px at the right
    sheared = cv2.warpAffine(
        right,
        np.float32([[1, 0, 0], [slope, 1, 0]]),
        right.shape[1::-1],
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )
    m = _measure(left, sheared)
    assert m.row_misalignment_px == pytest.approx(8.0 * REFERENCE_SIDE / w, abs=2.0)
    result = grade(m)
    assert result.grade == "failure" and "row_misalignment_px" in result.deciding


def test_rectification_shear_and_swap_read_in_words(good):
    m = good[0]
    sheared = GradeMeasurements.from_dict({**m.as_dict(), "shear_deg": 14.2, "swapped": True})
    result = grade(sheared)
    assert result.grade == "failure" and result.deciding == ["shear_deg"]
    assert result.reasons[0] == "failure: rectification sheared 14.2 deg (> 8 deg)"
    assert result.reasons[1].startswith("some: eyes swapped on the card")
    # The measurement itself comes from the rectify metrics: 90 - midline angle.
    stages = {**CLEAN_STAGES, "rectify": {**CLEAN_STAGES["rectify"], "midline_angle": 75.8}}
    left = np.zeros((40, 40), np.uint8)
    measured = measure_card(left, left, np.zeros((40, 40)), np.zeros((40, 40)), np.ones((40, 40)), stages)
    assert measured.shear_deg == pytest.approx(14.2)


def test_textureless_pair_is_flagged_low_texture():
    flat = np.full((120, 160), 128, np.uint8)
    result = estimate_disparity(flat, flat.copy(), "keystone")
    m = measure_card(flat, flat.copy(), result.disp_left, result.disp_right, result.confidence, CLEAN_STAGES)
    assert m.textured_fraction == 0.0 and m.texture_gradient == 0.0
    assert m.row_misalignment_px is None and m.note_for("row_misalignment_px") == "too few textured pixels to follow rows"
    graded = grade(m)
    assert graded.grade == "failure" and "textured_fraction" in graded.deciding
    assert "failure: low texture: only 0 % of the view is textured (< 4 %)" in graded.reasons
    assert "note: row_misalignment_px not graded (too few textured pixels to follow rows)" in graded.reasons


def test_identical_views_are_measured_and_fail_on_zero_range(pair):
    left, _ = pair
    m = _measure(left, left.copy())
    assert m.disparity_range_px < 0.5 and m.photometric_error_rel < 0.02 and m.lr_consistency > 0.95
    result = grade(m)
    assert result.grade == "failure" and result.deciding == ["disparity_range_rel"]
    assert result.reasons[0].startswith(f"failure: disparity spans only {m.disparity_range_px:.1f} px (")
    assert result.reasons[0].endswith("of the width): little depth to see (< 0.15 %)")


def test_nan_and_inf_disparities_are_not_covered(pair, good):
    left, right = pair
    _, d_left, d_right, conf = good
    holed = d_left.copy()
    holed[:, : holed.shape[1] // 2] = np.nan
    holed[0, -5:] = np.inf
    holed[1, -3:] = 1e30  # finite but no match can be that far
    m = measure_card(left, right, holed, d_right, conf, CLEAN_STAGES)
    expected = (np.isfinite(holed) & (np.abs(holed) < 1e3))[left.max(axis=2) > 0].mean()
    assert m.coverage == pytest.approx(expected) and 0.45 < m.coverage < 0.52
    assert all(v is None or math.isfinite(v) for v in m.as_dict().values() if not isinstance(v, (bool, str)))
    result = grade(m)
    assert result.grade == "failure"
    # 49.987 % would print as the threshold itself at 0 decimals: the reason shows enough digits.
    assert result.reasons[0] == "failure: disparity covers 49.99 % of the view (< 50 %)"

    nothing = np.full_like(d_left, np.nan)
    empty = measure_card(left, right, nothing, nothing, None, {})
    assert empty.coverage == 0.0 and empty.disparity_range_px is None and empty.photometric_error is None
    assert empty.note_for("disparity_range_rel") == "no finite disparity on the photograph"
    assert empty.note_for("confident_fraction") == "no confidence map"
    assert grade(empty).reasons[0] == "failure: disparity covers 0 % of the view (< 50 %)"
    json.dumps(empty.as_dict(), allow_nan=False)


def test_bad_inputs_raise_typed_errors(pair, good):
    left, right = pair
    d = good[1]
    with pytest.raises(InvalidInputError, match="differ in size"):
        measure_card(left, right[:-2], d, d, None, {})
    with pytest.raises(InvalidInputError, match=r"disp_left: expected shape"):
        measure_card(left, right, d[:, :-40], d, None, {})
    with pytest.raises(InvalidInputError, match="uint8"):
        measure_card(left.astype(np.float32), right, d, d, None, {})
    tiny = np.zeros((8, 40), np.uint8)
    with pytest.raises(ImageTooSmallError):
        measure_card(tiny, tiny, np.zeros((8, 40)), None, None, {})


def test_missing_measurements_are_skipped_with_notes():
    result = grade(GradeMeasurements(coverage=0.95))
    assert result.grade == "few"
    assert result.reasons[0] == (
        "few: every measurement within thresholds (1 of 20 measured); nearest: coverage 95 % "
        "is 15 points from its some threshold (< 80 %)"
    )
    assert "note: swapped not graded (not measured)" in result.reasons
    assert len(result.notes) == 19
    missing = [row for row in result.checks if row["value"] is None]
    assert len(missing) == 19 and all(row["note"] == "not measured" for row in missing)


# ---------------------------------------------------------------------------------- uncertainty


def test_uncertainty_is_one_on_a_threshold_and_falls_with_the_log_ratio():
    assert grade(GradeMeasurements(coverage=0.8)).uncertainty == 1.0  # on the "some" line, still few
    # 1 px against the 2 px "some" threshold: ln 2 away, u = 1 - ln 2 / ln 4 = 0.5
    assert grade(GradeMeasurements(row_misalignment_px=1.0)).uncertainty == pytest.approx(0.5)
    # a sole failure at 8 px is ln 2 above its 4 px threshold
    alone = grade(GradeMeasurements(row_misalignment_px=8.0))
    assert alone.grade == "failure" and alone.uncertainty == pytest.approx(0.5)
    # two independent failures: no single crossing changes the grade
    both = grade(GradeMeasurements(row_misalignment_px=8.0, coverage=0.1))
    assert both.uncertainty == 0.0 and both.deciding == ["row_misalignment_px", "coverage"]
    # two some-level measurements: either one crossing into failure changes the grade (3 vs 4 px)
    assert grade(GradeMeasurements(row_misalignment_px=3.0, coverage=0.7)).uncertainty == pytest.approx(
        1 - math.log(4 / 3) / math.log(4), abs=1e-4
    )
    # with the some level switched off, the failure threshold is the one that matters for a few card
    off = GradeThresholds.from_dict({"row_misalignment_px": {"direction": "above", "some": None, "failure": 4.0}})
    assert grade(GradeMeasurements(row_misalignment_px=2.0), off).uncertainty == pytest.approx(0.5)
    # far from every threshold
    assert grade(GradeMeasurements(row_misalignment_px=0.1, coverage=1.0)).uncertainty == 0.0
    rng = np.random.default_rng(1)
    for _ in range(200):
        u = grade(
            GradeMeasurements(
                row_misalignment_px=float(rng.uniform(0, 10)), coverage=float(rng.uniform(0, 1)), swapped=bool(rng.integers(2))
            )
        ).uncertainty
        assert 0.0 <= u <= 1.0


# ----------------------------------------------------------------------------------- thresholds


def test_thresholds_round_trip_through_json_and_hash_stably():
    base = GradeThresholds()
    document = json.loads(json.dumps(base.to_dict()))
    assert document["row_misalignment_px"] == {"direction": "above", "some": 2.0, "failure": 4.0}
    assert GradeThresholds.from_dict(document) == base
    assert param_hash(GradeParams(GradeThresholds.from_dict(document))) == param_hash(GradeParams())
    moved = GradeThresholds.from_dict({"coverage": {"direction": "below", "some": 0.9, "failure": 0.5}})
    assert moved.coverage == Threshold("below", 0.9, 0.5) and moved.dy_p95_px == base.dy_p95_px
    assert param_hash(GradeParams(moved)) != param_hash(GradeParams())
    assert len(param_hash(GradeParams())) == 16


@pytest.mark.parametrize(
    "document, message",
    [
        ({"colour": {"direction": "above", "some": 1, "failure": 2}}, "unknown grade measurements: colour"),
        ({"coverage": {"direction": "above", "some": 0.8, "failure": 0.5}}, "direction must be 'below'"),
        ({"coverage": {"direction": "below", "some": 0.5, "failure": 0.8}}, "must be beyond"),
        ({"coverage": {"direction": "below", "some": float("nan"), "failure": 0.5}}, "finite number"),
        ({"coverage": {"direction": "below", "some": "high", "failure": 0.5}}, "finite number"),
        ([1, 2], "mapping"),
    ],
)
def test_bad_threshold_documents_are_refused(document, message):
    with pytest.raises(InvalidInputError, match=message):
        GradeThresholds.from_dict(document)


# -------------------------------------------------------------------------------------- fitting

# The curators' hidden rule in the synthetic population: stricter than the defaults on rows and
# photometric error, laxer on coverage.
HIDDEN = GradeThresholds.from_dict(
    {
        "row_misalignment_px": {"direction": "above", "some": 1.0, "failure": 2.5},
        "photometric_error_rel": {"direction": "above", "some": 0.3, "failure": 0.6},
        "coverage": {"direction": "below", "some": 0.7, "failure": 0.4},
    }
)


def _population(n: int, noise: float, seed: int) -> list[tuple[dict, str]]:
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(n):
        m = GradeMeasurements(
            good_match_fraction=float(rng.uniform(0.05, 0.35)),
            dy_p95_px=float(rng.uniform(0.1, 1.2)),
            shear_deg=float(rng.uniform(0, 2)),
            aspect_change=float(rng.uniform(1.0, 1.1)),
            rotation_deg=float(rng.uniform(0, 3)),
            kept_fraction=float(rng.uniform(0.9, 1.0)),
            swapped=False,
            row_misalignment_px=float(rng.gamma(1.5, 1.0)),
            coverage=float(1 - rng.beta(1, 6)),
            lr_consistency=float(rng.uniform(0.75, 0.95)),
            confident_fraction=float(rng.uniform(0.5, 0.8)),
            disparity_range_rel=float(rng.uniform(0.01, 0.1)),
            textured_fraction=float(rng.uniform(0.3, 0.8)),
            photometric_error_rel=float(rng.uniform(0.05, 0.8)),
        )
        label = grade(m, HIDDEN).grade
        if rng.random() < noise:
            label = str(rng.choice([g for g in GRADES if g != label]))
        rows.append((m.as_dict(), label))
    return rows


def test_fitted_thresholds_agree_with_curators_on_held_out_labels():
    rows = _population(300, noise=0.1, seed=0)
    report = fit_thresholds(rows, GradeThresholds(), folds=5, seed=0)
    held, base = report.held_out, report.baseline
    assert held["labels"] == 300 and sum(map(sum, held["confusion"])) == 300
    assert [sum(r) for r in held["confusion"]] == [sum(label == g for _, label in rows) for g in GRADES]
    assert held["accuracy"] >= 0.8 and held["cohen_kappa"] >= 0.65
    assert held["accuracy"] >= base["accuracy"] + 0.15 and held["cohen_kappa"] > base["cohen_kappa"] + 0.2
    for name in GRADES:
        assert held["per_class"][name]["precision"] >= 0.8
    # About a third of the 47 "few" labels are noise flipped from the other classes (measured:
    # few recall 0.53, some 0.93, failure 0.94).
    assert held["per_class"]["some"]["recall"] >= 0.85 and held["per_class"]["failure"]["recall"] >= 0.85
    assert held["per_class"]["few"]["recall"] >= 0.45
    # The fitted thresholds moved towards the hidden ones, and stay readable thresholds.
    fitted = report.thresholds
    assert 0.7 <= fitted.row_misalignment_px.some <= 1.4 and 2.0 <= fitted.row_misalignment_px.failure <= 3.0
    assert 0.25 <= fitted.photometric_error_rel.some <= 0.35
    assert any(change.startswith("row_misalignment_px some: 2 -> ") for change in report.changed)
    document = json.loads(json.dumps(report.as_dict(), allow_nan=False))
    assert GradeThresholds.from_dict(document["thresholds"]) == fitted
    # Training agreement is at least the held-out one (it is fitted on those labels).
    assert report.training["accuracy"] >= held["accuracy"]


def test_fitting_without_enough_labels_says_how_many_more():
    rows = _population(7, noise=0.0, seed=3)
    with pytest.raises(NotEnoughLabelsError, match=r"7 curator labels; at least 10 are needed .*\(3 more\)"):
        fit_thresholds(rows, GradeThresholds())
    same = [(m, "some") for m, _ in _population(12, noise=0.0, seed=4)]
    with pytest.raises(NotEnoughLabelsError, match="all 12 curator labels are 'some'"):
        fit_thresholds(same, GradeThresholds())
    with pytest.raises(InvalidInputError, match="unknown grade 'great'"):
        fit_thresholds([(rows[0][0], "great")] * 12, GradeThresholds())
    assert NotEnoughLabelsError("x").reason() == "not_enough_labels: x"


def test_paper_distribution_is_the_papers_711_card_sample():
    shares = paper_distribution()
    assert shares == {"few": 0.23, "some": 0.49, "failure": 0.28}
    assert sum(shares.values()) == pytest.approx(1.0)


# ----------------------------------------------------------------------------------- stage task


def _write_card(root: Path, left: np.ndarray, right: np.ndarray, maps: dict[str, np.ndarray]) -> dict:
    work = root / "cards" / "7"
    write_png(work / "left.png", left)
    write_png(work / "right.png", right)
    for name, values in maps.items():
        write_npy(work / f"{name}.npy", np.asarray(values, np.float32))
    inputs = {name: f"cards/7/{name}.npy" for name in maps}
    return {"left": "cards/7/left.png", "right": "cards/7/right.png", **inputs, "metrics": CLEAN_STAGES}


def test_grade_task_grades_a_card_from_its_files(tmp_path, pair, good):
    left, right = pair
    _, d_left, d_right, conf = good
    inputs = _write_card(tmp_path, left, right, {"disparity_left": d_left, "disparity_right": d_right, "confidence": conf})
    task = CardTask(
        card_id=7,
        content_hash="abc",
        image_path=str(tmp_path / "card.jpg"),
        work_dir=str(tmp_path / "cards" / "7"),
        data_dir=str(tmp_path),
        inputs=inputs,
    )
    params = GradeParams()
    record = grade_task(task, params)
    assert record.status == "done" and record.stage == "grade" and record.outcome == "few"
    assert record.param_hash == param_hash(params)
    assert record.reason.startswith("few: every measurement within thresholds (20 of 20 measured); nearest: ")
    assert set(record.metrics["nearest"]) >= {"measurement", "value", "threshold", "margin", "level"}
    assert len(record.metrics["checks"]) == 20 and record.metrics["uncertainty_reason"].startswith("uncertainty ")
    assert record.metrics["coverage"] == 1.0 and record.metrics["lr_consistency"] > 0.85
    assert record.metrics["thresholds_hash"] == param_hash(params.thresholds)
    assert record.metrics["deciding"] == [] and 0.0 <= record.metrics["uncertainty"] <= 1.0
    json.dumps(record.metrics, allow_nan=False)
    # The stored metrics read back as the same measurements (fitting reads them this way).
    assert GradeMeasurements.from_dict(record.metrics).as_dict() == good[0].as_dict()

    strict = GradeParams(GradeThresholds.from_dict({"lr_consistency": {"direction": "below", "some": 0.995, "failure": 0.99}}))
    failed_grade = grade_task(task, strict)
    assert failed_grade.outcome == "failure" and failed_grade.param_hash != record.param_hash
    assert failed_grade.reason.startswith("failure: left and right disparities agree on only ")


def test_grade_task_records_a_failure_for_a_missing_file(tmp_path, pair, good):
    left, right = pair
    _, d_left, d_right, conf = good
    inputs = _write_card(tmp_path, left, right, {"disparity_left": d_left, "disparity_right": d_right, "confidence": conf})
    (tmp_path / "cards" / "7" / "confidence.npy").unlink()
    task = CardTask(card_id=7, content_hash="abc", image_path="", work_dir=str(tmp_path), data_dir=str(tmp_path), inputs=inputs)
    record = grade_task(task, GradeParams())
    assert record.status == "failed" and record.outcome is None
    assert record.reason.startswith("pipeline_error: no such file: ") and record.reason.endswith("confidence.npy")
    (tmp_path / "cards" / "7" / "left.png").unlink()
    assert grade_task(task, GradeParams()).reason.startswith("unreadable_image: no such file")
    no_inputs = CardTask(card_id=8, content_hash="x", image_path="", work_dir=str(tmp_path), data_dir=str(tmp_path))
    assert grade_task(no_inputs, GradeParams()).reason == (
        "pipeline_error: missing inputs left, right, disparity_left, disparity_right, confidence: run rectify and disparity first"
    )

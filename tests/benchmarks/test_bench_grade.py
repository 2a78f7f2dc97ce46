"""``keystone bench grade``: cards made from Motorcycle go through the real stages; the ground
truth mapped through the card and the rectification explains the rectified pair; swapped eyes are
graded failure with their depth order as the reason, and a clean card has less true error."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from benchmarks.disparity import motorcycle_scene
from benchmarks.grade import (
    CASES,
    bench_grade_command,
    run_pipeline,
    spearman,
    summarise,
    true_bad2,
    true_points,
)
from simulation.cards import Degradation, make_card_from_pair


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    scene = motorcycle_scene()
    card = make_card_from_pair(scene.left, scene.right, seed=0, degradation=Degradation(), name="motorcycle-clean")
    run = run_pipeline(card.image, 92, tmp_path_factory.mktemp("clean"))
    return scene, card, run


def test_mapped_ground_truth_explains_the_rectified_pair(clean_run):
    scene, card, run = clean_run
    assert run.records["rectify"].status in ("done", "skipped"), run.records["rectify"].reason
    points = true_points(run, card.truth, scene.gt)
    assert points.left_eye_shown_left and points.col.size > 20000
    rectify = run.records["rectify"].artifacts
    left = cv2.imread(str(run.data_dir / rectify["left"]), cv2.IMREAD_GRAYSCALE).astype(float)
    right = cv2.imread(str(run.data_dir / rectify["right"]), cv2.IMREAD_GRAYSCALE).astype(float)
    target = np.rint(points.col - points.d_true).astype(int)
    ok = (target >= 0) & (target < right.shape[1])
    by_truth = np.abs(left[points.row[ok], points.col[ok]] - right[points.row[ok], target[ok]]).mean()
    by_zero = np.abs(left[points.row[ok], points.col[ok]] - right[points.row[ok], points.col[ok]]).mean()
    # Measured: 7.4 grey levels through the truth, 16.8 with no disparity.
    assert by_truth < 0.6 * by_zero


def test_the_truth_itself_scores_no_error_and_a_flat_map_scores_much(clean_run, tmp_path):
    scene, card, run = clean_run
    points = true_points(run, card.truth, scene.gt)
    disparity = run.records["disparity"]
    path = run.data_dir / disparity.artifacts["disparity_left"]
    original = np.load(path)
    try:
        perfect = np.full(original.shape, np.nan, np.float32)
        perfect[points.row, points.col] = points.d_true
        np.save(path, perfect)
        assert true_bad2(run, card.truth, scene.gt)["true_bad2"] < 1.0
        np.save(path, np.full(original.shape, float(np.median(points.d_true)), np.float32))
        assert true_bad2(run, card.truth, scene.gt)["true_bad2"] > 60.0
    finally:
        np.save(path, original)


def test_spearman_and_summary():
    assert spearman([0, 1, 2, 2], [1.0, 5.0, 9.0, 8.0]) == pytest.approx(0.9487, abs=1e-4)
    assert spearman([1, 1, 1], [1.0, 2.0, 3.0]) is None
    results = [
        {"grade": "few", "true_bad2": 20.0},
        {"grade": "some", "true_bad2": 40.0},
        {"grade": "failure", "true_bad2": 90.0},
        {"grade": "culled", "true_bad2": 100.0},
    ]
    summary = summarise(results)
    assert summary["ordered"] and summary["stopped"] == 1 and summary["spearman"] == 1.0
    assert summary["median_true_bad2"] == {"few": 20.0, "some": 40.0, "failure": 90.0}


def test_quick_bench_grades_swapped_eyes_failure_by_depth_order():
    result = CliRunner().invoke(bench_grade_command, ["--quick", "--case", "clean", "--case", "swapped-eyes", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    rows = {row["case"]: row for row in document["results"]}
    assert set(rows) == {"clean", "swapped-eyes"}
    for row in rows.values():
        assert {"scene", "case", "grade", "uncertainty", "true_bad2"} <= set(row) and row["scene"] == "motorcycle"
    swapped, clean = rows["swapped-eyes"], rows["clean"]
    assert swapped["grade"] == "failure" and swapped["nearest"]["measurement"] == "depth_order"
    assert swapped["true_bad2"] > 80.0 and not swapped["left_eye_shown_left"]
    assert clean["true_bad2"] < swapped["true_bad2"] - 20.0 and clean["grade"] in ("few", "some")
    assert document["summary"]["cards"] == 2


def test_unknown_case_is_a_clear_error():
    result = CliRunner().invoke(bench_grade_command, ["--case", "nope"])
    assert result.exit_code != 0 and "unknown case nope" in result.output
    assert len(CASES) >= 15


def test_real_cards_cover_every_labelled_card_and_pairs_become_one_scan(tmp_path):
    from benchmarks.grade_real import DEFAULT_DATA, _scan_of, read_labels, real_cards

    if not (DEFAULT_DATA / "stereocards").is_dir():
        pytest.skip("no shared data")
    cards = dict(real_cards(DEFAULT_DATA))
    labels = read_labels(DEFAULT_DATA / "labels" / "careful_grades.csv")
    assert labels and set(labels) <= set(cards)  # every labelled card is found, by the labels' own names
    assert not any("card_backs" in name for name in cards)
    pair = next(files for name, files in cards.items() if " + " in name)
    scan = cv2.imread(str(_scan_of(pair, tmp_path)))
    left = cv2.imread(str(pair[0]))
    assert scan.shape[1] == left.shape[1] + 24 + cv2.imread(str(pair[1])).shape[1]

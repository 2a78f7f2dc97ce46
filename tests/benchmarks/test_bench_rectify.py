"""benchmarks.rectify: ours (Loop-Zhang) against OpenCV's Hartley on the same F and inliers.

Synthetic pairs warp Motorcycle's right view (rotation, vertical shift, keystone), so the ground
truth disparity of the left view still holds and the recovered disparity can be scored.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.disparity import motorcycle_scene
from benchmarks.rectify import (
    BenchPair,
    benchmark_rectify,
    keystone_warp,
    real_pairs,
    synthetic_pairs,
)

KEYS = {
    "pair",
    "kind",
    "method",
    "dy_median",
    "dy_p95",
    "midline_deviation",
    "aspect_change",
    "epe",
    "bad2",
    "coverage",
    "gt_dy_p95",
    "seconds",
    "error",
}


@pytest.fixture(scope="module")
def hard_warp() -> dict:
    pairs = synthetic_pairs([motorcycle_scene()], ("rot3-dy20-keystone",), scale=0.5)
    return benchmark_rectify(pairs)


def _rows(document: dict, pair: str) -> tuple[dict, dict]:
    rows = {r["method"]: r for r in document["results"] if r["pair"] == pair}
    return rows["keystone"], rows["hartley"]


def test_ours_beats_hartley_on_distortion_with_equal_dy(hard_warp) -> None:
    ours, hartley = _rows(hard_warp, "motorcycle/rot3-dy20-keystone")
    assert ours["error"] is None and hartley["error"] is None
    assert ours["midline_deviation"] < 1.0  # measured 0.0
    assert hartley["midline_deviation"] > 3.0  # measured 5.4
    assert ours["dy_p95"] <= hartley["dy_p95"] + 0.1  # both ~0.7 px: same F, same inliers
    assert ours["aspect_change"] <= hartley["aspect_change"] + 1e-9
    # Geometric truth over every GT pixel: both rectify to well under a pixel.
    assert ours["gt_dy_p95"] < 1.0 and hartley["gt_dy_p95"] < 1.0
    # Disparity on the rectified pair, mapped back to the original left view: a usable map
    # (measured EPE 1.45 / 1.35 px, bad-2 12.8 / 12.8 % at half size), full coverage.
    for row in (ours, hartley):
        assert row["epe"] < 3.0 and row["bad2"] < 20.0 and row["coverage"] > 99.0
        assert row["seconds"] > 0
        assert set(row) >= KEYS
    summary = hard_warp["summary"]
    assert summary["compared_pairs"] == 1 and summary["keystone_beats_hartley"] == 1


def test_unwarped_pair_maps_back_exactly() -> None:
    """No warp at all: the pair is already rectified; ours is the identity and the disparity
    mapped back is the estimator's own (measured EPE 1.54 px, bad-2 8.6 %). Hartley shears the
    already rectified pair (measured 5.7 deg)."""
    scene = motorcycle_scene()
    pair = BenchPair("moto/none", "synthetic", scene.left, scene.right, scene.gt, np.eye(3))
    document = benchmark_rectify([pair])
    ours, hartley = _rows(document, "moto/none")
    assert ours["error"] is None and ours["warp_needed"] is False
    assert ours["midline_deviation"] == 0.0 and ours["dy_p95"] < 1.0
    assert ours["epe"] < 2.5 and ours["coverage"] > 99.0
    assert ours["gt_dy_p95"] == 0.0
    assert hartley["error"] is None and hartley["midline_deviation"] > 3.0


def test_typed_failure_is_an_entry_not_a_crash() -> None:
    rng = np.random.default_rng(0)
    blank = np.full((120, 160), 128, np.uint8)
    noise = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    document = benchmark_rectify([BenchPair("blank", "real", blank, noise)])
    assert len(document["results"]) == 2
    for row in document["results"]:
        assert row["error"] and row["error"].startswith("too_few_matches")
        assert row["dy_p95"] is None
    assert document["summary"]["compared_pairs"] == 0
    assert document["summary"]["keystone"]["failures"] == 1


def test_keystone_warp_is_the_documented_composition() -> None:
    M = keystone_warp(741, 500, 0.0, 20.0, 0.0)
    assert np.allclose(M, [[1, 0, 0], [0, 1, 20], [0, 0, 1]])
    M = keystone_warp(741, 500, 3.0, 0.0, 0.0)
    centre = M @ np.array([370.0, 249.5, 1.0])
    assert np.allclose(centre[:2] / centre[2], [370.0, 249.5])
    assert math.isclose(math.degrees(math.atan2(M[1, 0], M[0, 0])), 3.0)


def test_real_pairs_load(shared_data: Path) -> None:
    pairs = real_pairs(shared_data)
    names = {p.name for p in pairs}
    assert any(n.startswith("full_cards/") for n in names)
    assert any(n.startswith("keystone_mast_raw_scans/") for n in names)
    assert any(n.startswith("jps/") for n in names)
    for p in pairs:
        assert p.kind == "real" and p.gt is None and min(p.left.shape[:2]) >= 16


def test_a_real_card_both_methods(shared_data: Path) -> None:
    """One real NYPL card (no ground truth): ours keeps the midlines square, Hartley shears."""
    pairs = [p for p in real_pairs(shared_data) if p.name == "full_cards/nypl_stereogranimator_demo1"]
    assert pairs
    document = benchmark_rectify(pairs)
    ours, hartley = _rows(document, pairs[0].name)
    assert ours["error"] is None and hartley["error"] is None
    assert ours["epe"] is None  # no ground truth
    assert ours["midline_deviation"] < 1.0
    assert ours["midline_deviation"] <= hartley["midline_deviation"]
    assert ours["dy_p95"] <= hartley["dy_p95"] + 0.1 and ours["dy_p95"] < 2.0

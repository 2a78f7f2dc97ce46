"""benchmarks.filter: the filter's timing (``keystone bench filter``)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from benchmarks.filter import benchmark_filter, default_bench_cards, synthetic_bench_cards


def test_benchmark_reports_medians_and_restores_threads():
    previous = cv2.getNumThreads()
    cards = synthetic_bench_cards()[1:2]  # the small web-scan card keeps this fast
    report = benchmark_filter(cards, repeats=2)
    assert cv2.getNumThreads() == previous
    assert report["target_seconds"] == 0.35 and report["threads"] == 1 and report["repeats"] == 2
    (row,) = report["results"]
    assert row["card"] == "synthetic/motorcycle_web_card.png" and row["outcome"] == "pass"
    assert len(row["half_size"]) == 2 and max(row["half_size"]) <= 600
    for key in ("split_seconds", "detect_seconds", "match_seconds"):
        assert 0 < row[key] < row["total_seconds"]
    assert report["median_total_seconds"] == row["total_seconds"]
    json.dumps(report, allow_nan=False)


def test_default_bench_cards_fall_back_to_synthetic_cards(tmp_path):
    cards = default_bench_cards(None)
    assert [name for name, _ in cards] == [name for name, _ in default_bench_cards(tmp_path)]
    assert len(cards) == 3 and all(card.dtype == np.uint8 for _, card in cards)


def test_default_bench_cards_use_the_real_scans(shared_data):
    names = [name for name, _ in default_bench_cards(shared_data)]
    assert len(names) == 11
    assert names[-2:] == ["keystone_mast_raw_scans/09995.jpg", "keystone_mast_raw_scans/09997.jpg"]


@pytest.mark.bench
def test_filter_meets_the_time_target_on_one_core(shared_data):
    report = benchmark_filter(default_bench_cards(shared_data), repeats=3)
    assert report["median_total_seconds"] <= 0.35

"""Load on loopback: 50 simulated annotators against the app under waitress on SQLite, over real HTTP.

Bounded in time (a few hundred requests, short thinking). Correctness is asserted here; speed
is reported by ``keystone bench crowd`` and not asserted (a shared 2-core machine makes timed
assertions flaky).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from annotation.bench import latency_summary, run_crowd_bench

ANNOTATORS, TASKS, N, REPLAY_EVERY = 50, 4, 3, 2


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root: Path = tmp_path_factory.mktemp("crowd-load")
    return run_crowd_bench(ANNOTATORS, TASKS, n=N, think_ms=(0.0, 20.0), replay_every=REPLAY_EVERY, root=root)


@pytest.mark.timeout(120)
def test_fifty_annotators_lose_and_duplicate_nothing(report: dict) -> None:
    assert report["client_errors"] == []
    assert report["stopped"] == {"done": ANNOTATORS}  # everyone got all their tasks
    assert report["answers_submitted"] == ANNOTATORS * TASKS
    assert report["answers_stored"] == ANNOTATORS * TASKS
    assert report["lost"] == 0 and report["unacknowledged"] == 0
    assert report["duplicates"] == 0 and report["over_capacity_items"] == 0
    assert report["status_5xx"] == 0 and report["status_4xx"] == 0
    # Retried POSTs (every second submit posted twice) returned the stored answer, not a new one.
    assert report["replays"] == ANNOTATORS * (TASKS // REPLAY_EVERY)
    assert report["replays_ok"] == report["replays"]


@pytest.mark.timeout(120)
def test_every_latency_was_recorded(report: dict) -> None:
    submits, fetches = report["submit"], report["fetch_next"]
    assert submits["count"] == ANNOTATORS * TASKS
    assert fetches["count"] >= ANNOTATORS * TASKS  # plus retries while every slot was held
    assert fetches["count"] == report["fetch_next_first"]["count"] + report["fetch_next_steady"]["count"]
    assert report["fetch_next_first"]["count"] == ANNOTATORS
    for row in (submits, fetches):
        assert 0 < row["p50_ms"] <= row["p95_ms"] <= row["max_ms"] and math.isfinite(row["max_ms"])
    assert report["requests"] == fetches["count"] + submits["count"] + report["replays"]
    assert report["throughput_rps"] > 0


def test_latency_summary_percentiles() -> None:
    assert latency_summary([]) == {"count": 0, "p50_ms": None, "p95_ms": None, "max_ms": None}
    row = latency_summary([float(v) for v in range(1, 101)])
    assert row == {"count": 100, "p50_ms": 50.5, "p95_ms": 95.05, "max_ms": 100.0}

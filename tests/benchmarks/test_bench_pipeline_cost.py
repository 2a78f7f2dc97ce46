"""``keystone bench pipeline``: CPU seconds per card and stage on a card run through the real stages."""

from __future__ import annotations

import json

from app.cli import cli


def test_bench_pipeline_reports_cpu_seconds_for_every_stage_a_card_reached(runner):
    result = runner.invoke(cli, ["bench", "pipeline", "--synthetic", "--limit", "1", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    (row,) = document["results"]
    assert row["card"] == "motorcycle_760px.jpg" and row["width"] == 760
    assert row["filter_outcome"] == "pass" and row["failed"] == {}
    assert set(row["cpu_seconds"]) == {"filter", "rectify", "disparity", "grade", "views"}
    assert all(seconds > 0 for seconds in row["cpu_seconds"].values())
    default = sum(row["cpu_seconds"][name] for name in ("filter", "rectify", "disparity", "grade"))
    assert abs(row["pipeline_cpu_seconds"] - default) < 1e-3
    assert row["views_cpu_seconds"] == row["cpu_seconds"]["views"]
    summary = document["summary"]
    assert summary["cards"] == 1 and summary["reached_grade"] == 1
    assert summary["median_pipeline_cpu_seconds"] == row["pipeline_cpu_seconds"]
    assert document["peak_rss_mb"] > 50


def test_bench_pipeline_refuses_an_unknown_stage(runner):
    result = runner.invoke(cli, ["bench", "pipeline", "--synthetic", "--stages", "filter,sharpen"])
    assert result.exit_code == 2 and "sharpen" in result.output

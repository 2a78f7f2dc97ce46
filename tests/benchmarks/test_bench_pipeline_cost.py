"""``keystone bench pipeline``: CPU seconds per card and stage on a card run through the real stages."""

from __future__ import annotations

import json

from app.cli import cli


def test_bench_pipeline_reports_cpu_seconds_for_every_stage_a_card_reached(runner):
    result = runner.invoke(cli, ["bench", "pipeline", "--synthetic", "--limit", "1", "--variant", "work", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert list(document["variants"]) == ["work"] and document["comparison"] is None
    (row,) = document["results"]
    assert row["card"] == "motorcycle_760px.jpg" and row["width"] == 760
    assert row["filter_outcome"] == "pass" and row["failed"] == {}
    assert set(row["cpu_seconds"]) == {"filter", "orientation", "rectify", "disparity", "grade", "views"}
    assert all(seconds > 0 for seconds in row["cpu_seconds"].values())
    default = sum(row["cpu_seconds"][name] for name in ("filter", "orientation", "rectify", "disparity", "grade"))
    assert abs(row["pipeline_cpu_seconds"] - default) < 1e-3
    assert row["views_cpu_seconds"] == row["cpu_seconds"]["views"]
    summary = document["summary"]
    assert summary["cards"] == 1 and summary["reached_grade"] == 1
    assert summary["median_pipeline_cpu_seconds"] == row["pipeline_cpu_seconds"]
    assert document["peak_rss_mb"] > 50
    # timed on a second pass; the first (one-time costs charged to the card) is reported beside it
    assert document["warmed_up"] is True
    (first,) = document["first_pass_by_size"]
    assert first["size"] == "<1000 px" and first["median_pipeline_cpu_seconds"] > 0


def test_bench_pipeline_cold_times_the_first_pass(runner):
    result = runner.invoke(
        cli, ["bench", "pipeline", "--synthetic", "--limit", "1", "--variant", "work", "--stages", "filter", "--cold", "--json"]
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["warmed_up"] is False and document["first_pass_by_size"] is None
    assert document["results"][0]["cpu_seconds"]["filter"] > 0


def test_bench_pipeline_sets_chained_stages_beside_stage_by_stage(runner):
    """The default (chained, as ``keystone run``) and ``--stage-by-stage`` side by side: the same
    outcomes, every stage timed in both, and their ratio per scan size."""
    result = runner.invoke(
        cli,
        ["bench", "pipeline", "--synthetic", "--limit", "1", "--variant", "stage-by-stage", "--variant", "work"]
        + ["--stages", "filter,orientation,rectify,disparity,grade", "--cold", "--json"],
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    chained, staged = document["variants"]["work"]["results"][0], document["variants"]["stage-by-stage"]["results"][0]
    assert (
        (chained["filter_outcome"], chained["grade"]) == (staged["filter_outcome"], staged["grade"]) == ("pass", chained["grade"])
    )
    assert chained["grade"] in ("few", "some", "failure")
    assert set(chained["cpu_seconds"]) == set(staged["cpu_seconds"]) == {"filter", "orientation", "rectify", "disparity", "grade"}
    (row,) = document["comparison"]
    assert row["chained_over_stage_by_stage"] == round(row["work"] / row["stage-by-stage"], 3)


def test_bench_pipeline_refuses_an_unknown_stage(runner):
    result = runner.invoke(cli, ["bench", "pipeline", "--synthetic", "--stages", "filter,sharpen"])
    assert result.exit_code == 2 and "sharpen" in result.output


def test_bench_pipeline_runs_full_and_working_resolution_side_by_side(runner):
    """The 3000 px Motorcycle card: the working resolution costs less than full resolution in the
    same run, and each variant reports its own peak memory and medians per scan size."""
    result = runner.invoke(cli, ["bench", "pipeline", "--synthetic", "--stages", "filter,rectify,disparity,grade", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert set(document["variants"]) == {"full", "work"}
    for run in document["variants"].values():
        assert run["summary"]["reached_grade"] == 3 and run["peak_rss_mb"] > 50
        assert [group["size"] for group in run["summary"]["by_size"]] == ["<1000 px", "1000-2000 px", ">=2000 px"]
    big = next(row for row in document["comparison"] if row["size"] == ">=2000 px")
    assert big["work"] < big["full"] and big["work_over_full"] == round(big["work"] / big["full"], 3)
    assert document["results"] == document["variants"]["work"]["results"]

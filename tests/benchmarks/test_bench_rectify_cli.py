"""``keystone bench rectify``: JSON shape and the readable table, on the quick set (Motorcycle,
half size, the hardest synthetic warp). The command needs no app or database."""

from __future__ import annotations

import json

from click.testing import CliRunner

from benchmarks.rectify import bench_rectify_command

ROW_KEYS = {"pair", "method", "dy_median", "dy_p95", "midline_deviation", "aspect_change", "epe", "bad2", "seconds", "error"}


def test_json_shape_quick() -> None:
    result = CliRunner().invoke(bench_rectify_command, ["--quick", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)  # one JSON document and nothing else on stdout
    assert set(document) == {"results", "summary"}
    rows = document["results"]
    assert [r["method"] for r in rows] == ["keystone", "hartley"]
    for row in rows:
        assert set(row) >= ROW_KEYS
        assert row["pair"] == "motorcycle/rot3-dy20-keystone" and row["error"] is None
        for key in ("dy_median", "dy_p95", "midline_deviation", "aspect_change", "epe", "bad2", "seconds"):
            assert isinstance(row[key], float) and row[key] >= 0
    ours, hartley = rows
    assert ours["midline_deviation"] < 1.0 and hartley["midline_deviation"] > 3.0
    assert ours["dy_p95"] <= hartley["dy_p95"] + 0.1
    summary = document["summary"]
    assert set(summary) >= {"keystone", "hartley", "compared_pairs", "keystone_beats_hartley", "criterion"}
    assert summary["compared_pairs"] == 1 and summary["keystone_beats_hartley"] == 1
    assert summary["keystone"]["synthetic"]["pairs"] == 1 and summary["hartley"]["real"]["pairs"] == 0


def test_table_and_help() -> None:
    runner = CliRunner()
    result = runner.invoke(bench_rectify_command, ["--quick", "--no-disparity", "--repeats", "2"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].split()[:2] == ["pair", "method"]
    assert any(line.startswith("motorcycle/rot3-dy20-keystone") and " keystone " in line for line in lines)
    assert any("keystone beats hartley on 1 of 1 pairs" in line for line in lines)
    help_text = runner.invoke(bench_rectify_command, ["--help"]).output
    for option in ("--json", "--repeats", "--quick", "--shared-data"):
        assert option in help_text

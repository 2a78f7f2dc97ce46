"""``keystone bench views``: the views stage's old and new code side by side on a card run through
the real stages, with the output difference of the rasteriser."""

from __future__ import annotations

import json

from app.cli import cli


def test_bench_views_times_old_and_new_and_shows_the_rasteriser_unchanged(runner):
    result = runner.invoke(cli, ["bench", "views", "--synthetic", "--limit", "1", "--repeats", "1", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    (row,) = document["results"]
    assert row["card"] == "motorcycle_760px.jpg" and row["status"] == {"old": "done", "new": "done"}
    assert row["cpu_seconds"]["old"] > 0 and row["cpu_seconds"]["new"] > 0
    assert row["colour"] is True  # the new code keeps the card's colour
    raster = row["rasteriser"]
    # The same triangle rule through the old and the new rasteriser: the same picture, to float32.
    assert raster["differing_fraction"] <= 1e-4 and raster["coverage_differs_fraction"] <= 1e-4
    assert raster["psnr_db"] > 60
    assert raster["reproject_cpu_seconds"]["new"] < raster["reproject_cpu_seconds"]["old"]
    assert row["viewer_bytes"]["new"] < row["viewer_bytes"]["old"] / 3
    assert raster["crack_fraction"]["stage_rule"] <= raster["crack_fraction"]["paper_rule"]
    summary = document["summary"]
    assert summary["compared"] == 1 and summary["rasteriser_within_tolerance"] is True
    assert summary["median_cpu_seconds"] == row["cpu_seconds"] and summary["speed_up"] > 0

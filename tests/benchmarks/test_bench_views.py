"""``keystone bench views``: the views stage's old code (a recorded commit, taken from git) and the
new code side by side on a card run through the real stages, with the output difference of the
rasteriser; without git or that commit, the new code alone, and it says so."""

from __future__ import annotations

import json
from pathlib import Path

from app.cli import cli
from benchmarks.views import BASELINE_COMMIT, checkout_baseline


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
    assert summary["baseline"] == {"commit": BASELINE_COMMIT, "available": True, "unavailable_because": None}
    assert summary["compared"] == 1 and summary["rasteriser_within_tolerance"] is True
    assert summary["median_cpu_seconds"] == row["cpu_seconds"] and summary["speed_up"] > 0


def test_the_old_code_is_the_recorded_commit_s_pipeline(tmp_path: Path) -> None:
    tree, why = checkout_baseline(BASELINE_COMMIT, tmp_path / "old")
    assert why is None and tree is not None
    # Before the vectorised rasteriser: pipeline/views.py still has the per-chunk loop, and no mesh PNGs.
    assert "def _raster_chunk(" in (tree / "pipeline" / "views.py").read_text()
    assert not (tree / "app").exists()  # only pipeline/ is taken


def test_without_the_commit_or_git_it_says_why(tmp_path: Path, monkeypatch) -> None:
    missing = "0" * 40
    assert checkout_baseline(missing, tmp_path / "a") == (None, f"commit {missing} is not in this checkout")
    elsewhere = tmp_path / "plain"
    elsewhere.mkdir()
    tree, why = checkout_baseline(BASELINE_COMMIT, tmp_path / "b", repo=elsewhere)
    assert tree is None and why is not None and "not a git checkout" in why
    monkeypatch.setattr("benchmarks.views.shutil.which", lambda _name: None)
    assert checkout_baseline(BASELINE_COMMIT, tmp_path / "c") == (None, "git is not installed")


def test_bench_views_times_the_new_code_alone_when_the_old_is_unavailable(runner):
    missing = "0" * 40
    args = ["bench", "views", "--synthetic", "--limit", "1", "--repeats", "1", "--baseline", missing, "--json"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert f"old code unavailable: commit {missing} is not in this checkout; timing the current code only" in result.stderr
    document = json.loads(result.stdout)
    (row,) = document["results"]
    assert row["status"] == {"new": "done"} and set(row["cpu_seconds"]) == {"new"} and "rasteriser" not in row
    summary = document["summary"]
    assert summary["baseline"]["available"] is False and summary["compared"] == 0 and summary["timed"] == 1
    assert summary["median_cpu_seconds"]["old"] is None and summary["speed_up"] is None

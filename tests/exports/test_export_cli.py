"""keystone export / verify / bench export on the command line: JSON shapes and exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def test_export_json_then_verify_json(runner, tmp_path, processed_cards, review_card) -> None:
    ids = processed_cards(2)
    review_card(ids[0], "few")
    review_card(ids[1], "some")

    dry = runner.invoke(args=["export", "--out", str(tmp_path / "out"), "--dry-run", "--json"])
    assert dry.exit_code == 0, dry.output
    plan = json.loads(dry.stdout)
    assert plan["dry_run"] is True and plan["version"] == "1.0.0" and plan["cards"] == 2
    assert plan["changes"]["added"] == ids and not (tmp_path / "out").exists()

    result = runner.invoke(
        args=[
            "export",
            "--out",
            str(tmp_path / "out"),
            "--min-grade",
            "few",
            "--format",
            "parquet,keystonedepth",
            "--notes",
            "first cut",
            "--json",
        ]
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert {"version", "path", "cards", "formats", "changes", "seconds", "files"} <= document.keys()
    assert document["version"] == "1.0.0" and document["cards"] == 1 and document["formats"] == ["keystonedepth", "parquet"]
    assert document["files"] == len((Path(document["path"]) / "SHA256SUMS").read_text().splitlines()) + 1
    assert "first cut" in (Path(document["path"]) / "README.md").read_text()

    checked = runner.invoke(args=["verify", document["path"], "--json"])
    assert checked.exit_code == 0, checked.output
    verdict = json.loads(checked.stdout)
    assert verdict["ok"] is True and verdict["problems"] == [] and verdict["checked"] == document["files"] - 1

    (Path(document["path"]) / "README.md").write_text("tampered\n")
    broken = runner.invoke(args=["verify", document["path"], "--json"])
    assert broken.exit_code == 1
    assert json.loads(broken.stdout)["problems"] == [
        {"path": "README.md", "problem": "sha256 does not match SHA256SUMS (file changed or corrupted)"}
    ]
    human = runner.invoke(args=["verify", document["path"]])
    assert human.exit_code == 1 and "README.md: sha256 does not match" in human.output


def test_export_without_accepted_cards_exits_1_with_a_clear_error(runner, tmp_path) -> None:
    result = runner.invoke(args=["export", "--out", str(tmp_path / "out"), "--json"])
    assert result.exit_code == 1
    assert "no curator-accepted cards" in json.loads(result.stdout)["error"]
    human = runner.invoke(args=["export", "--out", str(tmp_path / "out")])
    assert human.exit_code == 1 and "Error: no curator-accepted cards" in human.output


def test_export_refuses_an_unknown_format(runner, tmp_path) -> None:
    result = runner.invoke(args=["export", "--out", str(tmp_path / "out"), "--format", "zip"])
    assert (
        result.exit_code == 2
        and "Expected formats from keystonedepth, parquet, webdataset, views, stereo, iiif, got zip" in result.output
    )


def test_bench_export_small(runner) -> None:
    result = runner.invoke(args=["bench", "export", "--cards", "20", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["benchmark"] == "export" and document["cards"] == 20 and document["verified"] is True
    assert document["cards_per_second"] > 0 and 50 < document["peak_rss_mb"] < document["target_rss_mb"]


def test_bench_export_map_size_scales_the_synthetic_maps(runner) -> None:
    result = runner.invoke(args=["bench", "export", "--cards", "6", "--map-size", "64", "--format", "parquet", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["view_size"] == [100, 75] and document["depth_size"] == [64, 64]
    assert document["cards"] == 6 and document["verified"] is True


def test_bench_export_refuses_a_tiny_map_size(runner) -> None:
    result = runner.invoke(args=["bench", "export", "--cards", "6", "--map-size", "8"])
    assert result.exit_code == 2 and "--map-size" in result.output


@pytest.mark.bench
def test_bench_export_real_size_maps_stay_under_500_mb(runner) -> None:
    result = runner.invoke(args=["bench", "export", "--cards", "250", "--map-size", "512", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["view_size"] == [800, 600] and document["verified"] is True
    assert document["peak_rss_mb"] < 500


@pytest.mark.bench
def test_bench_export_10000_cards_stays_under_500_mb(runner) -> None:
    result = runner.invoke(args=["bench", "export", "--cards", "10000", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["cards"] == 10_000 and document["verified"] is True
    assert document["peak_rss_mb"] < 500


def test_verify_of_a_missing_folder_exits_1(runner, tmp_path) -> None:
    result = runner.invoke(args=["verify", str(tmp_path / "nowhere"), "--no-mlcroissant", "--json"])
    assert result.exit_code == 1
    assert json.loads(result.stdout) == {
        "ok": False,
        "path": str(tmp_path / "nowhere"),
        "checked": 0,
        "problems": [{"path": str(tmp_path / "nowhere"), "problem": "not a folder"}],
    }

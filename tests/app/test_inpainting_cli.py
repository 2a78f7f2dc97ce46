"""``keystone bench inpainting --json`` and ``keystone train-inpainting`` on tiny settings."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

pytest.importorskip("torch")

from app.inpainting_cli import bench_inpainting_command, train_inpainting_command


def test_bench_inpainting_json_shape():
    result = CliRunner().invoke(bench_inpainting_command, ["--json", "--steps", "5", "--size", "32"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    pairs = {(r["method"], r["channel"]) for r in doc["results"]}
    assert pairs == {(m, c) for m in ("network", "telea", "navier-stokes", "none") for c in ("intensity", "depth")}
    assert all(r["l1"] is not None and r["l1"] >= 0 for r in doc["results"])
    assert doc["training_seconds"] > 0 and doc["steps"] == 5 and doc["test_samples"] > 0
    assert isinstance(doc["network_beats_classical_on_depth"], bool)
    inits = {(r["method"], r["channel"]): r["l1"] for r in doc["init_results"]}
    assert set(inits) == {("navier-stokes", "intensity"), ("background-fill", "depth")}
    # the intensity init is Navier-Stokes itself: the same fill, the same error
    assert inits[("navier-stokes", "intensity")] == pytest.approx(
        next(r["l1"] for r in doc["results"] if r["method"] == "navier-stokes" and r["channel"] == "intensity"))
    paired = doc["depth_per_sample"]
    assert paired["samples"] == doc["test_samples"] and 0 <= paired["network_beats_best_classical"] <= paired["samples"]
    low, high = paired["bootstrap_ci95"]
    assert low <= paired["l1_difference_vs_best_classical"] <= high


def test_train_inpainting_checkpoints_and_resumes(tmp_path):
    runner = CliRunner()
    args = ["--out", str(tmp_path), "--size", "32", "--checkpoint-every", "2", "--json"]
    first = runner.invoke(train_inpainting_command, [*args, "--steps", "2"])
    assert first.exit_code == 0, first.output
    assert json.loads(first.output)["step"] == 2
    assert (tmp_path / "checkpoint.pt").is_file() and (tmp_path / "config.json").is_file()
    second = runner.invoke(train_inpainting_command, [*args, "--steps", "3"])
    doc = json.loads(second.output)
    assert doc["start_step"] == 2 and doc["step"] == 3


def test_train_on_the_catalogues_own_gd_images(runner, tmp_path, make_card_with_views) -> None:  # type: ignore[no-untyped-def]
    card_id, record = make_card_with_views(160, "few")
    result = runner.invoke(train_inpainting_command,
                           ["--out", str(tmp_path / "run"), "--source", "catalogue", "--size", "32", "--steps", "2",
                            "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    assert document["source"] == "catalogue" and document["step"] == 2
    # One 160 x 108 v0, cropped at 32 px with stride 16 and flipped: a real, non-empty training set.
    assert document["gd_crops"] >= 20 and (tmp_path / "run" / "checkpoint.pt").is_file()


def test_train_on_an_empty_catalogue_says_what_to_run(runner, tmp_path) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(train_inpainting_command, ["--out", str(tmp_path / "run"), "--source", "catalogue"])
    assert result.exit_code == 1 and "keystone run --stages views" in result.output

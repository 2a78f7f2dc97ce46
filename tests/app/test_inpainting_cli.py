"""``keystone train-inpainting`` on tiny settings."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

pytest.importorskip("torch")

from app.inpainting_cli import train_inpainting_command


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
    result = runner.invoke(
        train_inpainting_command,
        ["--out", str(tmp_path / "run"), "--source", "catalogue", "--size", "32", "--steps", "2", "--json"],
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    assert document["source"] == "catalogue" and document["step"] == 2
    # One 160 x 108 v0, cropped at 32 px with stride 16 and flipped: a real, non-empty training set.
    assert document["gd_crops"] >= 20 and (tmp_path / "run" / "checkpoint.pt").is_file()


def test_train_on_an_empty_catalogue_says_what_to_run(runner, tmp_path) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(train_inpainting_command, ["--out", str(tmp_path / "run"), "--source", "catalogue"])
    assert result.exit_code == 1 and "keystone run --stages views" in result.output

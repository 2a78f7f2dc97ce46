"""``keystone run`` and ``keystone cards``: the filter over the catalogue, resumable, per-card failures."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import delete, func, select

from app.cli import cli
from core.db import db
from core.models import Card, StageResult

pytestmark = pytest.mark.both_databases


@pytest.fixture
def catalogue(tmp_path: Path, runner, mount_pair) -> Path:  # type: ignore[no-untyped-def]
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path / "scans"
    folder.mkdir()
    Image.fromarray(mount_pair(left, right)).save(folder / "stereo.jpg", quality=92)
    Image.fromarray(mount_pair(right[:, ::-1], left[:, ::-1])).save(folder / "stereo_mirrored_scene.png")
    astronaut = data.astronaut()[:400, :500]
    coffee = np.ascontiguousarray(data.coffee()[:, :500])
    Image.fromarray(mount_pair(astronaut, coffee)).save(folder / "two_unrelated_photos.png")
    result = runner.invoke(cli, ["ingest", str(folder), "--json"])
    assert result.exit_code == 0, result.output
    return folder


def _cards(runner, *args: str) -> dict:  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, ["cards", "--json", *args])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_filter_routes_cards_and_cards_json_has_the_documented_shape(app, runner, catalogue):
    result = runner.invoke(cli, ["run", "--stages", "filter", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)["stages"][0]
    assert report["stage"] == "filter" and report["processed"] == 3 and report["failed"] == 0

    listing = _cards(runner)["cards"]
    by_source = {card["source"]: card for card in listing}
    assert set(by_source) == {"stereo.jpg", "stereo_mirrored_scene.png", "two_unrelated_photos.png"}
    for card in listing:
        assert set(card) >= {"id", "source", "accession", "stages", "orientation"}
        assert set(card["stages"]) == {
            "filter",
            "orientation",
            "judge",
            "crop",
            "rectify",
            "disparity",
            "grade",
            "review",
            "views",
        }
        # keystone cards --json (README.md): null flags while undecided (the orientation step has not run yet).
        assert card["orientation"] == {
            "upside_down": None,
            "inverted": None,
            "swapped": None,
            "decided_by": None,
            "confidence": None,
        }
        assert set(card["stages"]["filter"]) >= {"status", "reason", "metrics"}
    stereo = by_source["stereo.jpg"]["stages"]["filter"]
    assert stereo["status"] == "done" and stereo["outcome"] == "pass"
    assert stereo["metrics"]["good_match_fraction"] > 0.05
    assert stereo["metrics"]["denominator"]
    assert by_source["stereo_mirrored_scene.png"]["stages"]["filter"]["outcome"] == "pass"
    unrelated = by_source["two_unrelated_photos.png"]["stages"]
    assert unrelated["filter"]["outcome"] == "culled"
    assert unrelated["rectify"]["status"] == "skipped" and "culled" in unrelated["rectify"]["reason"]
    assert by_source["stereo.jpg"]["stages"]["rectify"]["status"] == "pending"
    assert "orientation is undecided" in by_source["stereo.jpg"]["stages"]["rectify"]["reason"]
    assert by_source["stereo.jpg"]["stages"]["judge"]["status"] == "pending"
    assert unrelated["orientation"]["status"] == "skipped" and "culled" in unrelated["orientation"]["reason"]

    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "stereo.jpg"))
        assert card.state == "pass"
        artifacts = card.latest_results()["filter"].artifacts
        for name in ("left", "right"):
            assert (Path(app.config["KEYSTONE_DATA_DIR"]) / artifacts[name]).is_file()


def test_rerun_skips_finished_cards_and_changed_parameters_rerun(app, runner, catalogue, monkeypatch):
    first = json.loads(runner.invoke(cli, ["run", "--json"]).stdout)["stages"][0]
    again = json.loads(runner.invoke(cli, ["run", "--json"]).stdout)["stages"][0]
    assert (first["processed"], again["processed"], again["already_done"]) == (3, 0, 3)

    import runs.cli
    from pipeline.filter import FilterParams
    from pipeline.stages.spec import StageSpec
    from runs.specs import available_stages

    original = available_stages

    def stricter():  # type: ignore[no-untyped-def]
        stages = original()
        spec = stages["filter"]
        params = FilterParams(review_fraction=0.9)
        import functools

        from pipeline.stages.filter import filter_task

        stages["filter"] = StageSpec("filter", params, functools.partial(filter_task, params=params), spec.eligible_states)
        return stages

    monkeypatch.setattr(runs.cli, "available_stages", stricter)
    changed = json.loads(runner.invoke(cli, ["run", "--json"]).stdout)["stages"][0]
    assert changed["processed"] == 3 and changed["param_hash"] != first["param_hash"]
    with app.app_context():
        filter_rows = select(func.count()).select_from(StageResult).where(StageResult.stage == "filter")
        assert db.session.scalar(filter_rows) == 6


def test_process_pool_gives_the_same_results_as_inline(app, runner, catalogue, tmp_path):
    runner.invoke(cli, ["run", "--json"])
    inline = {c["source"]: c["stages"]["filter"]["metrics"]["good_matches"] for c in _cards(runner)["cards"]}
    with app.app_context():
        db.session.execute(delete(StageResult))
        db.session.commit()
    result = runner.invoke(cli, ["run", "--workers", "2", "--json"])
    assert result.exit_code == 0, result.output
    pooled = {c["source"]: c["stages"]["filter"]["metrics"]["good_matches"] for c in _cards(runner)["cards"]}
    assert pooled == inline


def test_an_inline_run_is_one_worker_with_a_pool_workers_set_up():
    """`--workers 1` runs the stages in the command's own process: one OpenCV and one BLAS
    thread there too (run in a fresh interpreter, without the thread variables a pool worker sets)."""
    import subprocess
    import sys

    from pipeline.runner import ONE_THREAD_ENVIRONMENT

    code = (
        "import cv2, json, threadpoolctl\n"
        "from runs.executors import make_executor\n"
        "before = cv2.getNumThreads()\n"
        "with make_executor('local', 1, None) as executor:\n"
        "    blas = {i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas'}\n"
        "    print(json.dumps([executor is None, before, cv2.getNumThreads(), sorted(blas)]))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ONE_THREAD_ENVIRONMENT}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    inline, before, opencv, blas = json.loads(result.stdout.strip().splitlines()[-1])
    assert inline and opencv == 1 and blas == [1], (before, opencv, blas)


def test_a_broken_original_fails_with_a_typed_reason_and_the_rest_goes_on(app, runner, catalogue):
    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "stereo.jpg"))
        stored = Path(app.config["KEYSTONE_DATA_DIR"]) / card.stored_path
    os.chmod(stored, 0o644)
    stored.write_bytes(stored.read_bytes()[:500])  # disk damage after ingest
    result = runner.invoke(cli, ["run", "--json"])
    assert result.exit_code == 1
    report = json.loads(result.stdout)["stages"][0]
    assert report["failed"] == 1 and report["done"] == 2
    assert report["failures"][0]["reason"].startswith("unreadable_image:")
    states = {c["source"]: c["stages"]["filter"]["status"] for c in _cards(runner, "--stage", "filter")["cards"]}
    assert states == {"stereo.jpg": "failed", "stereo_mirrored_scene.png": "done", "two_unrelated_photos.png": "done"}
    assert _cards(runner, "--state", "failed")["cards"][0]["source"] == "stereo.jpg"


def test_unknown_stage_is_a_usage_error(runner):
    result = runner.invoke(cli, ["run", "--stages", "filter,teleport"])
    assert result.exit_code == 2
    assert "teleport" in result.output and "available: filter" in result.output


def test_dask_executor_without_dask_says_how_to_get_it(runner):
    try:
        import distributed  # noqa: F401
    except ImportError:
        result = runner.invoke(cli, ["run", "--executor", "dask"])
        assert result.exit_code == 1 and "pip install 'dask[distributed]'" in result.output
    else:
        pytest.skip("dask.distributed is installed")


def test_rectify_stage_warps_a_misaligned_pair_and_skips_an_aligned_one(app, runner, tmp_path, decide_orientation, mount_pair):
    import cv2
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    height, width = right.shape[:2]
    tilt = cv2.getRotationMatrix2D((width / 2, height / 2), 1.5, 1.0)
    tilt[1, 2] += 6.0  # and 6 px down, as antique mounts are
    tilted = cv2.warpAffine(right, tilt, (width, height), borderMode=cv2.BORDER_REFLECT)
    folder = tmp_path / "pairs"
    folder.mkdir()
    Image.fromarray(mount_pair(left, tilted)).save(folder / "tilted.png")
    Image.fromarray(mount_pair(left, right)).save(folder / "aligned.png")
    assert runner.invoke(cli, ["ingest", str(folder)]).exit_code == 0
    decide_orientation()  # a curator knows both are upright positives in eye order
    result = runner.invoke(cli, ["run", "--stages", "filter,rectify,disparity", "--json"])
    assert result.exit_code == 0, result.output
    reports = {r["stage"]: r for r in json.loads(result.stdout)["stages"]}
    assert reports["rectify"]["processed"] == 2 and reports["rectify"]["failed"] == 0

    stages = {c["source"]: c["stages"]["rectify"] for c in _cards(runner)["cards"]}
    # Aligned halves need no projective warp; at most a translation when the two split boxes
    # trim different margins and so would make some disparity negative.
    aligned = stages["aligned.png"]
    assert "already rectified within tolerance" in aligned["reason"]
    assert aligned["status"] == "skipped" or "translated" in aligned["reason"]
    assert aligned["metrics"]["H_l"] == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    tilted_result = stages["tilted.png"]
    assert tilted_result["status"] == "done", tilted_result["reason"]
    assert tilted_result["metrics"]["dy_p95"] < 1.5
    assert abs(tilted_result["metrics"]["midline_angle"] - 90) < 1
    assert tilted_result["metrics"]["disparity_min"] >= -0.5

    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "tilted.png"))
        artifacts = card.latest_results()["rectify"].artifacts
        data_dir = Path(app.config["KEYSTONE_DATA_DIR"])
        camera = json.loads((data_dir / artifacts["rectification"]).read_text())
        crop = card.latest_results()["rectify"].metrics["crop_alignment"]
        assert crop["status"] == "done" and crop["left_box_before"] == card.latest_results()["filter"].metrics["left_box"]
        assert abs(crop["dy"] - 6) <= 2  # the right view was moved 6 px down (and tilted 1.5 deg)
        left_size = (crop["left_box"][2] - crop["left_box"][0], crop["left_box"][3] - crop["left_box"][1])
        right_size = (crop["right_box"][2] - crop["right_box"][0], crop["right_box"][3] - crop["right_box"][1])
        assert left_size == right_size
        assert len(camera["H_l"]) == 3 and camera["left_box"] == crop["left_box"]
        with Image.open(data_dir / artifacts["left"]) as rect_left, Image.open(data_dir / artifacts["right"]) as rect_right:
            assert rect_left.size == rect_right.size

    disparity = {c["source"]: c["stages"]["disparity"] for c in _cards(runner)["cards"]}
    for source in ("aligned.png", "tilted.png"):
        assert disparity[source]["status"] == "done", disparity[source]["reason"]
        metrics = disparity[source]["metrics"]
        assert metrics["coverage"] > 0.8 and metrics["backend"] == "keystone"
        assert 0 < metrics["disparity_p5"] < metrics["disparity_p50"] < metrics["disparity_p95"] < 120
    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "aligned.png"))
        artifacts = card.latest_results()["disparity"].artifacts
        depth_512 = np.load(data_dir / artifacts["depth_512"])
        disparity_512 = np.load(data_dir / artifacts["disparity_512"])
        assert depth_512.shape == disparity_512.shape == (512, 512)
        assert np.isfinite(depth_512).all() and (depth_512 >= 0).all()
        full = np.load(data_dir / artifacts["disparity_left"])
        assert full.dtype == np.float32 and abs(full.shape[0] - 500) <= 30 and abs(full.shape[1] - 741) <= 60

    # The default run adds the grade stage: only it has work; a second run has none at all.
    graded = json.loads(runner.invoke(cli, ["run", "--json"]).stdout)["stages"]
    # The orientation step runs too. The photos fill their halves, so the photo-area finder keeps
    # the split; but the step now decides both cards itself (the learned upright cue), agreeing
    # with the curator, and rectification's inputs name who decided: it reruns once, on the
    # same flags and boxes.
    assert [(r["stage"], r["processed"]) for r in graded] == [
        ("filter", 0),
        ("orientation", 2),
        ("rectify", 2),
        ("disparity", 0),
        ("grade", 2),
    ]
    assert graded[4]["failed"] == 0 and sum(graded[4]["outcomes"].values()) == 2
    again = json.loads(runner.invoke(cli, ["run", "--json"]).stdout)["stages"]
    assert [r["processed"] for r in again] == [0, 0, 0, 0, 0]


def _approve(app, card_id: int, kind: str, label: dict) -> None:  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch
    from annotation.models import Aggregate

    with app.app_context():
        batch = create_batch([card_id], kind, 1, 0.0)
        db.session.add(
            Aggregate(
                batch_id=batch.id,
                card_id=card_id,
                kind=kind,
                label=label,
                posterior={},
                confident=True,
                state="approved",
                answers=1,
            )
        )
        db.session.commit()


def test_rectify_consumes_approved_crowd_judgements_and_boxes(app, runner, tmp_path, mount_pair):
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path / "crowd"
    folder.mkdir()
    Image.fromarray(mount_pair(left, right)).save(folder / "in_review.png")
    Image.fromarray(np.ascontiguousarray(mount_pair(left, right)[::-1, ::-1])).save(folder / "upside_down.png")
    assert runner.invoke(cli, ["ingest", str(folder)]).exit_code == 0
    assert runner.invoke(cli, ["run", "--stages", "filter"]).exit_code == 0
    with app.app_context():
        review = db.session.scalar(select(Card).where(Card.source_name == "in_review.png"))
        review.state = "review"  # as if the filter had sent it to people
        db.session.commit()
        review_id = review.id
        turned_id = db.session.scalar(select(Card.id).where(Card.source_name == "upside_down.png"))

    first = json.loads(runner.invoke(cli, ["run", "--stages", "rectify", "--json"]).stdout)["stages"][0]
    assert first["processed"] == 0  # both wait: the review card for its judgement, both for their orientation
    by_id = {c["id"]: c["stages"]["rectify"] for c in _cards(runner)["cards"]}
    assert by_id[review_id]["status"] == by_id[turned_id]["status"] == "pending"

    # A judgement that does not say which eye is which leaves the card undecided (the step did not run).
    _approve(app, turned_id, "judge", {"is_stereo": True, "upside_down": True, "inverted": False})
    assert json.loads(runner.invoke(cli, ["run", "--stages", "rectify", "--json"]).stdout)["stages"][0]["processed"] == 0
    assert {c["id"]: c for c in _cards(runner)["cards"]}[turned_id]["orientation"]["swapped"] is None

    _approve(app, review_id, "judge", {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": False})
    _approve(app, review_id, "crop", {"left": [10, 10, 700, 480], "right": [775, 12, 1465, 482]})
    _approve(app, turned_id, "judge", {"is_stereo": True, "upside_down": True, "inverted": False, "swapped": False})
    second = json.loads(runner.invoke(cli, ["run", "--stages", "rectify", "--json"]).stdout)["stages"][0]
    assert second["processed"] == 2 and second["failed"] == 0  # the judged review card, and the turned card
    listing = {c["id"]: c for c in _cards(runner)["cards"]}
    assert listing[turned_id]["orientation"] == {
        "upside_down": True,
        "inverted": False,
        "swapped": False,
        "decided_by": "crowd",
        "confidence": 1.0,
    }

    by_id = {c["id"]: c["stages"]["rectify"] for c in _cards(runner)["cards"]}
    crowd = by_id[review_id]["metrics"]
    assert crowd["box_source"].startswith("crowd consensus")
    assert crowd["crop_alignment"]["left_box_before"] == [10, 10, 700, 480]
    turned = by_id[turned_id]["metrics"]
    assert turned["orientation"]["status"] == "done" and turned["orientation"]["applied"] == ["rotated 180 deg"]
    assert turned["swapped"] is False and turned["disparity_max"] > 20

    third = json.loads(runner.invoke(cli, ["run", "--stages", "rectify", "--json"]).stdout)["stages"][0]
    assert third["processed"] == 0 and third["already_done"] == 2

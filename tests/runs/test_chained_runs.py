"""Chained stages (``keystone run``'s default): a worker takes a card on through the stages whose
inputs are its own results, and the database ends up as a stage-by-stage run leaves it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import delete, select, update

from app.cli import cli
from core.db import db
from core.models import Card, StageResult
from pipeline.records import param_hash
from runs.claims import Driver, StageClaim
from runs.specs import available_stages

pytestmark = pytest.mark.both_databases

DEFAULT_STAGES = ("filter", "orientation", "rectify", "disparity", "grade")


@pytest.fixture
def catalogue(tmp_path: Path, runner, mount_pair) -> Path:  # type: ignore[no-untyped-def]
    """Two stereo cards (a JPEG, whose filter and orientation decodes are reduced, and a PNG) and
    a card of two unrelated photos the filter culls."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path / "scans"
    folder.mkdir()
    Image.fromarray(mount_pair(left, right)).resize((2 * 1520, 2 * 500)).save(folder / "stereo_large.jpg", quality=92)
    Image.fromarray(mount_pair(right[:, ::-1], left[:, ::-1])).save(folder / "stereo_mirrored_scene.png")
    astronaut = data.astronaut()[:400, :500]
    coffee = np.ascontiguousarray(data.coffee()[:, :500])
    Image.fromarray(mount_pair(astronaut, coffee)).save(folder / "two_unrelated_photos.png")
    result = runner.invoke(cli, ["ingest", str(folder), "--json"])
    assert result.exit_code == 0, result.output
    return folder


def _timeless(value: Any, stage: str = "") -> Any:
    """A record's metrics without what the clock sets: durations, and the grade's inputs digest
    (its inputs hold the earlier stages' metrics, durations too)."""
    if isinstance(value, dict):
        return {
            k: _timeless(v) for k, v in value.items() if "seconds" not in k and not (stage == "grade" and k == "inputs_digest")
        }
    if isinstance(value, list):
        return [_timeless(v) for v in value]
    return value


def _results(app) -> dict[tuple[str, str], tuple[Any, ...]]:  # type: ignore[no-untyped-def]
    with app.app_context():
        rows = db.session.execute(select(Card.source_name, StageResult).join(StageResult, StageResult.card_id == Card.id)).all()
        return {
            (source, result.stage): (
                result.param_hash,
                result.status,
                result.outcome,
                result.reason,
                _timeless(result.metrics, result.stage),
                result.artifacts,
            )
            for source, result in rows
        }


def _run(runner, *args: str, code: int = 0) -> dict[str, dict[str, Any]]:  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, ["run", "--json", *args])
    assert result.exit_code == code, result.output
    return {report["stage"]: report for report in json.loads(result.stdout)["stages"]}


def test_a_chained_run_writes_what_a_stage_by_stage_run_writes(app, runner, catalogue, decide_orientation):
    decide_orientation()  # every card upright, so rectification runs after the orientation step
    by_stage = _run(runner, "--stage-by-stage")
    expected = _results(app)
    assert {stage for _, stage in expected} == set(DEFAULT_STAGES)
    assert by_stage["grade"]["processed"] == 2 and all(r["chained"] == 0 for r in by_stage.values())
    with app.app_context():  # back to freshly ingested cards
        db.session.execute(delete(StageResult))
        db.session.execute(update(Card).values(state="ingested"))
        db.session.commit()

    chained = _run(runner, "--workers", "2")  # a process pool: the chains travel to workers
    assert _results(app) == expected
    # The culled card goes no further than the filter; both stereo cards through every stage,
    # the orientation step chained after the filter, disparity and grade after rectification.
    assert chained["filter"]["processed"] == 3 and chained["filter"]["chained"] == 0
    assert chained["orientation"]["processed"] == 2 and chained["orientation"]["chained"] == 2
    assert chained["rectify"]["processed"] == 2 and chained["rectify"]["chained"] == 0
    for stage in ("disparity", "grade"):
        assert chained[stage]["processed"] == 2 and chained[stage]["chained"] == 2
        assert chained[stage]["already_done"] == 0 and chained[stage]["failed"] == 0
    assert {stage: r["outcomes"] for stage, r in chained.items()} == {stage: r["outcomes"] for stage, r in by_stage.items()}

    again = _run(runner)
    assert all(report["processed"] == 0 for report in again.values()), again


def test_a_card_another_run_holds_for_a_follower_stage_is_left_to_it(app, runner, catalogue):
    with app.app_context():
        card_id = db.session.scalar(select(Card.id).where(Card.source_name == "stereo_large.jpg"))
        other = Driver(db.engine, ttl_s=600, driver_id="other-run")
        phash = param_hash(available_stages()["orientation"].params)
        assert other.claim("orientation", phash, [card_id], {card_id: None}).claimed == [card_id]

    reports = _run(runner, "--stages", "filter,orientation", "--no-wait", code=3)
    assert reports["filter"]["processed"] == 3
    # The other stereo card was chained; the held one is left to its holder, and said so.
    assert reports["orientation"]["chained"] == 1 and reports["orientation"]["processed"] == 1
    assert reports["orientation"]["still_held"] == 1
    with app.app_context():
        stages = set(db.session.scalars(select(StageResult.stage).where(StageResult.card_id == card_id)))
        assert stages == {"filter"}
        # This run freed every claim it held: only the other run's is left.
        assert [(c.card_id, c.driver) for c in db.session.scalars(select(StageClaim))] == [(card_id, "other-run")]

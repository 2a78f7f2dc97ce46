"""The orientation flow end to end: decided by the step, by the crowd, by a curator; the flow
rule (undecided cards are not rectified, graded, accepted or released)."""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import select

from app.cli import cli
from core.db import db

pytestmark = pytest.mark.both_databases


def _cards(runner) -> dict[str, dict]:  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, ["cards", "--json"])
    assert result.exit_code == 0, result.output
    return {card["source"]: card for card in json.loads(result.stdout)["cards"]}


def _run(runner, *stages: str) -> dict:  # type: ignore[no-untyped-def]
    args = ["run", "--json"] + (["--stages", ",".join(stages)] if stages else [])
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def _approve_judge(app, card_id: int, batch_id: int, label: dict, state: str = "approved") -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate

    with app.app_context():
        db.session.add(
            Aggregate(
                batch_id=batch_id,
                card_id=card_id,
                kind="judge",
                label=label,
                posterior={"upside_down": 0.99, "inverted": 0.98},
                confident=state == "approved",
                state=state,
                answers=5,
                reasons="" if state == "approved" else "inverted: 0.6 < 0.95",
            )
        )
        db.session.commit()


@pytest.fixture
def flow_cards(tmp_path: Path, runner, mount_pair) -> Path:  # type: ignore[no-untyped-def]
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path / "scans"
    folder.mkdir()
    card = mount_pair(left, right)
    Image.fromarray(card).save(folder / "upright.png")
    Image.fromarray(np.ascontiguousarray(card[::-1, ::-1])).save(folder / "turned.png")
    Image.fromarray(255 - card).save(folder / "negative.png")
    assert runner.invoke(cli, ["ingest", str(folder)]).exit_code == 0
    return folder


def test_orientation_decided_by_crowd_and_curator_and_undecided_cards_wait(
    app, runner, client, login, csrf_token, flow_cards, monkeypatch
):  # type: ignore[no-untyped-def]
    # The step decides these three Motorcycle cards itself (the learned upright cue); a threshold
    # no card reaches, with no proposals for a grid, makes every one wait for a one-card judge
    # task, which is the path under test.
    import pipeline.stages.orientation as orientation_stage
    from pipeline.orientation import OrientationParams
    from pipeline.stages.orientation import OrientationStageParams

    strict = OrientationParams(auto_probability=0.99999, confirm_probability=0.99999)
    # The driver takes a stage's default parameters from the stage module's declaration.
    lenient_stage = dataclasses.replace(orientation_stage.STAGE, params=lambda: OrientationStageParams(orientation=strict))
    monkeypatch.setattr(orientation_stage, "STAGE", lenient_stage)
    first = _run(runner)
    stages = {s["stage"]: s for s in first["stages"]}
    assert [s["stage"] for s in first["stages"]] == ["filter", "orientation", "rectify", "disparity", "grade"]
    # The step is not sure of the eye order of any of these: every one waits for people,
    # although the filter passed all three.
    assert stages["orientation"]["processed"] == 3 and stages["orientation"]["outcomes"] == {"ask": 3}
    assert stages["rectify"]["processed"] == stages["grade"]["processed"] == 0
    assert first["waiting_for_people"] == {"orientation": 3, "filter_review": 0}
    cards = _cards(runner)
    for card in cards.values():
        assert card["state"] == "pass"
        assert card["orientation"]["decided_by"] is None and card["orientation"]["swapped"] is None
        assert card["stages"]["judge"]["status"] == "pending" and "people" in card["stages"]["judge"]["reason"]
        assert card["stages"]["rectify"]["status"] == "pending"
        step = card["stages"]["orientation"]
        assert step["outcome"] == "ask" and set(step["metrics"]["flags"]) == {"upside_down", "inverted", "swapped"}
        assert all(isinstance(w, str) for f in step["metrics"]["flags"].values() for w in f["evidence"])
    # The negative flag is read confidently, even while the card waits.
    assert cards["negative.png"]["stages"]["orientation"]["metrics"]["flags"]["inverted"]["p"] > 0.95
    assert cards["upright.png"]["stages"]["orientation"]["metrics"]["flags"]["inverted"]["p"] < 0.05

    # The crowd's judge queue takes them whatever their filter band.
    batch = runner.invoke(cli, ["crowd", "create-batch", "--from-review", "--n", "3", "--json"])
    assert batch.exit_code == 0, batch.output
    batch_doc = json.loads(batch.stdout)
    assert batch_doc["items"] == 3
    again = runner.invoke(cli, ["crowd", "create-batch", "--from-review", "--n", "3", "--json"])
    assert again.exit_code == 2 and "no cards" in again.output  # on their way already: not asked twice
    ids = {name: card["id"] for name, card in cards.items()}
    # The crowd: the turned card is upside down (the judge asked the eye order); the negative is
    # inverted, and the judge did not ask the eye order: it stays undecided until a person says.
    _approve_judge(
        app, ids["turned.png"], batch_doc["batch"], {"is_stereo": True, "upside_down": True, "inverted": False, "swapped": False}
    )
    _approve_judge(app, ids["negative.png"], batch_doc["batch"], {"is_stereo": True, "upside_down": False, "inverted": True})
    # A curator decides the upright card on its review page (a form POST with the CSRF token).
    curator = login("curator")
    page = client.get(f"/review/cards/{ids['upright.png']}")
    assert page.status_code == 200 and 'id="orientation-form"' in page.get_data(as_text=True)
    token = csrf_token(f"/review/cards/{ids['upright.png']}")
    refused = client.post(
        f"/review/cards/{ids['upright.png']}/orientation", data={"upside_down": "no", "inverted": "no", "swapped": "no"}
    )
    assert refused.status_code == 400  # no CSRF token
    response = client.post(
        f"/review/cards/{ids['upright.png']}/orientation",
        data={"upside_down": "no", "inverted": "no", "swapped": "no", "note": "looked at it", "csrf_token": token},
    )
    assert response.status_code == 303
    bad = client.post(f"/review/cards/{ids['upright.png']}/orientation", data={"upside_down": "sideways", "csrf_token": token})
    assert bad.status_code == 400 and "upside_down" in bad.get_data(as_text=True)

    cards = _cards(runner)
    negative = cards["negative.png"]
    assert negative["orientation"]["inverted"] is True and negative["orientation"]["swapped"] is None
    assert negative["stages"]["judge"] == {
        "status": "pending",
        "outcome": None,
        "reason": "waiting for people (swapped undecided)",
        "metrics": negative["stages"]["judge"]["metrics"],
    }
    token = csrf_token(f"/review/cards/{ids['negative.png']}")
    assert (
        client.post(f"/review/cards/{ids['negative.png']}/orientation", data={"swapped": "no", "csrf_token": token}).status_code
        == 303
    )
    cards = _cards(runner)
    assert cards["upright.png"]["orientation"] == {
        "upside_down": False,
        "inverted": False,
        "swapped": False,
        "decided_by": "curator",
        "confidence": 1.0,
    }
    assert cards["turned.png"]["orientation"]["decided_by"] == "crowd"
    assert cards["turned.png"]["orientation"]["upside_down"] is True
    negative = cards["negative.png"]["orientation"]  # the crowd's inverted, the curator's eye order
    assert negative["decided_by"] == "curator" and negative["inverted"] is True and negative["swapped"] is False
    assert cards["turned.png"]["stages"]["judge"]["status"] == "done"
    with app.app_context():
        from core.audit import AuditEvent

        event = db.session.scalar(select(AuditEvent).where(AuditEvent.entity == "orientation").order_by(AuditEvent.id))
        assert event.card_id == ids["upright.png"] and event.actor == curator.username
        assert event.before["decided_by"] is None and event.after["decided_by"] == "curator"
        assert event.why == "looked at it"

    second = _run(runner)
    stages = {s["stage"]: s for s in second["stages"]}
    assert stages["rectify"]["processed"] == 3 and stages["rectify"]["failed"] == 0
    assert stages["grade"]["processed"] == 3 and second["waiting_for_people"]["orientation"] == 0
    cards = _cards(runner)
    turned = cards["turned.png"]["stages"]["rectify"]["metrics"]
    assert turned["orientation"]["applied"] == ["rotated 180 deg"]
    assert turned["orientation_used"] == {"upside_down": True, "inverted": False, "swapped": False}
    # The turned card's boxes, back on the scan, are where the upright card's are, turned.
    width = cards["turned.png"]["stages"]["filter"]["metrics"]["card_size"][0]
    right_eye = turned["scanned_boxes"]["right_eye"]
    assert right_eye[2] <= width // 2 + 12  # the right eye's photo is on the scan's left, turned
    assert cards["negative.png"]["stages"]["rectify"]["metrics"]["orientation"]["applied"] == ["intensities inverted"]
    # Corrected, the three are the same pair: the same disparity range within a few px.
    ranges = [cards[name]["stages"]["disparity"]["metrics"]["disparity_p95"] for name in cards]
    assert max(ranges) - min(ranges) < 6, ranges

    # Accept and release: the curator accepts all three; then the upright card's override is
    # cleared (undecided again) and the turned card's judgement is disputed in a new batch.
    from core.models import Person
    from review.models import CardReview
    from review.tasks import ReviewError, decide

    with app.app_context():
        person = db.session.get(Person, curator.id)
        for name in ("upright.png", "turned.png", "negative.png"):
            review = db.session.scalar(select(CardReview).where(CardReview.card_id == ids[name]))
            decide(review.id, "change", expected_version=review.version, curator=person, grade="some")
    token = csrf_token(f"/review/cards/{ids['upright.png']}")
    client.post(
        f"/review/cards/{ids['upright.png']}/orientation",
        data={"upside_down": "", "inverted": "", "swapped": "", "csrf_token": token},
    )
    assert _cards(runner)["upright.png"]["orientation"]["decided_by"] is None
    from annotation.batches import create_batch

    with app.app_context():
        dispute_batch = create_batch([ids["turned.png"]], "judge", 3, 0.0).id
    _approve_judge(
        app, ids["turned.png"], dispute_batch, {"is_stereo": True, "upside_down": True, "inverted": False}, state="needs_curator"
    )
    with app.app_context():
        person = db.session.get(Person, curator.id)
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == ids["upright.png"]))
        with pytest.raises(ReviewError) as refused_accept:
            decide(review.id, "change", expected_version=review.version, curator=person, grade="few")
        assert refused_accept.value.status == 409 and "orientation is undecided" in refused_accept.value.message

    preview = runner.invoke(cli, ["export", "--out", str(flow_cards.parent / "releases"), "--dry-run", "--json"])
    assert preview.exit_code == 0, preview.output
    plan = json.loads(preview.stdout)
    excluded = {row["card_id"]: row["reason"] for row in plan["excluded"]}
    assert "orientation is undecided" in excluded[ids["upright.png"]]
    assert "the crowd disagrees on its judgement" in excluded[ids["turned.png"]]
    assert plan["cards"] == 1
    published = runner.invoke(cli, ["export", "--out", str(flow_cards.parent / "releases"), "--json"])
    assert published.exit_code == 0, published.output
    release = json.loads(published.stdout)
    assert release["cards"] == 1 and {row["card_id"] for row in release["excluded"]} == {ids["upright.png"], ids["turned.png"]}
    released = [json.loads(line) for line in (Path(release["path"]) / "cards.jsonl").read_text().splitlines()]
    assert [row["card_id"] for row in released] == [ids["negative.png"]]
    assert released[0]["orientation_corrections"] == ["intensities inverted"]


def test_a_confident_step_decides_and_its_correction_is_applied(app, runner, flow_cards, monkeypatch):  # type: ignore[no-untyped-def]
    """The step decides a card itself when its posterior clears ``auto_probability``; measured on
    these synthetic cards at the default 0.9 it never does, so the test lowers the bar."""
    import runs.cli
    from pipeline.orientation import OrientationParams
    from pipeline.stages.orientation import OrientationStageParams, orientation_task
    from pipeline.stages.spec import StageSpec
    from runs.specs import available_stages

    original = available_stages

    def lenient():  # type: ignore[no-untyped-def]
        stages = original()
        params = OrientationStageParams(orientation=OrientationParams(auto_probability=0.6))
        spec = stages["orientation"]
        stages["orientation"] = StageSpec(
            "orientation",
            params,
            functools.partial(orientation_task, params=params),
            spec.eligible_states,
            spec.inputs,
            spec.requires,
            spec.ready,
        )
        return stages

    monkeypatch.setattr(runs.cli, "available_stages", lenient)
    report = _run(runner, "filter", "orientation", "rectify")
    stages = {s["stage"]: s for s in report["stages"]}
    cards = _cards(runner)
    auto = {name: card for name, card in cards.items() if card["orientation"]["decided_by"] == "auto"}
    assert auto, {name: card["stages"]["orientation"]["reason"] for name, card in cards.items()}
    assert stages["rectify"]["processed"] == len(auto)
    truth = {"upright.png": (False, False, False), "turned.png": (True, False, False), "negative.png": (False, True, False)}
    for name, card in auto.items():
        orientation = card["orientation"]
        assert (orientation["upside_down"], orientation["inverted"], orientation["swapped"]) == truth[name]
        assert orientation["confidence"] >= 0.6
        assert card["stages"]["judge"]["status"] == "skipped" and "orientation step decided" in card["stages"]["judge"]["reason"]
        assert card["stages"]["rectify"]["status"] in ("done", "skipped")
        assert card["stages"]["rectify"]["metrics"]["orientation_used"] == dict(
            zip(("upside_down", "inverted", "swapped"), truth[name])
        )
    for name in set(cards) - set(auto):
        assert cards[name]["stages"]["rectify"]["status"] == "pending"

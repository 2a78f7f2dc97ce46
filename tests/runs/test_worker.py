"""The loop: a curator's decision makes results stale, the background worker recomputes them, and
an acceptance applies only to the results it was given (issue 32).

Cards are the Motorcycle stereo card (real photographs); rectification, disparity and grade are
computed by the real pipeline through ``keystone worker --once``.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select

STAGES = "rectify,disparity,grade"


def _motorcycle(number: int) -> np.ndarray:
    """A distinct card per number (content hashes must differ): the same pair, another crop."""
    from PIL import Image
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    half = (296, 200)
    x0 = 12 * number
    views = [np.asarray(Image.fromarray(v[:, x0 : x0 + 700]).resize(half, Image.Resampling.BOX)) for v in (left, right)]
    strip = np.full((half[1], 12, 3), 200, np.uint8)
    return np.concatenate([views[0], strip, views[1]], axis=1)


@pytest.fixture
def two_cards(app, make_card, add_stage_result, decide_orientation) -> list[int]:  # type: ignore[no-untyped-def]
    ids = []
    for number in range(2):
        card = make_card(image=_motorcycle(number), accession=f"1996.0009.{17827 + number}")
        add_stage_result(card, "filter")
        ids.append(card)
    decide_orientation(ids)
    return ids


def _worker_once(runner: Any) -> dict[str, Any]:
    result = runner.invoke(args=["worker", "--once", "--stages", STAGES, "--json"])
    assert result.exit_code == 0, result.output
    rounds = [json.loads(line) for line in result.output.splitlines() if line.startswith("{")]
    assert len(rounds) == 1
    return rounds[0]


def _curator(app, make_person) -> Any:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person

    info = make_person("curator", username="carol")
    with app.app_context():
        person = db.session.get(Person, info.id)
        db.session.expunge(person)
        return person


def _review(card_id: int) -> Any:
    from core.db import db
    from review.models import CardReview

    db.session.expire_all()
    return db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))


def test_a_changed_eye_order_is_recomputed_by_the_worker_and_goes_back_to_the_curator(  # type: ignore[no-untyped-def]
    app, runner, two_cards, make_person, decide_orientation, data_dir, tmp_path
) -> None:
    from core.audit import AuditEvent
    from core.db import db
    from core.models import Card
    from exports.catalogue import stream_release_cards
    from exports.release import publish_release
    from exports.verify import verify_release
    from review.tasks import ReviewError, card_results_digest, decide
    from runs.card_state import card_states

    accepted, waiting = two_cards
    first = _worker_once(runner)
    assert {stage["stage"]: stage["processed"] for stage in first["stages"]} == {"rectify": 2, "disparity": 2, "grade": 2}
    assert first["failed"] == 0 and first["trigger"] == "once"
    curator = _curator(app, make_person)
    with app.app_context():
        review = _review(accepted)  # the grade's write synced both into the queue
        assert review.decision == "pending" and _review(waiting).decision == "pending"
        shown = card_results_digest(db.session.get(Card, accepted))
        decide(review.id, "accept", expected_version=review.version, curator=curator, shown_results=shown)
        assert set(_review(accepted).accepted_results) == {"rectify", "disparity"}

    # A curator: the eyes are exchanged on both cards. At once both are stale...
    decide_orientation([accepted, waiting], swapped=True)
    with app.app_context():
        cards = list(db.session.scalars(select(Card).where(Card.id.in_(two_cards)).order_by(Card.id)))
        states = card_states(cards)
        for card in two_cards:
            assert set(states[card].stale or {}) == {"rectify", "disparity", "grade"}
            assert states[card].statuses["rectify"]["stale"] is True
        # ...the waiting one cannot be accepted...
        review = _review(waiting)
        with pytest.raises(ReviewError) as refused:
            decide(review.id, "accept", expected_version=review.version, curator=curator)
        assert refused.value.status == 409 and "its rectify result is out of date" in refused.value.message
        # ...and a release plan leaves the accepted one out, saying why.
        left_out: list[Any] = []
        assert list(stream_release_cards([accepted], data_dir, left_out)) == []
        assert [row.card_id for row in left_out] == [accepted]
        assert "its rectify result is out of date (rectified with another orientation" in left_out[0].reason
        db.session.remove()
    dry = runner.invoke(args=["export", "--out", str(tmp_path / "out"), "--dry-run", "--json"])
    # the only accepted card is left out, and the refusal says why
    assert dry.exit_code == 1
    assert f"left out: card {accepted}: its rectify result is out of date" in json.loads(dry.output)["error"]

    # The worker recomputes both with the new eye order; both wait for the curator again.
    second = _worker_once(runner)
    assert {stage["stage"]: stage["processed"] for stage in second["stages"]} == {"rectify": 2, "disparity": 2, "grade": 2}
    with app.app_context():
        cards = list(db.session.scalars(select(Card).where(Card.id.in_(two_cards)).order_by(Card.id)))
        states = card_states(cards)
        for card in cards:
            assert card.latest_results()["rectify"].metrics["orientation_used"]["swapped"] is True
            assert states[card.id].stale == {} and states[card.id].blockers == []
        reopened = _review(accepted)
        assert (reopened.decision, reopened.grade, reopened.accepted_results) == ("pending", None, None)
        trail = db.session.scalar(
            select(AuditEvent).where(AuditEvent.card_id == accepted, AuditEvent.action == "reopened_after_recompute")
        )
        assert trail is not None and trail.actor == "pipeline"
        assert trail.why.startswith("its rectify result was recomputed on ") and "after the acceptance on" in trail.why
        assert trail.before["decision"] == "accepted" and trail.after["decision"] == "pending"
        # A page opened before the recomputation cannot accept what it did not show.
        with pytest.raises(ReviewError) as outdated:
            decide(reopened.id, "accept", expected_version=reopened.version, curator=curator, shown_results=shown)
        assert outdated.value.status == 409 and "were recomputed since you opened it" in outdated.value.message
        for card in two_cards:
            review = _review(card)
            digest = card_results_digest(db.session.get(Card, card))
            decide(review.id, "change", expected_version=review.version, curator=curator, grade="some", shown_results=digest)
        report = publish_release(tmp_path / "releases", min_grade="some", actor_label="test")
        assert report.cards == 2 and report.excluded == []
    release = tmp_path / "releases" / report.version
    assert verify_release(release, validate_croissant=False).problems == []
    records = [json.loads(line) for line in (release / "cards.jsonl").read_text().splitlines()]
    assert all(record["acceptance"]["accepted_results"]["rectify"]["computed_at"] for record in records)
    assert all(
        record["acceptance"]["inputs_now"]["rectify"] == record["pipeline"]["rectify"]["inputs_digest"] for record in records
    )


def test_verify_finds_a_stale_result_or_an_outdated_acceptance_in_the_release_records(tmp_path) -> None:
    from exports.verify import VerifyReport, check_released_cards

    computed = {"param_hash": "p", "inputs_digest": "a", "computed_at": "2026-11-27T10:00:00+00:00"}
    sound = {
        "key": "card_000001",
        "pipeline": {"rectify": computed, "disparity": {**computed, "inputs_digest": "d"}},
        "acceptance": {
            "decided_at": "2026-11-27T11:00:00+00:00",
            "accepted_results": {"rectify": computed, "disparity": {**computed, "inputs_digest": "d"}},
            "inputs_now": {"rectify": "a", "disparity": "d"},
        },
    }
    stale = json.loads(json.dumps(sound)) | {"key": "card_000002"}
    stale["acceptance"]["inputs_now"]["rectify"] = "b"  # the decisions moved on: swapped eyes
    early = json.loads(json.dumps(sound)) | {"key": "card_000003"}
    early["acceptance"]["decided_at"] = "2026-11-27T09:00:00+00:00"
    other = json.loads(json.dumps(sound)) | {"key": "card_000004"}
    other["acceptance"]["accepted_results"]["rectify"]["computed_at"] = "2026-11-27T08:00:00+00:00"
    legacy = {"key": "card_000005", "pipeline": {"rectify": computed}}  # released before acceptances were recorded
    cards = tmp_path / "cards.jsonl"
    cards.write_text("\n".join(json.dumps(record) for record in (sound, stale, early, other, legacy)) + "\n")
    report = VerifyReport(str(tmp_path))
    check_released_cards(cards, report)
    found = [problem["problem"] for problem in report.problems]
    assert len(found) == 4, found
    assert found[0].startswith("card card_000002: its released rectify was computed from other decisions")
    assert found[1].startswith("card card_000003: its acceptance (2026-11-27T09:00:00+00:00) predates its released rectify")
    assert found[2].startswith("card card_000003: its acceptance (2026-11-27T09:00:00+00:00) predates its released disparity")
    assert found[3].startswith("card card_000004: its acceptance was given another rectify result")


def test_a_ruling_not_a_stereo_pair_withdraws_the_card_from_the_flow_and_the_release(  # type: ignore[no-untyped-def]
    app, make_card, add_stage_result, make_person, data_dir
) -> None:
    from annotation.models import Aggregate, Batch
    from core.db import db
    from core.models import Card
    from exports.catalogue import stream_release_cards
    from review.tasks import ReviewError, decide, resolve_aggregate, sync_reviews
    from runs.card_state import card_states

    card = make_card()
    add_stage_result(card, "filter")
    for stage in ("rectify", "disparity"):
        add_stage_result(card, stage, outcome=None)
    add_stage_result(card, "grade", outcome="few", metrics={"uncertainty": 0.2, "reasons": ["clean"]})
    curator = _curator(app, make_person)
    with app.app_context():
        sync_reviews([card])
        batch = Batch(kind="judge")
        db.session.add(batch)
        db.session.flush()
        dispute = Aggregate(
            batch_id=batch.id, card_id=card, kind="judge", label={}, state="needs_curator", reasons="split", answers=3
        )
        db.session.add(dispute)
        db.session.commit()
        resolve_aggregate(
            dispute.id,
            {"is_stereo": False, "upside_down": False, "inverted": False, "swapped": False},
            curator=curator,
            note="two different photographs",
        )
        review = _review(card)
        assert (review.decision, review.grade) == ("rejected", None)
        assert review.note == f"withdrawn: ruled not a stereo pair on dispute {dispute.id}"
        state = card_states([db.session.get(Card, card)])[card]
        why = f"it was judged not a stereo pair by a curator's ruling on dispute {dispute.id}"
        assert state.withdrawn == why and state.blockers == [why] and state.waiting_for == ()
        for stage in ("rectify", "disparity", "grade"):
            assert state.statuses[stage]["stale_reason"] == f"withdrawn: {why}"
        assert state.sentence == (
            f"This card has left the flow: {why}, so it is not rectified, graded, accepted or released; "
            "its earlier rectify, disparity, grade are withdrawn."
        )
        with pytest.raises(ReviewError) as refused:
            decide(review.id, "change", expected_version=review.version, curator=curator, grade="few")
        assert refused.value.status == 409 and why in refused.value.message
        # even if someone set it accepted by hand, no release takes it
        review.decision, review.grade = "accepted", "few"
        db.session.commit()
        left_out: list[Any] = []
        assert list(stream_release_cards([card], data_dir, left_out)) == []
        assert [(row.card_id, row.reason) for row in left_out] == [(card, why)]


def test_the_worker_runs_a_round_when_people_decide_and_not_when_nothing_changed(  # type: ignore[no-untyped-def]
    app, two_cards, make_person, data_dir
) -> None:
    from core.db import db
    from review.orientation import override_orientation
    from runs.claims import Driver
    from runs.worker import BackgroundWorker, PipelineWorker, live_workers

    curator = _curator(app, make_person)
    with app.app_context():
        driver = Driver(db.engine)
        rounds: list[Any] = []
        worker = BackgroundWorker(
            STAGES.split(","), None, driver, data_dir, poll_s=0.2, full_every_s=3600, on_round=rounds.append
        )
        thread_app = app

        def run() -> None:
            with thread_app.app_context(), driver.running():
                worker.run()

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        try:
            _until(lambda: len(rounds) >= 1, 180)
            assert rounds[0].trigger == "start" and rounds[0].computed == 6
            assert [row.id for row in live_workers()] == [driver.id]
            time.sleep(1.0)  # five polls with nothing decided: no round
            assert len(rounds) == 1
            override_orientation(
                two_cards[0], {"upside_down": "no", "inverted": "no", "swapped": "yes"}, curator=curator, note="eyes exchanged"
            )
            _until(lambda: len(rounds) >= 2, 180)
            assert rounds[1].trigger == "decisions"
            assert {stage["stage"]: stage["processed"] for stage in rounds[1].stages} == {
                "rectify": 1,
                "disparity": 1,
                "grade": 1,
            }
        finally:
            worker.stop.set()
            thread.join(60)
        db.session.expire_all()
        assert db.session.scalars(select(PipelineWorker)).all() == []  # gone with the worker


def _until(condition: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_a_round_keeps_optional_views_fresh_only_on_the_cards_that_have_them(app, make_card, add_stage_result) -> None:  # type: ignore[no-untyped-def]
    from runs.worker import optional_stages_to_refresh

    with_views, without = make_card(), make_card(image=_motorcycle(0))
    with app.app_context():
        assert optional_stages_to_refresh(STAGES.split(",")) == {}  # nobody computed views: none are started
    add_stage_result(with_views, "views", outcome=None)
    with app.app_context():
        assert optional_stages_to_refresh(STAGES.split(",")) == {"views": {without}}
        assert optional_stages_to_refresh([*STAGES.split(","), "views"]) == {}  # named: run as asked


def test_a_stale_card_a_driver_holds_says_it_is_being_recomputed(app, runner, two_cards, decide_orientation) -> None:  # type: ignore[no-untyped-def]
    from datetime import timedelta

    from core.db import db, utcnow
    from core.models import Card
    from runs.card_state import card_states
    from runs.claims import StageClaim

    _worker_once(runner)
    card = two_cards[0]
    decide_orientation([card], swapped=True)
    with app.app_context():
        now = utcnow()
        for stage, expires in (("rectify", now + timedelta(seconds=60)), ("disparity", now - timedelta(seconds=1))):
            db.session.add(
                StageClaim(
                    card_id=card,
                    stage=stage,
                    param_hash="p",
                    driver="host:1:abc",
                    claimed_at=now,
                    heartbeat_at=now,
                    expires_at=expires,
                )
            )
        db.session.commit()
        state = card_states([db.session.get(Card, card)])[card]
        assert state.recomputing == ("rectify",)  # the lapsed claim on disparity belongs to a dead driver
        assert state.statuses["rectify"]["recomputing"] is True and "recomputing" not in state.statuses["disparity"]
        assert state.sentence.endswith(": a pipeline worker is recomputing its rectify now.")
        assert state.blockers[0].endswith("; it is being recomputed now")


def test_a_round_that_raises_does_not_end_the_worker(app, two_cards, data_dir, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import runs.worker as worker_module
    from core.db import db
    from runs.claims import Driver
    from runs.worker import BackgroundWorker

    real = worker_module.run_round
    calls: list[str] = []

    def flaky(trigger: str, *args: Any, **kwargs: Any) -> Any:
        calls.append(trigger)
        if len(calls) == 1:
            raise RuntimeError("database is locked")
        return real(trigger, *args, **kwargs)

    monkeypatch.setattr(worker_module, "run_round", flaky)
    with app.app_context():
        driver = Driver(db.engine)
        rounds: list[Any] = []
        worker = BackgroundWorker(
            STAGES.split(","), None, driver, data_dir, poll_s=0.1, full_every_s=3600, on_round=rounds.append
        )

        def stop_after_a_round(done: Any) -> None:
            rounds.append(done)
            worker.stop.set()

        worker.on_round = stop_after_a_round
        with driver.running():
            worker.run()
    assert worker.failures == ["RuntimeError: database is locked"]
    assert calls == ["start", "start"] and rounds[0].computed == 6  # tried again, as a first round


def test_a_stop_in_the_middle_of_a_commit_still_removes_the_worker_row(app, data_dir, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """SIGTERM becomes SystemExit wherever the worker is, a commit included, which leaves the
    session unusable ("in 'committed' state"): the worker still leaves without a traceback of its
    own and takes its row with it (seen once on a loaded machine as a traceback at serve's stop)."""
    from sqlalchemy import select
    from sqlalchemy.exc import InvalidRequestError

    from core.db import db
    from runs.claims import Driver
    from runs.worker import BackgroundWorker, PipelineWorker

    with app.app_context():
        driver = Driver(db.engine)
        worker = BackgroundWorker(STAGES.split(","), None, driver, data_dir, poll_s=0.1, full_every_s=3600)
        real_rollback = db.session.rollback

        def broken_rollback() -> None:
            monkeypatch.setattr(db.session, "rollback", real_rollback)  # once: as after the interrupted commit
            raise InvalidRequestError("This session is in 'committed' state; no further SQL can be emitted")

        try:
            with worker.registered():
                assert len(db.session.scalars(select(PipelineWorker)).all()) == 1
                monkeypatch.setattr(db.session, "rollback", broken_rollback)
                raise SystemExit(0)
        except SystemExit:
            pass
        assert db.session.scalars(select(PipelineWorker)).all() == []

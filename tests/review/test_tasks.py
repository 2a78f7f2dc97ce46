"""Curator review use cases: syncing with the grader, the queue, decisions with optimistic
locking, bulk decisions, disputed crowd answers, gold, and the append-only audit trail."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from sqlalchemy import func, select, text
from sqlalchemy.exc import DatabaseError

# (automatic grade, uncertainty, reasons) for five cards; the queue sorts by uncertainty.
GRADED = [
    ("few", 0.20, ["sharp disparity"]),
    ("some", 0.90, ["vertical misalignment 2.1 px", "low confidence 41 %"]),
    ("failure", None, ["disparity coverage 12 %"]),
    ("some", 0.90, ["Low confidence 38 %"]),
    ("failure", 0.55, ["100% of matches on one plane_x"]),
]


@pytest.fixture
def graded(app, make_card, add_stage_result, card_image, decide_orientation) -> list[int]:  # type: ignore[no-untyped-def]
    ids = []
    for index, (grade, uncertainty, reasons) in enumerate(GRADED):
        collection = "east" if index % 2 == 0 else "west"
        card_id = make_card(card_image()[:, index:], state="pass", collection=collection)
        metrics: dict[str, Any] = {"reasons": reasons, "deciding": ["coverage"], "coverage": 0.8}
        if uncertainty is not None:
            metrics["uncertainty"] = uncertainty
        add_stage_result(card_id, "grade", outcome=grade, reason="; ".join(reasons), metrics=metrics)
        ids.append(card_id)
    decide_orientation(ids)  # the flow rule: only cards whose orientation is decided can be accepted
    return ids


@pytest.fixture
def synced(app, graded) -> list[int]:  # type: ignore[no-untyped-def]
    from review.tasks import sync_reviews

    with app.app_context():
        sync_reviews()
    return graded


@pytest.fixture
def person(app, make_person) -> Callable[..., Any]:  # type: ignore[no-untyped-def]
    """A curator as a detached Person row, as views pass ``current_user``."""
    from core.db import db
    from core.models import Person

    def make(name: str) -> Any:
        info = make_person("curator", username=name)
        with app.app_context():
            row = db.session.get(Person, info.id)
            db.session.expunge(row)
            return row

    return make


def review_of(card_id: int) -> Any:
    from core.db import db
    from review.models import CardReview

    db.session.expire_all()
    return db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))


def events(card_id: int | None = None, entity: str | None = None) -> list[Any]:
    from core.audit import AuditEvent
    from core.db import db

    query = select(AuditEvent).order_by(AuditEvent.id)
    if card_id is not None:
        query = query.where(AuditEvent.card_id == card_id)
    if entity is not None:
        query = query.where(AuditEvent.entity == entity)
    return list(db.session.scalars(query))


# ------------------------------------------------------------------------------------- sync


@pytest.mark.both_databases
def test_sync_creates_one_review_per_graded_card_and_is_idempotent(app, graded, make_card, card_image) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import sync_reviews

    ungraded = make_card(card_image()[:, 9:], state="pass")
    with app.app_context():
        first = sync_reviews()
        assert first.as_json() == {"created": 5, "updated": 0, "reopened": 0, "decided_changed": 0, "unchanged": 0}
        second = sync_reviews()
        assert second.as_json() == {"created": 0, "updated": 0, "reopened": 0, "decided_changed": 0, "unchanged": 5}
        assert review_of(ungraded) is None
        review = review_of(graded[1])
        assert (review.auto_grade, review.uncertainty, review.decision, review.grade, review.version) == (
            "some",
            0.9,
            "pending",
            None,
            1,
        )
        assert review_of(graded[2]).uncertainty is None
        created = events(entity="grade")
        assert [e.action for e in created] == ["graded"] * 5 and {e.actor for e in created} == {"pipeline"}
        assert created[1].after["auto_grade"] == "some"
        assert created[1].why == "vertical misalignment 2.1 px; low confidence 41 %"


def test_a_new_automatic_grade_updates_pending_cards_but_never_a_decided_grade(app, synced, add_stage_result, person) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import decide, sync_reviews

    curator = person("carol")
    pending, decided = synced[0], synced[1]
    with app.app_context():
        review = review_of(decided)
        decide(review.id, "change", expected_version=review.version, curator=curator, grade="failure")
    # New grader thresholds: a new parameter hash, new outcomes.
    add_stage_result(
        pending,
        "grade",
        outcome="some",
        param_hash="feedfacefeedface",
        metrics={"uncertainty": 0.4, "reasons": ["more blur"]},
        reason="more blur",
    )
    add_stage_result(
        decided,
        "grade",
        outcome="few",
        param_hash="feedfacefeedface",
        metrics={"uncertainty": 0.1, "reasons": ["fine"]},
        reason="fine",
    )
    with app.app_context():
        report = sync_reviews()
        assert (report.updated, report.decided_changed, report.unchanged) == (1, 1, 3)
        moved = review_of(pending)
        assert (moved.auto_grade, moved.auto_param_hash, moved.uncertainty, moved.decision) == (
            "some",
            "feedfacefeedface",
            0.4,
            "pending",
        )
        kept = review_of(decided)
        assert (kept.decision, kept.grade, kept.auto_grade) == ("changed", "failure", "few")
        (changed,) = [e for e in events(decided, "grade") if e.action == "auto_grade_changed_after_decision"]
        assert changed.before["auto_grade"] == "some" and changed.after["auto_grade"] == "few"
        assert changed.after["grade"] == "failure"
        (updated,) = [e for e in events(pending, "grade") if e.action == "auto_grade_changed"]
        assert (updated.before["auto_grade"], updated.after["auto_grade"], updated.why) == ("few", "some", "more blur")
        assert sync_reviews().unchanged == 5


# ------------------------------------------------------------------------------------- queue


def test_queue_sorts_by_uncertainty_then_card_and_filters(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Collection
    from review.tasks import (
        QueueFilters,
        ReviewError,
        decide,
        queue_neighbours,
        review_queue,
    )

    a, b, c, d, e = synced
    curator = person("carol")
    with app.app_context():
        page = review_queue()
        assert page.total == 5
        assert [row.card_id for row in page.rows] == [b, d, e, a, c]  # 0.9, 0.9, 0.55, 0.2, unknown
        assert page.rows[0].reasons == ["vertical misalignment 2.1 px", "low confidence 41 %"]
        assert [r.card_id for r in review_queue(grade="some").rows] == [b, d]
        assert [r.card_id for r in review_queue(reason="LOW CONF").rows] == [b, d]
        assert [r.card_id for r in review_queue(reason="100%").rows] == [e]  # % is literal
        assert review_queue(reason="1_0").total == 0  # so is _
        east = db.session.scalar(select(Collection.id).where(Collection.name == "east"))
        assert [r.card_id for r in review_queue(collection_id=east).rows] == [e, a, c]
        second = review_queue(limit=2, offset=2)
        assert ([r.card_id for r in second.rows], second.total) == ([e, a], 5)
        assert queue_neighbours(d, QueueFilters()) == (b, e)
        assert queue_neighbours(a, QueueFilters()) == (e, c)
        assert queue_neighbours(c, QueueFilters()) == (a, None)
        assert queue_neighbours(b, QueueFilters()) == (None, d)
        with pytest.raises(ReviewError, match="Unknown grade 'great'"):
            review_queue(grade="great")
        with pytest.raises(ReviewError, match="limit"):
            review_queue(limit=0)
        review = review_of(d)
        decide(review.id, "accept", expected_version=review.version, curator=curator)
        assert [r.card_id for r in review_queue().rows] == [b, e, a, c]
        assert [r.card_id for r in review_queue(decision="accepted").rows] == [d]
        assert review_queue(decision="all").total == 5
        # The decided card has left the queue; its neighbours are still where they were.
        assert queue_neighbours(d, QueueFilters()) == (b, e)


# ------------------------------------------------------------------------------------- decisions


@pytest.mark.both_databases
def test_accept_change_and_reject_set_the_grade_and_write_before_and_after(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Card
    from review.tasks import decide
    from runs.card_state import results_fingerprint

    curator = person("carol")
    with app.app_context():
        first, second, third = (review_of(card) for card in synced[:3])
        accepted = decide(first.id, "accept", expected_version=1, curator=curator, note="looks right")
        assert (accepted.decision, accepted.grade, accepted.version) == ("accepted", "few", 2)
        changed = decide(second.id, "change", expected_version=1, curator=curator, grade="failure", note="eyes swapped")
        assert (changed.decision, changed.grade) == ("changed", "failure")
        rejected = decide(third.id, "reject", expected_version=1, curator=curator, note="a card back")
        assert (rejected.decision, rejected.grade) == ("rejected", None)
        # A "change" to the automatic grade itself is an accept: the grader was right.
        same = decide(second.id, "change", expected_version=2, curator=curator, grade="some")
        assert (same.decision, same.grade, same.version) == ("accepted", "some", 3)

        stored = review_of(synced[1])
        assert (stored.decision, stored.grade, stored.reviewer_id, stored.version) == ("accepted", "some", curator.id, 3)
        assert stored.decided_at is not None
        trail = events(synced[1], "review")
        assert [e.action for e in trail] == ["change", "change"]
        assert trail[0].before == {
            "decision": "pending",
            "grade": None,
            "auto_grade": "some",
            "note": "",
            "reviewer_id": None,
            "version": 1,
            "accepted_results": None,
        }
        # the decision is given the results the card has (these cards have a grade only; the
        # loop's own tests in tests/runs/test_card_state.py give them a rectification)
        given = results_fingerprint(db.session.get(Card, synced[1]).latest_results())
        assert trail[0].after == {
            "decision": "changed",
            "grade": "failure",
            "auto_grade": "some",
            "note": "eyes swapped",
            "reviewer_id": curator.id,
            "version": 2,
            "accepted_results": given,
        }
        assert stored.accepted_results == given
        assert (trail[0].actor, trail[0].actor_id, trail[0].why) == ("carol", curator.id, "eyes swapped")
        assert trail[1].before["grade"] == "failure" and trail[1].after["grade"] == "some"
        assert events(synced[2], "review")[0].after["grade"] is None


def test_a_stale_version_is_a_conflict_that_names_who_and_when(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import ReviewConflict, decide

    alice, bob = person("alice"), person("bob")
    with app.app_context():
        review = review_of(synced[0])
        decide(review.id, "change", expected_version=1, curator=alice, grade="some")
        with pytest.raises(ReviewConflict) as caught:
            decide(review.id, "reject", expected_version=1, curator=bob)
        conflict = caught.value
        assert conflict.status == 409 and conflict.changed_by == "alice" and conflict.current_version == 2
        assert f"Card {synced[0]} was changed by alice at " in conflict.message
        assert f"{conflict.changed_at:%Y-%m-%d %H:%M:%S} UTC" in conflict.message
        assert "you saw version 1, it is now version 2: changed, grade some artifacts" in conflict.message
        stored = review_of(synced[0])
        assert (stored.decision, stored.grade, stored.version) == ("changed", "some", 2)
        assert len(events(synced[0], "review")) == 1  # the refused decision left no trace but the conflict


def test_bad_input_is_refused_and_changes_nothing(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import ReviewError, decide

    curator = person("carol")
    with app.app_context():
        review = review_of(synced[0])
        cases = [
            ({"action": "approve"}, "Unknown action 'approve'"),
            ({"action": "change"}, "Expected a grade from few, some, failure"),
            ({"action": "change", "grade": "great"}, "got 'great'"),
            ({"action": "send_back", "kind": "paint"}, "crop or judge"),
            ({"action": "accept", "note": "x" * 2001}, "at most 2000 characters"),
        ]
        for kwargs, message in cases:
            with pytest.raises(ReviewError, match=message):
                decide(review.id, expected_version=1, curator=curator, **kwargs)
        with pytest.raises(ReviewError, match="no review 999") as missing:
            decide(999, "accept", expected_version=1, curator=curator)
        assert missing.value.status == 404
        assert review_of(synced[0]).version == 1 and events(synced[0], "review") == []


def test_send_back_puts_the_card_in_a_crowd_batch_with_curator_gold(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Batch, BatchItem, GoldAnswer
    from core.db import db
    from review.tasks import decide

    curator = person("carol")
    with app.app_context():
        # synced[4] is 600 px wide; synced[3]'s gold box no longer fits it and is left out.
        db.session.add(
            GoldAnswer(
                card_id=synced[4], kind="crop", made_by=curator.id, answer={"left": [0, 0, 290, 200], "right": [306, 0, 596, 200]}
            )
        )
        db.session.add(
            GoldAnswer(
                card_id=synced[3], kind="crop", made_by=curator.id, answer={"left": [0, 0, 290, 200], "right": [306, 0, 900, 200]}
            )
        )
        db.session.commit()
        review = review_of(synced[0])
        decided = decide(review.id, "send_back", expected_version=1, curator=curator, note="boxes cut the sky")
        assert decided.decision == "sent_back" and decided.batch_id is not None
        batch = db.session.get(Batch, decided.batch_id)
        assert (batch.kind, batch.answers_per_item, batch.created_by) == ("crop", 3, curator.id)
        items = {(i.card_id, i.is_gold) for i in db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch.id))}
        assert items == {(synced[0], False), (synced[4], True)}
        assert review_of(synced[0]).grade is None
        review_event, batch_event = [e for e in events(synced[0]) if e.entity in ("review", "batch")]
        assert (review_event.action, review_event.after["sent_to"], review_event.why) == (
            "send_back",
            "crop",
            "boxes cut the sky",
        )
        assert batch_event.after == {"batch": batch.id, "kind": "crop", "answers_per_item": 3, "gold_items": [synced[4]]}
        # A judge send-back without gold answers of that kind has no gold items.
        other = review_of(synced[1])
        judged = decide(other.id, "send_back", expected_version=1, curator=curator, kind="judge")
        assert db.session.get(Batch, judged.batch_id).kind == "judge"
        assert (
            db.session.scalar(
                select(func.count())
                .select_from(BatchItem)
                .where(BatchItem.batch_id == judged.batch_id, BatchItem.is_gold.is_(True))
            )
            == 0
        )


def test_a_sent_back_card_graded_again_returns_to_the_queue(app, synced, add_stage_result, person) -> None:  # type: ignore[no-untyped-def]
    from datetime import timedelta

    from core.db import db, utcnow
    from core.models import StageResult
    from review.tasks import decide, review_queue, sync_reviews

    curator = person("carol")
    with app.app_context():
        review = review_of(synced[0])
        decide(review.id, "send_back", expected_version=1, curator=curator)
        assert synced[0] not in [r.card_id for r in review_queue().rows]
        assert sync_reviews().reopened == 0  # nothing new from the grader yet
        # The crowd redid the boxes; rectify, disparity and grade reran with the same parameters.
        result = db.session.scalar(select(StageResult).where(StageResult.card_id == synced[0], StageResult.stage == "grade"))
        result.started_at, result.outcome = utcnow() + timedelta(seconds=1), "some"
        db.session.commit()
        assert sync_reviews().reopened == 1
        back = review_of(synced[0])
        assert (back.decision, back.auto_grade, back.grade) == ("pending", "some", None)
        assert synced[0] in [r.card_id for r in review_queue().rows]
        assert events(synced[0], "grade")[-1].action == "regraded_after_send_back"


@pytest.mark.both_databases
def test_bulk_decisions_go_on_past_a_conflict(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import bulk_decide, decide

    alice, bob = person("alice"), person("bob")
    with app.app_context():
        reviews = [review_of(card) for card in synced[:3]]
        decide(reviews[1].id, "reject", expected_version=1, curator=alice)  # bob's page is now stale for this one
        outcomes = bulk_decide(
            [(r.id, 1) for r in reviews] + [(999, 1)], "change", curator=bob, grade="failure", note="bulk: all blurred"
        )
        assert [o.status for o in outcomes] == ["applied", "conflict", "applied", "error"]
        assert "was changed by alice" in outcomes[1].message and "no review 999" in outcomes[3].message
        assert outcomes[0].as_json()["grade"] == "failure"
        assert [(review_of(c).decision, review_of(c).grade) for c in synced[:3]] == [
            ("changed", "failure"),
            ("rejected", None),
            ("accepted", "failure"),
        ]  # the third was graded failure
        assert [e.actor for e in events(entity="review")] == ["alice", "bob", "bob"]


# ------------------------------------------------------------------------------------- audit


@pytest.mark.both_databases
def test_audit_events_cannot_be_changed_or_deleted(app, synced) -> None:  # type: ignore[no-untyped-def]
    from core.audit import AuditEvent, AuditTamperError
    from core.db import db

    with app.app_context():
        event = db.session.scalar(select(AuditEvent).order_by(AuditEvent.id).limit(1))
        event.why = "rewritten"
        with pytest.raises(AuditTamperError, match="append-only"):
            db.session.commit()
        db.session.rollback()
        db.session.delete(db.session.get(AuditEvent, event.id))
        with pytest.raises(AuditTamperError):
            db.session.flush()
        db.session.rollback()
        for statement in ("UPDATE audit_events SET why = 'rewritten'", "DELETE FROM audit_events"):
            with pytest.raises(DatabaseError, match="append-only"):
                db.session.execute(text(statement))
            db.session.rollback()
        assert db.session.scalar(select(func.count()).select_from(AuditEvent)) == 5
        assert db.session.scalar(select(func.count()).select_from(AuditEvent).where(AuditEvent.why == "rewritten")) == 0


def test_card_history_is_oldest_first(app, synced, person) -> None:  # type: ignore[no-untyped-def]
    from review.tasks import card_history, decide

    curator = person("carol")
    with app.app_context():
        review = review_of(synced[0])
        decide(review.id, "accept", expected_version=1, curator=curator)
        decide(review.id, "reject", expected_version=2, curator=curator, note="a duplicate")
        history = card_history(synced[0])
        assert [(e.entity, e.action) for e in history] == [("grade", "graded"), ("review", "accept"), ("review", "reject")]
        assert history[2].before["decision"] == "accepted" and history[2].after["decision"] == "rejected"
        assert card_history(synced[1])[0].card_id == synced[1] and len(card_history(synced[1])) == 1


# ------------------------------------------------------------------------------------- disputes


@pytest.fixture
def disputed(app, make_card, card_image, decide_orientation) -> dict[str, int]:  # type: ignore[no-untyped-def]
    """Two aggregates waiting for a curator: a judge one and a crop one."""
    from annotation.batches import create_batch
    from annotation.models import Aggregate
    from core.db import db

    cards = [make_card(card_image()[:, 20 + i :], state="review") for i in range(2)]
    decide_orientation(cards)
    with app.app_context():
        judge, crop = create_batch([cards[0]], "judge", 3, 0.0), create_batch([cards[1]], "crop", 3, 0.0)
        rows = {
            "judge": Aggregate(
                batch_id=judge.id,
                card_id=cards[0],
                kind="judge",
                state="needs_curator",
                label={"is_stereo": True, "upside_down": False, "inverted": False},
                posterior={"is_stereo": [0.45, 0.55]},
                reasons="is_stereo: posterior 0.55 < 0.9",
                answers=3,
            ),
            "crop": Aggregate(
                batch_id=crop.id,
                card_id=cards[1],
                kind="crop",
                state="needs_curator",
                label={"left": [2, 3, 280, 190], "right": [300, 3, 590, 190]},
                reasons="left box: mean IoU 0.41 < 0.7",
                answers=3,
            ),
        }
        db.session.add_all(rows.values())
        db.session.commit()
        return {kind: row.id for kind, row in rows.items()} | {"judge_card": cards[0], "crop_card": cards[1]}


@pytest.mark.both_databases
def test_resolving_a_disputed_judgement_makes_it_truth_and_gold(app, disputed, person) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, GoldAnswer
    from core.db import db
    from review.tasks import ReviewConflict, disputed_aggregates, resolve_aggregate

    carol, dave = person("carol"), person("dave")
    with app.app_context():
        rows, total = disputed_aggregates()
        assert total == 2 and [r.id for r in rows] == [disputed["judge"], disputed["crop"]]
        label = {"is_stereo": True, "upside_down": True, "inverted": False}
        resolved = resolve_aggregate(disputed["judge"], label, curator=carol, make_gold=True, note="sky at the bottom")
        assert resolved.label == label and resolved.gold_id is not None
        db.session.expire_all()
        aggregate = db.session.get(Aggregate, disputed["judge"])
        assert (aggregate.state, aggregate.label, aggregate.resolved_by) == ("approved", label, carol.id)
        gold = db.session.get(GoldAnswer, resolved.gold_id)
        assert (gold.card_id, gold.kind, gold.answer, gold.made_by) == (disputed["judge_card"], "judge", label, carol.id)
        agg_event, gold_event = events(disputed["judge_card"])
        assert (agg_event.entity, agg_event.before["state"], agg_event.after["state"]) == (
            "aggregate",
            "needs_curator",
            "approved",
        )
        assert agg_event.before["label"]["upside_down"] is False and agg_event.after["label"]["upside_down"] is True
        assert (gold_event.entity, gold_event.action, gold_event.after["answer"]) == ("gold", "made_gold", label)
        assert disputed_aggregates()[1] == 1
        with pytest.raises(ReviewConflict, match="already resolved by carol"):
            resolve_aggregate(disputed["judge"], label, curator=dave)


def test_resolving_a_crop_checks_the_boxes_and_can_skip_gold(app, disputed, person) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, GoldAnswer
    from core.db import db
    from review.tasks import ReviewError, resolve_aggregate

    carol = person("carol")
    with app.app_context():
        for label, message in [
            ({"left": [0, 0, 280, 190], "right": [300, 0, 9000, 190]}, "right box is refused"),
            ({"left": [0, 0, 280, 190]}, "right box as four numbers"),
            ({"left": [0, 0, 280, 190], "right": [300, 0, 590, 190], "extra": 1}, "Unexpected fields"),
        ]:
            with pytest.raises(ReviewError, match=message):
                resolve_aggregate(disputed["crop"], label, curator=carol, make_gold=True)
        assert db.session.get(Aggregate, disputed["crop"]).state == "needs_curator"
        resolved = resolve_aggregate(disputed["crop"], {"left": [1, 2, 281.5, 190], "right": [300, 2, 580, 190]}, curator=carol)
        assert resolved.gold_id is None and resolved.label["left"] == [1.0, 2.0, 281.5, 190.0]
        assert db.session.scalar(select(func.count()).select_from(GoldAnswer)) == 0
        assert [e.entity for e in events(disputed["crop_card"])] == ["aggregate"]


@pytest.mark.both_databases
def test_accept_is_refused_while_the_cards_judgement_or_crop_is_disputed(app, disputed, person, add_stage_result):
    from review.tasks import ReviewError, decide, resolve_aggregate, sync_reviews

    carol = person("carol")
    card = disputed["judge_card"]
    add_stage_result(card, "grade", outcome="few", metrics={"uncertainty": 0.2, "reasons": ["clean"]})
    with app.app_context():
        sync_reviews([card])
        review = review_of(card)
        for action, grade in (("accept", None), ("change", "some")):
            with pytest.raises(
                ReviewError,
                match=r"cannot be accepted while the crowd disagrees on its judgement "
                rf"\(batch \d+, dispute {disputed['judge']}\)",
            ) as refused:
                decide(review.id, action, expected_version=review.version, curator=carol, grade=grade)
            assert refused.value.status == 409
        assert review_of(card).decision == "pending" and events(card, "review") == []
        # rejecting or sending back stays possible: neither releases the card
        resolve_aggregate(disputed["judge"], {"is_stereo": True, "upside_down": True, "inverted": False}, curator=carol)
        review = review_of(card)
        decided = decide(review.id, "accept", expected_version=review.version, curator=carol)
        assert (decided.decision, decided.grade) == ("accepted", "few")

"""runs/card_state.py: where a card stands (statuses, what it waits for, stale results, the
sentence), and that the pages, the CLI, the review gate and the release plan give its answer."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from sqlalchemy import event, select
from sqlalchemy.orm import selectinload

FLAGS = ("upside_down", "inverted", "swapped")
SURE = {flag: {"p": 0.02, "decided": True, "value": False, "evidence": []} for flag in FLAGS}
UNSURE_SWAP = {**SURE, "swapped": {"p": 0.6, "decided": False, "value": None, "evidence": []}}


def _states(app, *card_ids: int) -> dict[int, Any]:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Card
    from runs.card_state import card_states

    with app.app_context():
        cards = list(
            db.session.scalars(
                select(Card).where(Card.id.in_(card_ids)).order_by(Card.id).options(selectinload(Card.stage_results))
            )
        )
        return card_states(cards)


def _passed(make_card, add_stage_result, image, *, decided: bool = True, state: str = "pass") -> int:  # type: ignore[no-untyped-def]
    card = make_card(image)
    add_stage_result(card, "filter", outcome=state)
    flags = SURE if decided else UNSURE_SWAP
    add_stage_result(
        card,
        "orientation",
        outcome="auto" if decided else "ask",
        metrics={"flags": flags, "confidence": 0.98 if decided else 0.6},
    )
    return card


def _with_current_inputs(app, add_stage_result, card_id: int, stage: str, **kwargs: Any) -> int:  # type: ignore[no-untyped-def]
    """A finished result of ``stage`` whose recorded inputs digest is the digest of the inputs
    the stage builds now, as ``keystone run`` records it; for rectify also the orientation and
    boxes it used."""
    from core.db import db
    from core.hooks import approved_decisions
    from core.models import Card
    from pipeline.records import inputs_digest
    from runs.specs import available_stages

    with app.app_context():
        card = db.session.get(Card, card_id)
        inputs = dict(available_stages()[stage].inputs(card, approved_decisions([card_id]).get(card_id, {})))
    metrics = {**kwargs.pop("metrics", {}), "inputs_digest": inputs_digest(inputs)}
    if stage == "rectify":
        metrics |= {"orientation_used": {flag: inputs[flag] for flag in FLAGS}, "box_source": inputs["box_source"]}
    return add_stage_result(card_id, stage, outcome=kwargs.pop("outcome", None), metrics=metrics, **kwargs)


def _graded(app, make_card, add_stage_result, image) -> int:  # type: ignore[no-untyped-def]
    card = _passed(make_card, add_stage_result, image)
    _with_current_inputs(app, add_stage_result, card, "rectify")
    add_stage_result(card, "disparity", outcome=None)
    add_stage_result(card, "grade", outcome="few", metrics={"uncertainty": 0.2, "reasons": ["clean"]})
    return card


def _aggregate(app, card_id: int, *, state: str, label: dict[str, Any] | None = None, kind: str = "judge") -> tuple[int, int]:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, Batch
    from core.db import db

    with app.app_context():
        batch = Batch(kind=kind)
        db.session.add(batch)
        db.session.flush()
        row = Aggregate(
            batch_id=batch.id,
            card_id=card_id,
            kind=kind,
            label=label or {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": False},
            state=state,
            reasons="upside_down posterior 0.55 < 0.9" if state == "needs_curator" else "",
            answers=3,
        )
        db.session.add(row)
        db.session.commit()
        return batch.id, row.id


# ----------------------------------------------------------------------------- what it waits for


def test_an_undecided_orientation_is_what_the_card_waits_for_on_every_page(
    app, client, login, make_card, add_stage_result, card_image
) -> None:  # type: ignore[no-untyped-def]
    card = _passed(make_card, add_stage_result, card_image(), decided=False)
    state = _states(app, card)[card]
    reason = "its orientation is undecided (waiting for people (the orientation step is not sure of swapped))"
    assert [(w.kind, w.subject, w.reason) for w in state.waiting_for] == [("decision", "orientation", reason)]
    assert state.blockers == [reason]
    assert state.statuses["rectify"]["status"] == "pending" and "undecided" in state.statuses["rectify"]["reason"]
    assert state.sentence == (
        f"This card waits for people: {reason}, and it is not rectified, graded, accepted or released until it is decided."
    )
    assert state.stale == {}
    # The curator's page used to say "waiting for its rectify stage": its stage list left out orientation.
    login("curator")
    for url in (f"/review/cards/{card}", f"/cards/{card}"):
        page = client.get(url).get_data(as_text=True)
        assert "This card waits for people: its orientation is undecided" in page, url
        assert "waiting for its rectify stage" not in page, url


def test_a_card_without_an_orientation_result_waits_for_the_orientation_stage(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    card = make_card(card_image())
    add_stage_result(card, "filter", outcome="pass")
    state = _states(app, card)[card]
    assert [(w.kind, w.subject) for w in state.waiting_for] == [("stage", "orientation")]
    assert state.sentence == "This card is not graded yet: it is waiting for its orientation stage."
    assert state.blockers == ["its orientation is undecided (waiting for the orientation step (not run yet))"]


def test_filter_review_waits_for_the_crowd_and_a_dispute_for_a_curator(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    from core.db import db
    from runs.card_state import waiting_for_people

    image = card_image()
    review = _passed(make_card, add_stage_result, image[:, 1:], state="review")
    disputed = _passed(make_card, add_stage_result, image[:, 2:], state="review")
    asked = _passed(make_card, add_stage_result, image[:, 3:], decided=False)
    crop_disputed = _passed(make_card, add_stage_result, image[:, 4:], decided=False)
    batch, dispute = _aggregate(app, disputed, state="needs_curator")
    crop_batch, crop_dispute = _aggregate(
        app, crop_disputed, state="needs_curator", kind="crop", label={"left": [0, 0, 280, 190], "right": [300, 0, 580, 190]}
    )
    states = _states(app, review, disputed, asked, crop_disputed)

    assert [(w.kind, w.subject) for w in states[review].waiting_for] == [("crowd", "judge")]
    assert states[review].sentence == (
        "The filter sent this card to review: it is waiting for the crowd's judgement of whether it is a stereo pair."
    )
    assert states[review].blockers == []
    assert states[review].statuses["judge"]["status"] == "pending"

    wait = f"the crowd disagrees on its judgement (batch {batch}, dispute {dispute})"
    assert [(w.kind, w.subject, w.reason) for w in states[disputed].waiting_for] == [("curator", "dispute", wait)]
    assert states[disputed].blockers == [wait]
    assert states[disputed].sentence == f"This card waits for a curator: {wait}; resolve it under Disputed crowd answers."
    assert states[disputed].statuses["judge"]["reason"] == "waiting for a curator: upside_down posterior 0.55 < 0.9"

    # a disputed crop leaves the orientation to the crowd; both hold the card back
    assert [(w.kind, w.subject) for w in states[crop_disputed].waiting_for] == [
        ("curator", "dispute"),
        ("decision", "orientation"),
    ]
    assert states[crop_disputed].blockers[1] == f"the crowd disagrees on its crop (batch {crop_batch}, dispute {crop_dispute})"

    with app.app_context():
        # the crowd's work, not the curators': the disputed judgement is left out
        expected = {"orientation": [asked, crop_disputed], "filter_review": [review]}
        assert waiting_for_people() == expected and waiting_for_people(chunk=1) == expected
        db.session.remove()


def test_culled_rectify_failed_and_graded_failure(app, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    image = card_image()
    culled = make_card(image[:, 1:])
    add_stage_result(culled, "filter", outcome="culled", reason="culled: 0.4 % good matches")
    broken = _passed(make_card, add_stage_result, image[:, 2:])
    add_stage_result(broken, "rectify", status="failed", outcome=None, reason="degenerate_geometry: planar scene")
    failure = _passed(make_card, add_stage_result, image[:, 3:])
    _with_current_inputs(app, add_stage_result, failure, "rectify")
    add_stage_result(failure, "disparity", outcome=None)
    add_stage_result(failure, "grade", outcome="failure", reason="failure: sheared 14.0 deg (> 10 deg)")
    states = _states(app, culled, broken, failure)

    assert states[culled].waiting_for == () and states[culled].blockers == [
        "its orientation is undecided (waiting for the orientation step (not run yet))"
    ]
    assert states[culled].sentence.startswith("The filter culled this card (culled: 0.4 % good matches)")
    assert {stage: s["status"] for stage, s in states[culled].statuses.items() if stage != "filter"} == dict.fromkeys(
        ("orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views"), "skipped"
    )

    assert states[broken].waiting_for == () and states[broken].blockers == []
    assert states[broken].sentence == (
        "The rectify stage failed on this card (degenerate_geometry: planar scene), so it has no automatic grade to review."
    )
    for stage in ("disparity", "grade", "views"):
        assert states[broken].statuses[stage] == {
            "status": "skipped",
            "outcome": None,
            "metrics": {},
            "reason": "not run: rectification failed (degenerate_geometry: planar scene)",
        }

    assert states[failure].statuses["views"]["reason"] == "not needed: graded failure"
    assert states[failure].stale == {} and states[failure].blockers == []
    assert [(w.kind, w.subject) for w in states[failure].waiting_for] == [("stage", "review")]
    assert states[failure].sentence == "This card is graded but not yet in the review queue: sync the queue with the grader."


def test_every_stage_after_a_failed_filter_or_rectification_says_why(app, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    """A card the filter could not read, and the crop of a card whose rectification failed, are
    not left pending with no reason (issue 35.5): each such stage is skipped and says why."""
    unreadable = make_card(card_image()[:, 5:], state="failed")
    add_stage_result(
        unreadable, "filter", status="failed", outcome=None, reason="unreadable_image: image holds no finite pixel values"
    )
    broken = _passed(make_card, add_stage_result, card_image()[:, 6:])
    add_stage_result(broken, "rectify", status="failed", outcome=None, reason="too_few_matches: 9 < 12")
    states = _states(app, unreadable, broken)

    why = "not run: the filter failed (unreadable_image: image holds no finite pixel values)"
    after_filter = {stage: info for stage, info in states[unreadable].statuses.items() if stage != "filter"}
    assert after_filter == dict.fromkeys(after_filter, {"status": "skipped", "outcome": None, "reason": why, "metrics": {}})
    assert set(after_filter) == {"orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views"}
    assert states[broken].statuses["crop"]["status"] == "skipped"
    assert states[broken].statuses["crop"]["reason"] == (
        "not asked: rectification failed (too_few_matches: 9 < 12); a curator can send the card to the crowd for crop boxes"
    )
    assert {
        stage: info["reason"]
        for stage, info in states[broken].statuses.items()
        if info["status"] != "done" and not info["reason"]
    } == {}


# ----------------------------------------------------------------------------- staleness


@pytest.mark.both_databases
def test_a_curators_eye_order_makes_the_rectification_stale_everywhere(
    app, runner, client, login, make_card, add_stage_result, card_image, make_person, decide_orientation, data_dir
) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person
    from exports.catalogue import stream_release_cards
    from review.models import CardReview
    from review.tasks import ReviewError, decide, sync_reviews

    card = _graded(app, make_card, add_stage_result, card_image())
    fresh = _graded(app, make_card, add_stage_result, card_image()[:, 4:])
    assert _states(app, card)[card].stale == {}
    decide_orientation([card], swapped=True)  # a curator: the eyes are exchanged on this card

    state = _states(app, card)[card]
    rectified = (
        "rectified with another orientation (upside_down=False, inverted=False, swapped=False; "
        "now upside_down=False, inverted=False, swapped=True)"
    )
    assert state.stale == {
        "rectify": rectified,
        "disparity": "computed from its rectify result, which is out of date",
        "grade": "computed from its disparity result, which is out of date",
    }
    blocker = f"its rectify result is out of date ({rectified}), and so is its disparity, grade computed from it; the next pipeline run recomputes it"
    assert state.blockers == [blocker]
    assert state.sentence == (
        f"This card's rectify result is out of date ({rectified}): no background worker is running: "
        "`keystone worker` or `keystone run` recomputes it."
    )

    # keystone cards: stale entries say so; fresh ones keep the documented shape
    result = runner.invoke(args=["cards", "--json"])
    assert result.exit_code == 0, result.output
    rows = {row["id"]: row for row in json.loads(result.output)["cards"]}
    assert rows[card]["stages"]["rectify"]["stale"] is True
    assert rows[card]["stages"]["rectify"]["stale_reason"] == rectified
    assert rows[card]["stages"]["grade"]["stale_reason"] == "computed from its disparity result, which is out of date"
    assert "stale" not in rows[card]["stages"]["filter"] and "stale_reason" not in rows[card]["stages"]["views"]
    assert all(set(info) == {"status", "outcome", "reason", "metrics"} for info in rows[fresh]["stages"].values())

    # the catalogue's card page shows it
    login("curator")
    page = client.get(f"/cards/{card}").get_data(as_text=True)
    assert "Out of date: rectified with another orientation" in page

    # the curator's page says why it cannot be accepted; the review gate refuses, with the same words
    with app.app_context():
        sync_reviews([card, fresh])
    assert f"Not accepted now: {blocker}." in client.get(f"/review/cards/{card}").get_data(as_text=True)
    assert 'id="card-blockers"' not in client.get(f"/review/cards/{fresh}").get_data(as_text=True)
    curator = make_person("curator", username="carol")
    with app.app_context():
        person = db.session.get(Person, curator.id)
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card))
        with pytest.raises(ReviewError) as refused:
            decide(review.id, "accept", expected_version=review.version, curator=person)
        assert refused.value.status == 409
        assert refused.value.message == (
            f"Card {card} cannot be accepted: {blocker}. "
            "It comes back to the queue once it is recomputed (the background worker does it, or keystone run)"
        )
        other = db.session.scalar(select(CardReview).where(CardReview.card_id == fresh))
        assert decide(other.id, "accept", expected_version=other.version, curator=person).decision == "accepted"
        # the release plan leaves it out for the same reason (accepted before the override)
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card))
        review.decision, review.grade = "accepted", "few"
        db.session.commit()
        excluded: list[Any] = []
        list(stream_release_cards([card, fresh], data_dir, excluded))
        assert [(row.card_id, row.reason) for row in excluded if row.card_id == card] == [(card, blocker)]
        assert all(row.card_id != fresh or "out of date" not in row.reason for row in excluded)
        db.session.remove()


def test_a_new_crop_decision_makes_the_rectification_stale(app, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, Batch
    from core.db import db

    card = _graded(app, make_card, add_stage_result, card_image())
    with app.app_context():
        batch = Batch(kind="crop")
        db.session.add(batch)
        db.session.flush()
        db.session.add(
            Aggregate(
                batch_id=batch.id,
                card_id=card,
                kind="crop",
                label={"left": [2, 2, 280, 190], "right": [302, 2, 580, 190]},
                state="approved",
                answers=3,
            )
        )
        db.session.commit()
        batch_id = batch.id
    state = _states(app, card)[card]
    assert state.stale is not None and state.stale["rectify"] == (
        "rectified from the boxes of the filter split (0123456789abcdef); "
        f"the boxes now come from the crowd consensus (batch {batch_id})"
    )
    assert list(state.stale) == ["rectify", "disparity", "grade"]


def test_without_a_digest_a_result_older_than_its_source_is_stale_and_with_one_the_digest_decides(
    app, make_card, add_stage_result, card_image
) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Card, StageResult
    from pipeline.records import inputs_digest, param_hash
    from runs.planning import pending_cards
    from runs.specs import available_stages

    card = _passed(make_card, add_stage_result, card_image())
    rectify = _with_current_inputs(app, add_stage_result, card, "rectify", artifacts={"left": "l.png", "right": "r.png"})
    with app.app_context():
        phash = param_hash(available_stages()["disparity"].params)
    disparity = add_stage_result(card, "disparity", outcome=None, param_hash=phash)  # no digest recorded
    start = datetime(2026, 11, 1, 12, 0, tzinfo=UTC)

    def started(rectify_at: datetime, disparity_at: datetime) -> None:
        with app.app_context():
            db.session.get(StageResult, rectify).started_at = rectify_at
            db.session.get(StageResult, disparity).started_at = disparity_at
            db.session.commit()

    def planned() -> list[int]:
        with app.app_context():
            todo, _ = pending_cards(available_stages()["disparity"], phash)
            db.session.remove()
            return [row.card_id for row in todo]

    started(start, start + timedelta(seconds=5))
    assert _states(app, card)[card].stale == {}
    # rectification redone after the disparity was measured
    started(start + timedelta(seconds=9), start + timedelta(seconds=5))
    state = _states(app, card)[card]
    assert state.stale == {"disparity": "computed before its latest rectify result"}
    assert state.statuses["disparity"]["stale"] is True
    assert planned() == [card]  # without a digest the planner reruns it too

    # With the digest of the inputs disparity would build now (the rectification, redone in
    # place on the same flags and boxes, left them as they were), the planner does not rerun
    # it, and it is not stale: the two agree.
    with app.app_context():
        card_row = db.session.get(Card, card)
        inputs = available_stages()["disparity"].inputs(card_row, {})
        db.session.get(StageResult, disparity).metrics = {"inputs_digest": inputs_digest(dict(inputs))}
        db.session.commit()
    assert planned() == []
    assert _states(app, card)[card].stale == {}


# ----------------------------------------------------------------------------- batches


def test_card_states_reads_a_batch_with_a_fixed_number_of_queries(app, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Card
    from runs.card_state import card_states
    from runs.specs import available_stages

    image = card_image()
    ids = [_passed(make_card, add_stage_result, image[:, n:], decided=n % 2 == 0) for n in range(1, 13)]

    def queries(card_ids: list[int]) -> int:
        with app.app_context():
            specs = available_stages()
            cards = list(db.session.scalars(select(Card).where(Card.id.in_(card_ids)).options(selectinload(Card.stage_results))))
            seen: list[str] = []

            def count(*args: Any) -> None:
                seen.append(args[2])

            event.listen(db.engine, "before_cursor_execute", count)
            try:
                states = card_states(cards, specs=specs)
            finally:
                event.remove(db.engine, "before_cursor_execute", count)
            assert set(states) == set(card_ids)
            return len(seen)

    assert queries(ids[:2]) == queries(ids)


def test_stale_views_are_shown_but_hold_nothing_back(app, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    card = _graded(app, make_card, add_stage_result, card_image())
    add_stage_result(card, "views", outcome=None, metrics={"inputs_digest": "computed-from-another-grade"})
    state = _states(app, card)[card]
    assert state.stale == {"views": "its inputs changed since the views stage ran"}
    assert state.statuses["views"]["stale"] is True and state.blockers == []
    assert state.sentence == "This card is graded but not yet in the review queue: sync the queue with the grader."

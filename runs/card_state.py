"""Where a card stands: every stage's status with its reason, and what the card waits for."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import selectinload

from core.db import db
from core.hooks import people_work
from core.models import Card, StageResult
from pipeline.decided_orientation import card_orientation, is_decided, public_orientation
from pipeline.stages.spec import flow_stages
from runs.planning import PLAN_CHUNK
from runs.specs import approved_annotations


def waiting_for_people(chunk: int = PLAN_CHUNK) -> dict[str, list[int]]:
    """Cards that wait for the crowd's judgement, by why: ``orientation`` (the orientation step
    asked, or failed, and no crowd or curator has decided it yet) and ``filter_review`` (the
    filter sent it to review and no judgement has come back). A card whose judgement waits
    for a curator (a dispute) is the curators' work, not counted here; nor a card whose
    orientation step has not run."""
    waiting: dict[str, list[int]] = {"orientation": [], "filter_review": []}
    after = 0
    while True:
        cards = list(
            db.session.scalars(
                select(Card)
                .where(Card.state.in_(("pass", "review")), Card.id > after)
                .order_by(Card.id)
                .limit(chunk)
                .options(selectinload(Card.stage_results))
            )
        )
        if not cards:
            return waiting
        work = people_and_decisions([card.id for card in cards])
        for card in cards:
            own = work.get(card.id, {})
            disputed = own.get("judge") is not None and own["judge"].state == "needs_curator"
            if disputed or _judged_not_stereo(own):
                continue
            step = card.latest_results().get("orientation")
            if step is not None and not is_decided(card_orientation(card, own.get("approved", {}))):
                waiting["orientation"].append(card.id)
            elif card.state == "review" and "judge" not in own.get("approved", {}):
                waiting["filter_review"].append(card.id)
        after = cards[-1].id
        db.session.expunge_all()


DOWNSTREAM_OF_CULL = ("orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views")
DOWNSTREAM_OF_RECTIFY = ("disparity", "grade", "views")


def people_and_decisions(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """:func:`core.hooks.people_work` per card (the crowd's latest aggregates, the curator
    review), plus ``"approved"``: the approved decisions the orientation is resolved from
    (:func:`approved_annotations`)."""
    work = people_work(card_ids)
    for card_id, approved in approved_annotations(card_ids).items():
        work.setdefault(card_id, {})["approved"] = approved
    return work


def _status(
    status: str, reason: str | None = None, outcome: str | None = None, metrics: dict[str, Any] | None = None
) -> dict[str, Any]:
    return {"status": status, "outcome": outcome, "reason": reason, "metrics": metrics or {}}


def _crowd_status(
    stage: str, card: Card, aggregate: Any, latest: dict[str, StageResult], orientation: dict[str, Any] | None = None
) -> dict[str, Any]:
    if aggregate is not None:
        metrics = {"label": aggregate.label, "batch": aggregate.batch_id, "answers": aggregate.answers}
        if aggregate.state == "needs_curator":
            return _status("pending", f"waiting for a curator: {aggregate.reasons}", metrics=metrics)
        who = (
            f"curator decision (batch {aggregate.batch_id})"
            if aggregate.resolved_by
            else f"crowd consensus (batch {aggregate.batch_id})"
        )
        outcome = None
        if stage == "judge":
            outcome = "stereo" if aggregate.label.get("is_stereo", True) else "not_stereo"
        return _status("done", who, outcome, metrics)
    if stage == "judge" and card.state == "pass":
        orientation = orientation or card_orientation(card, {})
        if orientation["decided_by"] == "auto":
            return _status(
                "skipped",
                "not needed: the filter passed the card as a stereo pair and the orientation "
                f"step decided it (confidence {orientation['confidence']})",
            )
        if orientation["decided_by"] in ("curator", "operator", "crowd"):
            # crowd without a judge aggregate: people confirmed the step's proposal in a grid.
            return _status("skipped", f"not needed: {orientation['source']}")
        return _status("pending", f"waiting for {orientation['waiting_for']}" if orientation["waiting_for"] else None)
    rectify = latest.get("rectify")
    if stage == "crop" and rectify is not None and rectify.status != "failed":
        return _status("skipped", f"not needed: rectified from {rectify.metrics.get('box_source', 'the filter split')}")
    return _status("pending")


def _review_status(review: Any, latest: dict[str, StageResult]) -> dict[str, Any]:
    if review is None or review.decision == "pending":
        grade = latest.get("grade")
        if grade is None and "disparity" in latest and latest["disparity"].status == "failed":
            return _status("skipped", f"not run: disparity failed ({latest['disparity'].reason})")
        return _status("pending", "waiting for a curator" if review is not None else None)
    metrics = {"grade": review.grade, "auto_grade": review.auto_grade, "version": review.version}
    if review.decision == "sent_back":
        return _status("pending", f"sent back to the crowd: {review.note}".rstrip(": "), metrics=metrics)
    return _status("done", review.note or None, review.decision, metrics)


def _judged_not_stereo(work: dict[str, Any]) -> bool:
    judge = work.get("approved", {}).get("judge")
    return judge is not None and judge.label.get("is_stereo", True) is False


def card_orientation_field(card: Card, work: dict[str, Any]) -> dict[str, Any]:
    """The ``orientation`` of ``keystone cards --json`` (README.md): null flags while undecided."""
    return public_orientation(card_orientation(card, work.get("approved", {})))


def card_stage_statuses(
    card: Card, only_stage: str | None = None, work: dict[str, Any] | None = None
) -> dict[str, dict[str, Any]]:
    """The stage status map of ``keystone cards --json``: every stage, ``pending`` if not run.

    ``work`` is the card's entry of :func:`people_work` (crowd aggregates and the review); it is
    loaded here when not given.
    """
    latest = card.latest_results()
    if work is None:
        work = people_and_decisions([card.id]).get(card.id, {})
    statuses: dict[str, dict[str, Any]] = {}
    orientation = card_orientation(card, work.get("approved", {}))
    for stage in flow_stages() if only_stage is None else (only_stage,):
        result = latest.get(stage)
        if (
            stage == "judge"
            and card.state in ("pass", "review")
            and not is_decided(orientation)
            and "orientation" in latest
            and not _judged_not_stereo(work)
        ):
            # The flow rule: an undecided card waits for people, whatever its filter band.
            status = _crowd_status(stage, card, work.get(stage), latest, orientation)
            statuses[stage] = (
                status
                if status["status"] == "pending"
                else _status("pending", f"waiting for {orientation['waiting_for']}", metrics=status["metrics"])
            )
        elif (
            stage == "rectify"
            and result is None
            and card.state in ("pass", "review")
            and not is_decided(orientation)
            and not _judged_not_stereo(work)
        ):
            statuses[stage] = _status(
                "pending", f"not run: the orientation is undecided, waiting for {orientation['waiting_for']}"
            )
        elif card.state == "culled" and stage in DOWNSTREAM_OF_CULL and result is None:
            filter_reason = latest["filter"].reason if "filter" in latest else "culled"
            statuses[stage] = _status("skipped", f"not needed: the card was culled by the filter ({filter_reason})")
        elif stage in ("judge", "crop"):
            statuses[stage] = _crowd_status(stage, card, work.get(stage), latest, orientation)
        elif stage == "review":
            statuses[stage] = _review_status(work.get("review"), latest)
        elif result is not None:
            statuses[stage] = result.as_status()
        elif stage in DOWNSTREAM_OF_RECTIFY and "rectify" in latest and latest["rectify"].status == "failed":
            statuses[stage] = _status("skipped", f"not run: rectification failed ({latest['rectify'].reason})")
        elif stage == "views" and "grade" in latest and latest["grade"].outcome == "failure":
            statuses[stage] = _status("skipped", "not needed: graded failure")
        else:
            statuses[stage] = _status("pending")
    return statuses

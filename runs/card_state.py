"""Where a card stands, worked out in one place: every stage's status with its reason, what the
card waits for, which of its results are stale, and the one sentence the pages show.

Everyone asks this module: ``keystone cards`` and ``keystone run``'s count of cards waiting for
people (:mod:`runs.cli`), the catalogue's and the curators' card pages, the review gate (a card
with :attr:`CardState.blockers` is not accepted) and the release plan (nor released).

A result is *stale* when the card's inputs moved on after it was computed: its recorded
``metrics.inputs_digest`` is not the digest of the inputs its stage would build now (a curator
changed the eye order or the crop after rectification ran), or it was computed from a stale
result, or, recording no digest, it is older than the result of the stage it was computed from
(``StageSpec.requires``: the rectification was redone after the disparity was measured). Where
a digest is recorded it decides, as it does for the planner (``runs.planning.pending_cards``):
a rectification redone in place on the same flags and boxes leaves the disparity's inputs as
they were, and the run does not redo it, so neither is it called stale here.

Entry points take cards in batches (:func:`card_states`: people's work, their decisions and the
stage catalogue are read once per batch; the cards' ``stage_results`` should be loaded with
them), so a caller that pages through the catalogue ``PLAN_CHUNK`` cards at a time stays linear.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import selectinload

from core.db import db
from core.hooks import approved_decisions, people_work
from core.models import Card, StageResult
from pipeline.decided_orientation import FLAGS, card_orientation, is_decided
from pipeline.records import inputs_digest
from pipeline.stages.spec import StageSpec, flow_stages
from runs.planning import PLAN_CHUNK
from runs.specs import available_stages

__all__ = [
    "DOWNSTREAM_OF_CULL",
    "DOWNSTREAM_OF_RECTIFY",
    "CardState",
    "Waiting",
    "card_state",
    "card_states",
    "waiting_for_people",
]

DOWNSTREAM_OF_CULL = ("orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views")
DOWNSTREAM_OF_RECTIFY = ("disparity", "grade", "views")
# The stages a card goes through before a curator sees it, in flow order (views is opt-in).
GRADED_BY = ("filter", "orientation", "rectify", "disparity", "grade")
FINISHED = ("done", "skipped")
CROWD_WORK = {"judge": "judgement", "crop": "crop", "confirm": "confirmation"}

WaitKind = Literal["crowd", "curator", "decision", "stage"]


@dataclass(frozen=True)
class Waiting:
    """One thing a card waits for.

    ``kind``: ``crowd`` (a judgement or crop from the crowd), ``curator`` (a dispute to resolve,
    a review to make), ``decision`` (an undecided orientation, people asked) or ``stage`` (a
    pipeline stage not run yet); ``subject``: what exactly (``judge``, ``crop``, ``dispute``,
    ``review``, ``orientation`` or a stage name); ``reason``: in words; ``aggregate_id``: for a
    dispute, the crowd aggregate a curator resolves (pages link straight to it).
    """

    kind: WaitKind
    subject: str
    reason: str
    aggregate_id: int | None = None


@dataclass(frozen=True)
class CardState:
    """Where one card stands (see the module docstring)."""

    card_id: int
    # stage -> {"status", "outcome", "reason", "metrics"} (+ "stale", "stale_reason" when stale),
    # the stage map of ``keystone cards --json``
    statuses: dict[str, dict[str, Any]]
    # the orientation the pipeline uses (pipeline.decided_orientation.resolve_orientation)
    orientation: dict[str, Any]
    # what it waits for, most pressing first; empty when nothing (culled, failed, accepted, ...)
    waiting_for: tuple[Waiting, ...]
    # stage -> why its latest finished result is out of date; None when not checked
    stale: dict[str, str] | None
    # the one sentence the pages show
    sentence: str

    @property
    def blockers(self) -> list[str]:
        """Why the card may not be accepted or released now (empty: nothing holds it back):
        an undecided orientation, a crowd dispute, a stale result its grade rests on (stale
        views, which are optional, are shown but hold nothing back)."""
        found = []
        if not is_decided(self.orientation):
            # whether or not the step has run: nothing is accepted or released undecided
            found.append(f"its orientation is undecided (waiting for {self.orientation['waiting_for']})")
        found += [wait.reason for wait in self.disputes]
        reasons = self.stale or {}
        stale = [stage for stage in reasons if stage in GRADED_BY]
        if stale:
            first, after = stale[0], stale[1:]
            found.append(
                f"its {first} result is out of date ({reasons[first]})"
                + (f", and so is its {', '.join(after)} computed from it" if after else "")
                + "; run the pipeline again"
            )
        return found

    @property
    def disputes(self) -> list[Waiting]:
        return [wait for wait in self.waiting_for if wait.subject == "dispute"]


# ----------------------------------------------------------------------------- entry points


def card_state(card: Card, *, specs: Mapping[str, StageSpec] | None = None) -> CardState:
    """:func:`card_states` of one card."""
    return card_states([card], specs=specs)[card.id]


def card_states(
    cards: Sequence[Card],
    only_stage: str | None = None,
    *,
    specs: Mapping[str, StageSpec] | None = None,
    check_stale: bool = True,
) -> dict[int, CardState]:
    """Where each card stands, by card id. People's work and decisions are read for all
    ``cards`` at once and the stage catalogue (``specs``, :func:`runs.specs.available_stages`
    when not given) once; load the cards' ``stage_results`` with them.

    ``only_stage``: compute that stage's status alone (``keystone cards --stage``).
    ``check_stale=False``: skip the inputs digests (``stale`` is then None).
    """
    if not cards:
        return {}
    if check_stale and specs is None:
        specs = available_stages()
    work = _people_and_decisions([card.id for card in cards])
    return {card.id: _state(card, work.get(card.id, {}), specs or {}, only_stage, check_stale) for card in cards}


def waiting_for_people(chunk: int = PLAN_CHUNK) -> dict[str, list[int]]:
    """Cards whose next step is the crowd's, by why: ``orientation`` (the orientation step
    asked, or failed, and no crowd or curator has decided it yet) and ``filter_review`` (the
    filter sent it to review and no judgement has come back). A card whose judgement is
    disputed waits for a curator, not the crowd, and is not counted; nor a card whose
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
        for card_id, state in card_states(cards, check_stale=False).items():
            subjects = {(wait.kind, wait.subject) for wait in state.waiting_for}
            if ("decision", "orientation") in subjects:
                waiting["orientation"].append(card_id)
            elif ("crowd", "judge") in subjects:
                waiting["filter_review"].append(card_id)
        after = cards[-1].id
        db.session.expunge_all()


# ----------------------------------------------------------------------------- one card


def _people_and_decisions(card_ids: list[int]) -> dict[int, dict[str, Any]]:
    """:func:`core.hooks.people_work` per card (the crowd's latest aggregates in any state, the
    curator review), plus ``"approved"``: the approved decisions stage inputs and the
    orientation are built from (:func:`core.hooks.approved_decisions`)."""
    work = people_work(card_ids)
    for card_id, approved in approved_decisions(card_ids).items():
        work.setdefault(card_id, {})["approved"] = approved
    return work


def _state(
    card: Card, work: dict[str, Any], specs: Mapping[str, StageSpec], only_stage: str | None, check_stale: bool
) -> CardState:
    latest = card.latest_results()
    approved = work.get("approved", {})
    orientation = card_orientation(card, approved)
    statuses = _statuses(card, latest, work, orientation, only_stage)
    stale = _stale(card, latest, approved, specs) if check_stale else None
    for stage, reason in (stale or {}).items():
        if stage in statuses:
            statuses[stage] = {**statuses[stage], "stale": True, "stale_reason": reason}
    waiting = _waiting_for(card, latest, work, orientation)
    return CardState(card.id, statuses, orientation, waiting, stale, _sentence(card, latest, work, waiting, stale or {}))


def _judged_not_stereo(work: dict[str, Any]) -> bool:
    judge = work.get("approved", {}).get("judge")
    return judge is not None and judge.label.get("is_stereo", True) is False


def _in_flow(card: Card, work: dict[str, Any]) -> bool:
    """The card is a stereo pair the flow carries on (not culled, failed or judged no pair)."""
    return card.state in ("pass", "review") and not _judged_not_stereo(work)


def _waiting_for(
    card: Card, latest: dict[str, StageResult], work: dict[str, Any], orientation: dict[str, Any]
) -> tuple[Waiting, ...]:
    found: list[Waiting] = []
    for kind, aggregate in sorted(work.items()):
        if kind in CROWD_WORK and getattr(aggregate, "state", None) == "needs_curator":
            found.append(
                Waiting(
                    "curator",
                    "dispute",
                    f"the crowd disagrees on its {CROWD_WORK[kind]} (batch {aggregate.batch_id}, dispute {aggregate.id})",
                    aggregate.id,
                )
            )
    if not _in_flow(card, work):
        return tuple(found)
    # A disputed judgement (and the orientation it decides) is with a curator, not the crowd.
    judge = work.get("judge")
    with_people = judge is None or judge.state != "needs_curator"
    if with_people and not is_decided(orientation) and "orientation" in latest:
        found.append(
            Waiting("decision", "orientation", f"its orientation is undecided (waiting for {orientation['waiting_for']})")
        )
    elif with_people and card.state == "review" and "judge" not in work.get("approved", {}):
        found.append(Waiting("crowd", "judge", "the crowd's judgement of whether it is a stereo pair"))
    review = work.get("review")
    if review is not None and review.decision == "sent_back":
        found.append(Waiting("crowd", "review", "the crowd's new answers (a curator sent it back)"))
    elif review is not None and review.decision == "pending":
        found.append(Waiting("curator", "review", "a curator's review of its grade"))
    if found or review is not None:
        return tuple(found)  # people hold it: the next stage is not what it waits for
    for stage in GRADED_BY:
        result = latest.get(stage)
        if result is None or result.status not in FINISHED:
            if result is None:
                found.append(Waiting("stage", stage, f"its {stage} stage"))
            break
    else:
        found.append(Waiting("stage", "review", "the review queue's sync with the grader"))
    return tuple(found)


# ----------------------------------------------------------------------------- staleness


def _stale(
    card: Card, latest: dict[str, StageResult], approved: dict[str, Any], specs: Mapping[str, StageSpec]
) -> dict[str, str]:
    """Stage -> why its latest finished result is out of date, in flow order."""
    stale: dict[str, str] = {}
    for name, spec in specs.items():
        result = latest.get(name)
        if result is None or result.status not in FINISHED:
            continue
        reason = None
        recorded = (result.metrics or {}).get("inputs_digest")
        if spec.inputs is not None and recorded is not None:
            inputs = dict(spec.inputs(card, approved))
            if inputs_digest(inputs) != recorded:
                reason = _what_changed(name, result, inputs)
        source = latest.get(spec.requires) if spec.requires else None
        if reason is None and spec.requires in stale:
            reason = f"computed from its {spec.requires} result, which is out of date"
        if reason is None and recorded is None and _older_than_source(result, source):
            reason = f"computed before its latest {spec.requires} result"
        if reason is not None:
            stale[name] = reason
    return stale


def _utc(moment: datetime) -> datetime:
    return moment.astimezone(UTC) if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


def _older_than_source(result: StageResult, source: StageResult | None) -> bool:
    """Whether ``result`` started before the latest finished result of the stage it was computed
    from; results without a start time (written by hand) are never older."""
    if source is None or source.status not in FINISHED or result.started_at is None or source.started_at is None:
        return False
    return _utc(source.started_at) > _utc(result.started_at)


def _flags_words(flags: Mapping[str, Any]) -> str:
    return ", ".join(f"{flag}={'undecided' if flags.get(flag) is None else flags.get(flag)}" for flag in FLAGS)


def _what_changed(stage: str, result: StageResult, inputs: dict[str, Any]) -> str:
    """Why a result's inputs digest no longer matches, as precisely as its metrics tell."""
    metrics = result.metrics or {}
    if stage == "rectify":
        used = metrics.get("orientation_used")
        if used is not None and any(used.get(flag) != inputs.get(flag) for flag in FLAGS):
            return f"rectified with another orientation ({_flags_words(used)}; now {_flags_words(inputs)})"
        was, now = metrics.get("box_source"), inputs.get("box_source")
        if was is not None and now is not None and was != now:
            return f"rectified from the boxes of the {was}; the boxes now come from the {now}"
    return f"its inputs changed since the {stage} stage ran"


# ----------------------------------------------------------------------------- statuses


def _status(
    status: str, reason: str | None = None, outcome: str | None = None, metrics: dict[str, Any] | None = None
) -> dict[str, Any]:
    return {"status": status, "outcome": outcome, "reason": reason, "metrics": metrics or {}}


def _crowd_status(
    stage: str, card: Card, aggregate: Any, latest: dict[str, StageResult], orientation: dict[str, Any]
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


def _statuses(
    card: Card, latest: dict[str, StageResult], work: dict[str, Any], orientation: dict[str, Any], only_stage: str | None
) -> dict[str, dict[str, Any]]:
    """The stage status map of ``keystone cards --json``: every stage, ``pending`` if not run."""
    statuses: dict[str, dict[str, Any]] = {}
    undecided_in_flow = _in_flow(card, work) and not is_decided(orientation)
    for stage in flow_stages() if only_stage is None else (only_stage,):
        result = latest.get(stage)
        if stage == "judge" and undecided_in_flow and "orientation" in latest:
            # The flow rule: an undecided card waits for people, whatever its filter band.
            status = _crowd_status(stage, card, work.get(stage), latest, orientation)
            statuses[stage] = (
                status
                if status["status"] == "pending"
                else _status("pending", f"waiting for {orientation['waiting_for']}", metrics=status["metrics"])
            )
        elif stage == "rectify" and result is None and undecided_in_flow:
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


# ----------------------------------------------------------------------------- the sentence


GRADE_WORDS = {"few": "few artifacts", "some": "some artifacts", "failure": "failure"}


def _sentence(
    card: Card, latest: dict[str, StageResult], work: dict[str, Any], waiting: tuple[Waiting, ...], stale: dict[str, str]
) -> str:
    """Where the card stands, in one sentence: culled, judged no pair, a failed stage, what it
    waits for, a stale result, the curator's decision, or the stage it waits for."""
    filtered = latest.get("filter")
    if card.state == "culled" or (filtered is not None and filtered.outcome == "culled"):
        why = f" ({filtered.reason})" if filtered is not None and filtered.reason else ""
        return (
            f"The filter culled this card{why}: it is not a usable stereo pair, so it is not graded and "
            "there is nothing to review."
        )
    for stage in ("filter", "rectify", "disparity", "grade"):
        result = latest.get(stage)
        if result is not None and result.status == "failed":
            return (
                f"The {stage} stage failed on this card ({result.reason or 'no reason recorded'}), so it has no "
                "automatic grade to review."
            )
    if _judged_not_stereo(work):
        judge = work["approved"]["judge"]
        return (
            f"The crowd judged this card not a stereo pair (batch {judge.batch_id}), so it is not rectified, graded or released."
        )
    first = waiting[0] if waiting else None
    if first is not None and first.subject == "dispute":
        return f"This card waits for a curator: {first.reason}; resolve it under Disputed crowd answers."
    if first is not None and first.kind == "decision":
        return (
            f"This card waits for people: {first.reason}, and it is not rectified, graded, accepted or "
            "released until it is decided."
        )
    if first is not None and first.kind == "crowd" and first.subject == "judge":
        return f"The filter sent this card to review: it is waiting for {first.reason}."
    outdated = next((name for name in stale if name in GRADED_BY), None)
    if outdated is not None:
        return f"This card's {outdated} result is out of date ({stale[outdated]}): the next pipeline run redoes it."
    review = work.get("review")
    if review is not None and review.decision != "pending":
        if review.decision == "sent_back":
            return "A curator sent this card back to the crowd: it leaves the review queue until it is graded again."
        if review.decision == "rejected":
            return "A curator rejected this card: it is not released."
        return f"A curator accepted this card with the grade {GRADE_WORDS.get(review.grade or '', review.grade)}."
    if review is not None:
        return "This card is graded and waits for a curator's review."
    grade = latest.get("grade")
    if grade is not None and grade.status == "done":
        return "This card is graded but not yet in the review queue: sync the queue with the grader."
    next_stage = next((wait.subject for wait in waiting if wait.kind == "stage"), "grade")
    return f"This card is not graded yet: it is waiting for its {next_stage} stage."

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

An *acceptance* applies to the results it was given (:func:`results_fingerprint`, recorded on the
review when a curator accepts or changes a grade): once the rectification or disparity is
recomputed, the acceptance is outdated, the card is not released under it, and the review sync
sends it back to the curator. A card judged not a stereo pair leaves the flow: its earlier
rectify, disparity and grade are marked withdrawn, and nothing of it is accepted or released.

A stage a pipeline driver holds a live claim on is being computed now (``recomputing``), and a
stale result is recomputed without anyone at a terminal when a background worker is running
(:mod:`runs.worker`); the sentence says which.

Entry points take cards in batches (:func:`card_states`: people's work, their decisions and the
stage catalogue are read once per batch; the cards' ``stage_results`` should be loaded with
them), so a caller that pages through the catalogue ``PLAN_CHUNK`` cards at a time stays linear.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
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
    "ACCEPTED_STAGES",
    "DOWNSTREAM_OF_CULL",
    "DOWNSTREAM_OF_RECTIFY",
    "CardState",
    "Waiting",
    "card_state",
    "card_states",
    "results_fingerprint",
    "waiting_for_people",
]

DOWNSTREAM_OF_CULL = ("orientation", "judge", "crop", "rectify", "disparity", "grade", "review", "views")
DOWNSTREAM_OF_RECTIFY = ("disparity", "grade", "views")
# The stages a card goes through before a curator sees it, in flow order (views is opt-in).
GRADED_BY = ("filter", "orientation", "rectify", "disparity", "grade")
FINISHED = ("done", "skipped")
# The results an acceptance is given: the released images and disparity come from these. The
# orientation step and the grade are not among them: the rectification's inputs carry the
# orientation it used, and a regraded card keeps the curator's final grade (review.tasks).
ACCEPTED_STAGES = ("rectify", "disparity")
# Results a ruling "not a stereo pair" withdraws.
WITHDRAWN_BY_NOT_STEREO = ("rectify", "disparity", "grade", "views")
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
    # the stages a pipeline driver is computing for this card now (a live claim)
    recomputing: tuple[str, ...] = ()
    # why its curator's acceptance no longer applies (results recomputed since); None if it does
    outdated_acceptance: str | None = None
    # why it left the flow (judged not a stereo pair, and by whom); None while in it
    withdrawn: str | None = None
    # stage -> the inputs digest it would be given now, from people's current decisions (the
    # release records it beside the digest each result was computed from; keystone verify compares)
    inputs_now: dict[str, str] = field(default_factory=dict)

    @property
    def blockers(self) -> list[str]:
        """Why the card may not be accepted now (empty: nothing holds it back): judged not a
        stereo pair, an undecided orientation, a crowd dispute, a stale result its grade rests
        on (stale views, which are optional, are shown but hold nothing back)."""
        found = []
        if self.withdrawn is not None:
            found.append(self.withdrawn)
            return found
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
                + ("; it is being recomputed now" if self.recomputing else "; the next pipeline run recomputes it")
            )
        return found

    @property
    def release_blockers(self) -> list[str]:
        """Why the card may not be released now: :attr:`blockers`, and an acceptance given
        other results than the card has now."""
        found = self.blockers
        if self.outdated_acceptance is not None and self.withdrawn is None:
            found.append(self.outdated_acceptance)
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
    card_ids = [card.id for card in cards]
    work = _people_and_decisions(card_ids)
    claimed = claimed_stages(card_ids)
    worker = live_worker() is not None if check_stale else False
    return {
        card.id: _state(card, work.get(card.id, {}), specs or {}, only_stage, check_stale, claimed.get(card.id, ()), worker)
        for card in cards
    }


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
    card: Card,
    work: dict[str, Any],
    specs: Mapping[str, StageSpec],
    only_stage: str | None,
    check_stale: bool,
    recomputing: tuple[str, ...] = (),
    worker_alive: bool = False,
) -> CardState:
    latest = card.latest_results()
    approved = work.get("approved", {})
    orientation = card_orientation(card, approved)
    statuses = _statuses(card, latest, work, orientation, only_stage)
    withdrawn = _withdrawn(work)
    digests: dict[str, str] = {}
    stale = _stale(card, latest, approved, specs, digests) if check_stale else None
    if withdrawn is not None and stale is not None:
        # Its earlier results are not redone: they are withdrawn, and say so.
        for stage in WITHDRAWN_BY_NOT_STEREO:
            result = latest.get(stage)
            if result is not None and result.status in FINISHED:
                stale[stage] = f"withdrawn: {withdrawn}"
    for stage, reason in (stale or {}).items():
        if stage in statuses:
            statuses[stage] = {**statuses[stage], "stale": True, "stale_reason": reason}
    for stage in recomputing:
        if stage in statuses:
            statuses[stage] = {**statuses[stage], "recomputing": True}
    waiting = _waiting_for(card, latest, work, orientation)
    outdated = acceptance_outdated(work.get("review"), latest)
    sentence = _sentence(card, latest, work, waiting, stale or {}, recomputing, worker_alive, outdated)
    return CardState(card.id, statuses, orientation, waiting, stale, sentence, recomputing, outdated, withdrawn, digests)


def _withdrawn(work: dict[str, Any]) -> str | None:
    """Why the card left the flow, if people judged it not a stereo pair."""
    if not _judged_not_stereo(work):
        return None
    judge = work["approved"]["judge"]
    who = (
        f"a curator's ruling on dispute {judge.id}"
        if getattr(judge, "resolved_by", None)
        else f"the crowd (batch {judge.batch_id})"
    )
    return f"it was judged not a stereo pair by {who}"


def results_fingerprint(latest: Mapping[str, StageResult]) -> dict[str, dict[str, Any]]:
    """What an acceptance is given: per stage of :data:`ACCEPTED_STAGES` with a finished result,
    its parameter hash, inputs digest and start time (ISO 8601, UTC). JSON-safe; recorded on the
    review by an accept or a grade change, and in the release's card records."""
    found: dict[str, dict[str, Any]] = {}
    for stage in ACCEPTED_STAGES:
        result = latest.get(stage)
        if result is None or result.status not in FINISHED:
            continue
        found[stage] = {
            "param_hash": result.param_hash,
            "inputs_digest": (result.metrics or {}).get("inputs_digest"),
            "computed_at": None if result.started_at is None else _utc(result.started_at).isoformat(),
        }
    return found


def acceptance_outdated(review: Any, latest: Mapping[str, StageResult]) -> str | None:
    """Why a curator's accept or grade change no longer applies to the card's results (one of
    :data:`ACCEPTED_STAGES` was recomputed or is gone since), or None. A review decided before
    the results were recorded on it (``accepted_results`` None) is compared by time."""
    if review is None or review.decision not in ("accepted", "changed"):
        return None
    decided = review.decided_at
    when = f"the acceptance on {_when(decided)}" if decided is not None else "the acceptance"
    given = getattr(review, "accepted_results", None)
    if given is None:
        if decided is None:
            return None
        for stage in ACCEPTED_STAGES:
            result = latest.get(stage)
            if result is not None and result.started_at is not None and _utc(result.started_at) > _utc(decided):
                return f"its {stage} result was recomputed on {_when(result.started_at)}, after {when}"
        return None
    now = results_fingerprint(latest)
    for stage in ACCEPTED_STAGES:
        if given.get(stage) == now.get(stage):
            continue
        if stage not in now:
            return f"its {stage} result, which {when} was given, is gone"
        computed = now[stage].get("computed_at")
        moment = _when(datetime.fromisoformat(computed)) if computed else "since"
        return f"its {stage} result was recomputed on {moment}, after {when}"
    return None


def _when(moment: datetime) -> str:
    return _utc(moment).strftime("%Y-%m-%d %H:%M UTC")


def claimed_stages(card_ids: Sequence[int]) -> dict[int, tuple[str, ...]]:
    """The stages a live pipeline driver holds a claim on, per card (a claim past its expiry
    belongs to a driver that died: not counted)."""
    from runs.claims import StageClaim

    found: dict[int, list[str]] = {}
    now = datetime.now(UTC)
    for start in range(0, len(card_ids), PLAN_CHUNK):
        rows = db.session.execute(
            select(StageClaim.card_id, StageClaim.stage, StageClaim.expires_at).where(
                StageClaim.card_id.in_(list(card_ids[start : start + PLAN_CHUNK]))
            )
        )
        for card_id, stage, expires_at in rows:
            if _utc(expires_at) > now:
                found.setdefault(card_id, []).append(stage)
    return {card_id: tuple(stages) for card_id, stages in found.items()}


def live_worker() -> Any:
    """A background worker (:mod:`runs.worker`) that is alive now, or None."""
    from runs.worker import live_workers

    workers = live_workers()
    return workers[0] if workers else None


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
    card: Card,
    latest: dict[str, StageResult],
    approved: dict[str, Any],
    specs: Mapping[str, StageSpec],
    digests: dict[str, str] | None = None,
) -> dict[str, str]:
    """Stage -> why its latest finished result is out of date, in flow order. ``digests``, if
    given, collects the inputs digest each stage would be given now (for the release records)."""
    stale: dict[str, str] = {}
    for name, spec in specs.items():
        result = latest.get(name)
        if result is None or result.status not in FINISHED:
            continue
        reason = None
        recorded = (result.metrics or {}).get("inputs_digest")
        if spec.inputs is not None and recorded is not None:
            inputs = dict(spec.inputs(card, approved))
            digest = inputs_digest(inputs)
            if digests is not None:
                digests[name] = digest
            if digest != recorded:
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
        failed = next(
            (latest[name] for name in ("rectify", "disparity") if name in latest and latest[name].status == "failed"), None
        )
        if grade is None and failed is not None:
            return _status("skipped", f"not run: {failed.stage} failed ({failed.reason})")
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
    filter_failed = latest["filter"] if "filter" in latest and latest["filter"].status == "failed" else None
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
        elif filter_failed is not None and stage in DOWNSTREAM_OF_CULL and result is None:
            # a card the filter could not read goes no further: every later stage says why
            statuses[stage] = _status("skipped", f"not run: the filter failed ({filter_failed.reason or 'no reason recorded'})")
        elif stage == "crop" and work.get("crop") is None and "rectify" in latest and latest["rectify"].status == "failed":
            statuses[stage] = _status(
                "skipped",
                f"not asked: rectification failed ({latest['rectify'].reason}); a curator can send the card to the "
                "crowd for crop boxes",
            )
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
    card: Card,
    latest: dict[str, StageResult],
    work: dict[str, Any],
    waiting: tuple[Waiting, ...],
    stale: dict[str, str],
    recomputing: tuple[str, ...] = (),
    worker_alive: bool = False,
    outdated: str | None = None,
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
    withdrawn = _withdrawn(work)
    if withdrawn is not None:
        earlier = [stage for stage in WITHDRAWN_BY_NOT_STEREO if stage in latest and latest[stage].status in FINISHED]
        also = f"; its earlier {', '.join(earlier)} {'is' if len(earlier) == 1 else 'are'} withdrawn" if earlier else ""
        return f"This card has left the flow: {withdrawn}, so it is not rectified, graded, accepted or released{also}."
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
    out_of_date = next((name for name in stale if name in GRADED_BY), None)
    if out_of_date is not None:
        if recomputing:
            then = f"a pipeline worker is recomputing its {', '.join(recomputing)} now"
        elif worker_alive:
            then = "the background worker recomputes it shortly, and the card comes back to the review queue"
        else:
            then = "no background worker is running: `keystone worker` or `keystone run` recomputes it"
        return f"This card's {out_of_date} result is out of date ({stale[out_of_date]}): {then}."
    if recomputing:
        return f"A pipeline worker is computing this card's {', '.join(recomputing)} now."
    if outdated is not None:
        return f"This card's acceptance no longer applies: {outdated}. It goes back to the review queue."
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

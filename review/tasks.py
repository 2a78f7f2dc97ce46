"""Use cases of curator review: the queue, decisions, disputed crowd answers and the audit trail.

Every function runs inside the caller's app context, takes no request objects and commits its
own transaction. A change and the audit event that describes it are committed together.
Errors a curator can cause are :class:`ReviewError` (with an HTTP status and a sentence);
a decision made against an older version of a card's review is a :class:`ReviewConflict`
that names who changed the card and when, so nobody silently overwrites a colleague.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import and_, func, or_, select
from sqlalchemy.orm import selectinload
from sqlalchemy.orm.exc import StaleDataError

from annotation.models import Aggregate, Answer, BatchItem, GoldAnswer
from core.audit import AuditEvent, record_event
from core.db import db, utcnow
from core.models import Card, Person, StageResult

from .models import GRADE_NAMES, GRADES, CardReview

ACTIONS: tuple[str, ...] = ("accept", "change", "send_back", "reject")
QUEUE_DECISIONS: tuple[str, ...] = ("pending", "accepted", "changed", "sent_back", "rejected", "all")
SEND_BACK_KINDS: tuple[str, ...] = ("crop", "judge")
SEND_BACK_ANSWERS = 3  # answers per item in a batch made by sending a card back
SEND_BACK_GOLD_ITEMS = 3  # curator-made gold answers mixed into such a batch, when there are any
SEND_BACK_GOLD_RATE = 0.25
MAX_NOTE_CHARS = 2000
SYNC_CHUNK = 500  # cards per transaction in sync_reviews; also under SQLite's bound-parameter limit


class ReviewError(Exception):
    """Something a curator asked that cannot be done: shown to them, ``status`` for the HTTP reply."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


class ReviewConflict(ReviewError):
    """The card changed since the curator loaded it; ``message`` names who changed it and when."""

    def __init__(
        self,
        message: str,
        *,
        review_id: int,
        card_id: int,
        current_version: int,
        changed_by: str | None,
        changed_at: datetime | None,
    ) -> None:
        super().__init__(message, 409)
        self.review_id = review_id
        self.card_id = card_id
        self.current_version = current_version
        self.changed_by = changed_by
        self.changed_at = changed_at


class CardHeldBack(ReviewError):
    """An accept or grade change refused (409) because :mod:`runs.card_state` holds the card back;
    ``dispute_ids``: the crowd aggregates to resolve first, so the answer can link to them."""

    def __init__(self, message: str, *, card_id: int, dispute_ids: Sequence[int] = ()) -> None:
        super().__init__(message, 409)
        self.card_id = card_id
        self.dispute_ids = tuple(dispute_ids)


def _aware(moment: datetime | None) -> datetime | None:
    # SQLite hands back naive datetimes for DateTime(timezone=True); they were stored as UTC.
    return moment if moment is None or moment.tzinfo else moment.replace(tzinfo=UTC)


def _when(moment: datetime | None) -> str:
    moment = _aware(moment)
    return f"{moment:%Y-%m-%d %H:%M:%S} UTC" if moment else "an unknown time"


# ---------------------------------------------------------------------------------------------
# Syncing reviews with the automatic grade


def grade_uncertainty(metrics: dict[str, Any] | None) -> float | None:
    """The grader's ``uncertainty`` in [0, 1] (0 = sure, 1 = on a threshold), None if absent or not finite."""
    value = (metrics or {}).get("uncertainty")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return min(1.0, max(0.0, float(value)))


def grade_reasons(result: StageResult | None) -> list[str]:
    """The grader's reasons in words: ``metrics["reasons"]``, else the "; "-joined ``reason``."""
    if result is None:
        return []
    listed = (result.metrics or {}).get("reasons")
    if isinstance(listed, list) and all(isinstance(r, str) for r in listed):
        return list(listed)
    return [part.strip() for part in (result.reason or "").split(";") if part.strip()]


@dataclass(frozen=True)
class _Grade:
    """The columns of a grade result that a review is synced from."""

    card_id: int
    param_hash: str
    outcome: str
    reason: str | None
    metrics: dict[str, Any]
    ran_at: datetime | None


def _latest_grades(card_ids: Sequence[int]) -> dict[int, _Grade]:
    """The newest usable grade per card: status done and an outcome that is a grade.

    Results are upserted in place when a stage reruns with the same parameters, so "newest" is
    by when it ran (``started_at``, else ``created_at``), then by id. Plain rows, not ORM
    objects: a sync over 250,000 cards should not build an identity map of results.
    """
    latest: dict[int, tuple[tuple[datetime, int], _Grade]] = {}
    rows = db.session.execute(
        select(
            StageResult.id,
            StageResult.card_id,
            StageResult.param_hash,
            StageResult.outcome,
            StageResult.reason,
            StageResult.metrics,
            StageResult.started_at,
            StageResult.created_at,
        ).where(
            StageResult.card_id.in_(card_ids),
            StageResult.stage == "grade",
            StageResult.status == "done",
            StageResult.outcome.in_(GRADES),
        )
    )
    for result_id, card_id, phash, outcome, reason, metrics, started_at, created_at in rows:
        ran_at = _aware(started_at or created_at)
        key = (ran_at or utcnow(), result_id)
        if card_id not in latest or key > latest[card_id][0]:
            latest[card_id] = (key, _Grade(card_id, phash, outcome, reason, metrics or {}, ran_at))
    return {card_id: entry[1] for card_id, entry in latest.items()}


def _grade_reasons_of(grade: _Grade) -> str:
    listed = grade.metrics.get("reasons")
    if isinstance(listed, list) and all(isinstance(r, str) for r in listed):
        return "; ".join(listed)
    return grade.reason or ""


@dataclass
class SyncReport:
    created: int = 0
    updated: int = 0  # pending reviews whose automatic grade changed
    reopened: int = 0  # sent-back cards graded again, accepted ones recomputed: back in the queue
    decided_changed: int = 0  # decided cards whose automatic grade changed (final grade kept)
    unchanged: int = 0

    def as_json(self) -> dict[str, int]:
        return dict(self.__dict__)


def _auto_snapshot(review: CardReview) -> dict[str, Any]:
    return {
        "auto_grade": review.auto_grade,
        "auto_param_hash": review.auto_param_hash,
        "uncertainty": review.uncertainty,
        "decision": review.decision,
        "grade": review.grade,
    }


def sync_reviews(card_ids: Iterable[int] | None = None) -> SyncReport:
    """Create or update one :class:`CardReview` per graded card from its latest grade result.

    A new automatic grade on a pending card replaces the old one (audit entity ``grade``). A
    decided card keeps its final grade and decision; the new automatic grade is recorded on the
    review and in the audit trail so the curator's label can be compared with it. A card sent
    back to the crowd and graded again after that returns to the queue as pending. Running it
    twice changes nothing the second time. Commits every :data:`SYNC_CHUNK` cards.
    """
    report = SyncReport()
    if card_ids is None:
        graded = select(StageResult.card_id).where(StageResult.stage == "grade", StageResult.status == "done").distinct()
        wanted = sorted(db.session.scalars(graded))
    else:
        wanted = sorted(set(card_ids))
    for start in range(0, len(wanted), SYNC_CHUNK):
        chunk = wanted[start : start + SYNC_CHUNK]
        grades = _latest_grades(chunk)
        reviews = {r.card_id: r for r in db.session.scalars(select(CardReview).where(CardReview.card_id.in_(chunk)))}
        # Events need review ids: collect them, flush the chunk once, then write them.
        events: list[tuple[CardReview, str, dict[str, Any] | None, _Grade]] = []
        for card_id in chunk:
            grade = grades.get(card_id)
            if grade is not None:
                _sync_one(reviews.get(card_id), grade, report, events)
        db.session.flush()
        for review, action, before, grade in events:
            record_event(
                entity="grade",
                action=action,
                card_id=review.card_id,
                entity_id=review.id,
                actor_label="pipeline",
                before=before,
                after=_auto_snapshot(review),
                why=_grade_reasons_of(grade),
            )
        _reopen_outdated_acceptances([r for r in reviews.values() if r.decision in ("accepted", "changed")], report)
        db.session.commit()
    return report


def _reopen_outdated_acceptances(decided: list[CardReview], report: SyncReport) -> None:
    """Send back to the queue every accepted card whose results were recomputed after the
    acceptance (:func:`runs.card_state.acceptance_outdated`): the curator looks again at what
    will be released. The trail says why (entity ``review``, action ``reopened_after_recompute``)."""
    from runs.card_state import acceptance_outdated

    if not decided:
        return
    cards = {
        card.id: card
        for card in db.session.scalars(
            select(Card).where(Card.id.in_([r.card_id for r in decided])).options(selectinload(Card.stage_results))
        )
    }
    for review in decided:
        card = cards.get(review.card_id)
        why = acceptance_outdated(review, card.latest_results()) if card is not None else None
        if why is None:
            continue
        before = review_snapshot(review)
        review.decision, review.grade, review.decided_at, review.accepted_results = "pending", None, None, None
        db.session.flush()
        record_event(
            entity="review",
            action="reopened_after_recompute",
            card_id=review.card_id,
            entity_id=review.id,
            actor_label="pipeline",
            before=before,
            after=review_snapshot(review),
            why=f"{why}: the acceptance applied to the results it was given; a curator looks again",
        )
        report.reopened += 1


def _sync_one(
    review: CardReview | None,
    grade: _Grade,
    report: SyncReport,
    events: list[tuple[CardReview, str, dict[str, Any] | None, _Grade]],
) -> None:
    uncertainty = grade_uncertainty(grade.metrics)
    if review is None:
        review = CardReview(
            card_id=grade.card_id,
            auto_grade=grade.outcome,
            auto_param_hash=grade.param_hash,
            uncertainty=uncertainty,
            decision="pending",
            note="",
        )
        db.session.add(review)
        events.append((review, "graded", None, grade))
        report.created += 1
        return
    same_grade = (review.auto_grade, review.auto_param_hash) == (grade.outcome, grade.param_hash)
    decided_at = _aware(review.decided_at)
    regraded_after_send_back = (
        review.decision == "sent_back" and grade.ran_at is not None and decided_at is not None and grade.ran_at > decided_at
    )
    if same_grade and review.uncertainty == uncertainty and not regraded_after_send_back:
        report.unchanged += 1
        return
    before = _auto_snapshot(review)
    review.auto_grade, review.auto_param_hash, review.uncertainty = grade.outcome, grade.param_hash, uncertainty
    if regraded_after_send_back:
        review.decision, review.grade = "pending", None
        action = "regraded_after_send_back"
        report.reopened += 1
    elif review.decision == "pending":
        action = "auto_grade_changed"
        report.updated += 1
    else:
        # Never touch a curator's final grade; the trail shows the grader now disagrees (or agrees).
        action = "auto_grade_changed_after_decision"
        report.decided_changed += 1
    events.append((review, action, before, grade))


# ---------------------------------------------------------------------------------------------
# The queue


@dataclass(frozen=True)
class QueueFilters:
    grade: str | None = None  # the automatic grade
    collection_id: int | None = None
    reason: str | None = None  # substring of the grader's reasons, case-insensitive
    decision: str = "pending"  # or "all"

    def __post_init__(self) -> None:
        if self.grade is not None and self.grade not in GRADES:
            raise ReviewError(f"Unknown grade {self.grade!r}; expected one of {', '.join(GRADES)}")
        if self.decision not in QUEUE_DECISIONS:
            raise ReviewError(f"Unknown decision {self.decision!r}; expected one of {', '.join(QUEUE_DECISIONS)}")
        if self.reason is not None and len(self.reason) > 200:
            raise ReviewError("Expected a reason filter of at most 200 characters")

    def query_args(self) -> dict[str, Any]:
        args = {
            "grade": self.grade,
            "collection": self.collection_id,
            "reason": self.reason,
            "decision": self.decision if self.decision != "pending" else None,
        }
        return {key: value for key, value in args.items() if value not in (None, "")}


@dataclass(frozen=True)
class QueueRow:
    review_id: int
    card_id: int
    version: int
    auto_grade: str | None
    grade: str | None
    decision: str
    uncertainty: float | None
    reasons: list[str]
    collection: str
    title: str
    content_hash: str


@dataclass(frozen=True)
class QueuePage:
    rows: list[QueueRow]
    total: int
    limit: int
    offset: int


def _escape_like(text: str) -> str:
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def _grade_join() -> Any:
    # The grade result the review was synced from: unique by (card, stage, parameters).
    return and_(
        StageResult.card_id == CardReview.card_id,
        StageResult.stage == "grade",
        StageResult.param_hash == CardReview.auto_param_hash,
    )


def _queue_conditions(filters: QueueFilters) -> list[Any]:
    conditions: list[Any] = []
    if filters.decision != "all":
        conditions.append(CardReview.decision == filters.decision)
    if filters.grade is not None:
        conditions.append(CardReview.auto_grade == filters.grade)
    if filters.collection_id is not None:
        conditions.append(Card.collection_id == filters.collection_id)
    if filters.reason:
        conditions.append(StageResult.reason.ilike(f"%{_escape_like(filters.reason.strip())}%", escape="\\"))
    return conditions


def _queue_select(filters: QueueFilters, *columns: Any) -> Any:
    query = select(*columns).select_from(CardReview)
    if filters.collection_id is not None:
        query = query.join(Card, Card.id == CardReview.card_id)
    if filters.reason:
        query = query.join(StageResult, _grade_join())
    return query.where(*_queue_conditions(filters))


QUEUE_ORDER = (CardReview.uncertainty.desc().nulls_last(), CardReview.card_id)


def review_queue(
    grade: str | None = None,
    collection_id: int | None = None,
    reason: str | None = None,
    decision: str = "pending",
    limit: int = 50,
    offset: int = 0,
) -> QueuePage:
    """Reviews sorted by uncertainty (most uncertain first; unknown last), then card id.

    ``grade`` filters the automatic grade, ``reason`` is a case-insensitive substring of the
    grader's reasons, ``decision`` is one of :data:`QUEUE_DECISIONS`. One query for the page
    (card, collection and grade result joined), one for the count.
    """
    if not 1 <= limit <= 500:
        raise ReviewError(f"Expected 1 <= limit <= 500, got {limit}")
    if offset < 0:
        raise ReviewError(f"Expected offset >= 0, got {offset}")
    filters = QueueFilters(grade, collection_id, reason or None, decision)
    total = db.session.scalar(_queue_select(filters, func.count())) or 0
    query = (
        select(CardReview, Card, StageResult)
        .join(Card, Card.id == CardReview.card_id)
        .outerjoin(StageResult, _grade_join())
        .where(*_queue_conditions(filters))
        .options(selectinload(Card.collection))
        .order_by(*QUEUE_ORDER)
        .limit(limit)
        .offset(offset)
    )
    rows = []
    for review, card, result in db.session.execute(query):
        metadata = card.source_metadata or {}
        title = str(metadata.get("title") or metadata.get("Title") or card.accession or card.source_name)
        rows.append(
            QueueRow(
                review.id,
                card.id,
                review.version,
                review.auto_grade,
                review.grade,
                review.decision,
                review.uncertainty,
                grade_reasons(result),
                card.collection.name,
                title,
                card.content_hash,
            )
        )
    return QueuePage(rows, total, limit, offset)


def queue_neighbours(card_id: int, filters: QueueFilters) -> tuple[int | None, int | None]:
    """(previous, next) card ids around ``card_id`` in the queue order, by keyset.

    Works whether or not the card itself still matches the filters (after a decision it has
    left the pending queue, and "next" is the card that followed it).
    """
    review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
    if review is None:
        return None, None
    u, base = review.uncertainty, _queue_select(filters, CardReview.card_id)
    if u is not None:
        after = base.where(
            or_(
                CardReview.uncertainty < u,
                and_(CardReview.uncertainty == u, CardReview.card_id > card_id),
                CardReview.uncertainty.is_(None),
            )
        )
        before = base.where(or_(CardReview.uncertainty > u, and_(CardReview.uncertainty == u, CardReview.card_id < card_id)))
        following = db.session.scalar(after.order_by(*QUEUE_ORDER).limit(1))
        previous = db.session.scalar(before.order_by(CardReview.uncertainty.asc(), CardReview.card_id.desc()).limit(1))
        return previous, following
    following = db.session.scalar(
        base.where(CardReview.uncertainty.is_(None), CardReview.card_id > card_id).order_by(CardReview.card_id).limit(1)
    )
    previous = db.session.scalar(
        base.where(CardReview.uncertainty.is_(None), CardReview.card_id < card_id).order_by(CardReview.card_id.desc()).limit(1)
    )
    if previous is None:
        previous = db.session.scalar(
            base.where(CardReview.uncertainty.is_not(None))
            .order_by(CardReview.uncertainty.asc(), CardReview.card_id.desc())
            .limit(1)
        )
    return previous, following


# ---------------------------------------------------------------------------------------------
# Decisions


def review_snapshot(review: CardReview) -> dict[str, Any]:
    return {
        "decision": review.decision,
        "grade": review.grade,
        "auto_grade": review.auto_grade,
        "note": review.note,
        "reviewer_id": review.reviewer_id,
        "version": review.version,
        "accepted_results": review.accepted_results,
    }


def _last_change(review: CardReview) -> tuple[str | None, datetime | None]:
    """Who last changed this review and when, from the audit trail (else the review's own fields)."""
    last = db.session.scalar(
        select(AuditEvent)
        .where(AuditEvent.entity.in_(("review", "grade")), AuditEvent.entity_id == review.id)
        .order_by(AuditEvent.id.desc())
        .limit(1)
    )
    if last is not None:
        return last.actor, _aware(last.at)
    who = db.session.get(Person, review.reviewer_id) if review.reviewer_id else None
    return (who.username if who else None), _aware(review.decided_at or review.updated_at)


def _flush_or_conflict(review_id: int, expected_version: int) -> None:
    """Flush the review's change; the flush bumps its version, and a concurrent writer's flush
    makes this one stale: then roll back and raise the conflict with the review as it now is."""
    try:
        db.session.flush()
    except StaleDataError:
        db.session.rollback()
        fresh = db.session.get(CardReview, review_id, populate_existing=True)
        assert fresh is not None
        conflict = _conflict(fresh, expected_version)
        db.session.rollback()
        raise conflict from None


def _review_at_version(review_id: int, expected_version: int) -> CardReview:
    """The review as stored now, if it is still at the version the curator saw; else roll back
    and raise (404 for no such review, :class:`ReviewConflict` naming who changed it)."""
    review = db.session.get(CardReview, review_id, populate_existing=True)
    if review is None:
        db.session.rollback()
        raise ReviewError(f"There is no review {review_id}", 404)
    if review.version != expected_version:
        conflict = _conflict(review, expected_version)
        db.session.rollback()
        raise conflict
    return review


def _conflict(review: CardReview, expected_version: int) -> ReviewConflict:
    who, when = _last_change(review)
    state = review.decision.replace("_", " ")
    if review.grade:
        state += f", grade {GRADE_NAMES[review.grade]}"
    message = (
        f"Card {review.card_id} was changed by {who or 'someone'} at {_when(when)} while you had it open "
        f"(you saw version {expected_version}, it is now version {review.version}: {state}). "
        "Nothing was saved; reload the card to see their change before deciding."
    )
    return ReviewConflict(
        message, review_id=review.id, card_id=review.card_id, current_version=review.version, changed_by=who, changed_at=when
    )


def _gold_for_batch(kind: str, exclude: int) -> dict[int, dict[str, Any]]:
    """The newest curator-made gold answers of ``kind``; one that no longer fits its card is left out
    rather than blocking the send-back (create_batch refuses a batch with any invalid gold)."""
    from annotation.answers import validate_payload
    from annotation.task_errors import TaskError

    gold: dict[int, dict[str, Any]] = {}
    rows = db.session.execute(
        select(GoldAnswer, Card)
        .join(Card, Card.id == GoldAnswer.card_id)
        .where(GoldAnswer.kind == kind, GoldAnswer.card_id != exclude)
        .order_by(GoldAnswer.id.desc())
        .limit(4 * SEND_BACK_GOLD_ITEMS)
    )
    for row, card in rows:
        try:
            gold[row.card_id] = validate_payload(kind, row.answer, card)
        except TaskError:
            continue
        if len(gold) == SEND_BACK_GOLD_ITEMS:
            break
    return gold


@dataclass(frozen=True)
class Decided:
    review_id: int
    card_id: int
    decision: str
    grade: str | None
    version: int
    batch_id: int | None = None  # the crowd batch a sent-back card went into


def decide(
    review_id: int,
    action: str,
    *,
    expected_version: int,
    curator: Person,
    grade: str | None = None,
    note: str = "",
    kind: str = "crop",
    shown_results: str | None = None,
) -> Decided:
    """Apply a curator's decision to one review, refusing it if the review moved on meanwhile.

    An accept or a grade change is given the card's results as they are (recorded on the
    review: an acceptance applies to those only); with ``shown_results`` (the digest the
    curator's page showed, :func:`card_results_digest`) it is refused if they were recomputed
    since the page was loaded.

    accept: the automatic grade becomes the final grade. change: ``grade`` does (a change to
    the automatic grade itself is recorded as an accept). send_back: the card goes into a new
    crowd batch of ``kind`` (crop or judge, with curator-made gold items mixed in when there are
    any) and leaves the queue until it is graded again. reject: never released, no grade.
    The review, its audit event (before, after, why = ``note``) and any batch commit together.
    """
    if action not in ACTIONS:
        raise ReviewError(f"Unknown action {action!r}; expected one of {', '.join(ACTIONS)}")
    if isinstance(expected_version, bool) or not isinstance(expected_version, int):
        raise ReviewError(f"Expected the review version you saw as a whole number, got {expected_version!r}")
    note = (note or "").strip()
    if len(note) > MAX_NOTE_CHARS:
        raise ReviewError(f"Expected a note of at most {MAX_NOTE_CHARS} characters, got {len(note)}")
    if action == "change" and grade not in GRADES:
        raise ReviewError(f"Expected a grade from {', '.join(GRADES)} to change to, got {grade!r}")
    if action == "send_back" and kind not in SEND_BACK_KINDS:
        raise ReviewError(f"Expected the crowd task to send back to be crop or judge, got {kind!r}")
    review = _review_at_version(review_id, expected_version)
    if action == "accept" and review.auto_grade is None:
        db.session.rollback()
        raise ReviewError(f"Card {review.card_id} has no automatic grade to accept; choose a grade instead")
    given = None
    if action in ("accept", "change"):
        _refuse_a_card_held_back(review)
        given = _results_given(review, shown_results)
    before = review_snapshot(review)
    decision, final = {
        "accept": ("accepted", review.auto_grade),
        "change": ("accepted" if grade == review.auto_grade else "changed", grade),
        "send_back": ("sent_back", None),
        "reject": ("rejected", None),
    }[action]
    review.decision, review.grade, review.note = decision, final, note
    review.reviewer_id, review.decided_at = curator.id, utcnow()
    # The acceptance applies to these results only: recomputed ones go back to a curator.
    review.accepted_results = given
    _flush_or_conflict(review_id, expected_version)
    after = review_snapshot(review)
    if action == "send_back":
        after["sent_to"] = kind
    record_event(
        entity="review",
        action=action,
        card_id=review.card_id,
        entity_id=review.id,
        actor=curator,
        before=before,
        after=after,
        why=note,
    )
    outcome = Decided(review.id, review.card_id, review.decision, review.grade, review.version)
    if action != "send_back":
        db.session.commit()
        return outcome
    return _send_back(outcome, kind, curator, note)


def _results_given(review: CardReview, shown_results: str | None) -> dict[str, Any]:
    """The results an accept or grade change is given (runs.card_state.results_fingerprint).
    ``shown_results``: the digest of those the curator's page showed (:func:`results_digest`);
    if the card's results were recomputed since, the decision is refused rather than applied
    to results nobody looked at."""
    from runs.card_state import results_fingerprint

    given = results_fingerprint(review.card.latest_results())
    if shown_results is not None and shown_results != results_digest(given):
        db.session.rollback()
        raise ReviewError(
            f"Card {review.card_id}'s results were recomputed since you opened it: nothing was saved. "
            "Reload the card and look at its new results before deciding.",
            409,
        )
    return given


def results_digest(fingerprint: dict[str, Any]) -> str:
    """A short digest of a results fingerprint, for a page to send back with a decision (the
    pipeline's sorted-JSON digest, as each result's inputs are digested)."""
    from pipeline.records import inputs_digest

    return inputs_digest(fingerprint)


def card_results_digest(card: Card) -> str:
    """:func:`results_digest` of the results ``card`` has now (what its review page shows)."""
    from runs.card_state import results_fingerprint

    return results_digest(results_fingerprint(card.latest_results()))


def _refuse_a_card_held_back(review: CardReview) -> None:
    """The review gate: a card :mod:`runs.card_state` says is held back (a crowd dispute, an
    undecided orientation, a stale result) is not accepted; the same answer keeps it out of a
    release."""
    from pipeline.decided_orientation import is_decided
    from runs.card_state import card_state

    state = card_state(review.card)
    card_id = review.card_id
    if state.disputes:
        db.session.rollback()
        what = " and ".join(wait.reason.removeprefix("the crowd disagrees on ") for wait in state.disputes)
        raise CardHeldBack(
            f"Card {card_id} cannot be accepted while the crowd disagrees on {what}: "
            "resolve it under Disputed crowd answers first",
            card_id=card_id,
            dispute_ids=[wait.aggregate_id for wait in state.disputes if wait.aggregate_id is not None],
        )
    if state.blockers:
        db.session.rollback()
        then = (
            "Nothing of it is accepted or released"
            if state.withdrawn is not None
            else "Decide its orientation on the card's page (or wait for the crowd) first"
            if not is_decided(state.orientation)
            else "It comes back to the queue once it is recomputed (the background worker does it, or keystone run)"
        )
        raise CardHeldBack(f"Card {card_id} cannot be accepted: {'; '.join(state.blockers)}. {then}", card_id=card_id)


def _send_back(outcome: Decided, kind: str, curator: Person, note: str) -> Decided:
    from annotation.batches import create_batch
    from annotation.task_errors import TaskError

    gold = _gold_for_batch(kind, outcome.card_id)
    try:
        # create_batch commits: the decision, its audit event and the batch land together.
        batch = create_batch(
            [outcome.card_id], kind, SEND_BACK_ANSWERS, SEND_BACK_GOLD_RATE if gold else 0.0, gold=gold, created_by=curator.id
        )
    except TaskError as exc:
        db.session.rollback()
        raise ReviewError(f"Card {outcome.card_id} could not be sent back to the crowd: {exc.message}", exc.status) from exc
    # The batch id exists only once create_batch has committed; link it in the trail right after.
    record_event(
        entity="batch",
        action="created_for_send_back",
        card_id=outcome.card_id,
        entity_id=batch.id,
        actor=curator,
        before=None,
        after={"batch": batch.id, "kind": kind, "answers_per_item": SEND_BACK_ANSWERS, "gold_items": sorted(gold)},
        why=note,
    )
    db.session.commit()
    return Decided(outcome.review_id, outcome.card_id, outcome.decision, outcome.grade, outcome.version, batch.id)


def undo_decision(review_id: int, *, expected_version: int, curator: Person) -> Decided:
    """Put a review back as it was before its latest decision (accept, change, send back, reject).

    ``expected_version`` is the version the decision left: if anyone changed the card since,
    the undo is refused as a :class:`ReviewConflict`. Undoing a send-back removes the crowd
    batch it made, refused (409) once an annotator has answered in it or holds a task from it.
    The restored review and an audit event (action ``undo``) commit together.
    """
    from annotation.models import Batch, Reservation

    if isinstance(expected_version, bool) or not isinstance(expected_version, int):
        raise ReviewError(f"Expected the review version to undo as a whole number, got {expected_version!r}")
    review = _review_at_version(review_id, expected_version)
    last = db.session.scalar(
        select(AuditEvent)
        .where(AuditEvent.entity == "review", AuditEvent.entity_id == review.id)
        .order_by(AuditEvent.id.desc())
        .limit(1)
    )
    if last is None or last.action not in ACTIONS or not isinstance(last.before, dict):
        db.session.rollback()
        raise ReviewError(f"Card {review.card_id} has no decision to undo", 409)
    batch = None
    if last.action == "send_back":
        batch_id = db.session.scalar(
            select(AuditEvent.entity_id)
            .where(
                AuditEvent.entity == "batch",
                AuditEvent.action == "created_for_send_back",
                AuditEvent.card_id == review.card_id,
                AuditEvent.id > last.id,
            )
            .order_by(AuditEvent.id)
            .limit(1)
        )
        batch = db.session.get(Batch, batch_id) if batch_id is not None else None
        if batch is not None:
            item_ids = [item.id for item in batch.items]
            answered = db.session.scalar(select(func.count()).select_from(Answer).where(Answer.item_id.in_(item_ids)))
            held = db.session.scalar(select(func.count()).select_from(Reservation).where(Reservation.item_id.in_(item_ids)))
            if answered or held:
                db.session.rollback()
                raise ReviewError(
                    f"Card {review.card_id} cannot be taken back from crowd batch {batch.id}: "
                    f"annotators have already answered ({answered}) or hold tasks ({held}) in it",
                    409,
                )
    before, previous = review_snapshot(review), last.before
    review.decision = previous.get("decision") or "pending"
    review.grade = previous.get("grade")
    review.note = previous.get("note") or ""
    review.reviewer_id = previous.get("reviewer_id")
    review.accepted_results = previous.get("accepted_results")
    if review.decision == "pending":
        review.decided_at = None
    _flush_or_conflict(review_id, expected_version)
    after = review_snapshot(review)
    if batch is not None:
        after["removed_batch"] = batch.id
        record_event(
            entity="batch",
            action="removed_by_undo",
            card_id=review.card_id,
            entity_id=batch.id,
            actor=curator,
            before={"batch": batch.id, "kind": batch.kind},
            after=None,
            why=f"undo of the send-back of card {review.card_id}",
        )
        db.session.delete(batch)
    record_event(
        entity="review",
        action="undo",
        card_id=review.card_id,
        entity_id=review.id,
        actor=curator,
        before=before,
        after=after,
        why=f"undo of {last.action.replace('_', ' ')} (audit event {last.id})",
    )
    db.session.commit()
    return Decided(review.id, review.card_id, review.decision, review.grade, review.version)


def redo_decision(review_id: int, *, expected_version: int, curator: Person) -> Decided:
    """Make again the decision the review's latest undo took back (accept, change, send back,
    reject), with its grade, note and crowd task, as a new decision by ``curator``.

    ``expected_version`` is the version the undo left; refused as a :class:`ReviewConflict` if
    anyone changed the card since, and (409) unless the latest change to the review is an undo.
    An accept or a grade change is given the card's results as they are now, as any decision is;
    a send-back makes a new crowd batch (the undo removed the first one).
    """
    if isinstance(expected_version, bool) or not isinstance(expected_version, int):
        raise ReviewError(f"Expected the review version to redo from as a whole number, got {expected_version!r}")
    review = _review_at_version(review_id, expected_version)
    events = select(AuditEvent).where(AuditEvent.entity == "review", AuditEvent.entity_id == review.id)
    last = db.session.scalar(events.order_by(AuditEvent.id.desc()).limit(1))
    undone = (
        db.session.scalar(
            events.where(AuditEvent.id < last.id, AuditEvent.action.in_(ACTIONS)).order_by(AuditEvent.id.desc()).limit(1)
        )
        if last is not None and last.action == "undo"
        else None
    )
    if undone is None or not isinstance(undone.after, dict):
        db.session.rollback()
        raise ReviewError(f"Card {review.card_id} has no undone decision to redo", 409)
    card_id, after = review.card_id, undone.after
    db.session.rollback()  # decide() reads the review afresh at the same version
    decided = decide(
        review_id,
        undone.action,
        expected_version=expected_version,
        curator=curator,
        grade=after.get("grade") if undone.action == "change" else None,
        note=str(after.get("note") or ""),
        kind=str(after.get("sent_to") or "crop"),
    )
    assert decided.card_id == card_id
    return decided


@dataclass(frozen=True)
class BulkOutcome:
    review_id: int
    status: str  # applied | conflict | error
    message: str = ""
    decided: Decided | None = None

    def as_json(self) -> dict[str, Any]:
        document: dict[str, Any] = {"review": self.review_id, "status": self.status, "message": self.message}
        if self.decided is not None:
            document.update(
                card=self.decided.card_id, decision=self.decided.decision, grade=self.decided.grade, version=self.decided.version
            )
        return document


def bulk_decide(
    review_ids_with_versions: Sequence[tuple[int, int]],
    action: str,
    *,
    curator: Person,
    grade: str | None = None,
    note: str = "",
    kind: str = "crop",
) -> list[BulkOutcome]:
    """:func:`decide` for each (review id, version seen); one conflict or refusal never stops the others."""
    if action not in ACTIONS:
        raise ReviewError(f"Unknown action {action!r}; expected one of {', '.join(ACTIONS)}")
    if not review_ids_with_versions:
        raise ReviewError("Select at least one card")
    outcomes = []
    for review_id, version in review_ids_with_versions:
        try:
            decided = decide(review_id, action, expected_version=version, curator=curator, grade=grade, note=note, kind=kind)
        except ReviewConflict as exc:
            outcomes.append(BulkOutcome(review_id, "conflict", exc.message))
        except ReviewError as exc:
            outcomes.append(BulkOutcome(review_id, "error", exc.message))
        else:
            outcomes.append(BulkOutcome(review_id, "applied", decided=decided))
    return outcomes


# ---------------------------------------------------------------------------------------------
# Disputed crowd answers


def disputed_aggregates(limit: int = 50, offset: int = 0) -> tuple[list[Aggregate], int]:
    """Crowd aggregates waiting for a curator (oldest first) and how many there are."""
    condition = Aggregate.state == "needs_curator"
    total = db.session.scalar(select(func.count()).select_from(Aggregate).where(condition)) or 0
    rows = list(db.session.scalars(select(Aggregate).where(condition).order_by(Aggregate.id).limit(limit).offset(offset)))
    return rows, total


def aggregate_answers(aggregate: Aggregate) -> list[Answer]:
    """The individual crowd answers behind an aggregate (flagged workers' answers included, marked)."""
    return list(
        db.session.scalars(
            select(Answer)
            .join(BatchItem, Answer.item_id == BatchItem.id)
            .where(BatchItem.batch_id == aggregate.batch_id, BatchItem.card_id == aggregate.card_id)
            .order_by(Answer.id)
        )
    )


def _aggregate_snapshot(aggregate: Aggregate) -> dict[str, Any]:
    return {
        "state": aggregate.state,
        "label": aggregate.label,
        "reasons": aggregate.reasons,
        "resolved_by": aggregate.resolved_by,
        "batch": aggregate.batch_id,
        "kind": aggregate.kind,
    }


@dataclass(frozen=True)
class Resolved:
    aggregate_id: int
    card_id: int
    label: dict[str, Any]
    gold_id: int | None


def resolve_aggregate(aggregate_id: int, label: Any, *, curator: Person, make_gold: bool = False, note: str = "") -> Resolved:
    """A curator's answer for a disputed crowd aggregate becomes the card's truth.

    ``label`` is checked as a crowd answer would be (judge: ``is_stereo``/``upside_down``/
    ``inverted`` booleans; crop: ``left``/``right`` boxes ``[x0, y0, x1, y1]`` in original
    pixels inside the card). With ``make_gold`` it is also stored as the card's gold answer
    for later batches (replacing an older one of the same kind). Audit: entity ``aggregate``
    and, for gold, entity ``gold``; all in one transaction.
    """
    from annotation.answers import validate_payload
    from annotation.task_errors import TaskError

    note = (note or "").strip()
    if len(note) > MAX_NOTE_CHARS:
        raise ReviewError(f"Expected a note of at most {MAX_NOTE_CHARS} characters, got {len(note)}")
    aggregate = db.session.get(Aggregate, aggregate_id, populate_existing=True)
    if aggregate is None:
        db.session.rollback()
        raise ReviewError(f"There is no crowd aggregate {aggregate_id}", 404)
    if aggregate.state != "needs_curator":
        who = db.session.get(Person, aggregate.resolved_by) if aggregate.resolved_by else None
        message = (
            f"The crowd answer for card {aggregate.card_id} was already resolved by "
            f"{who.username if who else 'the crowd consensus'} at {_when(aggregate.updated_at)}; "
            "nothing was saved. Reload to see it."
        )
        db.session.rollback()
        raise ReviewConflict(
            message,
            review_id=aggregate.id,
            card_id=aggregate.card_id,
            current_version=0,
            changed_by=who.username if who else None,
            changed_at=_aware(aggregate.updated_at),
        )
    card = db.session.get(Card, aggregate.card_id)
    assert card is not None
    try:
        canonical = validate_payload(aggregate.kind, label, card)
    except TaskError as exc:
        db.session.rollback()
        raise ReviewError(exc.message) from exc
    before = _aggregate_snapshot(aggregate)
    aggregate.label, aggregate.state, aggregate.resolved_by = canonical, "approved", curator.id
    db.session.flush()
    record_event(
        entity="aggregate",
        action="resolved",
        card_id=card.id,
        entity_id=aggregate.id,
        actor=curator,
        before=before,
        after=_aggregate_snapshot(aggregate),
        why=note,
    )
    gold_id = None
    if make_gold:
        gold = db.session.scalar(select(GoldAnswer).where(GoldAnswer.card_id == card.id, GoldAnswer.kind == aggregate.kind))
        gold_before = None if gold is None else {"answer": gold.answer, "made_by": gold.made_by}
        if gold is None:
            gold = GoldAnswer(card_id=card.id, kind=aggregate.kind, answer=canonical, made_by=curator.id)
            db.session.add(gold)
        else:
            gold.answer, gold.made_by = canonical, curator.id
        db.session.flush()
        record_event(
            entity="gold",
            action="made_gold" if gold_before is None else "replaced_gold",
            card_id=card.id,
            entity_id=gold.id,
            actor=curator,
            before=gold_before,
            after={"answer": canonical, "made_by": curator.id, "kind": aggregate.kind},
            why=note,
        )
        gold_id = gold.id
    if aggregate.kind == "judge" and canonical.get("is_stereo") is False:
        _withdraw_review(card.id, aggregate.id, curator)
    db.session.commit()
    return Resolved(aggregate.id, card.id, canonical, gold_id)


def _withdraw_review(card_id: int, aggregate_id: int, curator: Person) -> None:
    """A ruling "not a stereo pair" takes the card out of the flow: its review, pending or
    decided, becomes rejected (so it leaves the queue and no release holds it), in the same
    transaction as the ruling, and the trail says why."""
    review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
    if review is None or review.decision == "rejected":
        return
    before = review_snapshot(review)
    review.decision, review.grade, review.accepted_results = "rejected", None, None
    review.note = f"withdrawn: ruled not a stereo pair on dispute {aggregate_id}"
    review.reviewer_id, review.decided_at = curator.id, utcnow()
    db.session.flush()
    record_event(
        entity="review",
        action="withdrawn_not_stereo",
        card_id=card_id,
        entity_id=review.id,
        actor=curator,
        before=before,
        after=review_snapshot(review),
        why=f"ruled not a stereo pair on dispute {aggregate_id}: its earlier rectify, disparity and grade are withdrawn",
    )


# ---------------------------------------------------------------------------------------------
# History


def card_history(card_id: int) -> list[AuditEvent]:
    """Every audit event about ``card_id``, oldest first."""
    return list(
        db.session.scalars(select(AuditEvent).where(AuditEvent.card_id == card_id).order_by(AuditEvent.at, AuditEvent.id))
    )


@dataclass
class CrowdView:
    """What the crowd said about a card: the latest aggregate per kind and the answers behind it."""

    crop: Aggregate | None = None
    judge: Aggregate | None = None
    crop_answers: list[Answer] = field(default_factory=list)
    judge_answers: list[Answer] = field(default_factory=list)


def crowd_view(card_id: int) -> CrowdView:
    view = CrowdView()
    for aggregate in db.session.scalars(select(Aggregate).where(Aggregate.card_id == card_id).order_by(Aggregate.id)):
        setattr(view, aggregate.kind, aggregate)  # the newest of each kind wins
    if view.crop is not None:
        view.crop_answers = aggregate_answers(view.crop)
    if view.judge is not None:
        view.judge_answers = aggregate_answers(view.judge)
    return view

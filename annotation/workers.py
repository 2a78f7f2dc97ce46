"""Crowd workers: finding or making them, their gold accuracy and flags, Prolific submission checks.

Every function here runs inside the caller's app context; the writers commit their own transaction.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError

from core.db import db, one_writer, read_only

from .aggregation import (
    HALVES,
    LabelAnswer,
    box_iou,
    flag_workers,
    gold_accuracy,
)
from .crowd_settings import gold_threshold, min_gold
from .models import Answer, Batch, BatchItem, CrowdSession, Reservation, Worker
from .queries import LOCK_ITEMS, on_sqlite, recount_items, run_prebuilt
from .questions import grid_questions, judge_questions, keys
from .task_errors import TaskError


def get_or_create_worker(provider: str, external_id: str, person_id: int | None = None) -> Worker:
    """Find the worker by (provider, external id) or make one; a race is settled by the unique key."""
    query = select(Worker).where(Worker.provider == provider, Worker.external_id == external_id)
    worker = db.session.scalar(query)
    if worker is not None:
        return worker
    worker = Worker(provider=provider, external_id=external_id, person_id=person_id, token=secrets.token_urlsafe(24))
    db.session.add(worker)
    try:
        db.session.commit()
    except IntegrityError:
        db.session.rollback()
        worker = db.session.scalar(query)
        assert worker is not None
    return worker


def account_worker(person_id: int, username: str) -> Worker:
    """The invited worker of a logged-in account (``account:<username>``), made on first use."""
    worker = db.session.scalar(
        select(Worker).where(Worker.provider == "invite", Worker.person_id == person_id).order_by(Worker.id).limit(1)
    )
    return worker or get_or_create_worker("invite", f"account:{username}", person_id=person_id)


def gold_label(kind: str, answer: Mapping[str, Any], gold: Mapping[str, Any]) -> int:
    """1 when the answer matches gold: every judgement both have, every tap of a confirm card,
    or both boxes at IoU >= 0.5."""
    if kind == "confirm":
        return int(all(bool(answer.get(flag)) == bool(gold.get(flag)) for flag in keys(grid_questions())))
    if kind == "judge":
        return int(all(bool(answer[q]) == bool(gold[q]) for q in keys(judge_questions()) if q in answer and q in gold))
    return int(all(box_iou(answer[h], gold[h])[0, 0] >= 0.5 for h in HALVES))


def update_worker_quality(worker_ids: Iterable[int] | None = None) -> dict[int, dict[str, Any]]:
    """Gold accuracy per worker; those below the threshold are flagged with all their answers.

    Scores are read in a read transaction; the write lock is taken only when a worker must be
    newly flagged (every gold submit calls this, and almost all of them change nothing).
    """
    query = (
        select(Answer.item_id, Answer.worker_id, Answer.payload, BatchItem.gold_answer, Batch.kind)
        .join(BatchItem, Answer.item_id == BatchItem.id)
        .join(Batch, BatchItem.batch_id == Batch.id)
        .where(BatchItem.is_gold.is_(True))
    )
    if worker_ids is not None:
        query = query.where(Answer.worker_id.in_(list(worker_ids)))
    threshold = gold_threshold()
    with read_only():
        labels = [
            LabelAnswer(item_id, worker_id, gold_label(kind, payload, gold_answer or {}))
            for item_id, worker_id, payload, gold_answer, kind in db.session.execute(query)
        ]
        scores = gold_accuracy(labels, {a.item_id: 1 for a in labels})
        flagged = flag_workers(scores, threshold, min_gold())
        newly = (
            list(db.session.scalars(select(Worker.id).where(Worker.id.in_(list(flagged)), Worker.flagged.is_(False))))
            if flagged
            else []
        )
    if newly:
        no_sync = {"synchronize_session": False}  # the commit below expires whatever the session holds
        with one_writer():
            # Their answers stop filling slots and their open reservations go back to the pool
            # at once: every item they touched is recounted (locked first on PostgreSQL, so a
            # submit holding one of those items cannot wait on these rows while we wait on it).
            touched = sorted(
                set(db.session.scalars(select(Answer.item_id).where(Answer.worker_id.in_(newly))))
                | set(
                    db.session.scalars(
                        select(Reservation.item_id).where(Reservation.worker_id.in_(newly), Reservation.answered_at.is_(None))
                    )
                )
            )
            if touched and not on_sqlite():
                run_prebuilt(LOCK_ITEMS, {"item_ids": touched})
            db.session.execute(update(Worker).where(Worker.id.in_(newly)).values(flagged=True).execution_options(**no_sync))
            db.session.execute(
                update(Answer).where(Answer.worker_id.in_(newly)).values(flagged=True).execution_options(**no_sync)
            )
            db.session.execute(
                delete(Reservation)
                .where(Reservation.worker_id.in_(newly), Reservation.answered_at.is_(None))
                .execution_options(**no_sync)
            )
            recount_items(touched, locked=True)
            db.session.commit()
    return {
        int(w): {"correct": s.correct, "total": s.total, "accuracy": s.accuracy, "flagged": w in flagged}
        for w, s in scores.items()
    }


def set_worker_flag(worker_id: int, flagged: bool) -> Worker:
    """A curator flags a worker (their answers leave aggregation, their open tasks go back to the
    pool: what failing gold does) or clears them (answers count again, they are served again).

    A cleared worker who is still below the gold threshold is flagged again at their next gold
    answer: clearing overrides the past, not the rule.
    """
    worker = db.session.get(Worker, worker_id)
    if worker is None:
        raise TaskError(f"No worker {worker_id}", 404)
    no_sync = {"synchronize_session": False}
    with one_writer():
        touched = sorted(
            set(db.session.scalars(select(Answer.item_id).where(Answer.worker_id == worker_id)))
            | set(
                db.session.scalars(
                    select(Reservation.item_id).where(Reservation.worker_id == worker_id, Reservation.answered_at.is_(None))
                )
            )
        )
        if touched and not on_sqlite():
            run_prebuilt(LOCK_ITEMS, {"item_ids": touched})
        db.session.execute(update(Worker).where(Worker.id == worker_id).values(flagged=flagged).execution_options(**no_sync))
        db.session.execute(
            update(Answer).where(Answer.worker_id == worker_id).values(flagged=flagged).execution_options(**no_sync)
        )
        if flagged:
            db.session.execute(
                delete(Reservation)
                .where(Reservation.worker_id == worker_id, Reservation.answered_at.is_(None))
                .execution_options(**no_sync)
            )
        recount_items(touched, locked=True)
        db.session.commit()
    db.session.refresh(worker)
    return worker


@dataclass(frozen=True)
class SubmissionCheck:
    """What a researcher should do with one Prolific submission (participant id), and why."""

    participant: str
    decision: str  # "approve", "reject" or "unknown"
    reason: str
    sessions: int
    completed: int
    answers: int

    def as_json(self) -> dict[str, Any]:
        return {
            "participant": self.participant,
            "decision": self.decision,
            "reason": self.reason,
            "sessions": self.sessions,
            "completed": self.completed,
            "answers": self.answers,
        }


def check_prolific_submissions(participants: Sequence[str], study: str | None = None) -> list[SubmissionCheck]:
    """For each Prolific participant id: approve when a session of theirs reached the completion
    step (where the completion code is handed out) with answers and they are not flagged on gold;
    reject when flagged; unknown when this tool never saw them or they gave no answer.
    ``study`` (a STUDY_ID) limits the sessions considered.
    """
    out = []
    for participant in dict.fromkeys(p.strip() for p in participants if p.strip()):
        worker = db.session.scalar(select(Worker).where(Worker.provider == "prolific", Worker.external_id == participant))
        if worker is None:
            out.append(SubmissionCheck(participant, "unknown", "never opened this study here", 0, 0, 0))
            continue
        query = select(CrowdSession).where(CrowdSession.worker_id == worker.id)
        if study:
            query = query.where(CrowdSession.study == study)
        sessions = list(db.session.scalars(query))
        ids = [s.id for s in sessions]
        answers = (
            db.session.scalar(
                select(func.count()).select_from(Answer).where(Answer.worker_id == worker.id, Answer.session_id.in_(ids))
            )
            if ids
            else 0
        )
        completed = sum(s.completed_at is not None for s in sessions)
        if worker.flagged or any(s.flagged for s in sessions):
            decision, reason = "reject", "flagged: failed the known-answer (gold) cards"
        elif not sessions:
            decision, reason = "unknown", "no session in this study"
        elif not completed:
            decision, reason = "unknown", "never reached the completion step (no completion code was shown)"
        elif not answers:
            decision, reason = "unknown", "reached the completion step without answering a card"
        else:
            decision, reason = "approve", f"completed with {answers} answers"
        out.append(SubmissionCheck(participant, decision, reason, len(sessions), completed, int(answers or 0)))
    return out

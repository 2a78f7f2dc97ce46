"""Choosing the next crowd task for a worker: a pure strategy over ids, counts and times.

Doccano-style: no ORM, no database. The caller (use-case code in the web app) loads the batch
state into the small records below, calls :func:`next_assignment`, and writes the returned
:class:`Assignment` as a reservation row. Everything here is deterministic given its inputs,
including the gold draw, so every rule is testable without a clock or a database.

Conventions
-----------
- Item and worker ids are opaque hashables (ints or strings); ``str()`` of them feeds the
  deterministic hashes, so they must have a stable ``str``.
- Times are timezone-aware ``datetime`` values; a reservation is open while ``now < expires_at``.
- ``answers_per_item`` (N) counts stored answers *plus* open reservations, so N workers can
  hold an item at once but never N + 1; an expired reservation stops counting and the slot
  goes back to the pool.
- Gold items are *not* capped at N: every worker should be testable on every gold item, and
  their answers are never aggregated into the batch result.
"""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Hashable, Iterable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from enum import StrEnum

__all__ = [
    "Assignment",
    "AssignmentPolicy",
    "BatchItem",
    "NoTask",
    "NoTaskReason",
    "Reservation",
    "gold_draw",
    "next_assignment",
]


@dataclass(frozen=True)
class BatchItem:
    """One item (a card's judge or crop task) of a batch, as stored so far.

    ``answered_by`` holds the workers with a stored answer; its size is the answer count.
    """

    item_id: Hashable
    answered_by: frozenset[Hashable] = field(default_factory=frozenset)

    @property
    def answer_count(self) -> int:
        return len(self.answered_by)


@dataclass(frozen=True)
class Reservation:
    """A task handed to a worker and not yet answered; it lapses at ``expires_at``."""

    item_id: Hashable
    worker_id: Hashable
    expires_at: datetime

    def is_open(self, now: datetime) -> bool:
        return now < self.expires_at


@dataclass(frozen=True)
class AssignmentPolicy:
    """Batch settings. ``gold_rate`` is the probability that a draw serves a gold item."""

    answers_per_item: int = 3
    gold_rate: float = 0.1
    reservation_ttl: timedelta = timedelta(minutes=10)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.answers_per_item < 1:
            raise ValueError(f"Expected answers_per_item >= 1, got {self.answers_per_item}")
        if not 0.0 <= self.gold_rate <= 1.0:
            raise ValueError(f"Expected 0 <= gold_rate <= 1, got {self.gold_rate}")
        if self.reservation_ttl <= timedelta(0):
            raise ValueError(f"Expected a positive reservation_ttl, got {self.reservation_ttl}")


@dataclass(frozen=True)
class Assignment:
    """The task to serve. ``is_gold`` stays server-side: the page must look like any other task."""

    item_id: Hashable
    is_gold: bool
    expires_at: datetime


class NoTaskReason(StrEnum):
    WORKER_FLAGGED = "worker_flagged"  # below the quality threshold: served nothing more
    BATCH_COMPLETE = "batch_complete"  # every item has N stored answers
    NOTHING_LEFT_FOR_WORKER = "nothing_left_for_worker"  # the rest was answered by this worker
    ALL_RESERVED = "all_reserved"  # open slots are held by others; retry after ``retry_after``


@dataclass(frozen=True)
class NoTask:
    """Why nothing was served. ``retry_after`` is set for ``ALL_RESERVED`` only."""

    reason: NoTaskReason
    retry_after: datetime | None = None


def _unit_hash(*parts: object) -> float:
    """A uniform number in [0, 1) from the parts; stable across processes (unlike ``hash``)."""
    digest = hashlib.blake2b(":".join(str(p) for p in parts).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0**64


def gold_draw(worker_id: Hashable, answer_count: int, policy: AssignmentPolicy) -> bool:
    """Whether this worker's next task should be gold.

    Keyed on (seed, worker, how many answers the worker has given) so that a page reload
    before answering draws the same way (no fishing for non-gold tasks), while successive
    tasks are independent draws at rate ``gold_rate``.
    """
    return _unit_hash(policy.seed, "gold", worker_id, answer_count) < policy.gold_rate


def next_assignment(
    items: Iterable[BatchItem],
    reservations: Iterable[Reservation],
    gold_item_ids: Collection[Hashable],
    worker_id: Hashable,
    now: datetime,
    *,
    policy: AssignmentPolicy = AssignmentPolicy(),
    flagged_workers: Collection[Hashable] = frozenset(),
) -> Assignment | NoTask:
    """Choose the next task for ``worker_id`` in one batch.

    Args:
        items: every item of the batch, gold included (gold ids listed in ``gold_item_ids``).
        reservations: reservations of this batch; lapsed ones are ignored, so the caller
            need not clean them up first.
        gold_item_ids: the items whose true answer curators know.
        worker_id: who asks.
        now: the current time (aware); also the base of the returned ``expires_at``.
        policy: N, gold rate, reservation lifetime and seed.
        flagged_workers: workers whose gold accuracy fell below the threshold.

    Returns:
        An :class:`Assignment`, or a :class:`NoTask` saying why there is none.

    Rules: never an item this worker answered or holds open; a regular item is open while
    stored answers + open reservations < N; gold is served with probability ``gold_rate``
    (falling back to a regular item when the worker has seen every gold item, and vice versa
    only while regular work remains: a worker is never kept busy on gold alone).

    Among open regular items the one closest to completion wins (most answers + holds).
    Why: aggregation, approval and the pipeline consume *finished* items; spreading answers
    thinly leaves the whole batch at N - 1 for a long time, and a worker who leaves early
    then costs the least. Ties break on a per-worker hash, so concurrent workers asking at
    once mostly pick different items instead of racing for the same row.
    """
    if worker_id in flagged_workers:
        return NoTask(NoTaskReason.WORKER_FLAGGED)

    items = list(items)
    gold = set(gold_item_ids)
    open_holds: dict[Hashable, int] = {}
    held_by_worker: set[Hashable] = set()
    expiry_by_item: dict[Hashable, datetime] = {}
    for r in reservations:
        if not r.is_open(now):
            continue  # lapsed: its slot is back in the pool
        open_holds[r.item_id] = open_holds.get(r.item_id, 0) + 1
        if r.worker_id == worker_id:
            held_by_worker.add(r.item_id)
        first = expiry_by_item.get(r.item_id)
        expiry_by_item[r.item_id] = r.expires_at if first is None else min(first, r.expires_at)

    expires_at = now + policy.reservation_ttl
    answers_by_worker = sum(1 for it in items if worker_id in it.answered_by)

    def available_to_worker(it: BatchItem) -> bool:
        return worker_id not in it.answered_by and it.item_id not in held_by_worker

    regular = [it for it in items if it.item_id not in gold]
    regular_open = [
        it
        for it in regular
        if available_to_worker(it)
        and it.answer_count + open_holds.get(it.item_id, 0) < policy.answers_per_item
    ]
    gold_open = [it for it in items if it.item_id in gold and available_to_worker(it)]

    if gold_open and regular_open and gold_draw(worker_id, answers_by_worker, policy):
        # Least-seen gold first, so gold answers spread over all gold items.
        chosen = min(
            gold_open,
            key=lambda it: (it.answer_count, _unit_hash(policy.seed, worker_id, it.item_id)),
        )
        return Assignment(chosen.item_id, True, expires_at)

    if regular_open:
        chosen = min(
            regular_open,
            key=lambda it: (
                -(it.answer_count + open_holds.get(it.item_id, 0)),
                _unit_hash(policy.seed, worker_id, it.item_id),
            ),
        )
        return Assignment(chosen.item_id, False, expires_at)

    if all(it.answer_count >= policy.answers_per_item for it in regular):
        return NoTask(NoTaskReason.BATCH_COMPLETE)
    # Some items still need answers. Are they blocked only by other workers' holds?
    blocked = [
        it
        for it in regular
        if available_to_worker(it) and it.answer_count < policy.answers_per_item
    ]
    if blocked:
        retry = min(expiry_by_item[it.item_id] for it in blocked if it.item_id in expiry_by_item)
        return NoTask(NoTaskReason.ALL_RESERVED, retry_after=retry)
    return NoTask(NoTaskReason.NOTHING_LEFT_FOR_WORKER)

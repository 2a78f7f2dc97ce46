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
- Among equally complete items the highest :func:`item_rank` wins: one fixed pseudo-random
  rank per item (the batch's shuffle), the same for every worker. Why not a per-worker order: a
  database can walk one stored order with an index and stop at the first open item, so the
  web app finds a task in time independent of the batch size (see :mod:`annotation.reservations`,
  which implements this rule in SQL and is tested against this function).
"""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Hashable, Iterable, Mapping
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
    "item_rank",
    "least_seen_gold",
    "next_assignment",
]


@dataclass(frozen=True)
class BatchItem:
    """One item (a card's judge or crop task) of a batch, as stored so far.

    ``answered_by`` holds the workers with a stored answer; its size is the answer count.
    ``rank`` is the item's place in the batch's shuffle; None means :func:`item_rank` of the
    policy's seed and the item id (what the web app stores).
    """

    item_id: Hashable
    answered_by: frozenset[Hashable] = field(default_factory=frozenset)
    rank: int | None = None

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


RANK_BITS = 63  # ranks fit a signed 64-bit integer column on SQLite and PostgreSQL


def item_rank(seed: Hashable, item_id: Hashable) -> int:
    """The item's place in its batch's shuffle: a stable pseudo-random integer in [0, 2**63)."""
    digest = hashlib.blake2b(f"{seed}:rank:{item_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") >> (64 - RANK_BITS)


def gold_draw(worker_id: Hashable, served: int, policy: AssignmentPolicy) -> bool:
    """Whether this worker's next task should be gold.

    Keyed on (seed, worker, ``served``: how many items of the batch the worker has answered
    or holds open) so that a page reload before answering draws the same way (no fishing for
    non-gold tasks), while successive tasks, the preloaded one included, are independent
    draws at rate ``gold_rate``.
    """
    return _unit_hash(policy.seed, "gold", worker_id, served) < policy.gold_rate


def least_seen_gold(answer_counts: Mapping[Hashable, int], worker_id: Hashable, policy: AssignmentPolicy) -> Hashable:
    """The gold item to serve among ``answer_counts`` (gold item -> answers so far; not empty).

    Least-answered first, so gold answers spread over all gold items; ties break on a
    per-worker hash, so workers do not all meet the gold items in one order.
    """
    return min(answer_counts, key=lambda item_id: (answer_counts[item_id], _unit_hash(policy.seed, worker_id, item_id)))


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
    then costs the least. Ties go to the highest rank in the batch's shuffle (:func:`item_rank`).
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
    served = sum(1 for it in items if worker_id in it.answered_by) + len(held_by_worker)

    def available_to_worker(it: BatchItem) -> bool:
        return worker_id not in it.answered_by and it.item_id not in held_by_worker

    regular = [it for it in items if it.item_id not in gold]
    regular_open = [
        it
        for it in regular
        if available_to_worker(it) and it.answer_count + open_holds.get(it.item_id, 0) < policy.answers_per_item
    ]
    gold_open = [it for it in items if it.item_id in gold and available_to_worker(it)]

    if gold_open and regular_open and gold_draw(worker_id, served, policy):
        chosen_gold = least_seen_gold({it.item_id: it.answer_count for it in gold_open}, worker_id, policy)
        return Assignment(chosen_gold, True, expires_at)

    if regular_open:
        chosen = max(
            regular_open,
            key=lambda it: (
                it.answer_count + open_holds.get(it.item_id, 0),
                it.rank if it.rank is not None else item_rank(policy.seed, it.item_id),
            ),
        )
        return Assignment(chosen.item_id, False, expires_at)

    if all(it.answer_count >= policy.answers_per_item for it in regular):
        return NoTask(NoTaskReason.BATCH_COMPLETE)
    # Some items still need answers. Are they blocked only by other workers' holds?
    blocked = [it for it in regular if available_to_worker(it) and it.answer_count < policy.answers_per_item]
    if blocked:
        retry = min(expiry_by_item[it.item_id] for it in blocked if it.item_id in expiry_by_item)
        return NoTask(NoTaskReason.ALL_RESERVED, retry_after=retry)
    return NoTask(NoTaskReason.NOTHING_LEFT_FOR_WORKER)

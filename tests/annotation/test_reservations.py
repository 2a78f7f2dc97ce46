"""The crowd task queue in the database (annotation.reservations): the index walk makes the pure
strategy's choices, the slot counters never drift from their rows, and a lapsed hold is released
once and renewed, never duplicated."""

from __future__ import annotations

import random
from datetime import timedelta

import pytest
from sqlalchemy import func, select

from annotation import assignment as strategy
from annotation.models import Answer, BatchItem, Reservation, Worker
from core.db import db, utcnow

JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False}
JUDGE_WRONG = {"is_stereo": False, "upside_down": True, "inverted": True}


def _pure_view(batch_id: int, now) -> tuple[list[strategy.BatchItem], list[strategy.Reservation], set[int], set[int]]:  # type: ignore[no-untyped-def]
    """The whole batch as the pure strategy takes it, straight from the rows (not the counters)."""
    items = db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch_id)).all()
    ids = [it.id for it in items]
    answered: dict[int, set[int]] = {}
    for item_id, worker_id in db.session.execute(
        select(Answer.item_id, Answer.worker_id).where(Answer.item_id.in_(ids), Answer.flagged.is_(False))
    ):
        answered.setdefault(item_id, set()).add(worker_id)
    holds = [
        strategy.Reservation(
            r.item_id, r.worker_id, r.expires_at if r.expires_at.tzinfo else r.expires_at.replace(tzinfo=now.tzinfo)
        )
        for r in db.session.scalars(select(Reservation).where(Reservation.item_id.in_(ids), Reservation.answered_at.is_(None)))
    ]
    flagged = set(db.session.scalars(select(Worker.id).where(Worker.flagged.is_(True))))
    return (
        [strategy.BatchItem(it.id, frozenset(answered.get(it.id, ())), it.rank) for it in items],
        holds,
        {it.id for it in items if it.is_gold},
        flagged,
    )


def _assert_counters_match_rows(batch_id: int) -> None:
    for item in db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch_id)):
        usable = db.session.scalar(
            select(func.count()).select_from(Answer).where(Answer.item_id == item.id, Answer.flagged.is_(False))
        )
        held = db.session.scalar(
            select(func.count())
            .select_from(Reservation)
            .where(Reservation.item_id == item.id, Reservation.answered_at.is_(None), Reservation.released_at.is_(None))
        )
        assert (item.answers, item.taken) == (usable, usable + held), f"item {item.id}"


@pytest.mark.both_databases
def test_the_index_walk_makes_the_pure_strategys_choices(app, bare_cards):  # type: ignore[no-untyped-def]
    """A random crowd (honest workers, two spammers who fail gold, holds that lapse, undos) against
    the database: before every fetch the pure strategy is asked the same question over the raw
    rows, and after every step the slot counters equal a recount of those rows."""
    from annotation.answers import submit, undo_last
    from annotation.providers import InviteProvider
    from annotation.reservations import next_tasks, open_tasks
    from annotation.task_errors import TaskError

    regular, gold = bare_cards(6), bare_cards(3)
    app.config.update(KEYSTONE_CROWD_MIN_GOLD=2, KEYSTONE_CROWD_RESERVATION_MINUTES=10)
    rng = random.Random(7)
    now = utcnow()
    decisions = {"task": 0, "gold": 0, **dict.fromkeys(strategy.NoTaskReason, 0)}
    with app.app_context():
        from annotation.batches import create_batch

        batch = create_batch(regular, "judge", n=3, gold_rate=0.3, gold={c: JUDGE_OK for c in gold})
        batch_id = batch.id
        workers = [InviteProvider.invite(f"w{i}").id for i in range(7)]
        spammers = set(workers[:2])
        for step in range(600):
            worker = rng.choice(workers)
            held = open_tasks(worker, "judge", now)
            roll = rng.random()
            if held and roll < 0.55:
                task = held[0]
                is_gold = task.card_id in gold
                payload = JUDGE_WRONG if (worker in spammers and is_gold) else JUDGE_OK
                try:
                    submit(worker, task.reservation_token, payload, f"key-{step:04d}-{worker}", now=now)
                except TaskError as error:  # the spammer was flagged and their holds withdrawn
                    assert error.status in (403, 409)
            elif roll < 0.62:
                try:
                    undo_last(worker, now=now)
                except TaskError as error:
                    assert error.status == 409  # nothing to undo
            elif roll < 0.70:
                now += timedelta(minutes=rng.choice([3, 6, 11]))  # some holds lapse
            else:
                items, holds, gold_ids, flagged = _pure_view(batch_id, now)
                policy = strategy.AssignmentPolicy(
                    answers_per_item=3, gold_rate=0.3, seed=batch_id, reservation_ttl=timedelta(minutes=10)
                )
                expected = strategy.next_assignment(items, holds, gold_ids, worker, now, policy=policy, flagged_workers=flagged)
                tasks, why = next_tasks(worker, "judge", hold=len(held) + 1, now=now)
                if isinstance(expected, strategy.Assignment):
                    new = [t for t in tasks if t.reservation_token not in {h.reservation_token for h in held}]
                    assert len(new) == 1 and why is None
                    chosen = db.session.scalar(select(Reservation.item_id).where(Reservation.token == new[0].reservation_token))
                    assert chosen == expected.item_id, f"step {step}"
                    decisions["gold" if expected.is_gold else "task"] += 1
                else:
                    assert [t.reservation_token for t in tasks] == [h.reservation_token for h in held]
                    assert why == expected, f"step {step}"
                    decisions[expected.reason] += 1
            db.session.rollback()
            _assert_counters_match_rows(batch_id)
        per_item = dict(
            db.session.execute(
                select(Answer.item_id, func.count())
                .join(BatchItem)
                .where(BatchItem.batch_id == batch_id, BatchItem.is_gold.is_(False), Answer.flagged.is_(False))
                .group_by(Answer.item_id)
            ).all()
        )
    # The run exercised every branch, and no item ever went past N usable answers.
    assert all(v > 0 for v in decisions.values()), decisions
    assert max(per_item.values()) <= 3


@pytest.mark.both_databases
def test_a_lapsed_hold_is_released_once_and_renewed_not_duplicated(app, bare_cards):  # type: ignore[no-untyped-def]
    from annotation.answers import submit
    from annotation.batches import create_batch
    from annotation.crowd_settings import DEFAULT_RESERVATION_MINUTES
    from annotation.reservations import next_tasks
    from annotation.task_errors import TaskError
    from annotation.workers import get_or_create_worker

    with app.app_context():
        create_batch(bare_cards(1), "judge", n=1, gold_rate=0.0)
        first, second = (get_or_create_worker("invite", name).id for name in ("first", "second"))
        now = utcnow()
        (task,), _ = next_tasks(first, hold=1, now=now)
        assert next_tasks(second, hold=1, now=now)[1].reason == strategy.NoTaskReason.ALL_RESERVED
        later = now + timedelta(minutes=DEFAULT_RESERVATION_MINUTES, seconds=1)
        (theirs,), _ = next_tasks(second, hold=1, now=later)  # the sweep put the slot back
        released = db.session.scalar(select(Reservation).where(Reservation.token == task.reservation_token))
        assert released.released_at is not None and released.answered_at is None
        with pytest.raises(TaskError, match="expired"):
            submit(first, task.reservation_token, JUDGE_OK, "late-answer-1", now=now + timedelta(minutes=1))
        db.session.rollback()
        item = db.session.get(BatchItem, released.item_id)
        assert (item.answers, item.taken) == (0, 1)
        submit(second, theirs.reservation_token, JUDGE_OK, "their-answer-1", now=later)
        # The first worker comes back after it is done: nothing left, and still one row of theirs.
        assert next_tasks(first, hold=1, now=later)[1].reason == strategy.NoTaskReason.BATCH_COMPLETE
        assert db.session.scalar(select(func.count()).select_from(Reservation).where(Reservation.worker_id == first)) == 1


@pytest.mark.both_databases
def test_a_submit_racing_the_sweep_cannot_overfill_an_item(app, bare_cards):  # type: ignore[no-untyped-def]
    """The submit read its hold as open a moment before it lapsed; a fetch swept it and handed the
    slot on. The late claim must fail rather than store an (N+1)th answer."""
    from annotation.answers import submit
    from annotation.batches import create_batch
    from annotation.reservations import next_tasks
    from annotation.task_errors import TaskError
    from annotation.workers import get_or_create_worker

    with app.app_context():
        create_batch(bare_cards(1), "judge", n=1, gold_rate=0.0)
        slow, fast = (get_or_create_worker("invite", name).id for name in ("slow", "fast"))
        now = utcnow()
        (task,), _ = next_tasks(slow, hold=1, now=now)
        lapse = task.expires_at
        next_tasks(fast, hold=1, now=lapse + timedelta(seconds=1))
        with pytest.raises(TaskError) as refused:
            submit(slow, task.reservation_token, JUDGE_OK, "slow-answer-1", now=lapse - timedelta(seconds=1))
        assert refused.value.status == 409
        db.session.rollback()
        assert db.session.scalar(select(func.count()).select_from(Answer)) == 0

"""The crowd task queue in the database (annotation.tasks): the index walk makes the pure strategy's
choices, the slot counters never drift from their rows, and the hot queries use their indexes."""

from __future__ import annotations

import random
from datetime import timedelta

import pytest
from sqlalchemy import func, select, text

from annotation import assignment as strategy
from annotation.models import Answer, BatchItem, Reservation, Worker
from app.db import db, utcnow
from app.models import Card, Collection

JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False}
JUDGE_WRONG = {"is_stereo": False, "upside_down": True, "inverted": True}


@pytest.fixture
def bare_cards(app):  # type: ignore[no-untyped-def]
    """``bare_cards(k)``: k card rows (no image files: the queue never opens them), their ids."""

    def make(k: int) -> list[int]:
        with app.app_context():
            group = db.session.scalar(select(Collection).where(Collection.name == "queue")) or Collection(name="queue")
            start = db.session.scalar(select(func.count()).select_from(Card))
            cards = [Card(collection=group, content_hash=f"{start + i:064x}", stored_path=f"originals/{start + i}.png",
                          source_name=f"q{start + i}.png", source_path=f"/q/{start + i}.png", width=604, height=200,
                          image_format="PNG", byte_size=1, source_metadata={}, state="review") for i in range(k)]
            db.session.add_all(cards)
            db.session.commit()
            return [c.id for c in cards]

    return make


def _pure_view(batch_id: int, now) -> tuple[list[strategy.BatchItem], list[strategy.Reservation], set[int], set[int]]:  # type: ignore[no-untyped-def]
    """The whole batch as the pure strategy takes it, straight from the rows (not the counters)."""
    items = db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch_id)).all()
    ids = [it.id for it in items]
    answered: dict[int, set[int]] = {}
    for item_id, worker_id in db.session.execute(select(Answer.item_id, Answer.worker_id).where(
            Answer.item_id.in_(ids), Answer.flagged.is_(False))):
        answered.setdefault(item_id, set()).add(worker_id)
    holds = [strategy.Reservation(r.item_id, r.worker_id, r.expires_at if r.expires_at.tzinfo else
                                  r.expires_at.replace(tzinfo=now.tzinfo))
             for r in db.session.scalars(select(Reservation).where(Reservation.item_id.in_(ids),
                                                                   Reservation.answered_at.is_(None)))]
    flagged = set(db.session.scalars(select(Worker.id).where(Worker.flagged.is_(True))))
    return ([strategy.BatchItem(it.id, frozenset(answered.get(it.id, ())), it.rank) for it in items], holds,
            {it.id for it in items if it.is_gold}, flagged)


def _assert_counters_match_rows(batch_id: int) -> None:
    for item in db.session.scalars(select(BatchItem).where(BatchItem.batch_id == batch_id)):
        usable = db.session.scalar(select(func.count()).select_from(Answer).where(
            Answer.item_id == item.id, Answer.flagged.is_(False)))
        held = db.session.scalar(select(func.count()).select_from(Reservation).where(
            Reservation.item_id == item.id, Reservation.answered_at.is_(None), Reservation.released_at.is_(None)))
        assert (item.answers, item.taken) == (usable, usable + held), f"item {item.id}"


@pytest.mark.both_databases
def test_the_index_walk_makes_the_pure_strategys_choices(app, bare_cards):  # type: ignore[no-untyped-def]
    """A random crowd (honest workers, two spammers who fail gold, holds that lapse, undos) against
    the database: before every fetch the pure strategy is asked the same question over the raw
    rows, and after every step the slot counters equal a recount of those rows."""
    from annotation.providers import InviteProvider
    from annotation.tasks import TaskError, next_tasks, open_tasks, submit, undo_last

    regular, gold = bare_cards(6), bare_cards(3)
    app.config.update(KEYSTONE_CROWD_MIN_GOLD=2, KEYSTONE_CROWD_RESERVATION_MINUTES=10)
    rng = random.Random(7)
    now = utcnow()
    decisions = {"task": 0, "gold": 0, **dict.fromkeys(strategy.NoTaskReason, 0)}
    with app.app_context():
        from annotation.tasks import create_batch

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
                policy = strategy.AssignmentPolicy(answers_per_item=3, gold_rate=0.3, seed=batch_id,
                                                   reservation_ttl=timedelta(minutes=10))
                expected = strategy.next_assignment(items, holds, gold_ids, worker, now, policy=policy,
                                                    flagged_workers=flagged)
                tasks, why = next_tasks(worker, "judge", hold=len(held) + 1, now=now)
                if isinstance(expected, strategy.Assignment):
                    new = [t for t in tasks if t.reservation_token not in {h.reservation_token for h in held}]
                    assert len(new) == 1 and why is None
                    chosen = db.session.scalar(select(Reservation.item_id).where(
                        Reservation.token == new[0].reservation_token))
                    assert chosen == expected.item_id, f"step {step}"
                    decisions["gold" if expected.is_gold else "task"] += 1
                else:
                    assert [t.reservation_token for t in tasks] == [h.reservation_token for h in held]
                    assert why == expected, f"step {step}"
                    decisions[expected.reason] += 1
            db.session.rollback()
            _assert_counters_match_rows(batch_id)
        per_item = dict(db.session.execute(select(Answer.item_id, func.count()).join(BatchItem).where(
            BatchItem.batch_id == batch_id, BatchItem.is_gold.is_(False), Answer.flagged.is_(False))
            .group_by(Answer.item_id)).all())
    # The run exercised every branch, and no item ever went past N usable answers.
    assert all(v > 0 for v in decisions.values()), decisions
    assert max(per_item.values()) <= 3


def test_hot_queries_walk_their_indexes(app, bare_cards):  # type: ignore[no-untyped-def]
    """SQLite's plans: the walk reads ix_crowd_batch_items_open in order (no sort of the batch),
    lapsed holds and a worker's open tasks come from the partial indexes."""
    from annotation import tasks

    with app.app_context():
        batch = tasks.create_batch(bare_cards(300), "judge", n=3, gold_rate=0.0)
        worker = tasks.get_or_create_worker("invite", "planner").id
        connection = db.session.connection()

        def plan(statement, **params) -> str:  # type: ignore[no-untyped-def]
            sql = statement.params(**params).compile(connection, compile_kwargs={"literal_binds": True})
            return "\n".join(row[-1] for row in connection.exec_driver_sql(f"EXPLAIN QUERY PLAN {sql}"))

        walk = plan(tasks._OPEN_ITEMS, batch_id=batch.id, worker_id=worker, n=3, limit=2)
        assert "ix_crowd_batch_items_open" in walk and "TEMP B-TREE" not in walk, walk
        lapsed = plan(tasks._LAPSED_ITEMS, now=utcnow())
        assert "ix_crowd_reservations_lapsing" in lapsed, lapsed
        # Bound, not literal: SQLite's compiler leaves the IS (NOT DISTINCT FROM) operand a placeholder.
        compiled = tasks._OPEN_TASKS.compile(connection)
        bound = {"worker_id": worker, "session_id": 1, "kind": "judge", "now": utcnow().isoformat(" ")}
        mine = "\n".join(row[-1] for row in connection.exec_driver_sql(
            f"EXPLAIN QUERY PLAN {compiled.string}", tuple(bound[name] for name in compiled.positiontup)))
        assert "ix_crowd_reservations_held" in mine, mine
        opened = plan(tasks._OPEN_BATCHES, kind="judge")
        assert "ix_crowd_batch_items_unfinished" in opened, opened
        # The gold draw's count starts from the worker's own rows, never from the batch's items.
        served = plan(tasks._SERVED, batch_id=batch.id, worker_id=worker)
        assert "ix_crowd_answers_worker_id" in served and "ix_crowd_reservations_held" in served, served
        assert "ix_crowd_batch_items_batch_id" not in served, served
        gold = plan(tasks._OPEN_GOLD, batch_id=batch.id, worker_id=worker)
        assert "(batch_id=? AND is_gold=?)" in gold, gold  # the gold items only


@pytest.mark.both_databases
def test_a_lapsed_hold_is_released_once_and_renewed_not_duplicated(app, bare_cards):  # type: ignore[no-untyped-def]
    from annotation import tasks

    with app.app_context():
        tasks.create_batch(bare_cards(1), "judge", n=1, gold_rate=0.0)
        first, second = (tasks.get_or_create_worker("invite", name).id for name in ("first", "second"))
        now = utcnow()
        (task,), _ = tasks.next_tasks(first, hold=1, now=now)
        assert tasks.next_tasks(second, hold=1, now=now)[1].reason == strategy.NoTaskReason.ALL_RESERVED
        later = now + timedelta(minutes=tasks.DEFAULT_RESERVATION_MINUTES, seconds=1)
        (theirs,), _ = tasks.next_tasks(second, hold=1, now=later)  # the sweep put the slot back
        released = db.session.scalar(select(Reservation).where(Reservation.token == task.reservation_token))
        assert released.released_at is not None and released.answered_at is None
        with pytest.raises(tasks.TaskError, match="expired"):
            tasks.submit(first, task.reservation_token, JUDGE_OK, "late-answer-1", now=now + timedelta(minutes=1))
        db.session.rollback()
        item = db.session.get(BatchItem, released.item_id)
        assert (item.answers, item.taken) == (0, 1)
        tasks.submit(second, theirs.reservation_token, JUDGE_OK, "their-answer-1", now=later)
        # The first worker comes back after it is done: nothing left, and still one row of theirs.
        assert tasks.next_tasks(first, hold=1, now=later)[1].reason == strategy.NoTaskReason.BATCH_COMPLETE
        assert db.session.scalar(select(func.count()).select_from(Reservation).where(
            Reservation.worker_id == first)) == 1


@pytest.mark.both_databases
def test_a_submit_racing_the_sweep_cannot_overfill_an_item(app, bare_cards):  # type: ignore[no-untyped-def]
    """The submit read its hold as open a moment before it lapsed; a fetch swept it and handed the
    slot on. The late claim must fail rather than store an (N+1)th answer."""
    from annotation import tasks

    with app.app_context():
        tasks.create_batch(bare_cards(1), "judge", n=1, gold_rate=0.0)
        slow, fast = (tasks.get_or_create_worker("invite", name).id for name in ("slow", "fast"))
        now = utcnow()
        (task,), _ = tasks.next_tasks(slow, hold=1, now=now)
        lapse = task.expires_at
        tasks.next_tasks(fast, hold=1, now=lapse + timedelta(seconds=1))
        with pytest.raises(tasks.TaskError) as refused:
            tasks.submit(slow, task.reservation_token, JUDGE_OK, "slow-answer-1", now=lapse - timedelta(seconds=1))
        assert refused.value.status == 409
        db.session.rollback()
        assert db.session.scalar(select(func.count()).select_from(Answer)) == 0


@pytest.mark.both_databases
def test_migration_counts_existing_rows_like_the_app(app, bare_cards):  # type: ignore[no-untyped-def]
    """Downgrade below the counters and upgrade again: the backfill equals the app's own recount."""
    from alembic import command

    from annotation import tasks
    from app.schema import alembic_config, upgrade

    with app.app_context():
        batch_id = tasks.create_batch(bare_cards(4), "judge", n=2, gold_rate=0.0).id
        workers = [tasks.get_or_create_worker("invite", f"m{i}").id for i in range(3)]
        now = utcnow()
        for worker in workers:
            held, _ = tasks.next_tasks(worker, hold=2, now=now)
            tasks.submit(worker, held[0].reservation_token, JUDGE_OK, f"mig-{worker}-0001", now=now)
        before = {row.id: (row.answers, row.taken, row.rank) for row in db.session.scalars(select(BatchItem))}
        db.session.remove()
        config = alembic_config(db.engine)
        with db.engine.begin() as connection:
            config.attributes["connection"] = connection
            command.downgrade(config, "0003")
        upgrade(db.engine)
        after = {row.id: (row.answers, row.taken, row.rank) for row in db.session.scalars(select(BatchItem))}
        assert after == before
        assert all(rank == strategy.item_rank(batch_id, item_id) for item_id, (_, _, rank) in after.items())
        assert sum(taken for _, taken, _ in after.values()) == 6  # 3 answers + 3 open holds
        assert db.session.execute(text("SELECT count(*) FROM crowd_reservations")).scalar() == 6

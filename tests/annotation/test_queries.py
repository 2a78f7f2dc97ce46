"""The crowd's prebuilt statements (annotation.queries): the hot queries use their indexes, and the
migration that added the slot counters counts existing rows exactly as recount_items does."""

from __future__ import annotations

import pytest
from sqlalchemy import select, text

from annotation import assignment as strategy
from annotation.models import BatchItem
from core.db import db, utcnow

JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False}


def test_hot_queries_walk_their_indexes(app, bare_cards):  # type: ignore[no-untyped-def]
    """SQLite's plans: the walk reads ix_crowd_batch_items_open in order (no sort of the batch),
    lapsed holds and a worker's open tasks come from the partial indexes."""
    from annotation import queries
    from annotation.batches import create_batch
    from annotation.workers import get_or_create_worker

    with app.app_context():
        batch = create_batch(bare_cards(300), "judge", n=3, gold_rate=0.0)
        worker = get_or_create_worker("invite", "planner").id
        connection = db.session.connection()

        def plan(statement, **params) -> str:  # type: ignore[no-untyped-def]
            sql = statement.params(**params).compile(connection, compile_kwargs={"literal_binds": True})
            return "\n".join(row[-1] for row in connection.exec_driver_sql(f"EXPLAIN QUERY PLAN {sql}"))

        walk = plan(queries.OPEN_ITEMS, batch_id=batch.id, worker_id=worker, n=3, limit=2)
        assert "ix_crowd_batch_items_open" in walk and "TEMP B-TREE" not in walk, walk
        lapsed = plan(queries.LAPSED_ITEMS, now=utcnow())
        assert "ix_crowd_reservations_lapsing" in lapsed, lapsed
        # Bound, not literal: SQLite's compiler leaves the IS (NOT DISTINCT FROM) operand a placeholder.
        compiled = queries.OPEN_TASKS.compile(connection)
        bound = {"worker_id": worker, "session_id": 1, "kind": "judge", "now": utcnow().isoformat(" ")}
        mine = "\n".join(
            row[-1]
            for row in connection.exec_driver_sql(
                f"EXPLAIN QUERY PLAN {compiled.string}", tuple(bound[name] for name in compiled.positiontup)
            )
        )
        assert "ix_crowd_reservations_held" in mine, mine
        opened = plan(queries.OPEN_BATCHES, kind="judge")
        assert "ix_crowd_batch_items_unfinished" in opened, opened
        # The gold draw's count starts from the worker's own rows, never from the batch's items.
        served = plan(queries.SERVED, batch_id=batch.id, worker_id=worker)
        assert "ix_crowd_answers_worker_id" in served and "ix_crowd_reservations_held" in served, served
        assert "ix_crowd_batch_items_batch_id" not in served, served
        gold = plan(queries.OPEN_GOLD, batch_id=batch.id, worker_id=worker)
        assert "(batch_id=? AND is_gold=?)" in gold, gold  # the gold items only


@pytest.mark.both_databases
def test_migration_counts_existing_rows_like_the_app(app, bare_cards):  # type: ignore[no-untyped-def]
    """Downgrade below the counters and upgrade again: the backfill equals the app's own recount."""
    from alembic import command

    from annotation.answers import submit
    from annotation.batches import create_batch
    from annotation.reservations import next_tasks
    from annotation.workers import get_or_create_worker
    from app.schema import alembic_config, upgrade

    with app.app_context():
        batch_id = create_batch(bare_cards(4), "judge", n=2, gold_rate=0.0).id
        workers = [get_or_create_worker("invite", f"m{i}").id for i in range(3)]
        now = utcnow()
        for worker in workers:
            held, _ = next_tasks(worker, hold=2, now=now)
            submit(worker, held[0].reservation_token, JUDGE_OK, f"mig-{worker}-0001", now=now)
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

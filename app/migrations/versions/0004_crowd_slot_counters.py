"""crowd slot counters: answers, taken and rank on batch items; released_at on reservations

Fetch-next used to load every item, reservation and answer of a batch to choose one task;
these columns let it walk an index instead (see annotation.reservations). Existing rows are counted
here exactly as annotation.queries.recount_items counts them.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""

import hashlib
from datetime import UTC, datetime

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

HELD = "answered_at IS NULL AND released_at IS NULL"


def item_rank(batch_id: int, item_id: int) -> int:
    # A frozen copy of annotation.assignment.item_rank as of this revision.
    digest = hashlib.blake2b(f"{batch_id}:rank:{item_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") >> 1


def upgrade() -> None:
    # Plain ALTER TABLE ADD/DROP COLUMN (SQLite >= 3.35 has both), never batch mode's table copy:
    # with foreign keys on, dropping the old copy of crowd_batch_items would cascade-delete every
    # answer and reservation.
    op.add_column("crowd_batch_items", sa.Column("answers", sa.Integer(), server_default="0", nullable=False))
    op.add_column("crowd_batch_items", sa.Column("taken", sa.Integer(), server_default="0", nullable=False))
    op.add_column("crowd_batch_items", sa.Column("rank", sa.BigInteger(), server_default="0", nullable=False))
    op.add_column("crowd_reservations", sa.Column("released_at", sa.DateTime(timezone=True), nullable=True))

    connection = op.get_bind()
    reservations = sa.table(
        "crowd_reservations",
        sa.column("answered_at", sa.DateTime(timezone=True)),
        sa.column("released_at", sa.DateTime(timezone=True)),
        sa.column("expires_at", sa.DateTime(timezone=True)),
    )
    now = datetime.now(UTC)
    # Holds that lapsed before this upgrade no longer count.
    connection.execute(
        reservations.update()
        .where(reservations.c.answered_at.is_(None), reservations.c.expires_at <= now)
        .values(released_at=now)
    )
    usable = "(SELECT count(*) FROM crowd_answers a WHERE a.item_id = crowd_batch_items.id AND NOT a.flagged)"
    held = (
        "(SELECT count(*) FROM crowd_reservations r WHERE r.item_id = crowd_batch_items.id "
        "AND r.answered_at IS NULL AND r.released_at IS NULL)"
    )
    connection.execute(sa.text(f"UPDATE crowd_batch_items SET answers = {usable}, taken = {usable} + {held}"))
    items = sa.table(
        "crowd_batch_items",
        sa.column("id", sa.Integer()),
        sa.column("batch_id", sa.Integer()),
        sa.column("rank", sa.BigInteger()),
    )
    ranks = [
        {"item": item_id, "rank": item_rank(batch_id, item_id)}
        for item_id, batch_id in connection.execute(sa.select(items.c.id, items.c.batch_id))
    ]
    if ranks:
        connection.execute(items.update().where(items.c.id == sa.bindparam("item")).values(rank=sa.bindparam("rank")), ranks)

    op.create_index("ix_crowd_batch_items_open", "crowd_batch_items", ["batch_id", "is_gold", "taken", "rank"])
    op.create_index("ix_crowd_batch_items_unfinished", "crowd_batch_items", ["batch_id", "is_gold", "answers"])
    op.create_index(
        "ix_crowd_reservations_held",
        "crowd_reservations",
        ["worker_id", "expires_at"],
        sqlite_where=sa.text(HELD),
        postgresql_where=sa.text(HELD),
    )
    op.create_index(
        "ix_crowd_reservations_lapsing",
        "crowd_reservations",
        ["expires_at"],
        sqlite_where=sa.text(HELD),
        postgresql_where=sa.text(HELD),
    )


def downgrade() -> None:
    op.drop_index("ix_crowd_reservations_lapsing", table_name="crowd_reservations")
    op.drop_index("ix_crowd_reservations_held", table_name="crowd_reservations")
    op.drop_index("ix_crowd_batch_items_unfinished", table_name="crowd_batch_items")
    op.drop_index("ix_crowd_batch_items_open", table_name="crowd_batch_items")
    op.drop_column("crowd_reservations", "released_at")
    for column in ("rank", "taken", "answers"):
        op.drop_column("crowd_batch_items", column)

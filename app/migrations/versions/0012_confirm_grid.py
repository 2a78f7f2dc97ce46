"""confirm grids: a third crowd task kind, and the orientation a confirm item shows

``crowd_batches``, ``crowd_aggregates`` and ``crowd_gold_answers`` accept kind ``confirm``
(people tap what looks wrong in a grid of cards shown as the orientation step would fix
them); ``crowd_batch_items.shown`` keeps the flags each confirm card is shown with;
``crowd_aggregates.state`` accepts ``escalated`` (a grid's crowd could not agree on a card: it
goes to a one-card judge task).

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

KIND_TABLES = ("crowd_batches", "crowd_aggregates", "crowd_gold_answers")


def _kinds(kinds: tuple[str, ...]) -> None:
    # SQLite cannot alter a CHECK in place: batch mode copies each table with the new one.
    for table in KIND_TABLES:
        with op.batch_alter_table(table, recreate="auto") as batch:
            batch.drop_constraint(op.f(f"ck_{table}_kind"), type_="check")
            batch.create_check_constraint(op.f(f"ck_{table}_kind"), "kind IN (" + ", ".join(repr(k) for k in kinds) + ")")


def _states(states: tuple[str, ...]) -> None:
    with op.batch_alter_table("crowd_aggregates", recreate="auto") as batch:
        batch.drop_constraint(op.f("ck_crowd_aggregates_state"), type_="check")
        batch.create_check_constraint(op.f("ck_crowd_aggregates_state"), "state IN (" + ", ".join(repr(s) for s in states) + ")")


def upgrade() -> None:
    _kinds(("judge", "crop", "confirm"))
    _states(("approved", "needs_curator", "escalated"))
    op.add_column(
        "crowd_batch_items",
        sa.Column("shown", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
    )


def downgrade() -> None:
    op.drop_column("crowd_batch_items", "shown")
    op.execute("DELETE FROM crowd_aggregates WHERE kind = 'confirm'")
    op.execute("DELETE FROM crowd_gold_answers WHERE kind = 'confirm'")
    op.execute("DELETE FROM crowd_batches WHERE kind = 'confirm'")
    _states(("approved", "needs_curator"))
    _kinds(("judge", "crop"))

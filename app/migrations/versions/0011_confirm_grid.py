"""confirm grids: a third crowd task kind, and the orientation a confirm item shows

``crowd_batches``, ``crowd_aggregates`` and ``crowd_gold_answers`` accept kind ``confirm``
(people tap what looks wrong in a grid of cards shown as the orientation step would fix
them); ``crowd_batch_items.shown`` keeps the flags each confirm card is shown with.

Revision ID: 0011
Revises: 0009a
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0011"
down_revision = "0009a"
branch_labels = None
depends_on = None

KIND_TABLES = ("crowd_batches", "crowd_aggregates", "crowd_gold_answers")


def _kinds(kinds: tuple[str, ...]) -> None:
    # SQLite cannot alter a CHECK in place: batch mode copies each table with the new one.
    for table in KIND_TABLES:
        with op.batch_alter_table(table, recreate="auto") as batch:
            batch.drop_constraint(op.f(f"ck_{table}_kind"), type_="check")
            batch.create_check_constraint(op.f(f"ck_{table}_kind"), "kind IN (" + ", ".join(repr(k) for k in kinds) + ")")


def upgrade() -> None:
    _kinds(("judge", "crop", "confirm"))
    op.add_column(
        "crowd_batch_items",
        sa.Column("shown", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
    )


def downgrade() -> None:
    op.drop_column("crowd_batch_items", "shown")
    _kinds(("judge", "crop"))

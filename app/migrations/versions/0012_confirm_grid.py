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

import re

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

KIND_TABLES = ("crowd_batches", "crowd_aggregates", "crowd_gold_answers")


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN (" + ", ".join(repr(v) for v in values) + ")"


def _sqlite_check(table: str, column: str, values: tuple[str, ...]) -> None:
    """Rewrite a CHECK of ``table`` in SQLite's schema text, in place (SQLite's own procedure for
    loosening or removing a CHECK: https://sqlite.org/lang_altertable.html, section 7).

    Not batch mode: it rebuilds the table, and dropping the old ``crowd_batches`` with foreign
    keys on (the app's connections turn them on, and the pragma cannot change inside the
    migration's transaction) cascades into every batch item, answer and aggregate. The new CHECK
    only widens or narrows the set of values, and the downgrade deletes the rows it excludes
    first, so every stored row satisfies it."""
    bind = op.get_bind()
    name = f"ck_{table}_{column}"
    sql = bind.exec_driver_sql("SELECT sql FROM sqlite_master WHERE type = 'table' AND name = ?", (table,)).scalar()
    new = re.sub(rf"CONSTRAINT {name} CHECK \({column} IN \([^)]*\)\)", f"CONSTRAINT {name} CHECK ({_in(column, values)})", sql)
    if new == sql:
        raise RuntimeError(f"{table}: no CHECK constraint {name} to rewrite in {sql!r}")
    version = bind.exec_driver_sql("PRAGMA schema_version").scalar()
    bind.exec_driver_sql("PRAGMA writable_schema = ON")
    bind.exec_driver_sql("UPDATE sqlite_master SET sql = ? WHERE type = 'table' AND name = ?", (new, table))
    bind.exec_driver_sql(f"PRAGMA schema_version = {int(version) + 1}")
    bind.exec_driver_sql("PRAGMA writable_schema = OFF")


def _check(table: str, column: str, values: tuple[str, ...]) -> None:
    if op.get_bind().dialect.name == "sqlite":
        _sqlite_check(table, column, values)
        return
    op.drop_constraint(op.f(f"ck_{table}_{column}"), table, type_="check")
    op.create_check_constraint(op.f(f"ck_{table}_{column}"), table, _in(column, values))


def _kinds(kinds: tuple[str, ...]) -> None:
    for table in KIND_TABLES:
        _check(table, "kind", kinds)


def _states(states: tuple[str, ...]) -> None:
    _check("crowd_aggregates", "state", states)


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

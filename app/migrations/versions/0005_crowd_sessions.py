"""crowd sessions: reservations and answers belong to one visit (Prolific session, MTurk assignment, invite)

Before this, a second visit with the same participant id got the same worker and could undo
the first visit's answers. Invited annotators get their one session and keep their rows;
existing Prolific and MTurk reservations and answers keep session_id NULL: no web session can
see, claim or undo them (they still count for the worker's N-answers rule).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None

SESSION_TABLES = ("crowd_reservations", "crowd_answers")
INVITE_SESSION_PREFIX = "invite-worker-"  # a frozen copy of annotation.sessions.INVITE_SESSION_PREFIX


def upgrade() -> None:
    op.create_table(
        "crowd_sessions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("worker_id", sa.Integer(), nullable=False),
        sa.Column("provider", sa.String(length=10), nullable=False),
        sa.Column("external_id", sa.String(length=200), nullable=False),
        sa.Column("study", sa.String(length=200), server_default="", nullable=False),
        sa.Column("address", sa.String(length=64), server_default="", nullable=False),
        sa.Column("flagged", sa.Boolean(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("completed_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint("provider IN ('invite', 'prolific', 'mturk')", name=op.f("ck_crowd_sessions_provider")),
        sa.ForeignKeyConstraint(
            ["worker_id"], ["crowd_workers.id"], name=op.f("fk_crowd_sessions_worker_id_crowd_workers"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_sessions")),
        sa.UniqueConstraint("provider", "external_id", name="crowd_session_provider_external"),
    )
    op.create_index("ix_crowd_sessions_worker_id", "crowd_sessions", ["worker_id"])
    op.create_index("ix_crowd_sessions_address", "crowd_sessions", ["address", "created_at"])
    op.create_index("ix_crowd_sessions_study", "crowd_sessions", ["provider", "study", "created_at"])

    # A plain indexed column, no foreign key: SQLite can add one only by copying the table, and
    # that copy would have to rebuild the partial indexes of crowd_reservations by hand. A
    # session is deleted only with its worker, whose own foreign keys take these rows along.
    for table in SESSION_TABLES:
        op.add_column(table, sa.Column("session_id", sa.Integer(), nullable=True))
        op.create_index(f"ix_{table}_session_id", table, ["session_id"])

    # An invited annotator has one session (their link is the credential), so their rows can
    # be given it now and they carry on where they were, undo included. Prolific and MTurk rows
    # cannot: which visit made them was never stored.
    op.execute(
        f"INSERT INTO crowd_sessions (worker_id, provider, external_id, study, address, flagged, created_at) "
        f"SELECT id, 'invite', '{INVITE_SESSION_PREFIX}' || id, '', '', FALSE, created_at "
        f"FROM crowd_workers WHERE provider = 'invite'"
    )
    for table in SESSION_TABLES:
        op.execute(
            f"UPDATE {table} SET session_id = (SELECT s.id FROM crowd_sessions s WHERE s.provider = 'invite' "
            f"AND s.worker_id = {table}.worker_id) "
            f"WHERE worker_id IN (SELECT id FROM crowd_workers WHERE provider = 'invite')"
        )


def downgrade() -> None:
    for table in SESSION_TABLES:
        op.drop_index(f"ix_{table}_session_id", table_name=table)
        op.drop_column(table, "session_id")  # plain ALTER TABLE DROP COLUMN (SQLite >= 3.35)
    op.drop_index("ix_crowd_sessions_study", table_name="crowd_sessions")
    op.drop_index("ix_crowd_sessions_address", table_name="crowd_sessions")
    op.drop_index("ix_crowd_sessions_worker_id", table_name="crowd_sessions")
    op.drop_table("crowd_sessions")

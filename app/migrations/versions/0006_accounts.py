"""accounts: session versions on people, the sign-in trail, and login throttles

people.session_version lets logging out (and a new password, and deactivation) end sessions on
the server; auth_events is the append-only trail of logins, failures, lockouts, logouts and
refused sessions; login_throttles counts failed password checks per account and per client
address, in the database so every server process shares one budget.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None

ACTIONS = "action IN ('login', 'login_failed', 'login_throttled', 'logout', 'session_refused')"


def upgrade() -> None:
    # Plain ADD COLUMN, never batch mode's table copy: with foreign keys on, dropping the old
    # copy of people would cascade-delete every role row.
    op.add_column("people", sa.Column("session_version", sa.Integer(), server_default="1", nullable=False))

    op.create_table(
        "auth_events",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("action", sa.String(length=30), nullable=False),
        sa.Column("username", sa.String(length=120), nullable=False),
        sa.Column("person_id", sa.Integer(), nullable=True),
        sa.Column("address", sa.String(length=64), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.CheckConstraint(ACTIONS, name=op.f("ck_auth_events_action")),
        sa.ForeignKeyConstraint(["person_id"], ["people.id"], name=op.f("fk_auth_events_person_id_people")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_auth_events")),
    )
    op.create_index(op.f("ix_auth_events_at"), "auth_events", ["at"], unique=False)
    op.create_index(op.f("ix_auth_events_person_id"), "auth_events", ["person_id"], unique=False)

    op.create_table(
        "login_throttles",
        sa.Column("scope", sa.String(length=10), nullable=False),
        sa.Column("subject", sa.String(length=120), nullable=False),
        sa.Column("window_started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("failures", sa.Integer(), nullable=False),
        sa.CheckConstraint("scope IN ('account', 'address')", name=op.f("ck_login_throttles_scope")),
        sa.PrimaryKeyConstraint("scope", "subject", name=op.f("pk_login_throttles")),
    )

    # Append-only in the database too, as audit_events (0003): a hand-written UPDATE or DELETE
    # is refused.
    if op.get_bind().dialect.name == "sqlite":
        for verb in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER auth_events_no_{verb.lower()} BEFORE {verb} ON auth_events "
                "BEGIN SELECT RAISE(ABORT, 'sign-in events are append-only'); END"
            )
    else:
        op.execute(
            "CREATE FUNCTION auth_events_append_only() RETURNS trigger LANGUAGE plpgsql AS "
            "$$ BEGIN RAISE EXCEPTION 'sign-in events are append-only'; END $$"
        )
        op.execute(
            "CREATE TRIGGER auth_events_append_only BEFORE UPDATE OR DELETE ON auth_events "
            "FOR EACH ROW EXECUTE FUNCTION auth_events_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS auth_events_no_update")
        op.execute("DROP TRIGGER IF EXISTS auth_events_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS auth_events_append_only ON auth_events")
        op.execute("DROP FUNCTION IF EXISTS auth_events_append_only()")
    op.drop_table("login_throttles")
    op.drop_index(op.f("ix_auth_events_person_id"), table_name="auth_events")
    op.drop_index(op.f("ix_auth_events_at"), table_name="auth_events")
    op.drop_table("auth_events")
    op.drop_column("people", "session_version")

"""review and releases: card reviews, grade models, audit, gold, releases

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "grade_models",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("thresholds", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("fitted_on", sa.Integer(), nullable=False),
        sa.Column("evaluation", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("created_by", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["created_by"], ["people.id"], name=op.f("fk_grade_models_created_by_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_grade_models")),
    )
    op.create_table(
        "releases",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("version", sa.String(length=40), nullable=False),
        sa.Column("path", sa.Text(), nullable=False),
        sa.Column("min_grade", sa.String(length=10), nullable=False),
        sa.Column("formats", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("card_count", sa.Integer(), nullable=False),
        sa.Column("stats", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("changes", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("notes", sa.Text(), nullable=False),
        sa.Column("manifest_sha256", sa.String(length=64), nullable=False),
        sa.Column("created_by", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["created_by"], ["people.id"], name=op.f("fk_releases_created_by_people"), ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_releases")),
        sa.UniqueConstraint("version", name=op.f("uq_releases_version")),
    )
    op.create_table(
        "audit_events",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=True),
        sa.Column("entity", sa.String(length=30), nullable=False),
        sa.Column("entity_id", sa.Integer(), nullable=True),
        sa.Column("action", sa.String(length=40), nullable=False),
        sa.Column("actor_id", sa.Integer(), nullable=True),
        sa.Column("actor", sa.String(length=200), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("before", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
        sa.Column("after", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
        sa.Column("why", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(["actor_id"], ["people.id"], name=op.f("fk_audit_events_actor_id_people")),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_audit_events_card_id_cards")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_audit_events")),
    )
    with op.batch_alter_table("audit_events", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_audit_events_at"), ["at"], unique=False)
        batch_op.create_index(batch_op.f("ix_audit_events_card_id"), ["card_id"], unique=False)

    op.create_table(
        "card_reviews",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("auto_grade", sa.String(length=10), nullable=True),
        sa.Column("auto_param_hash", sa.String(length=32), nullable=True),
        sa.Column("uncertainty", sa.Float(), nullable=True),
        sa.Column("grade", sa.String(length=10), nullable=True),
        sa.Column("decision", sa.String(length=12), nullable=False),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("reviewer_id", sa.Integer(), nullable=True),
        sa.Column("decided_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint(
            "auto_grade IS NULL OR auto_grade IN ('few', 'some', 'failure')", name=op.f("ck_card_reviews_auto_grade")
        ),
        sa.CheckConstraint(
            "decision IN ('pending', 'accepted', 'changed', 'sent_back', 'rejected')", name=op.f("ck_card_reviews_decision")
        ),
        sa.CheckConstraint("grade IS NULL OR grade IN ('few', 'some', 'failure')", name=op.f("ck_card_reviews_grade")),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_card_reviews_card_id_cards"), ondelete="CASCADE"),
        sa.ForeignKeyConstraint(
            ["reviewer_id"], ["people.id"], name=op.f("fk_card_reviews_reviewer_id_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_card_reviews")),
        sa.UniqueConstraint("card_id", name=op.f("uq_card_reviews_card_id")),
    )
    with op.batch_alter_table("card_reviews", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_card_reviews_decision"), ["decision"], unique=False)
        batch_op.create_index(batch_op.f("ix_card_reviews_grade"), ["grade"], unique=False)
    # The review queue's order (SQLite sorts NULLs last in DESC already and refuses NULLS LAST here).
    nulls_last = " NULLS LAST" if op.get_bind().dialect.name == "postgresql" else ""
    op.create_index("ix_card_reviews_queue", "card_reviews", ["decision", sa.text(f"uncertainty DESC{nulls_last}"), "card_id"])

    op.create_table(
        "crowd_gold_answers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=10), nullable=False),
        sa.Column("answer", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("made_by", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("kind IN ('judge', 'crop')", name=op.f("ck_crowd_gold_answers_kind")),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_crowd_gold_answers_card_id_cards"), ondelete="CASCADE"),
        sa.ForeignKeyConstraint(
            ["made_by"], ["people.id"], name=op.f("fk_crowd_gold_answers_made_by_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_gold_answers")),
        sa.UniqueConstraint("card_id", "kind", name="crowd_gold_card_kind"),
    )
    with op.batch_alter_table("crowd_gold_answers", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_crowd_gold_answers_card_id"), ["card_id"], unique=False)

    with op.batch_alter_table("crowd_aggregates", schema=None) as batch_op:
        batch_op.add_column(sa.Column("resolved_by", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(
            batch_op.f("fk_crowd_aggregates_resolved_by_people"), "people", ["resolved_by"], ["id"], ondelete="SET NULL"
        )

    # The audit trail is append-only in the database too, not just in the ORM: a hand-written
    # UPDATE or DELETE is refused.
    if op.get_bind().dialect.name == "sqlite":
        for verb in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER audit_events_no_{verb.lower()} BEFORE {verb} ON audit_events "
                "BEGIN SELECT RAISE(ABORT, 'audit events are append-only'); END"
            )
    else:
        op.execute(
            "CREATE FUNCTION audit_events_append_only() RETURNS trigger LANGUAGE plpgsql AS "
            "$$ BEGIN RAISE EXCEPTION 'audit events are append-only'; END $$"
        )
        op.execute(
            "CREATE TRIGGER audit_events_append_only BEFORE UPDATE OR DELETE ON audit_events "
            "FOR EACH ROW EXECUTE FUNCTION audit_events_append_only()"
        )


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS audit_events_no_update")
        op.execute("DROP TRIGGER IF EXISTS audit_events_no_delete")
    else:
        op.execute("DROP TRIGGER IF EXISTS audit_events_append_only ON audit_events")
        op.execute("DROP FUNCTION IF EXISTS audit_events_append_only()")
    with op.batch_alter_table("crowd_aggregates", schema=None) as batch_op:
        batch_op.drop_constraint(batch_op.f("fk_crowd_aggregates_resolved_by_people"), type_="foreignkey")
        batch_op.drop_column("resolved_by")

    with op.batch_alter_table("crowd_gold_answers", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_crowd_gold_answers_card_id"))

    op.drop_table("crowd_gold_answers")
    op.drop_index("ix_card_reviews_queue", table_name="card_reviews")
    with op.batch_alter_table("card_reviews", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_card_reviews_grade"))
        batch_op.drop_index(batch_op.f("ix_card_reviews_decision"))

    op.drop_table("card_reviews")
    with op.batch_alter_table("audit_events", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_audit_events_card_id"))
        batch_op.drop_index(batch_op.f("ix_audit_events_at"))

    op.drop_table("audit_events")
    op.drop_table("releases")
    op.drop_table("grade_models")

"""crowd: batches, items, workers, reservations, answers, aggregates

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "crowd_batches",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=10), nullable=False),
        sa.Column("answers_per_item", sa.Integer(), nullable=False),
        sa.Column("gold_rate", sa.Float(), nullable=False),
        sa.Column("created_by", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("kind IN ('judge', 'crop')", name=op.f("ck_crowd_batches_kind")),
        sa.CheckConstraint("answers_per_item >= 1", name=op.f("ck_crowd_batches_answers_per_item")),
        sa.CheckConstraint("gold_rate >= 0 AND gold_rate <= 1", name=op.f("ck_crowd_batches_gold_rate")),
        sa.ForeignKeyConstraint(
            ["created_by"], ["people.id"], name=op.f("fk_crowd_batches_created_by_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_batches")),
    )
    op.create_table(
        "crowd_workers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("provider", sa.String(length=10), nullable=False),
        sa.Column("external_id", sa.String(length=200), nullable=False),
        sa.Column("person_id", sa.Integer(), nullable=True),
        sa.Column("token", sa.String(length=64), nullable=False),
        sa.Column("flagged", sa.Boolean(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("provider IN ('invite', 'prolific', 'mturk')", name=op.f("ck_crowd_workers_provider")),
        sa.ForeignKeyConstraint(
            ["person_id"], ["people.id"], name=op.f("fk_crowd_workers_person_id_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_workers")),
        sa.UniqueConstraint("provider", "external_id", name="crowd_worker_provider_external"),
        sa.UniqueConstraint("token", name=op.f("uq_crowd_workers_token")),
    )
    op.create_table(
        "crowd_aggregates",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("batch_id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=10), nullable=False),
        sa.Column("posterior", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("label", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("confident", sa.Boolean(), nullable=False),
        sa.Column("state", sa.String(length=20), nullable=False),
        sa.Column("reasons", sa.Text(), nullable=False),
        sa.Column("answers", sa.Integer(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("kind IN ('judge', 'crop')", name=op.f("ck_crowd_aggregates_kind")),
        sa.CheckConstraint("state IN ('approved', 'needs_curator')", name=op.f("ck_crowd_aggregates_state")),
        sa.ForeignKeyConstraint(
            ["batch_id"], ["crowd_batches.id"], name=op.f("fk_crowd_aggregates_batch_id_crowd_batches"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_crowd_aggregates_card_id_cards"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_aggregates")),
        sa.UniqueConstraint("batch_id", "card_id", name="crowd_aggregate_batch_card"),
    )
    with op.batch_alter_table("crowd_aggregates", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_crowd_aggregates_batch_id"), ["batch_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_crowd_aggregates_card_id"), ["card_id"], unique=False)

    op.create_table(
        "crowd_batch_items",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("batch_id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("is_gold", sa.Boolean(), nullable=False),
        sa.Column("gold_answer", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
        sa.ForeignKeyConstraint(
            ["batch_id"], ["crowd_batches.id"], name=op.f("fk_crowd_batch_items_batch_id_crowd_batches"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_crowd_batch_items_card_id_cards"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_batch_items")),
        sa.UniqueConstraint("batch_id", "card_id", name="crowd_item_batch_card"),
    )
    with op.batch_alter_table("crowd_batch_items", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_crowd_batch_items_batch_id"), ["batch_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_crowd_batch_items_card_id"), ["card_id"], unique=False)

    op.create_table(
        "crowd_answers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("item_id", sa.Integer(), nullable=False),
        sa.Column("worker_id", sa.Integer(), nullable=False),
        sa.Column("payload", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("submitted_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("idempotency_key", sa.String(length=80), nullable=False),
        sa.Column("flagged", sa.Boolean(), nullable=False),
        sa.ForeignKeyConstraint(
            ["item_id"], ["crowd_batch_items.id"], name=op.f("fk_crowd_answers_item_id_crowd_batch_items"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["worker_id"], ["crowd_workers.id"], name=op.f("fk_crowd_answers_worker_id_crowd_workers"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_answers")),
        sa.UniqueConstraint("idempotency_key", name=op.f("uq_crowd_answers_idempotency_key")),
        sa.UniqueConstraint("item_id", "worker_id", name="crowd_answer_item_worker"),
    )
    with op.batch_alter_table("crowd_answers", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_crowd_answers_item_id"), ["item_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_crowd_answers_worker_id"), ["worker_id"], unique=False)

    op.create_table(
        "crowd_reservations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("item_id", sa.Integer(), nullable=False),
        sa.Column("worker_id", sa.Integer(), nullable=False),
        sa.Column("token", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("answered_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(
            ["item_id"],
            ["crowd_batch_items.id"],
            name=op.f("fk_crowd_reservations_item_id_crowd_batch_items"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["worker_id"], ["crowd_workers.id"], name=op.f("fk_crowd_reservations_worker_id_crowd_workers"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_crowd_reservations")),
        sa.UniqueConstraint("item_id", "worker_id", name="crowd_reservation_item_worker"),
        sa.UniqueConstraint("token", name=op.f("uq_crowd_reservations_token")),
    )
    with op.batch_alter_table("crowd_reservations", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_crowd_reservations_item_id"), ["item_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_crowd_reservations_worker_id"), ["worker_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("crowd_reservations", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_crowd_reservations_worker_id"))
        batch_op.drop_index(batch_op.f("ix_crowd_reservations_item_id"))

    op.drop_table("crowd_reservations")
    with op.batch_alter_table("crowd_answers", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_crowd_answers_worker_id"))
        batch_op.drop_index(batch_op.f("ix_crowd_answers_item_id"))

    op.drop_table("crowd_answers")
    with op.batch_alter_table("crowd_batch_items", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_crowd_batch_items_card_id"))
        batch_op.drop_index(batch_op.f("ix_crowd_batch_items_batch_id"))

    op.drop_table("crowd_batch_items")
    with op.batch_alter_table("crowd_aggregates", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_crowd_aggregates_card_id"))
        batch_op.drop_index(batch_op.f("ix_crowd_aggregates_batch_id"))

    op.drop_table("crowd_aggregates")
    op.drop_table("crowd_workers")
    op.drop_table("crowd_batches")

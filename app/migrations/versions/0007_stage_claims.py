"""stage claims: one driver per card-stage, with a heartbeat and an expiry

Two ``keystone run`` at once computed every card twice; a claim row per (card, stage) now
says which run computes it (see runs.claims).

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "stage_claims",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("stage", sa.String(length=30), nullable=False),
        sa.Column("param_hash", sa.String(length=32), nullable=False),
        sa.Column("driver", sa.String(length=120), nullable=False),
        sa.Column("claimed_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_stage_claims_card_id_cards"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_stage_claims")),
        sa.UniqueConstraint("card_id", "stage", name="card_stage"),
    )
    op.create_index("ix_stage_claims_driver", "stage_claims", ["driver"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_stage_claims_driver", table_name="stage_claims")
    op.drop_table("stage_claims")

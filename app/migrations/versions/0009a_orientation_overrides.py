"""orientation overrides: a curator's word on a card's upside_down / inverted / swapped flags

One row per card; a null flag leaves the orientation step's or the crowd's value in force
(see pipeline.decided_orientation). Every change is also written to the audit trail.

Revision ID: 0009a
Revises: 0008
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op

revision = "0009a"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "orientation_overrides",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("upside_down", sa.Boolean(), nullable=True),
        sa.Column("inverted", sa.Boolean(), nullable=True),
        sa.Column("swapped", sa.Boolean(), nullable=True),
        sa.Column("curator_id", sa.Integer(), nullable=True),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["card_id"], ["cards.id"], name=op.f("fk_orientation_overrides_card_id_cards"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["curator_id"], ["people.id"], name=op.f("fk_orientation_overrides_curator_id_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_orientation_overrides")),
        sa.UniqueConstraint("card_id", name=op.f("uq_orientation_overrides_card_id")),
    )


def downgrade() -> None:
    op.drop_table("orientation_overrides")

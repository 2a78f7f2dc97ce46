"""collection orientations: an operator's word on the orientation flags of a whole collection

One row per collection; a null flag is not said (the orientation step, the crowd and curators
decide it card by card), and a curator's override on one card wins over it (see
pipeline.decided_orientation). Every change is also written to the audit trail.

Revision ID: 0010
Revises: 0009a
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009a"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "collection_orientations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("collection_id", sa.Integer(), nullable=False),
        sa.Column("upside_down", sa.Boolean(), nullable=True),
        sa.Column("inverted", sa.Boolean(), nullable=True),
        sa.Column("swapped", sa.Boolean(), nullable=True),
        sa.Column("set_by_id", sa.Integer(), nullable=True),
        sa.Column("set_by_name", sa.String(length=200), nullable=False),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("set_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["collection_id"],
            ["collections.id"],
            name=op.f("fk_collection_orientations_collection_id_collections"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["set_by_id"], ["people.id"], name=op.f("fk_collection_orientations_set_by_id_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_collection_orientations")),
        sa.UniqueConstraint("collection_id", name=op.f("uq_collection_orientations_collection_id")),
    )


def downgrade() -> None:
    op.drop_table("collection_orientations")

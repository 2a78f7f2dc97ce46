"""upright head fits: a collection's refit of the orientation step's learned heads

One row per `keystone orientation fit`; the newest row of a collection (or of all collections,
collection_id null) is in force.

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "upright_head_fits",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("collection_id", sa.Integer(), nullable=True),
        sa.Column("version", sa.String(length=80), nullable=False),
        sa.Column("head", JSON, nullable=False),
        sa.Column("fitted_on", sa.Integer(), nullable=False),
        sa.Column("evaluation", JSON, nullable=False),
        sa.Column("created_by", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["collection_id"], ["collections.id"], name=op.f("fk_upright_head_fits_collection_id_collections"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["created_by"], ["people.id"], name=op.f("fk_upright_head_fits_created_by_people"), ondelete="SET NULL"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_upright_head_fits")),
        sa.UniqueConstraint("version", name=op.f("uq_upright_head_fits_version")),
    )
    op.create_index(op.f("ix_upright_head_fits_collection_id"), "upright_head_fits", ["collection_id"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_upright_head_fits_collection_id"), table_name="upright_head_fits")
    op.drop_table("upright_head_fits")

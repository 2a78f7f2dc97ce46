"""card stereo source: how a card's image was made from stereo inputs (MPO, left/right pair, JPS)

A card made from an MPO or a left/right pair, or a side-by-side file with a declared eye order,
records its originals (names, hashes, stored paths), the eye order and the automatic check of
it (see catalogue.stereo_ingest). NULL for an ordinary scan.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-24
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Plain ALTER TABLE, never batch mode's table copy: with foreign keys on, dropping the old
    # copy of cards would cascade-delete every row that references a card.
    op.add_column(
        "cards",
        sa.Column("stereo_source", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=True),
    )


def downgrade() -> None:
    op.drop_column("cards", "stereo_source")  # plain ALTER TABLE DROP COLUMN (SQLite >= 3.35)

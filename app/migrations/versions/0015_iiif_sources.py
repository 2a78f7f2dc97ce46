"""iiif sources: the IIIF canvas a card was ingested from

``cards.iiif_canvas_id``: the canvas's id, unique, so a retried or resumed ingest never makes a
second card of one canvas (catalogue.iiif_ingest). ``cards.iiif_source``: the manifest id, the
canvas's size, the Image API service, the size fetched and the rights statement, so a release can
put its crop boxes back on the museum's canvas (exports.formats.iiif). Both NULL for a card
ingested from a file.

Revision ID: 0015
Revises: 0014
Create Date: 2026-11-28
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Plain ALTER TABLE and a unique index, never batch mode's table copy: with foreign keys on,
    # dropping the old copy of cards would cascade-delete every row that references a card.
    op.add_column("cards", sa.Column("iiif_canvas_id", sa.String(1000), nullable=True))
    op.add_column("cards", sa.Column("iiif_source", JSON, nullable=True))
    op.create_index("ix_cards_iiif_canvas_id", "cards", ["iiif_canvas_id"], unique=True)


def downgrade() -> None:
    op.drop_index("ix_cards_iiif_canvas_id", table_name="cards")
    op.drop_column("cards", "iiif_source")
    op.drop_column("cards", "iiif_canvas_id")

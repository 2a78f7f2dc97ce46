"""the loop: what an acceptance was given, and the background workers that recompute

``card_reviews.accepted_results``: the results a curator's accept or grade change was given
(per stage: parameters, inputs digest, when it ran; the grade's outcome), so a recomputed result
goes back to the curator instead of being released under the old acceptance (issue 32). Null on
reviews decided before this revision: those are compared by time (a result computed after the
decision outdates it).

``pipeline_workers``: one row per running ``keystone worker`` (or the one ``keystone serve``
starts), beating while it lives, so the pages can say whether stale work will be recomputed
without anyone at a terminal.

``ix_crowd_aggregates_updated_at``: the worker's cue that crowd work arrived is the newest
aggregate change, read every few seconds; indexed, it is one lookup at any size.

Revision ID: 0014
Revises: 0013
Create Date: 2026-11-27
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_crowd_aggregates_updated_at", "crowd_aggregates", ["updated_at"])
    with op.batch_alter_table("card_reviews") as batch:
        batch.add_column(sa.Column("accepted_results", JSON, nullable=True))
    op.create_table(
        "pipeline_workers",
        sa.Column("id", sa.String(120), primary_key=True),
        sa.Column("host", sa.String(200), nullable=False),
        sa.Column("pid", sa.Integer(), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("beat_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("state", sa.String(20), nullable=False),
        sa.Column("rounds", sa.Integer(), nullable=False),
        sa.Column("last_round", JSON, nullable=True),
    )


def downgrade() -> None:
    op.drop_index("ix_crowd_aggregates_updated_at", table_name="crowd_aggregates")
    op.drop_table("pipeline_workers")
    with op.batch_alter_table("card_reviews") as batch:
        batch.drop_column("accepted_results")

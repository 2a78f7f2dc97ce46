"""catalogue: collections, cards, stage results, metadata, people

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:

    op.create_table(
        "collections",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("description", sa.Text(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_collections")),
        sa.UniqueConstraint("name", name=op.f("uq_collections_name")),
    )
    op.create_table(
        "people",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("username", sa.String(length=120), nullable=False),
        sa.Column("display_name", sa.String(length=200), nullable=False),
        sa.Column("password_hash", sa.String(length=300), nullable=True),
        sa.Column("active", sa.Boolean(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_people")),
        sa.UniqueConstraint("username", name=op.f("uq_people_username")),
    )
    op.create_table(
        "cards",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("collection_id", sa.Integer(), nullable=False),
        sa.Column("content_hash", sa.String(length=64), nullable=False),
        sa.Column("stored_path", sa.String(length=500), nullable=False),
        sa.Column("source_name", sa.String(length=500), nullable=False),
        sa.Column("source_path", sa.Text(), nullable=False),
        sa.Column("accession", sa.String(length=100), nullable=True),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("image_format", sa.String(length=20), nullable=False),
        sa.Column("byte_size", sa.BigInteger(), nullable=False),
        sa.Column(
            "source_metadata", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False
        ),
        sa.Column("state", sa.String(length=20), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("state IN ('ingested', 'pass', 'review', 'culled', 'failed')", name=op.f("ck_cards_state")),
        sa.ForeignKeyConstraint(["collection_id"], ["collections.id"], name=op.f("fk_cards_collection_id_collections")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_cards")),
        sa.UniqueConstraint("content_hash", name=op.f("uq_cards_content_hash")),
    )
    with op.batch_alter_table("cards", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_cards_accession"), ["accession"], unique=False)
        batch_op.create_index(batch_op.f("ix_cards_collection_id"), ["collection_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_cards_state"), ["state"], unique=False)

    op.create_table(
        "person_roles",
        sa.Column("person_id", sa.Integer(), nullable=False),
        sa.Column("role", sa.String(length=20), nullable=False),
        sa.CheckConstraint("role IN ('annotator', 'curator', 'exporter', 'admin')", name=op.f("ck_person_roles_role")),
        sa.ForeignKeyConstraint(["person_id"], ["people.id"], name=op.f("fk_person_roles_person_id_people"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("person_id", "role", name=op.f("pk_person_roles")),
    )
    op.create_table(
        "metadata_records",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("collection_id", sa.Integer(), nullable=False),
        sa.Column("record_key", sa.String(length=600), nullable=False),
        sa.Column("accession", sa.String(length=100), nullable=True),
        sa.Column("file_name", sa.String(length=500), nullable=True),
        sa.Column("fields", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("source_file", sa.Text(), nullable=False),
        sa.Column("row_number", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_metadata_records_card_id_cards"), ondelete="SET NULL"),
        sa.ForeignKeyConstraint(
            ["collection_id"], ["collections.id"], name=op.f("fk_metadata_records_collection_id_collections")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_metadata_records")),
        sa.UniqueConstraint("collection_id", "record_key", name="collection_record"),
    )
    with op.batch_alter_table("metadata_records", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_metadata_records_accession"), ["accession"], unique=False)
        batch_op.create_index(batch_op.f("ix_metadata_records_card_id"), ["card_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_metadata_records_collection_id"), ["collection_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_metadata_records_file_name"), ["file_name"], unique=False)

    op.create_table(
        "stage_results",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("card_id", sa.Integer(), nullable=False),
        sa.Column("stage", sa.String(length=30), nullable=False),
        sa.Column("param_hash", sa.String(length=32), nullable=False),
        sa.Column("status", sa.String(length=10), nullable=False),
        sa.Column("outcome", sa.String(length=30), nullable=True),
        sa.Column("reason", sa.Text(), nullable=True),
        sa.Column("metrics", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("artifacts", sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("seconds", sa.Float(), nullable=True),
        sa.Column("code_version", sa.String(length=40), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("status IN ('done', 'skipped', 'failed')", name=op.f("ck_stage_results_status")),
        sa.ForeignKeyConstraint(["card_id"], ["cards.id"], name=op.f("fk_stage_results_card_id_cards"), ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_stage_results")),
        sa.UniqueConstraint("card_id", "stage", "param_hash", name="card_stage_params"),
    )
    with op.batch_alter_table("stage_results", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_stage_results_card_id"), ["card_id"], unique=False)
        batch_op.create_index("ix_stage_results_stage_status", ["stage", "status"], unique=False)


def downgrade() -> None:

    with op.batch_alter_table("stage_results", schema=None) as batch_op:
        batch_op.drop_index("ix_stage_results_stage_status")
        batch_op.drop_index(batch_op.f("ix_stage_results_card_id"))

    op.drop_table("stage_results")
    with op.batch_alter_table("metadata_records", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_metadata_records_file_name"))
        batch_op.drop_index(batch_op.f("ix_metadata_records_collection_id"))
        batch_op.drop_index(batch_op.f("ix_metadata_records_card_id"))
        batch_op.drop_index(batch_op.f("ix_metadata_records_accession"))

    op.drop_table("metadata_records")
    op.drop_table("person_roles")
    with op.batch_alter_table("cards", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_cards_state"))
        batch_op.drop_index(batch_op.f("ix_cards_collection_id"))
        batch_op.drop_index(batch_op.f("ix_cards_accession"))

    op.drop_table("cards")
    op.drop_table("people")
    op.drop_table("collections")

"""Migrations are the schema: applying them gives exactly what the models declare."""

from __future__ import annotations

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect, text

from app.schema import (
    EXPRESSION_INDEXES,
    MigrationRefused,
    current_revision,
    ensure_schema,
    head_revision,
    include_object,
    target_metadata,
    upgrade,
)
from core.db import db

pytestmark = pytest.mark.both_databases


def _index_names(connection) -> set[str]:  # type: ignore[no-untyped-def]
    """Every index's name, from the catalogue itself: SQLite's reflection skips expression indexes."""
    if connection.dialect.name == "sqlite":
        return set(connection.exec_driver_sql("SELECT name FROM sqlite_master WHERE type = 'index'").scalars())
    return set(connection.exec_driver_sql("SELECT indexname FROM pg_indexes WHERE schemaname = current_schema()").scalars())


def test_models_and_migrations_agree(app):
    with app.app_context(), db.engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True, "include_object": include_object})
        diff = compare_metadata(context, target_metadata())
        indexes = _index_names(connection)
    assert diff == []
    # Autogenerate cannot compare these, so check the migrations made them.
    assert EXPRESSION_INDEXES <= indexes


def test_migrations_reach_head_and_ensure_is_idempotent(app):
    with app.app_context():
        assert current_revision(db.engine) == head_revision(db.engine) == "0015"
        assert ensure_schema(db.engine) is False
        tables = set(inspect(db.engine).get_table_names())
    assert {"collections", "cards", "stage_results", "people", "person_roles", "metadata_records", "stage_claims"} <= tables


def test_downgrade_to_base_and_back(app):
    with app.app_context():
        upgrade(db.engine, "head")
        from alembic import command

        from app.schema import alembic_config

        config = alembic_config(db.engine)
        with db.engine.begin() as connection:
            config.attributes["connection"] = connection
            command.downgrade(config, "base")
        assert "cards" not in inspect(db.engine).get_table_names()
        upgrade(db.engine)
        assert "cards" in inspect(db.engine).get_table_names()


def test_usernames_differing_only_in_case_stop_migration_0013_by_name(app):
    from alembic import command

    from app.schema import alembic_config

    def migrate(step, revision: str) -> None:  # type: ignore[no-untyped-def]
        config = alembic_config(db.engine)
        with db.engine.begin() as connection:
            config.attributes["connection"] = connection
            step(config, revision)

    with app.app_context():
        upgrade(db.engine, "head")
        migrate(command.downgrade, "0012")
        with db.engine.begin() as connection:
            for name in ("admin", "ADMIN", "Admin", "ada"):
                connection.execute(
                    text(
                        "INSERT INTO people (username, display_name, active, created_at) VALUES (:n, :n, true, CURRENT_TIMESTAMP)"
                    ),
                    {"n": name},
                )
        with pytest.raises(MigrationRefused) as refused:
            migrate(command.upgrade, "0013")
        message = refused.value.message
        assert "1 group(s)" in message and "'ADMIN' and 'Admin' and 'admin'" in message and "'ada'" not in message
        assert current_revision(db.engine) == "0012"
        with db.engine.begin() as connection:
            assert connection.execute(text("SELECT count(*) FROM people")).scalar() == 4  # nobody dropped
            connection.execute(text("DELETE FROM people WHERE username IN ('ADMIN', 'Admin')"))
        migrate(command.upgrade, "0013")
        assert current_revision(db.engine) == "0013"
        with db.engine.connect() as connection:
            assert "uq_people_username_lower" in _index_names(connection)


def test_sqlite_connection_settings(app):
    if app.config["SQLALCHEMY_DATABASE_URI"].startswith("postgresql"):
        pytest.skip("SQLite pragmas only")
    with app.app_context(), db.engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
        assert connection.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30_000
        connection.execute(text("SELECT 1"))

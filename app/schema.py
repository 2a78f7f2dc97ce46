"""Schema management: Alembic migrations are the only way the schema changes.

``keystone init`` applies them; commands that need the catalogue call :func:`ensure_schema`,
which upgrades to head (a no-op when current). A test checks models and migrations agree.
"""

from __future__ import annotations

from pathlib import Path

import click
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import MetaData
from sqlalchemy.engine import Engine

MIGRATIONS_DIR = Path(__file__).with_name("migrations")


class MigrationRefused(click.ClickException):
    """A migration that stopped before changing anything, with a sentence for the operator
    (``keystone init`` and every command that upgrades print it without a traceback)."""


# Indexes on expressions (sort order, NULLS LAST) that Alembic's autogenerate cannot compare:
# the migrations create them, autogenerate leaves them alone, and a test checks they exist.
EXPRESSION_INDEXES = frozenset({"ix_card_reviews_queue", "uq_people_username_lower"})


def include_object(obj: object, name: str | None, type_: str, reflected: bool, compare_to: object) -> bool:
    """Autogenerate filter: skip the expression indexes (see :data:`EXPRESSION_INDEXES`)."""
    return not (type_ == "index" and name in EXPRESSION_INDEXES)


def target_metadata() -> MetaData:
    """All models' metadata: importing the feature model modules registers their tables."""
    import annotation.models  # noqa: F401
    import exports.models  # noqa: F401
    import review.models  # noqa: F401
    import runs.claims  # noqa: F401  (stage_claims)
    import runs.worker  # noqa: F401  (pipeline_workers)
    from core import audit, models  # noqa: F401
    from core.db import db

    return db.metadata


def alembic_config(engine: Engine) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", engine.url.render_as_string(hide_password=False).replace("%", "%%"))
    return config


def head_revision(engine: Engine) -> str | None:
    return ScriptDirectory.from_config(alembic_config(engine)).get_current_head()


def current_revision(engine: Engine) -> str | None:
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def upgrade(engine: Engine, revision: str = "head") -> None:
    config = alembic_config(engine)
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def ensure_schema(engine: Engine) -> bool:
    """Upgrade to head if needed; returns True when migrations were applied."""
    if current_revision(engine) == head_revision(engine):
        return False
    upgrade(engine)
    return True

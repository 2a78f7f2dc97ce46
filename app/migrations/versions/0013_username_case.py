"""usernames: unique ignoring case

``people`` gets a unique index on ``lower(username)``, so ``ADMIN`` and ``Admin`` can no longer
be added beside ``admin`` (issue 32). Log-in finds a person ignoring case, which needs at most
one person per lower-cased name.

If existing people already collide, the upgrade stops and names them: which account to keep,
rename or merge (its reviews, audit trail, roles) is an admin's decision, never the migration's.
Rename all but one of each group in the database and run ``keystone init`` again.

``lower()`` is the database's own: PostgreSQL folds every letter its collation knows, SQLite
only A-Z. The app refuses case-variants of any alphabet before they reach the database
(core.people), so the index is the backstop for concurrent adds.

Revision ID: 0013
Revises: 0012
Create Date: 2026-11-27
"""

from alembic import op

from app.schema import MigrationRefused

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None

INDEX = "uq_people_username_lower"


def _collisions() -> list[list[str]]:
    """Groups of existing usernames that are equal under the database's ``lower()``."""
    rows = op.get_bind().exec_driver_sql("SELECT lower(username), username FROM people ORDER BY username").all()
    groups: dict[str, list[str]] = {}
    for folded, username in rows:
        groups.setdefault(folded, []).append(username)
    return [names for names in groups.values() if len(names) > 1]


def upgrade() -> None:
    collisions = _collisions()
    if collisions:
        listed = "; ".join(" and ".join(repr(name) for name in names) for names in collisions)
        raise MigrationRefused(
            f"Cannot make usernames unique ignoring case: {len(collisions)} group(s) of people differ only in case "
            f"({listed}). Nothing was changed. Rename all but one in each group in the database "
            "(UPDATE people SET username = 'new name' WHERE username = 'old name'), then run keystone init again."
        )
    # Plain SQL: both SQLite (3.9+) and PostgreSQL index an expression with the same statement.
    op.execute(f"CREATE UNIQUE INDEX {INDEX} ON people (lower(username))")


def downgrade() -> None:
    op.execute(f"DROP INDEX {INDEX}")

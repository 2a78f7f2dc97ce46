"""Database binding: one Flask-SQLAlchemy instance, SQLite tuned for concurrent writers.

SQLite facts measured on the project's machines (also in README.md): WAL + busy_timeout is not enough. A
deferred transaction that reads and then writes fails at once with "database is locked"
under concurrency (2,352 of 2,400 writes in a 16-writer test), because SQLite cannot upgrade
its read lock while another writer holds the database and busy_timeout does not apply to that
upgrade. Beginning write transactions with ``BEGIN IMMEDIATE`` takes the write lock up front,
where busy_timeout does wait (0 errors). So every transaction here begins IMMEDIATE unless the
caller marks it read-only with :func:`read_only`; PostgreSQL needs none of this.
"""

from __future__ import annotations

import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

from flask_sqlalchemy import SQLAlchemy
from sqlalchemy import JSON, MetaData, event
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Session

SQLITE_BUSY_TIMEOUT_MS = 30_000
READ_ONLY_OPTION = "keystone_read_only"

# Deterministic constraint names so Alembic can alter them on SQLite and PostgreSQL alike.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

JSONType = JSON().with_variant(JSONB(), "postgresql")


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


db = SQLAlchemy(model_class=Base)


def utcnow() -> datetime:
    return datetime.now(UTC)


@event.listens_for(Engine, "connect")
def _configure_sqlite(dbapi_connection: Any, _record: Any) -> None:
    if not isinstance(dbapi_connection, sqlite3.Connection):
        return
    # Take transaction control away from the driver so the "begin" hook decides the mode.
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


@event.listens_for(Engine, "begin")
def _begin_sqlite(connection: Any) -> None:
    if connection.dialect.name != "sqlite":
        return
    # Straight to the driver: BEGIN returns no rows, and every transaction pays for this hook
    # (exec_driver_sql's result machinery was a third of an empty read transaction's cost).
    mode = "DEFERRED" if connection.get_execution_options().get(READ_ONLY_OPTION) else "IMMEDIATE"
    connection.connection.driver_connection.execute(f"BEGIN {mode}")


@contextmanager
def read_only(session: Session | None = None) -> Iterator[Session]:
    """Run reads in a deferred transaction (SQLite): hot read paths don't queue behind writers.

    The transaction is rolled back on exit. Inside a transaction that is already open, reads
    simply join it (and leave it open): the mode of a begun transaction cannot change.
    """
    session = session or db.session()
    if session.in_transaction():
        yield session
        return
    session.connection(execution_options={READ_ONLY_OPTION: True})
    try:
        yield session
    finally:
        session.rollback()


# ---------------------------------------------------------------------------------------------
# One writer at a time, queued in the operating system instead of SQLite's busy handler

try:
    import fcntl
except ImportError:  # Windows: threads are gated, processes meet SQLite's busy handler
    fcntl = None  # type: ignore[assignment]

_THREAD_GATE = threading.Lock()
THREAD_GATE_TIMEOUT_S = 5.0


@contextmanager
def _process_gate(database: str) -> Iterator[None]:
    """An exclusive flock of ``<database>-writer-lock`` for the block (nothing for in-memory databases).

    Opened per use (a few microseconds): nothing to leak, and nothing a forked server worker
    could share with its parent. Read-only is enough for flock, so a lock file made by another
    user still works.
    """
    if fcntl is None or not database or database == ":memory:" or database.startswith("file:"):
        yield
        return
    try:
        descriptor = os.open(f"{database}-writer-lock", os.O_RDONLY | os.O_CREAT, 0o644)
    except OSError:  # a read-only folder: SQLite's busy handler alone, as without the gate
        yield
        return
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX)
        yield
    finally:
        os.close(descriptor)  # releases the lock


@contextmanager
def one_writer(session: Session | None = None) -> Iterator[None]:
    """On SQLite, let one short write transaction at a time in, across threads and server processes.

    Why: a writer that finds the database locked sleeps in SQLite's busy handler in growing
    steps (1, 2, 5, 10 ... 100 ms) however soon the lock frees, so under a crowd the sleeping,
    not the work, made the latency tail, and between two server processes the lock sat idle
    while both slept. Here threads of a process queue on a Python lock and processes on an
    flock of ``<database>-writer-lock``; both wake the moment the holder leaves. SQLite's busy
    handler stays the arbiter for writers that do not come through here (the pipeline runner,
    other commands). A session already in a write transaction holds SQLite's lock and goes
    straight in (waiting here could deadlock with a gate holder waiting for that lock); the
    thread gate gives up waiting after ``THREAD_GATE_TIMEOUT_S`` for the same reason.
    PostgreSQL needs none of this.
    """
    session = session or db.session()
    bind = session.get_bind()
    if bind.dialect.name != "sqlite" or (
        session.in_transaction() and not session.connection().get_execution_options().get(READ_ONLY_OPTION)
    ):
        yield
        return
    acquired = _THREAD_GATE.acquire(timeout=THREAD_GATE_TIMEOUT_S)
    try:
        if acquired:
            with _process_gate(bind.url.database or ""):
                yield
        else:
            yield
    finally:
        if acquired:
            _THREAD_GATE.release()

"""Fixtures shared by the suite: an app on a throwaway database, its client and CLI runner.

Tests marked ``both_databases`` run once on SQLite and once on PostgreSQL when a server
binary (``initdb``/``pg_ctl``) is on the machine: a throwaway cluster is started for the
session in a temporary folder, on a unix socket, then stopped. No mocks.
"""

from __future__ import annotations

import itertools
import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", REPO.parent / "shared" / "data"))


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "both_databases: run on SQLite and on PostgreSQL when available")


def find_pg_bin() -> Path | None:
    candidates = [os.environ.get("KEYSTONE_PG_BIN", "")]
    candidates += sorted((str(p) for p in Path("/usr/lib/postgresql").glob("*/bin")), reverse=True)
    which = shutil.which("pg_ctl")
    if which:
        candidates.append(str(Path(which).resolve().parent))
    for candidate in candidates:
        if candidate and (Path(candidate) / "initdb").exists() and (Path(candidate) / "pg_ctl").exists():
            return Path(candidate)
    return None


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "database" in metafunc.fixturenames:
        backends = ["sqlite"]
        if metafunc.definition.get_closest_marker("both_databases"):
            backends.append("postgresql")
        metafunc.parametrize("database", backends, indirect=True)


class PostgresCluster:
    """initdb + pg_ctl in a temporary folder; listens only on a unix socket in that folder."""

    def __init__(self, bin_dir: Path) -> None:
        self.bin_dir = bin_dir
        self.root = Path(tempfile.mkdtemp(prefix="keystone-pg-"))
        self.data = self.root / "data"
        self.socket_dir = self.root
        self.user = "keystone"
        self._run_as: list[str] = []
        if os.geteuid() == 0:
            # initdb refuses to run as root: run the server as an unprivileged account.
            account = "postgres" if _user_exists("postgres") else "nobody"
            self._run_as = ["runuser", "-u", account, "--"]
            uid = pwd.getpwnam(account).pw_uid
            gid = pwd.getpwnam(account).pw_gid
            os.chown(self.root, uid, gid)
        self._names = itertools.count()

    def _run(self, *args: str) -> None:
        subprocess.run([*self._run_as, *args], check=True, capture_output=True, timeout=120)

    def start(self) -> None:
        self._run(str(self.bin_dir / "initdb"), "-D", str(self.data), "-U", self.user, "--auth=trust", "-E", "UTF8", "--no-sync")
        options = f"-c listen_addresses='' -c unix_socket_directories={self.socket_dir} -c fsync=off -c max_connections=200"
        self._run(str(self.bin_dir / "pg_ctl"), "-D", str(self.data), "-o", options, "-l", str(self.root / "log"), "-w", "start")

    def stop(self) -> None:
        try:
            self._run(str(self.bin_dir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://{self.user}@/{database}?host={self.socket_dir}"

    def create_database(self) -> str:
        import psycopg

        name = f"keystone_test_{os.getpid()}_{next(self._names)}"
        with psycopg.connect(f"host={self.socket_dir} user={self.user} dbname=postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return name


def _user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    bin_dir = find_pg_bin()
    if bin_dir is None:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl) on this machine")
    cluster = PostgresCluster(bin_dir)
    cluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def database(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A SQLAlchemy URL for an empty database of the requested backend."""
    backend = getattr(request, "param", "sqlite")
    if backend == "postgresql":
        cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
        return cluster.url(cluster.create_database())
    return f"sqlite:///{tmp_path / 'keystone.sqlite3'}"


@pytest.fixture
def app(database: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    from app import create_app
    from app.db import db
    from app.schema import upgrade

    monkeypatch.setenv("KEYSTONE_INSTANCE_PATH", str(tmp_path / "instance"))
    application = create_app(
        {
            "TESTING": True,
            "SQLALCHEMY_DATABASE_URI": database,
            "KEYSTONE_DATA_DIR": str(tmp_path / "data"),
            "SECRET_KEY": "test-secret",
        }
    )
    with application.app_context():
        upgrade(db.engine)
    yield application
    with application.app_context():
        db.session.remove()
        db.engine.dispose()


@pytest.fixture
def client(app):  # type: ignore[no-untyped-def]
    return app.test_client()


@pytest.fixture
def runner(app):  # type: ignore[no-untyped-def]
    return app.test_cli_runner()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``$KEYSTONE_SHARED_DATA`` or ``../shared/data`` beside the checkout; skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} not present: real-data tests need ../shared/data")
    return SHARED_DATA

"""One driver per card-stage: two ``keystone run`` at once, killed runs, stale and live claims.

The concurrent runs are real processes (``python -m app run``) on one database. A barrier
(a write lock the test holds until both processes wait on it) starts them together, so the
test exercises the overlap instead of hoping for it.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select

from app.cli import cli
from core.db import db, utcnow
from core.models import StageResult
from runs.claims import StageClaim

pytestmark = pytest.mark.both_databases

REPO = Path(__file__).resolve().parents[2]
CARDS = 16


@pytest.fixture
def cards(make_card, card_image) -> list[int]:  # type: ignore[no-untyped-def]
    """``CARDS`` small distinct stereo cards (one pixel differs, so each has its own content hash)."""
    ids = []
    for index in range(CARDS):
        image = card_image(half=(148, 100), gutter=8).copy()
        image[0, 0] = (index, 255 - index, 7)
        ids.append(make_card(image))
    return ids


def _env(app, tmp_path: Path) -> dict[str, str]:  # type: ignore[no-untyped-def]
    return {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "KEYSTONE_DATABASE_URL": app.config["SQLALCHEMY_DATABASE_URI"],
        "KEYSTONE_DATA_DIR": app.config["KEYSTONE_DATA_DIR"],
        "KEYSTONE_SECRET_KEY": "test-secret",
        "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance"),
    }


def _start_run(app, tmp_path: Path, *args: str) -> subprocess.Popen[str]:  # type: ignore[no-untyped-def]
    return subprocess.Popen(
        [sys.executable, "-m", "app", "run", "--stages", "filter", "--json", *args],
        cwd=REPO,
        env=_env(app, tmp_path),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _filter_rows(app) -> int:  # type: ignore[no-untyped-def]
    with app.app_context():
        return db.session.scalar(select(func.count()).select_from(StageResult).where(StageResult.stage == "filter"))


def _claims(app) -> list[StageClaim]:  # type: ignore[no-untyped-def]
    with app.app_context():
        claims = list(db.session.scalars(select(StageClaim).order_by(StageClaim.card_id)))
        db.session.expunge_all()
        return claims


class _Barrier:
    """Hold the database's write lock (SQLite) or the claims table (PostgreSQL) until the
    runs wait on it, then let them all go at once."""

    def __init__(self, url: str) -> None:
        self.url = url
        if url.startswith("sqlite"):
            self.path = url.removeprefix("sqlite:///")
            self.connection = sqlite3.connect(self.path, isolation_level=None)
            self.connection.execute("BEGIN IMMEDIATE")
        else:
            import psycopg
            from sqlalchemy.engine import make_url

            parsed = make_url(url)
            self.connection = psycopg.connect(host=parsed.query["host"], user=parsed.username, dbname=parsed.database)
            self.connection.execute("LOCK TABLE stage_claims IN ACCESS EXCLUSIVE MODE")

    def _waiting(self, processes: list[subprocess.Popen[str]]) -> int:
        if self.url.startswith("sqlite"):
            if not Path("/proc/self/fd").is_dir():  # no /proc to look in: give the runs time instead
                time.sleep(5)
                return len(processes)

            # A run that has the database open is at (or just before) its first write, which waits.
            def has_open(pid: int) -> bool:
                folder = Path(f"/proc/{pid}/fd")
                try:
                    return any(os.readlink(fd) == self.path for fd in folder.iterdir())
                except OSError:
                    return False

            return sum(has_open(process.pid) for process in processes)
        return self.connection.execute(
            "SELECT count(*) FROM pg_locks WHERE relation = 'stage_claims'::regclass AND NOT granted"
        ).fetchone()[0]

    def release_when_waiting(self, processes: list[subprocess.Popen[str]], timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while self._waiting(processes) < len(processes):
            assert all(process.poll() is None for process in processes), "a run ended before the barrier"
            assert time.monotonic() < deadline, "the runs never reached the barrier"
            time.sleep(0.05)
        if self.url.startswith("sqlite"):
            time.sleep(0.3)  # from opening the file to waiting on the lock
        self.connection.commit() if not self.url.startswith("sqlite") else self.connection.execute("COMMIT")
        self.connection.close()


def _finish(process: subprocess.Popen[str], timeout_s: float = 120) -> tuple[int, dict, str]:
    stdout, stderr = process.communicate(timeout=timeout_s)
    assert "Traceback" not in stderr, stderr
    return process.returncode, json.loads(stdout) if stdout.strip() else {}, stderr


def test_two_concurrent_runs_compute_each_card_stage_once(app, cards, tmp_path, database):
    barrier = _Barrier(database)
    runs = [_start_run(app, tmp_path, "--claim-batch", "3") for _ in range(2)]
    barrier.release_when_waiting(runs)
    results = [_finish(run) for run in runs]

    reports = [document["stages"][0] for _, document, _ in results]
    assert [code for code, _, _ in results] == [0, 0], [stderr for _, _, stderr in results]
    processed = [report["processed"] for report in reports]
    # The figure: card-stages computed by both runs together, against the number of cards.
    assert sum(processed) == CARDS and _filter_rows(app) == CARDS, processed
    assert all(count > 0 for count in processed), f"the runs did not overlap: {processed}"
    for report in reports:
        # Every card is accounted for by each run: computed here, or by the other run meanwhile.
        assert report["processed"] + report["done_by_other_run"] + report["already_done"] == CARDS, report
        assert report["still_held"] == 0 and report["failed"] == 0
    assert sum(report["done_by_other_run"] for report in reports) == CARDS
    assert _claims(app) == []
    print(
        f"\n[{database.split(':')[0]}] two concurrent runs over {CARDS} cards computed {processed} = {sum(processed)} card-stages"
    )


def test_a_killed_run_blocks_nobody_for_longer_than_its_claim_ttl(app, cards, tmp_path, runner):
    killed = _start_run(app, tmp_path, "--claim-batch", "4", "--claim-ttl-s", "2")
    deadline = time.monotonic() + 60
    while not _claims(app):
        assert killed.poll() is None, killed.communicate()
        assert time.monotonic() < deadline, "the run never claimed a card"
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.communicate(timeout=30)
    left = _claims(app)
    written_by_killed = _filter_rows(app)
    assert left and all(claim.expires_at - claim.heartbeat_at == timedelta(seconds=2) for claim in left)

    clock = time.monotonic()
    result = runner.invoke(cli, ["run", "--stages", "filter", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)["stages"][0]
    held = {claim.card_id for claim in left}
    assert report["taken_over"] == report["held_by_other_run"] == len(held)
    assert report["processed"] + written_by_killed == CARDS
    assert _filter_rows(app) == CARDS and _claims(app) == []
    assert time.monotonic() - clock < 30  # waited out a 2 s lease, not the default 2 minutes


def _claim(app, card_id: int, driver: str, expires_in_s: float) -> None:  # type: ignore[no-untyped-def]
    now = utcnow()
    with app.app_context():
        db.session.add(
            StageClaim(
                card_id=card_id,
                stage="filter",
                param_hash="0" * 16,
                driver=driver,
                claimed_at=now - timedelta(seconds=300),
                heartbeat_at=now - timedelta(seconds=60),
                expires_at=now + timedelta(seconds=expires_in_s),
            )
        )
        db.session.commit()


def test_a_stale_claim_of_a_dead_run_is_taken_over(app, cards, runner):
    _claim(app, cards[3], "dead-host:4242:0badc0de", expires_in_s=-1)
    result = runner.invoke(cli, ["run", "--stages", "filter", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)["stages"][0]
    assert (report["processed"], report["taken_over"], report["held_by_other_run"]) == (CARDS, 1, 0)
    assert _filter_rows(app) == CARDS and _claims(app) == []


def test_a_live_claim_is_respected_and_no_wait_exits_3(app, cards, runner):
    _claim(app, cards[5], "busy-host:77:live0001", expires_in_s=3600)
    result = runner.invoke(cli, ["run", "--stages", "filter", "--no-wait", "--json"])
    assert result.exit_code == 3, result.output
    report = json.loads(result.stdout)["stages"][0]
    assert (report["processed"], report["held_by_other_run"], report["still_held"], report["taken_over"]) == (CARDS - 1, 1, 1, 0)
    assert "left 1 card(s) that another run holds (busy-host:77:live0001)" in result.stderr
    with app.app_context():
        assert db.session.scalar(select(StageResult).where(StageResult.card_id == cards[5])) is None
    assert [(claim.card_id, claim.driver) for claim in _claims(app)] == [(cards[5], "busy-host:77:live0001")]


def test_a_waiting_run_takes_over_a_claim_once_it_lapses(app, cards, runner):
    _claim(app, cards[0], "slow-host:78:live0002", expires_in_s=1.5)
    clock = time.monotonic()
    result = runner.invoke(cli, ["run", "--stages", "filter", "--json", "--claim-ttl-s", "4"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)["stages"][0]
    assert (report["processed"], report["held_by_other_run"], report["taken_over"], report["still_held"]) == (CARDS, 1, 1, 0)
    assert time.monotonic() - clock >= 1.0
    assert "filter: waiting for 1 card(s) held by another run (slow-host:78:live0002)" in result.stderr
    assert _filter_rows(app) == CARDS and _claims(app) == []


def test_write_records_upserts_a_row_another_transaction_inserted_meanwhile(app, cards, database):
    """The old read-then-insert died with UniqueViolation on PostgreSQL when another run inserted
    the same result between its read and its insert; the upsert waits and overwrites."""
    from sqlalchemy import create_engine

    from pipeline.records import StageRecord
    from runs.writes import write_records

    other = create_engine(database)
    connection = other.connect()
    transaction = connection.begin()
    connection.execute(
        StageResult.__table__.insert().values(
            card_id=cards[0],
            stage="filter",
            param_hash="p" * 16,
            status="failed",
            reason="first",
            metrics={},
            artifacts={},
            code_version="other",
            created_at=utcnow(),
        )
    )
    errors: list[BaseException] = []

    def write() -> None:
        with app.app_context():
            try:
                write_records(
                    [
                        StageRecord(
                            card_id=cards[0],
                            stage="filter",
                            param_hash="p" * 16,
                            status="done",
                            outcome="pass",
                            reason="second",
                            code_version="mine",
                        )
                    ]
                )
            except Exception as exc:  # noqa: BLE001 - reported to the test thread
                errors.append(exc)

    writer = threading.Thread(target=write)
    writer.start()
    time.sleep(0.5)  # the writer is now waiting on the uncommitted row (or SQLite's write lock)
    transaction.commit()
    connection.close()
    writer.join(timeout=60)
    other.dispose()
    assert errors == []
    with app.app_context():
        rows = list(db.session.scalars(select(StageResult).where(StageResult.card_id == cards[0])))
        assert [(row.status, row.reason, row.code_version) for row in rows] == [("done", "second", "mine")]


def test_a_failed_result_is_retried_under_a_claim(app, cards, runner, add_stage_result):
    from pipeline.filter import FilterParams
    from pipeline.records import param_hash

    add_stage_result(
        cards[7], status="failed", outcome=None, reason="unreadable_image: truncated", param_hash=param_hash(FilterParams())
    )
    result = runner.invoke(cli, ["run", "--stages", "filter", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)["stages"][0]
    assert (report["processed"], report["done_by_other_run"]) == (CARDS, 0)
    with app.app_context():
        retried = db.session.scalar(select(StageResult).where(StageResult.card_id == cards[7]))
        assert retried.status == "done"


def test_the_heartbeat_renews_a_live_drivers_claims_and_release_frees_them(app, cards):
    from runs.claims import Driver

    with app.app_context():
        driver = Driver(db.engine, ttl_s=2)
        with driver.running():
            claim = driver.claim("filter", "f" * 16, cards[:3], {card_id: None for card_id in cards[:3]})
            assert claim.claimed == sorted(cards[:3]) and claim.held == {}
            first = {c.card_id: c.expires_at for c in _claims(app)}
            time.sleep(1.2)  # two beats of 0.5 s
            renewed = {c.card_id: c.expires_at for c in _claims(app)}
            assert driver.heartbeats >= 1
            assert all(renewed[card_id] > first[card_id] for card_id in first)
            rival = Driver(db.engine, ttl_s=60).claim("filter", "f" * 16, cards[:4], {c: None for c in cards[:4]})
            assert rival.claimed == [cards[3]] and set(rival.held) == set(cards[:3])
        assert [claim.card_id for claim in _claims(app)] == [cards[3]]  # the first driver's claims are gone

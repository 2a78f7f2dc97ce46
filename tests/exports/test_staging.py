"""Staging folders of killed exports are cleared, running ones never; releases are world-readable."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from exports.staging import LOCK_SUFFIX, ReleaseStaging, remove_stale_partials

REPO = Path(__file__).resolve().parents[2]

# An export in its own process: take a staging folder, write into it, say where, then either
# die by SIGKILL (no cleanup code runs) or wait to be killed.
EXPORTER = r"""
import os, signal, sys
from pathlib import Path
from exports.staging import ReleaseStaging

staging = ReleaseStaging(Path(sys.argv[1]), sys.argv[2])
(staging.path / "cards.jsonl").write_bytes(b"x" * 1_000_000)
print(staging.path, flush=True)
if sys.argv[3] == "die":
    os.kill(os.getpid(), signal.SIGKILL)
sys.stdin.read()
"""


# A writer killed inside atomic_write, after writing but before the rename.
KILLED_WRITER = """
import os, signal, sys
from pipeline.io import atomic_write
with atomic_write(sys.argv[1]) as handle:
    handle.write(b"w" * 50_000)
    handle.flush()
    os.kill(os.getpid(), signal.SIGKILL)
"""


def _exporter(out: Path, version: str, mode: str) -> tuple[subprocess.Popen[str], Path]:
    child = subprocess.Popen(
        [sys.executable, "-c", EXPORTER, str(out), version, mode],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert child.stdout is not None
    return child, Path(child.stdout.readline().strip())


def _end(child: subprocess.Popen[str]) -> int:
    """Kill (if still running), reap and close the pipes; returns the exit status."""
    if child.poll() is None:
        child.kill()
    child.communicate(timeout=60)
    return child.returncode


def test_killed_exports_are_cleared_and_running_ones_kept(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    dead, dead_folder = _exporter(out, "1.0.0", "die")
    assert _end(dead) == -signal.SIGKILL
    live, live_folder = _exporter(out, "1.0.1", "wait")
    try:
        assert dead_folder.is_dir() and live_folder.is_dir()
        removed = remove_stale_partials(out)
        assert [(Path(r.path), r.bytes) for r in removed] == [(dead_folder, 1_000_000)]
        assert "no longer running" in removed[0].reason
        assert not dead_folder.exists() and not Path(str(dead_folder) + LOCK_SUFFIX).exists()
        assert (live_folder / "cards.jsonl").stat().st_size == 1_000_000  # a running export is left alone
        assert remove_stale_partials(out) == []
        _end(live)  # now it dies too: the next export clears it
        assert [Path(r.path) for r in remove_stale_partials(out)] == [live_folder]
        assert sorted(out.iterdir()) == []
    finally:
        _end(live)


def test_a_lock_held_in_this_process_also_protects_its_folder(tmp_path: Path) -> None:
    staging = ReleaseStaging(tmp_path, "2.0.0")
    try:
        assert remove_stale_partials(tmp_path) == [] and staging.path.is_dir()
        assert stat.S_IMODE(staging.path.stat().st_mode) == 0o700  # private while being written
    finally:
        staging.close()
    assert not staging.lock_path.exists()
    assert [Path(r.path) for r in remove_stale_partials(tmp_path)] == []  # folder without lock: too fresh
    old = time.time() - 16 * 60
    for path in [staging.path, *staging.path.rglob("*")]:
        os.utime(path, (old, old))
    removed = remove_stale_partials(tmp_path)
    assert [Path(r.path) for r in removed] == [staging.path] and "no lock and unchanged for 16 min" in removed[0].reason


def test_unlocked_partial_folders_go_only_when_nothing_in_them_changed_lately(tmp_path: Path) -> None:
    """Folders of exports from before locks: the newest file inside decides, not the folder's own time."""
    legacy = tmp_path / ".1.0.0.partial-abc123"
    (legacy / "data").mkdir(parents=True)
    (legacy / "data" / "train-00000.parquet").write_bytes(b"p" * 4096)
    old = time.time() - 3600
    os.utime(legacy, (old, old))
    os.utime(legacy / "data", (old, old))  # the shard inside is fresh: an export may still write it
    assert remove_stale_partials(tmp_path) == []
    os.utime(legacy / "data" / "train-00000.parquet", (old, old))
    removed = remove_stale_partials(tmp_path)
    assert [(Path(r.path), r.bytes) for r in removed] == [(legacy, 4096)]
    (tmp_path / "1.0.0").mkdir()  # a finished release is never a leftover
    (tmp_path / "notes.partial-x").mkdir()
    os.utime(tmp_path / "notes.partial-x", (old, old))
    assert remove_stale_partials(tmp_path) == []


def test_export_clears_killed_exports_and_publishes_world_readable_under_any_umask(
    app, runner, tmp_path, processed_cards, review_card
) -> None:
    ids = processed_cards(1)
    review_card(ids[0], "few")
    out = tmp_path / "out"
    out.mkdir()
    dead, dead_folder = _exporter(out, "1.0.0", "die")
    assert _end(dead) == -signal.SIGKILL
    live, live_folder = _exporter(out, "0.9.0", "wait")
    previous = os.umask(0o077)
    try:
        result = runner.invoke(args=["export", "--out", str(out), "--format", "keystonedepth,parquet", "--json"])
    finally:
        os.umask(previous)
        _end(live)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert [(Path(r["path"]), r["bytes"]) for r in report["leftovers_removed"]] == [(dead_folder, 1_000_000)]
    assert live_folder.is_dir()  # the other export was still running
    root = Path(report["path"])
    modes = {stat.S_IMODE(p.lstat().st_mode) for p in [root, *root.rglob("*")] if p.is_dir()}
    assert modes == {0o755}
    file_modes = {stat.S_IMODE(p.lstat().st_mode) for p in root.rglob("*") if p.is_file()}
    assert file_modes == {0o644} and len(list(root.rglob("*.png"))) >= 4
    verify = runner.invoke(args=["verify", str(root), "--no-mlcroissant", "--json"])
    assert verify.exit_code == 0, verify.output  # no lock file or stray entry inside the release


@pytest.mark.parametrize("age_minutes, kept", [(11, False), (2, True)])
def test_keystone_run_removes_temporary_files_of_killed_writers(app, runner, data_dir, make_card, age_minutes, kept) -> None:
    """A writer killed inside atomic_write leaves its .tmp: the next ``keystone run`` removes it
    from the card's work folder before the card runs again (and a killed ingest's from the store)
    once older than ten minutes, and leaves a fresh one (a concurrent writer's) alone."""
    from pipeline.records import card_work_dir, param_hash
    from runs.specs import available_stages

    card_id = make_card()
    with app.app_context():
        from core.db import db
        from core.models import Card

        card = db.session.get(Card, card_id)
        work = card_work_dir(data_dir, card.content_hash, "filter", param_hash(available_stages()["filter"].params))
    leftovers = []
    for target in (work / "left.png", data_dir / "originals" / "ab" / ("ab" * 32 + ".png")):
        killed = subprocess.run(
            [sys.executable, "-c", KILLED_WRITER, str(target)], env={**os.environ, "PYTHONPATH": str(REPO)}, check=False
        )
        assert killed.returncode == -signal.SIGKILL
        (leftover,) = target.parent.glob(f".{target.name}.*.tmp")
        then = time.time() - age_minutes * 60
        os.utime(leftover, (then, then))
        leftovers.append(leftover)
    result = runner.invoke(args=["run", "--stages", "filter", "--json"])
    assert result.exit_code == 0, result.output
    assert [path.exists() for path in leftovers] == [kept, kept]
    if not kept:
        assert "removed 1 temporary file(s) and 0 export staging folder(s) (0.1 MB)" in result.stderr
    assert json.loads(result.stdout)["stages"][0]["processed"] == 1  # and the card ran


def test_keystone_run_clears_killed_exports_in_the_releases_folder(app, runner, tmp_path, make_card) -> None:
    """The driver does not import exports: the app factory registers the staging cleaner with
    runs.leftovers, and ``keystone run`` clears a killed export's folder and keeps a running one's."""
    make_card()
    releases = tmp_path / "releases"
    releases.mkdir()
    app.config["KEYSTONE_RELEASES_DIR"] = str(releases)
    dead, dead_folder = _exporter(releases, "1.0.0", "die")
    assert _end(dead) == -signal.SIGKILL
    live, live_folder = _exporter(releases, "1.0.1", "wait")
    try:
        result = runner.invoke(args=["run", "--stages", "filter", "--json"])
        assert result.exit_code == 0, result.output
        assert "0 temporary file(s) and 1 export staging folder(s) (1.0 MB)" in result.stderr
        assert not dead_folder.exists() and live_folder.is_dir()
    finally:
        _end(live)

"""A release's staging folder, held by a lock while its export runs, and the clearing of those
that killed exports left behind.

An export writes into ``<out>/.<version>.partial-XXXX`` beside a lock file of the same name plus
``.lock``, on which it holds an exclusive ``flock`` for as long as it runs. The kernel drops the
lock when the process ends, however it ends (``kill -9`` included), so "the lock can be taken"
means "its export is dead" with no pid to check and no pid reuse to fear; a concurrent export's
folder is never touched. Partial folders without a lock file (written before locks existed) are
cleared only when nothing in them has changed for :data:`UNLOCKED_STALE_SECONDS`.

Releases are made world-readable (directories 0755, files 0644) with explicit modes just before
they move into place, whatever the umask: a release is meant to be published.

Publishing into ``<out>`` is one at a time: :class:`PublishLock` is an ``flock`` on the folder
itself, held from planning to recording, and a second publish meanwhile is refused at once
(:class:`PublishBusy`). Just before a finished release moves into place, the publish writes
``<out>/.<version>.publishing``, and removes it once the release is recorded; a marker found by
the next publish (under the lock, so its writer is dead) names a release folder that may be in
place but unrecorded, which :func:`clear_unrecorded` removes (:mod:`exports.release` says why).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import stat
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

PARTIAL_MARK = ".partial-"
LOCK_SUFFIX = ".lock"
PUBLISHING_SUFFIX = ".publishing"
UNLOCKED_STALE_SECONDS = 15 * 60
RELEASE_DIR_MODE = 0o755
RELEASE_FILE_MODE = 0o644


@dataclass(frozen=True)
class Leftover:
    """A staging folder (or lone lock file) removed, its size and why it was judged dead."""

    path: str
    bytes: int
    reason: str

    def as_json(self) -> dict[str, str | int]:
        return {"path": self.path, "bytes": self.bytes, "reason": self.reason}


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` still names the file open as ``fd`` (a cleaner may have unlinked it)."""
    try:
        on_disk = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (on_disk.st_dev, on_disk.st_ino) == (held.st_dev, held.st_ino)


class ReleaseStaging:
    """``<out>/.<version>.partial-XXXX``, locked by this process until :meth:`close`.

    The lock file is made and locked first and the folder named after it, so the folder never
    exists unlocked while its export lives."""

    def __init__(self, out: Path, version: str) -> None:
        while True:
            fd, name = tempfile.mkstemp(prefix=f".{version}{PARTIAL_MARK}", suffix=LOCK_SUFFIX, dir=out)
            fcntl.flock(fd, fcntl.LOCK_EX)  # waits only while a cleaner checks it
            if _same_file(fd, Path(name)):
                break
            os.close(fd)  # a cleaner took the fresh, not yet locked file for dead: make another
        os.write(fd, f"pid {os.getpid()}\n".encode())  # for a person looking; the lock is the truth
        self._fd: int | None = fd
        self.lock_path = Path(name)
        self.path = self.lock_path.with_name(self.lock_path.name[: -len(LOCK_SUFFIX)])
        self.path.mkdir(mode=0o700)  # private while being written; published 0755 by make_world_readable

    def close(self) -> None:
        """Drop the lock (after the folder was renamed into place or removed)."""
        if self._fd is None:
            return
        self.lock_path.unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None


def make_world_readable(root: Path) -> None:
    """Directories 0755 and files 0644 under ``root`` (itself included), set explicitly so the
    umask of whoever ran the export does not decide who can read a published release."""
    os.chmod(root, RELEASE_DIR_MODE)
    for folder, dirnames, filenames in os.walk(root):
        for name in dirnames:
            os.chmod(os.path.join(folder, name), RELEASE_DIR_MODE, follow_symlinks=False)
        for name in filenames:
            path = os.path.join(folder, name)
            if not os.path.islink(path):
                os.chmod(path, RELEASE_FILE_MODE)


def _tree_size_and_newest(root: Path) -> tuple[int, float]:
    size, newest = 0, os.lstat(root).st_mtime
    for folder, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            try:
                info = os.lstat(os.path.join(folder, name))
            except OSError:
                continue
            newest = max(newest, info.st_mtime)
            if stat.S_ISREG(info.st_mode):
                size += info.st_size
    return size, newest


def remove_stale_partials(
    out: Path, *, unlocked_stale_seconds: float = UNLOCKED_STALE_SECONDS, now: float | None = None
) -> list[Leftover]:
    """Remove the staging folders of dead exports in ``out``; returns what was removed.

    A folder whose lock another process holds is a running export and stays. A folder with no
    lock file stays until nothing in it changed for ``unlocked_stale_seconds``."""
    if not out.is_dir():
        return []
    now = time.time() if now is None else now
    removed: list[Leftover] = []
    for entry in sorted(out.iterdir()):
        if not entry.name.startswith(".") or PARTIAL_MARK not in entry.name:
            continue
        if entry.name.endswith(LOCK_SUFFIX) and entry.is_file():
            leftover = _clear_locked(entry)
            if leftover is not None:
                removed.append(leftover)
        elif entry.is_dir() and not entry.is_symlink() and not entry.with_name(entry.name + LOCK_SUFFIX).exists():
            size, newest = _tree_size_and_newest(entry)
            if now - newest >= unlocked_stale_seconds:
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(Leftover(str(entry), size, f"no lock and unchanged for {(now - newest) / 60:.0f} min"))
    return removed


def _clear_locked(lock_path: Path) -> Leftover | None:
    try:
        fd = os.open(lock_path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return None  # its export finished meanwhile
    except OSError:
        return None  # not ours to judge (another user's lock file)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return None  # a running export holds it
        if not _same_file(fd, lock_path):
            return None
        folder = lock_path.with_name(lock_path.name[: -len(LOCK_SUFFIX)])
        size = 0
        if folder.is_dir() and not folder.is_symlink():
            size, _ = _tree_size_and_newest(folder)
            shutil.rmtree(folder, ignore_errors=True)
        lock_path.unlink(missing_ok=True)  # last: while it exists no new export can take the name
        return Leftover(str(folder), size, "its export is no longer running (its lock was free)")
    finally:
        os.close(fd)


class PublishBusy(RuntimeError):
    """Another publish into the same folder is under way."""


class PublishLock:
    """An exclusive ``flock`` on the releases folder ``out`` for one publish, taken without waiting.

    On the folder itself (no lock file to leave behind or to race on); the kernel drops it when
    the process ends, however it ends."""

    def __init__(self, out: Path) -> None:
        fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise PublishBusy(
                f"another release is being published into {out} right now; nothing was published. "
                "Wait until it is done, then preview again"
            ) from None
        self._fd: int | None = fd

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def publishing_marker(out: Path, version: str) -> Path:
    """``<out>/.<version>.publishing``: written before a release moves into place, removed once recorded."""
    return out / f".{version}{PUBLISHING_SUFFIX}"


def write_publishing_marker(out: Path, version: str) -> Path:
    marker = publishing_marker(out, version)
    marker.write_text(f"pid {os.getpid()}\n")
    return marker


def publishing_markers(out: Path) -> list[tuple[str, Path]]:
    """(version, marker) of every publish marker in ``out``; call it holding the :class:`PublishLock`."""
    found = []
    for entry in sorted(out.glob(f".*{PUBLISHING_SUFFIX}")):
        if entry.is_file():
            found.append((entry.name[1 : -len(PUBLISHING_SUFFIX)], entry))
    return found


def clear_unrecorded(out: Path, version: str, marker: Path) -> Leftover | None:
    """Remove ``<out>/<version>`` (a release a killed publish moved into place but never recorded)
    and its marker. The folder is first renamed to a staging name, so it stops being a release at
    once even if this is killed too (the next export then clears it as a lockless partial)."""
    folder = out / version
    leftover = None
    if folder.is_dir() and not folder.is_symlink():
        size, _ = _tree_size_and_newest(folder)
        hidden = out / f".{version}{PARTIAL_MARK}unrecorded-{os.getpid()}-{time.time_ns()}"
        os.replace(folder, hidden)
        shutil.rmtree(hidden, ignore_errors=True)
        leftover = Leftover(str(folder), size, "a publish was killed after moving it into place, before recording it")
    marker.unlink(missing_ok=True)
    return leftover

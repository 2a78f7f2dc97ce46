"""The content-addressed store of original scans: hashing a file, storing it read-only under
``originals/<hash[:2]>/<sha256><ext>``, and the card that already holds those bytes.

Shared by :mod:`catalogue.ingest` (plain scans) and :mod:`catalogue.stereo_ingest` (MPO files,
left/right pairs, side-by-side files), which both store originals the same way.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from core.db import db
from core.models import Card
from pipeline.errors import ImageReadError

HASH_CHUNK = 1 << 20


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for chunk in iter(lambda: handle.read(HASH_CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def sha256_regular_file(path: Path) -> str:
    """The sha256 of ``path``, which must be a regular file.

    Opened without blocking and checked on the open descriptor: reading a named pipe would wait
    forever for a writer, and a device would never end. Raises :class:`ImageReadError` for a
    broken link or anything but a regular file, ``OSError`` when it cannot be read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        if path.is_symlink():
            raise ImageReadError("broken symbolic link") from None
        raise
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise ImageReadError(f"{_file_kind(mode)}, not an image file")
        handle = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    digest = hashlib.sha256()
    with handle:
        for chunk in iter(lambda: handle.read(HASH_CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def store_original(source: Path, content_hash: str, data_dir: Path, suffix: str | None = None) -> Path:
    """Copy ``source`` into the store atomically and make it read-only; returns the relative path.
    ``suffix``: the stored name's extension when the source's own name does not carry it (a download)."""
    relative = Path("originals") / content_hash[:2] / f"{content_hash}{(source.suffix if suffix is None else suffix).lower()}"
    target = data_dir / relative
    if target.exists():  # left by an interrupted run, or shared by name: same bytes by construction
        return relative
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".ingest-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as out, source.open("rb") as src:
            shutil.copyfileobj(src, out, HASH_CHUNK)
            out.flush()
            os.fsync(out.fileno())
        if sha256_file(Path(tmp)) != content_hash:
            raise OSError("the file changed while it was being copied")
        os.chmod(tmp, stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return relative


def database_reason(exc: SQLAlchemyError) -> str:
    """The database's own words for a failed statement, without SQL, parameters or traceback."""
    cause = getattr(exc, "orig", None) or exc
    lines = str(cause).strip().splitlines()
    return f"{type(cause).__name__}: {lines[0] if lines else 'no message'}"


def card_with_hash(content_hash: str) -> Card | None:
    try:
        return db.session.scalar(select(Card).where(Card.content_hash == content_hash))
    except SQLAlchemyError:
        db.session.rollback()
        return None


def discard_original(stored: Path) -> bool:
    try:
        stored.unlink(missing_ok=True)
    except OSError:
        return False
    return True


def duplicate_entry(path: Path, existing: Card) -> dict[str, Any]:
    return {
        "path": str(path),
        "card_id": existing.id,
        "reason": f"same content as card {existing.id} ({existing.source_name}); nothing to do",
    }

"""What every command shares: JSON output, the data dir, the schema check, progress bars."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import click
from flask import Flask, current_app

if TYPE_CHECKING:
    from sqlalchemy.engine import Engine


def emit_json(document: Any) -> None:
    """Print one JSON document on stdout (and nothing else goes to stdout with --json)."""
    click.echo(json.dumps(document, indent=2, default=str))


def data_dir() -> Path:
    return Path(current_app.config["KEYSTONE_DATA_DIR"]).resolve()


# The migrations belong to the composition root (app.schema), which the kernel must not import:
# the app factory registers how to bring the schema to head, and commands ask for it here.
SCHEMA_EXTENSION_KEY = "keystone.ensure_schema"


def register_schema(app: Flask, ensure_schema: Callable[[Engine], bool]) -> None:
    """Tell ``app`` how to bring a database to the head revision (True when migrations ran)."""
    app.extensions[SCHEMA_EXTENSION_KEY] = ensure_schema


def ensure_database() -> bool:
    """Make the data dir and bring the schema to head; True when migrations ran."""
    from core.db import db

    ensure_schema = current_app.extensions.get(SCHEMA_EXTENSION_KEY)
    if ensure_schema is None:
        raise RuntimeError("this app has no schema manager: build it with app.create_app, which registers app.schema's")
    data_dir().mkdir(parents=True, exist_ok=True)
    return bool(ensure_schema(db.engine))


class _Progress:
    """Progress reporting a stage can drive without knowing whether anyone is watching."""

    def __init__(self, progress: Any = None, task: Any = None) -> None:
        self._progress, self._task = progress, task

    def start(self, total: int) -> None:
        if self._progress is not None:
            self._progress.update(self._task, total=total)

    def advance(self, *_: Any) -> None:
        if self._progress is not None:
            self._progress.advance(self._task)


@contextmanager
def progress_bar(description: str, enabled: bool) -> Iterator[_Progress]:
    """A rich progress bar on stderr when it is a terminal; silent otherwise."""
    if not enabled or not sys.stderr.isatty():
        yield _Progress()
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
    ) as progress:
        yield _Progress(progress, progress.add_task(description, total=None))


def fail(message: str, as_json: bool) -> NoReturn:
    """End a command with exit status 1: ``{"error": message}`` on stdout under --json, else
    ``Error: message`` on stderr."""
    if as_json:
        emit_json({"error": message})
    else:
        click.echo(f"Error: {message}", err=True)
    raise SystemExit(1)


def say(message: str, as_json: bool) -> None:
    """Human messages go to stderr under --json so stdout stays one JSON document."""
    click.echo(message, err=as_json)

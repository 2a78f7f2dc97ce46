"""The commands the app package owns (``init``, ``serve``, and those defined beside the code they
drive: ``ingest``, ``run``, ``worker``, ``cards``, ``demo``, ``users``, ``check-homographies``,
``train-inpainting``), added to ``keystone`` by :func:`register_cli`."""

from __future__ import annotations

import click
from flask import current_app
from flask.cli import with_appcontext

from core.console import data_dir, emit_json, ensure_database


@click.command("init")
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document.")
@with_appcontext
def init_command(as_json: bool) -> None:
    """Create or upgrade the catalogue database (applies migrations)."""
    from app.schema import current_revision
    from core.db import db

    applied = ensure_database()
    document = {
        "database": db.engine.url.render_as_string(hide_password=True),
        "revision": current_revision(db.engine),
        "migrated": applied,
        "data_dir": str(data_dir()),
    }
    if as_json:
        emit_json(document)
    else:
        state = "Migrated" if applied else "Up to date"
        click.echo(f"{state}: {document['database']} at revision {document['revision']}; data in {document['data_dir']}")


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option("--port", default=5000, show_default=True, type=int, help="Port to listen on.")
@click.option(
    "--processes",
    type=click.IntRange(1, 64),
    default=None,
    help="Server processes [default: one per core on Linux and macOS (gunicorn), 1 elsewhere]. 1 runs waitress.",
)
@click.option(
    "--threads",
    type=click.IntRange(1, 256),
    default=None,
    help="Threads per process [default: 1 with several processes, 8 with one].",
)
@click.option(
    "--worker/--no-worker",
    "with_worker",
    default=True,
    show_default=True,
    help="Run the background worker beside the server: it recomputes pending and stale work as "
    "people decide (keystone worker). --no-worker where workers run elsewhere.",
)
@with_appcontext
def serve_command(host: str, port: int, threads: int | None, processes: int | None, with_worker: bool) -> None:
    """Serve the web app with a production WSGI server (gunicorn's pre-forked workers, or
    waitress) and, unless --no-worker, the background worker that closes the loop."""
    from app.serving import serve

    ensure_database()
    serve(
        current_app._get_current_object(),
        host=host,
        port=port,
        threads=threads,  # type: ignore[attr-defined]
        processes=processes,
        with_worker=with_worker,
    )


def register_cli(group: click.Group) -> None:
    """Add the app package's commands to ``group`` (the ``keystone`` command)."""
    from app.demo import demo_command
    from app.inpainting_cli import train_inpainting_command
    from catalogue.geometry import check_homographies_command
    from catalogue.ingest import ingest_command
    from core.people import users_group
    from runs.cli import cards_command, run_command, worker_command

    for command in (
        init_command,
        serve_command,
        ingest_command,
        run_command,
        worker_command,
        cards_command,
        demo_command,
        users_group,
        check_homographies_command,
        train_inpainting_command,
    ):
        group.add_command(command)

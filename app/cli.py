"""The ``keystone`` command: one click group on the Flask app factory, so commands get an app context.

Commands that report take ``--json`` and then print exactly one JSON document on stdout;
progress bars and messages go to stderr. Each command is defined by the module that owns it
and added here.
"""

from __future__ import annotations

import click
from flask import current_app
from flask.cli import FlaskGroup, with_appcontext

from . import create_app
from .console import data_dir, emit_json, ensure_database


def _create_app():  # type: ignore[no-untyped-def]
    return create_app()


cli = FlaskGroup(
    name="keystone",
    create_app=_create_app,
    add_default_commands=False,
    add_version_option=False,
    load_dotenv=False,
    set_debug_flag=False,
    help="Keystone: turn antique stereographs into a clean, graded, 3D dataset.\n\n"
    "Configuration: KEYSTONE_DATABASE_URL (default SQLite in the instance folder), "
    "KEYSTONE_DATA_DIR, KEYSTONE_SECRET_KEY. See the README for a tour.",
)


@cli.command("init")
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document.")
@with_appcontext
def init_command(as_json: bool) -> None:
    """Create or upgrade the catalogue database (applies migrations)."""
    from .db import db
    from .schema import current_revision

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


@cli.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to listen on.")
@click.option("--port", default=5000, show_default=True, type=int, help="Port to listen on.")
@click.option("--processes", type=click.IntRange(1, 64), default=None,
              help="Server processes [default: one per core on Linux and macOS (gunicorn), 1 elsewhere]. "
                   "1 runs waitress.")
@click.option("--threads", type=click.IntRange(1, 256), default=None,
              help="Threads per process [default: 1 with several processes, 8 with one].")
@with_appcontext
def serve_command(host: str, port: int, threads: int | None, processes: int | None) -> None:
    """Serve the web app with a production WSGI server: gunicorn's pre-forked workers, or waitress."""
    from .serving import serve

    ensure_database()
    serve(current_app._get_current_object(), host=host, port=port, threads=threads,  # type: ignore[attr-defined]
          processes=processes)


def _register() -> None:
    import exports.cli
    import review.cli
    from annotation.cli import crowd_group

    from .bench import bench_group
    from .demo import demo_command
    from .geometry import check_homographies_command
    from .ingest import ingest_command
    from .inpainting_cli import train_inpainting_command
    from .people import users_group
    from .runs import cards_command, run_command

    for command in (ingest_command, run_command, cards_command, bench_group, demo_command, users_group,
                    check_homographies_command, crowd_group, train_inpainting_command,
                    *review.cli.commands(), *exports.cli.commands()):
        cli.add_command(command)


_register()


def main() -> None:
    cli.main(prog_name="keystone")

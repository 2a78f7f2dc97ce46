"""The ``keystone`` console command: installed entry point, --help everywhere, init and users."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import click
import pytest

from app.cli import cli

pytestmark = pytest.mark.both_databases


def _all_commands(group: click.Group, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    found = []
    context = click.Context(group)
    for name in sorted(group.list_commands(context)):  # the bench group loads its commands on use
        command = group.get_command(context, name)
        found.append((*prefix, name))
        if isinstance(command, click.Group):
            found.extend(_all_commands(command, (*prefix, name)))
    return found


def test_installed_entry_point_runs(tmp_path):
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance")}
    keystone = shutil.which("keystone")
    command = [keystone] if keystone else [sys.executable, "-m", "app"]
    out = subprocess.run([*command, "--help"], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    for name in ("demo", "ingest", "run", "worker", "cards", "bench", "serve", "init", "users"):
        assert name in out.stdout


def test_every_command_has_help(runner):
    commands = _all_commands(cli)
    assert ("bench", "filter") in commands and ("users", "add") in commands
    for path in commands:
        result = runner.invoke(cli, [*path, "--help"])
        assert result.exit_code == 0, (path, result.output)
        assert "Usage:" in result.output


# The command tree before the features registered their own commands (register_cli): moving
# registration must neither lose nor add a command.
COMMAND_TREE = {
    "bench",
    "bench catalogue",
    "bench confirm-grid",
    "bench crowd",
    "bench disparity",
    "bench driver",
    "bench export",
    "bench filter",
    "bench grade",
    "bench grade-real",
    "bench iiif",
    "bench inpainting",
    "bench invariance",
    "bench pipeline",
    "bench probe",
    "bench rectify",
    "bench views",
    "bench walks",
    "bench workres",
    "cards",
    "check-homographies",
    "crowd",
    "crowd aggregate",
    "crowd create-batch",
    "crowd export",
    "crowd invite",
    "demo",
    "export",
    "grade",
    "grade fit",
    "grade show",
    "ingest",
    "init",
    "orientation",
    "orientation set",
    "orientation fit",
    "orientation show",
    "report",
    "run",
    "serve",
    "train-inpainting",
    "users",
    "users add",
    "users list",
    "verify",
    "worker",
}


def test_the_command_tree_is_the_features_registrations():
    assert {" ".join(path) for path in _all_commands(cli)} == COMMAND_TREE


def test_importing_the_command_imports_no_feature():
    code = (
        "import sys, app.cli; "
        "print(sorted(m for m in ('annotation', 'review', 'exports', 'runs.loop', 'app.bench') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_init_reports_json_and_is_idempotent(app, runner):
    result = runner.invoke(cli, ["init", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["revision"] == "0015" and document["migrated"] is False
    assert "password" not in document["database"]


def test_users_add_and_list(runner):
    result = runner.invoke(
        cli, ["users", "add", "ada", "--role", "curator", "--role", "exporter", "--password", "long enough pw"]
    )
    assert result.exit_code == 0, result.output
    again = runner.invoke(cli, ["users", "add", "ada", "--role", "curator", "--password", "long enough pw"])
    assert again.exit_code == 1 and "already exists" in again.output
    shouting = runner.invoke(cli, ["users", "add", "ADA", "--role", "curator", "--password", "long enough pw"])
    assert shouting.exit_code == 1 and "A person called 'ada' already exists" in shouting.output
    short = runner.invoke(cli, ["users", "add", "bob", "--role", "admin", "--password", "short"])
    assert short.exit_code == 2
    listing = json.loads(runner.invoke(cli, ["users", "list", "--json"]).stdout)
    assert listing == {"people": [{"id": 1, "username": "ada", "roles": ["curator", "exporter"], "active": True}]}


def test_plain_postgresql_urls_use_psycopg_3():
    from core.config import normalise_database_url

    assert normalise_database_url("postgresql://u@h/db") == "postgresql+psycopg://u@h/db"
    assert normalise_database_url("postgres://u@h/db") == "postgresql+psycopg://u@h/db"
    assert normalise_database_url("sqlite:////x.sqlite3") == "sqlite:////x.sqlite3"


def test_database_url_from_the_environment(database, tmp_path, monkeypatch):
    """KEYSTONE_DATABASE_URL picks the catalogue (plain postgresql:// URLs included)."""
    from app import create_app
    from core.db import db

    url = database.replace("postgresql+psycopg://", "postgresql://")
    monkeypatch.setenv("KEYSTONE_DATABASE_URL", url)
    monkeypatch.setenv("KEYSTONE_INSTANCE_PATH", str(tmp_path / "instance"))
    monkeypatch.setenv("KEYSTONE_DATA_DIR", str(tmp_path / "store"))
    application = create_app()
    result = application.test_cli_runner().invoke(cli, ["init", "--json"])
    with application.app_context():
        db.engine.dispose()  # close pooled connections now, not at garbage collection
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["migrated"] is True and document["revision"] == "0015"
    assert document["database"].split(":")[0] == ("postgresql+psycopg" if "postgresql" in url else "sqlite")
    assert document["data_dir"] == str(tmp_path / "store")

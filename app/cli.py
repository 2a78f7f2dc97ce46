"""The ``keystone`` command: one click group on the Flask app factory, so commands get an app context.

Commands that report take ``--json`` and then print exactly one JSON document on stdout;
progress bars and messages go to stderr. Each command is defined by the module that owns it;
each feature adds its own through a ``register_cli(group)`` function listed in
:data:`FEATURE_CLIS`, called the first time the group lists or looks up a command (click's
lazy-group pattern), so importing this module imports no feature.
"""

from __future__ import annotations

import importlib

import click
from flask import Flask
from flask.cli import FlaskGroup

from app import create_app

# "module:function" of each feature's register_cli(group), in the order they are called
FEATURE_CLIS = (
    "app.commands:register_cli",
    "app.bench:register_cli",
    "annotation.cli:register_cli",
    "review.cli:register_cli",
    "exports.cli:register_cli",
)


class KeystoneGroup(FlaskGroup):
    """The ``keystone`` group: the features register their commands on first use."""

    _features_registered = False

    def _register_features(self) -> None:
        if self._features_registered:
            return
        self._features_registered = True
        for target in FEATURE_CLIS:
            module_name, function = target.split(":")
            getattr(importlib.import_module(module_name), function)(self)

    def list_commands(self, ctx: click.Context) -> list[str]:
        self._register_features()
        return super().list_commands(ctx)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        self._register_features()
        return super().get_command(ctx, cmd_name)


def _create_app() -> Flask:
    return create_app()


cli = KeystoneGroup(
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


def main() -> None:
    cli.main(prog_name="keystone")

"""Serving the app with waitress, a pure-Python production WSGI server (no build step)."""

from __future__ import annotations

import click
from flask import Flask


def serve(app: Flask, host: str, port: int, threads: int = 8) -> None:
    from waitress import serve as waitress_serve

    click.echo(f"Keystone is serving on http://{host}:{port}/ (Ctrl+C to stop)", err=True)
    waitress_serve(app, host=host, port=port, threads=threads, ident="keystone")

"""Serving the app: gunicorn's pre-forked processes on Linux and macOS, waitress elsewhere.

Measured with `keystone bench crowd` (50 annotators, SQLite, the shared 2-core machine; see
the README): a Python process runs Python on one core at a time, and threads of one process
fight over that lock at every database call. Saturated, one waitress process served 180-340
requests/s with 8 threads but 465 with one, at 2.0 instead of 2.9-5.6 ms of CPU per request; two
gunicorn ``sync`` worker processes of one thread each served 488 with a p95 of 5 ms. A sync
worker takes a connection only when it is free, so the kernel spreads requests over idle
workers and a slow request (publishing a release from the web) holds one worker, not the
server. So the default is one single-threaded process per core; ``threads > 1`` runs
gunicorn's ``gthread`` workers instead, and one process runs waitress (pure Python, any OS).

The app is created once in the parent; database connections are dropped before the fork
(SQLite and psycopg connections must not cross one). SQLite writers of all the processes queue
at :func:`core.db.one_writer`.

Beside the server runs the background worker (:mod:`runs.worker`), a child process started
before the server listens and stopped after it stops, so people's decisions are recomputed with
no terminal: ``with_worker=False`` (``keystone serve --no-worker``) leaves it out, for an
operator who runs ``keystone worker`` elsewhere (on the cluster's machines). The worker gets the
app's database, data and releases folders in its environment, and exits by itself if the server
is killed (it watches its parent).

Every request runs in a fresh :class:`contextvars.Context` (:func:`one_context_per_request`).
``keystone serve`` is a click command, and Flask's CLI pushes an app context for it; a sync
worker forked from that process serves requests on the thread that holds it, and Flask reuses
an app context that is already current for the same app. ``flask.g`` (the logged-in person,
the CSRF token, the open database session) then outlived its request: fresh clients could not
log in, cookie-less requests were served as the last person on that worker, and a database
transaction that was never torn down held SQLite's write lock against the other workers.
"""

from __future__ import annotations

import contextvars
import os
import signal
from collections.abc import Callable, Iterable
from typing import Any

import click
from flask import Flask

Ready = Callable[[int], None]
WSGIApp = Callable[..., Any]
MAX_DEFAULT_PROCESSES = 8


def default_processes() -> int:
    """One server process per core where gunicorn runs (POSIX), capped; one elsewhere."""
    return min(MAX_DEFAULT_PROCESSES, os.cpu_count() or 1) if os.name == "posix" else 1


def default_threads(processes: int) -> int:
    """Single-threaded workers when there are several processes; 8 threads for a lone process,
    so one slow request does not hold up every other."""
    return 1 if processes > 1 else 8


def describe(processes: int, threads: int) -> str:
    if processes == 1:
        return f"waitress, 1 process x {threads} threads"
    kind = "sync" if threads == 1 else "gthread"
    return f"gunicorn {kind} workers, {processes} processes x {threads} thread{'s' if threads > 1 else ''}"


def one_context_per_request(app: WSGIApp) -> WSGIApp:
    """Wrap a WSGI app so each call starts from an empty context, whatever the serving thread holds.

    Flask pushes (and pops) its own app and request contexts inside the call, so nothing set
    by one request, or by the command that started the server, is visible to the next.
    """

    def isolated(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
        return contextvars.Context().run(app, environ, start_response)  # type: ignore[no-any-return]

    isolated.keystone_app = app  # type: ignore[attr-defined]  # the app's settings stay reachable
    return isolated


def worker_environment(app: WSGIApp) -> dict[str, str]:
    """This process's environment, with the app's database, data, releases and instance folders
    spelled out, so a ``keystone worker`` child works on what the server serves (``keystone
    demo`` configures its app in code, not in the environment)."""
    env = dict(os.environ)
    target = getattr(app, "keystone_app", app)
    config = getattr(target, "config", None) or {}
    for name, key in (
        ("KEYSTONE_DATABASE_URL", "SQLALCHEMY_DATABASE_URI"),
        ("KEYSTONE_DATA_DIR", "KEYSTONE_DATA_DIR"),
        ("KEYSTONE_RELEASES_DIR", "KEYSTONE_RELEASES_DIR"),
        ("KEYSTONE_INPAINT_CHECKPOINT", "KEYSTONE_INPAINT_CHECKPOINT"),
    ):
        if config.get(key):
            env[name] = str(config[key])
    instance = getattr(target, "instance_path", None)
    if instance:
        env["KEYSTONE_INSTANCE_PATH"] = str(instance)
    return env


def serve(
    app: WSGIApp,
    host: str,
    port: int,
    threads: int | None = None,
    processes: int | None = None,
    on_ready: Ready | None = None,
    with_worker: bool = True,
) -> None:
    """Serve until interrupted; ``on_ready(port)`` is called once listening (port 0 picks a free one).

    ``processes`` and ``threads`` default to :func:`default_processes` and :func:`default_threads`.
    ``with_worker``: run the background worker beside the server (see the module docstring).
    """
    processes = default_processes() if processes is None else processes
    threads = default_threads(processes) if threads is None else threads
    if processes < 1 or threads < 1:
        raise click.UsageError(f"Expected at least one process and one thread, got {processes} and {threads}")
    wsgi = one_context_per_request(app)
    on_ready = on_ready or (
        lambda bound: click.echo(
            f"Keystone is serving on http://{host}:{bound}/ ({describe(processes, threads)}; Ctrl+C to stop)", err=True
        )
    )
    worker = None
    if with_worker:
        from runs.worker import start_server_worker

        worker = start_server_worker(worker_environment(app))
    previous = signal.getsignal(signal.SIGTERM)
    if processes == 1:
        # waitress leaves SIGTERM to Python's default, which ends the process at once: unwind
        # instead, so the worker is stopped below (gunicorn handles SIGTERM itself, then exits).
        signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        if processes == 1:
            _serve_waitress(wsgi, host, port, threads, on_ready)
        else:
            _serve_gunicorn(app, wsgi, host, port, threads, processes, on_ready)
    finally:
        signal.signal(signal.SIGTERM, previous)
        if worker is not None:
            from runs.worker import stop_server_worker

            stop_server_worker(worker)


def _exit_on_sigterm(signum: int, frame: Any) -> None:
    raise SystemExit(0)


def max_body_bytes(app: WSGIApp) -> int | None:
    """The largest request body the app accepts (Flask's ``MAX_CONTENT_LENGTH``), if it says."""
    target = getattr(app, "keystone_app", app)
    config = getattr(target, "config", None)
    value = config.get("MAX_CONTENT_LENGTH") if config is not None else None
    return int(value) if value else None


def _serve_waitress(app: WSGIApp, host: str, port: int, threads: int, on_ready: Ready) -> None:
    import logging

    from waitress import create_server

    # waitress warns "Task queue depth is N" whenever requests queue for a thread; that is
    # what a busy server does, not a fault.
    logging.getLogger("waitress.queue").setLevel(logging.ERROR)
    # waitress buffers a whole request body (1 GB by default) before the app can answer 413;
    # cap it at the app's own limit so an oversized upload is cut off at the door.
    limit = max_body_bytes(app)
    options = {"max_request_body_size": limit} if limit else {}
    server = create_server(app, host=host, port=port, threads=threads, ident="keystone", **options)
    on_ready(int(server.effective_port))  # type: ignore[union-attr]
    server.run()


def _serve_gunicorn(app: WSGIApp, wsgi: WSGIApp, host: str, port: int, threads: int, processes: int, on_ready: Ready) -> None:
    if os.name != "posix":
        raise click.UsageError("--processes above 1 needs gunicorn, which runs on Linux and macOS only")
    from gunicorn.app.base import BaseApplication

    from core.db import db

    if isinstance(app, Flask):
        with app.app_context():
            db.engine.dispose()  # no pooled connection may be inherited by the workers

    def when_ready(server: Any) -> None:
        on_ready(int(server.LISTENERS[0].sock.getsockname()[1]))

    class _Application(BaseApplication):  # type: ignore[misc]
        def load_config(self) -> None:
            settings = {
                "bind": f"[{host}]:{port}" if ":" in host else f"{host}:{port}",
                "workers": processes,
                "worker_class": "sync" if threads == 1 else "gthread",
                "threads": threads,
                "preload_app": True,
                "when_ready": when_ready,
                # A worker busy longer than this is killed and replaced; publishing a release
                # from the web takes minutes at 10,000 cards.
                "timeout": 600,
                "graceful_timeout": 30,
                "keepalive": 5,
                "accesslog": None,
                "errorlog": "-",
                "loglevel": "warning",
                "proc_name": "keystone",
            }
            for key, value in settings.items():
                self.cfg.set(key, value)

        def load(self) -> WSGIApp:
            return wsgi

    _Application().run()

"""``keystone serve``: waitress in one process, gunicorn's pre-forked workers with --processes N."""

from __future__ import annotations

import http.client
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

SERVING = re.compile(r"serving on http://127\.0\.0\.1:(\d+)/")


def _group_pids(leader: int) -> set[int]:
    """Every live process whose process group is ``leader`` (the server and any workers it forked)."""
    pids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == leader and fields[0] != "Z":
            pids.add(int(stat.parent.name))
    return pids


def _start_server(env: dict[str, str], *options: str) -> tuple[subprocess.Popen[str], int, str]:
    """`keystone serve --port 0 OPTIONS`: the process, the port it listens on and its "serving on" line."""
    server = subprocess.Popen(
        [sys.executable, "-m", "app", "serve", "--port", "0", *options],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    assert server.stderr is not None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = server.stderr.readline()
        assert line, f"the server stopped before listening (exit {server.poll()})"
        if match := SERVING.search(line):
            return server, int(match.group(1)), line
    raise AssertionError("no 'serving on' line within 60 s")


def _stop_server(server: subprocess.Popen[str]) -> str:
    server.send_signal(signal.SIGTERM)
    try:
        _, rest = server.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(server.pid, signal.SIGKILL)
        server.communicate()
        raise
    return rest


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="counts the server's processes in Linux /proc")
@pytest.mark.parametrize(
    "options", [["--processes", "1"], ["--processes", "2", "--threads", "2"], []], ids=["waitress", "gunicorn-gthread", "default"]
)
def test_serve_answers_from_the_requested_processes_and_stops_cleanly(tmp_path, options):
    from app.serving import default_processes, default_threads, describe

    processes = int(options[1]) if options else default_processes()
    threads = int(options[3]) if len(options) > 2 else default_threads(processes)
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance")}
    server, port, line = _start_server(env, *options)
    try:
        assert describe(processes, threads) in line
        statuses = []
        for _ in range(12):  # separate connections, so the kernel spreads them over the workers
            connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            connection.request("GET", "/auth/login")
            response = connection.getresponse()
            statuses.append(response.status)
            assert b"<form" in response.read()
            connection.close()
        assert statuses == [200] * 12
        # The parent, plus one worker per process when gunicorn forks them (it starts listening
        # before the last worker is forked), plus the background pipeline worker.
        expected = (1 if processes == 1 else processes + 1) + 1
        deadline = time.monotonic() + 20
        while len(_group_pids(server.pid)) < expected and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(_group_pids(server.pid)) == expected
        # the background worker beside them has registered itself
        with sqlite3.connect(tmp_path / "instance" / "keystone.sqlite3") as database:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                rows = database.execute("SELECT pid, state FROM pipeline_workers").fetchall()
                if rows:
                    break
                time.sleep(0.1)
        assert len(rows) == 1 and rows[0][0] in _group_pids(server.pid)
    finally:
        rest = _stop_server(server)
    assert "Traceback" not in rest, rest
    time.sleep(0.2)
    assert _group_pids(server.pid) == set(), "a worker outlived the server"


# -- One identity per request under the real default server -----------------------------------

CSRF_FIELD = re.compile(r'name="csrf_token"[^>]*value="([^"]+)"')


def _socket_inodes(server_port: int, client_port: int) -> set[str]:
    """Inodes of the server-side sockets of the connection from ``client_port`` (IPv4 loopback)."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        local_port, remote_port = int(fields[1].split(":")[1], 16), int(fields[2].split(":")[1], 16)
        if local_port == server_port and remote_port == client_port:
            inodes.add(fields[9])
    return inodes


def _serving_worker(workers: set[int], server_port: int, client_port: int) -> int | None:
    """The worker process whose file descriptors hold the accepted end of this connection."""
    inodes = _socket_inodes(server_port, client_port)
    for pid in workers:
        try:
            links = {os.readlink(fd) for fd in Path(f"/proc/{pid}/fd").iterdir()}
        except OSError:
            continue
        if any(f"socket:[{inode}]" in links for inode in inodes):
            return pid
    return None


def _hold(port: int, workers: set[int]) -> tuple[http.client.HTTPConnection, int | None]:
    """A connection that sends nothing: the sync worker that accepts it blocks reading it, and is
    busy until the connection closes. Returns the connection and that worker."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.connect()
    client_port = connection.sock.getsockname()[1]
    worker = None
    deadline = time.monotonic() + 10
    while worker is None and time.monotonic() < deadline:
        worker = _serving_worker(workers, port, client_port)
        if worker is None:
            time.sleep(0.01)
    return connection, worker


def _fetch(
    port: int, path: str, workers: set[int], cookie: str | None = None, method: str = "GET", body: str | None = None
) -> tuple[int, dict[str, str], str, int | None]:
    """One request on its own connection: status, headers, body and the worker that served it.

    The connection is opened first and the worker found while it waits for the request line
    (a sync worker accepts a connection, then blocks reading it).
    """
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.connect()
    client_port = connection.sock.getsockname()[1]
    worker = None
    deadline = time.monotonic() + 10
    while worker is None and time.monotonic() < deadline:
        worker = _serving_worker(workers, port, client_port)
        if worker is None:
            time.sleep(0.01)
    headers = {"Cookie": cookie} if cookie else {}
    if body is not None:
        headers["Content-Type"] = "application/x-www-form-urlencoded"
    connection.request(method, path, body=body, headers=headers)
    response = connection.getresponse()
    text = response.read().decode()
    connection.close()
    return response.status, {k.lower(): v for k, v in response.getheaders()}, text, worker


def _log_in(port: int, workers: set[int], username: str, password: str) -> tuple[int, str | None, int | None]:
    """A fresh client's login through the form: the POST's status and the session cookie it got."""
    from urllib.parse import urlencode

    status, headers, page, _ = _fetch(port, "/auth/login", workers)
    assert status == 200
    token = CSRF_FIELD.search(page)
    assert token, "the login form carries no CSRF token"
    cookie = headers.get("set-cookie", "").split(";")[0]
    body = urlencode({"csrf_token": token.group(1), "username": username, "password": password, "next": ""})
    status, headers, page, worker = _fetch(port, "/auth/login", workers, cookie=cookie, method="POST", body=body)
    session = headers.get("set-cookie", "").split(";")[0] or None
    return status, session, worker


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="finds the serving worker in Linux /proc")
def test_default_server_gives_each_request_its_own_identity(tmp_path):
    """Fresh clients log in, and after an admin has, cookie-less requests go to the login page on
    every worker (the CLI's app context once leaked flask.g between requests of a sync worker)."""
    from app.serving import default_processes

    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance")}
    password = "correct horse battery"
    subprocess.run(
        [sys.executable, "-m", "app", "users", "add", "boss", "--role", "admin", "--password", password],
        env=env,
        check=True,
        capture_output=True,
    )
    # Only the web workers here: the background pipeline worker is not one of them.
    options = ["--no-worker"] + ([] if default_processes() >= 2 else ["--processes", "2"])
    server, port, _ = _start_server(env, *options)
    try:
        expected = max(2, default_processes())
        deadline = time.monotonic() + 20
        while len(_group_pids(server.pid) - {server.pid}) < expected and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = _group_pids(server.pid) - {server.pid}
        assert len(workers) == expected

        logins = [_log_in(port, workers, "boss", password) for _ in range(6)]
        assert [status for status, _, _ in logins] == [302] * 6, "a fresh client could not log in"
        assert all(session for _, session, _ in logins)

        admin_cookie = logins[-1][1]
        status, _, page, _ = _fetch(port, "/auth/people", workers, cookie=admin_cookie)
        assert status == 200 and "boss" in page
        seen: dict[int, list[int]] = {}
        for _ in range(80):
            status, headers, _, worker = _fetch(port, "/auth/people", workers)
            assert worker is not None, "no worker accepted the connection"
            seen.setdefault(worker, []).append(status)
            assert status == 302 and "/auth/login" in headers["location"], (worker, status)
            if set(seen) == workers and min(len(v) for v in seen.values()) >= 3:
                break
            # An admin request between the anonymous ones, on whichever worker takes it.
            _fetch(port, "/auth/people", workers, cookie=admin_cookie)
        # On a loaded machine one worker can take every connection. Make the others answer: hold
        # every worker busy with an idle connection, free only one that has not answered yet, and
        # send the request it alone can take.
        holds = [_hold(port, workers) for _ in workers]
        try:
            for missing in workers - set(seen):
                index = next(i for i, (_, held_by) in enumerate(holds) if held_by == missing)
                holds[index][0].close()
                status, headers, _, worker = _fetch(port, "/auth/people", workers)
                seen.setdefault(worker, []).append(status)
                assert status == 302 and "/auth/login" in headers["location"], (worker, status)
                holds[index] = _hold(port, workers)
        finally:
            for connection, _ in holds:
                connection.close()
        assert set(seen) == workers, f"only workers {sorted(seen)} of {sorted(workers)} answered"
    finally:
        rest = _stop_server(server)
    assert "Traceback" not in rest, rest


@pytest.mark.parametrize("options", [["--processes", "1"], ["--processes", "2"]], ids=["waitress", "gunicorn"])
def test_an_oversized_body_is_refused_at_the_door(tmp_path, options):
    """A body over the app's limit is a 413 under every server (waitress would otherwise buffer
    up to 1 GB of it before the app could answer)."""
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance"), "KEYSTONE_MAX_REQUEST_BYTES": "65536"}
    server, port, _ = _start_server(env, *options)
    try:
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        body = b"x" * (2 * 1024 * 1024)
        try:
            connection.request("POST", "/auth/login", body=body, headers={"Content-Type": "application/x-www-form-urlencoded"})
            response = connection.getresponse()
            status, text = response.status, response.read().decode(errors="replace")
        except (BrokenPipeError, ConnectionResetError):
            status, text = None, ""  # the server hung up mid-upload after refusing it: also a refusal
        finally:
            connection.close()
        assert status in (413, None)
        if options == ["--processes", "1"] and status == 413:
            assert "exceeds max_body of 65536" in text  # waitress itself stopped reading
        # and the server still answers the next request normally
        check = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        check.request("GET", "/auth/login")
        assert check.getresponse().status == 200
        check.close()
    finally:
        rest = _stop_server(server)
    assert "Traceback" not in rest, rest

"""``keystone serve``: waitress in one process, gunicorn's pre-forked workers with --processes N."""

from __future__ import annotations

import http.client
import os
import re
import signal
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


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="counts the server's processes in Linux /proc")
@pytest.mark.parametrize("options", [["--processes", "1"], ["--processes", "2", "--threads", "2"], []],
                         ids=["waitress", "gunicorn-gthread", "default"])
def test_serve_answers_from_the_requested_processes_and_stops_cleanly(tmp_path, options):
    from app.serving import default_processes, default_threads, describe

    processes = int(options[1]) if options else default_processes()
    threads = int(options[3]) if len(options) > 2 else default_threads(processes)
    env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance")}
    server = subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", "0", *options], env=env,
                              stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert server.stderr is not None
        port = None
        deadline = time.monotonic() + 60
        while port is None and time.monotonic() < deadline:
            line = server.stderr.readline()
            assert line, f"the server stopped before listening (exit {server.poll()})"
            if match := SERVING.search(line):
                port = int(match.group(1))
        assert port, "no 'serving on' line within 60 s"
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
        # before the last worker is forked).
        expected = 1 if processes == 1 else processes + 1
        deadline = time.monotonic() + 20
        while len(_group_pids(server.pid)) < expected and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(_group_pids(server.pid)) == expected
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            _, rest = server.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.communicate()
            raise
    assert "Traceback" not in rest, rest
    time.sleep(0.2)
    assert _group_pids(server.pid) == set(), "a worker outlived the server"

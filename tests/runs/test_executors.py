"""The executors a run computes on, and the in-flight window each gives: two cards per worker
thread (a dask cluster's, read from its scheduler, in tests/runs/test_dask_cluster.py)."""

from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor

import pytest

from pipeline.runner import RestartingProcessPool
from runs.executors import dispatch_window, make_executor, worker_threads


def test_inline_is_one_thread():
    assert worker_threads(None) == 1
    assert dispatch_window(None) == 2


def test_a_pool_gives_its_worker_count():
    with RestartingProcessPool(3) as pool:
        assert worker_threads(pool) == 3 and dispatch_window(pool) == 6
    with ThreadPoolExecutor(5) as threads:
        assert worker_threads(threads) == 5 and dispatch_window(threads) == 10


def test_the_local_executor_of_a_run_gives_its_workers():
    with make_executor("local", 4, None) as pool:
        assert dispatch_window(pool) == 8


class _Opaque(Executor):
    pass


def test_an_executor_that_does_not_say_its_size_is_refused():
    with pytest.raises(TypeError, match="give run_tasks a window"):
        worker_threads(_Opaque())

"""The executors a run computes on: inline, a restarting process pool, or a dask cluster."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Executor
from contextlib import contextmanager

from pipeline.runner import RestartingProcessPool, init_worker


@contextmanager
def make_executor(kind: str, workers: int, scheduler: str | None) -> Iterator[Executor | None]:
    if kind == "dask":
        try:
            from distributed import Client
        except ImportError as exc:
            raise RuntimeError("the dask executor needs dask.distributed: pip install 'dask[distributed]'") from exc
        from pipeline.dask_worker import OneThreadWorkerPlugin

        client = Client(scheduler) if scheduler else Client(n_workers=workers, threads_per_worker=1, processes=True)
        try:
            # Every worker, those that join later too, gets what a local pool worker gets.
            client.register_plugin(OneThreadWorkerPlugin())
            yield client.get_executor()
        finally:
            client.close()
    elif kind == "local":
        if workers <= 1:
            # Inline: this process is the one worker, and gets a pool worker's set-up (one
            # OpenCV and BLAS thread, freed memory kept): `--workers 1` uses one core, and the
            # kernel does not zero the same pages for every card (measured on 42 cards: system
            # CPU 5.05 -> ~1.1 s, docs/SCALE.md).
            init_worker()
            yield None
            return
        with RestartingProcessPool(workers) as pool:
            yield pool
    else:
        raise ValueError(f"unknown executor {kind!r}; expected local or dask")

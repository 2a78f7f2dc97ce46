"""What a dask worker needs before it takes cards: the set-up a local pool worker gets.

Imported only by the dask executor (``keystone run --executor dask``), which needs
``dask[distributed]`` (the ``cluster`` extra) on the driver and on every worker.
"""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from .runner import init_worker

__all__ = ["OneThreadWorkerPlugin"]


class OneThreadWorkerPlugin(WorkerPlugin):
    """Runs :func:`pipeline.runner.init_worker` in every worker process of the cluster, those that
    join after the run started included: the driver parallelises by card, so OpenCV and BLAS
    threads inside a worker only add their overhead (each worker process is meant to run with
    ``--nthreads 1``, one per core; docs/CLUSTER.md)."""

    name = "keystone-one-thread"

    def setup(self, worker: Any) -> None:
        init_worker()

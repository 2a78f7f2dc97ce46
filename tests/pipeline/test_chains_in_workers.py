"""A chained card in a real worker imports no web stack: a process pool worker and a dask worker
run filter -> orientation -> a probe stage (tests/pipeline/worker_probe.py) through
:func:`pipeline.chains.run_chain`, and the probe reports what its process has imported.

The pool (:class:`pipeline.runner.RestartingProcessPool`) starts workers from a ``forkserver``
and a dask nanny spawns them, so a worker does not inherit this process's modules; this test
imports Flask and SQLAlchemy here first, so a pool that forked from it would fail.
"""

from __future__ import annotations

import functools
import importlib
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.chains import ChainOutcome, ChainTask, run_chain
from pipeline.io import write_png
from pipeline.records import CardTask, card_work_dir, param_hash
from pipeline.runner import RestartingProcessPool
from pipeline.stages.spec import declared_stages

sys.path.insert(0, str(Path(__file__).parent))  # worker_probe, for this process and (via sys.path) its workers
from worker_probe import PROBE, ProbeParams, forbidden_loaded  # noqa: E402

CONTENT_HASH = "ab" * 32


def _chain(tmp_path: Path, card: np.ndarray) -> tuple[Callable[[ChainTask], ChainOutcome], ChainTask]:
    """A freshly ingested card's chain: the filter leads, the orientation step and the probe follow."""
    image = tmp_path / "card.png"
    write_png(image, card)
    data_dir = tmp_path / "data"
    stages = declared_stages()
    lead, orientation = (stages[name].spec(stages[name].params()) for name in ("filter", "orientation"))
    task = CardTask(
        card_id=1,
        content_hash=CONTENT_HASH,
        image_path=str(image),
        work_dir=str(card_work_dir(data_dir, CONTENT_HASH, "filter", param_hash(lead.params))),
        data_dir=str(data_dir),
    )
    chain = ChainTask(lead=task, state="ingested", results=(), claimed=("orientation", "probe"))
    steps = (orientation, PROBE.spec(ProbeParams()))
    return functools.partial(run_chain, lead=lead.task, steps=steps), chain


def _probe_report(outcome: ChainOutcome) -> dict[str, Any]:
    made = [(record.stage, record.status) for record, _ in outcome.records]
    assert made == [("filter", "done"), ("orientation", "done"), ("probe", "done")], [r.reason for r, _ in outcome.records]
    probe = outcome.records[-1][0]
    # The probe's inputs were built in the worker from the chain's fresh records.
    assert probe.metrics["inputs"]["boxes"]["left_box"] and "decided_by" in probe.metrics["inputs"]["orientation"]
    return probe.metrics


def test_a_process_pool_worker_runs_a_chain_without_the_web_stack(tmp_path: Path, card_image: Any) -> None:
    for name in ("flask", "sqlalchemy", "click"):  # loaded here, so a worker that inherited them would show them
        importlib.import_module(name)
    function, chain = _chain(tmp_path, card_image())
    pool = RestartingProcessPool(1)
    try:
        outcome = pool.submit(function, chain).result(timeout=300)
    finally:
        pool.shutdown()
    report = _probe_report(outcome)
    assert report["pid"] != os.getpid()
    assert report["forbidden_loaded"] == []


def test_a_dask_worker_runs_a_chain_without_the_web_stack(tmp_path: Path, card_image: Any) -> None:
    distributed = pytest.importorskip("distributed")
    from pipeline.dask_worker import OneThreadWorkerPlugin

    function, chain = _chain(tmp_path, card_image())
    with (
        distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster,
        distributed.Client(cluster) as client,
    ):
        client.register_plugin(OneThreadWorkerPlugin())  # as runs.executors.make_executor does
        (before,) = client.run(forbidden_loaded).values()
        outcome = client.get_executor().submit(function, chain).result(timeout=300)
        (after,) = client.run(forbidden_loaded).values()
    report = _probe_report(outcome)
    assert report["pid"] != os.getpid()
    # distributed imports click itself (its command line); the chain adds nothing to that.
    assert set(before) <= {"click"}, before
    assert report["forbidden_loaded"] == after == before, (before, report["forbidden_loaded"], after)

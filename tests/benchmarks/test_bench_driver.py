"""``keystone bench driver`` on a tiny catalogue: the report's shape and sane values (the 25,000
and 250,000-card runs are ``keystone bench driver``, outside the test run)."""

from __future__ import annotations

import json

from sqlalchemy import func, select

from app.cli import cli
from core.db import db
from core.models import Card


def test_bench_driver_reports_each_rate_the_window_and_memory_on_its_own_catalogue(app, runner):
    result = runner.invoke(cli, ["bench", "driver", "--cards", "300", "--cards", "120", "--workers", "2", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["executor"] == "local" and document["workers"] == 2 and document["database"] == "sqlite"
    assert [run["cards"] for run in document["runs"]] == [300, 120]
    for run in document["runs"]:
        assert run["processed"] == run["cards"] and run["failed"] == 0
        for rate in ("planned_per_second", "dispatched_per_second", "written_per_second"):
            assert run[rate] > 0, rate
        assert run["worker_threads"] == 2 and run["window"] == 4
        assert 1 <= run["most_in_flight"] <= run["window"]
        assert 0 < run["driver_cpu_ms_per_card"] < 1000
        assert 0 < run["rss_before_mb"] <= run["peak_rss_mb"]
        assert run["memory_measure"].startswith(("VmHWM", "ru_maxrss"))
    with app.app_context():  # the configured database is not the bench's
        assert db.session.scalar(select(func.count()).select_from(Card)) == 0


def test_the_no_op_task_returns_a_passing_filter_record_without_an_image():
    from benchmarks.driver import noop_task
    from pipeline.records import CardTask

    record = noop_task(
        CardTask(card_id=7, content_hash="0" * 64, image_path="/nonexistent", work_dir="", data_dir=""), param_hash="p"
    )
    assert (record.card_id, record.stage, record.param_hash, record.status, record.outcome) == (7, "filter", "p", "done", "pass")

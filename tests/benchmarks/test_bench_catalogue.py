"""``keystone bench catalogue`` on a small catalogue, on SQLite and PostgreSQL (the 25,000 and
250,000-card runs are ``keystone bench catalogue --cards N``, outside the default run)."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import func, select

from app.cli import cli
from core.db import db
from core.models import Card, Collection, Person, StageResult

pytestmark = pytest.mark.both_databases

OPERATIONS = (
    "plan_filter",
    "plan_rectify",
    "plan_disparity",
    "plan_grade",
    "cards_json",
    "catalogue_page",
    "catalogue_deep_page",
    "review_queue",
    "report",
    "export_plan",
)


def test_bench_catalogue_times_every_operation_and_leaves_the_database_as_it_found_it(app, runner):
    result = runner.invoke(cli, ["bench", "catalogue", "--cards", "300", "--repeats", "1", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    assert document["cards"] == 300
    assert document["build_seconds"] > 0
    for name in OPERATIONS:
        assert document[f"{name}_seconds"] > 0, name
    assert 0 < document["cards_json_peak_rss_mb"] <= document["peak_rss_mb"]
    with app.app_context():
        assert document["database"] == db.engine.dialect.name
        assert db.session.scalar(select(func.count()).select_from(Card)) == 0
        assert db.session.scalar(select(func.count()).select_from(StageResult)) == 0
        assert db.session.scalar(select(func.count()).select_from(Collection)) == 0
        assert db.session.scalar(select(func.count()).select_from(Person)) == 0


def test_bench_catalogue_refuses_a_database_with_cards(app, runner, make_card):
    make_card()
    result = runner.invoke(cli, ["bench", "catalogue", "--cards", "10", "--json"])
    assert result.exit_code == 1
    assert "already holds 1 cards" in result.output
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Card)) == 1

"""``keystone bench catalogue``: the catalogue's everyday operations at collection size.

Builds a synthetic catalogue of N cards with stage results (filter for every card; rectify,
disparity and grade for the cards that passed; a curator review per graded card) in the
configured database by bulk insert, then times what operators, curators and exporters do
with it, none of which computes anything for a card:

- ``plan_<stage>_seconds``: planning each stage of ``keystone run`` (which cards need it);
- ``cards_json_seconds``: ``keystone cards --json --collection C`` (a quarter of the cards),
  in a child process writing to /dev/null; its own peak memory is ``cards_json_peak_rss_mb``;
- ``catalogue_page_seconds`` / ``catalogue_deep_page_seconds``: ``/cards``, first and last page;
- ``review_queue_seconds``: ``/review/``, the curators' queue;
- ``report_seconds``: ``keystone report``'s figures;
- ``export_plan_seconds``: planning a release (``keystone export --dry-run``).

Each time is the median of ``repeats`` runs. ``peak_rss_mb`` is the largest peak resident
memory of this process and the child. The database must hold no cards: the bench owns what it
builds and deletes it afterwards (``keep=True`` leaves it).
"""

from __future__ import annotations

import hashlib
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import click
from flask.cli import with_appcontext

from benchmarks.export import peak_rss_mb

COLLECTIONS = 4
CHUNK = 5000
PASS_EVERY, REVIEW_EVERY = 10, 10  # of ten cards: 8 pass, 1 goes to people, 1 is culled
GRADES = ("few", "some", "some", "failure")  # near the paper's 23 / 49 / 28 %
DECISIONS = ("pending", "pending", "accepted", "pending", "rejected")
BENCH_PARAM_HASH = "benchcatalogue00"
RUN_STAGES = ("filter", "rectify", "disparity", "grade")


def _state(number: int) -> str:
    position = number % PASS_EVERY
    return "culled" if position == 0 else "review" if position == 1 else "pass"


def _grade_metrics(number: int) -> dict[str, Any]:
    """Measurements the size of a real grade record (14 values, reasons, levels)."""
    values = {f"measurement_{index:02d}": round(((number * 7919 + index * 104729) % 1000) / 1000, 3) for index in range(14)}
    return {
        "measurements": values,
        "uncertainty": values["measurement_00"],
        "reasons": [f"some: measurement {index} near its threshold" for index in range(2)],
    }


def build_catalogue(count: int, echo: Callable[[str], None]) -> float:
    """Bulk-insert ``count`` cards with stage results and reviews; seconds taken."""
    from sqlalchemy import insert, select

    from core.db import db
    from core.models import Card, Collection, StageResult
    from review.models import CardReview

    clock = time.perf_counter()
    collection_ids = []
    for index in range(COLLECTIONS):
        collection = Collection(name=f"bench-catalogue-{index}")
        db.session.add(collection)
        db.session.flush()
        collection_ids.append(collection.id)
    db.session.commit()
    for start in range(0, count, CHUNK):
        numbers = range(start, min(count, start + CHUNK))
        cards = [
            {
                "collection_id": collection_ids[number % COLLECTIONS],
                "content_hash": hashlib.sha256(f"bench-catalogue-{number}".encode()).hexdigest(),
                "stored_path": f"originals/bench/{number:07d}.jpg",
                "source_name": f"bench-{number:07d}.jpg",
                "source_path": "(synthetic)",
                "accession": f"2026.0002.{number:06d}",
                "width": 1400,
                "height": 700,
                "image_format": "JPEG",
                "byte_size": 350_000,
                "state": _state(number),
                "source_metadata": {"title": f"Synthetic card {number}", "date": "1898", "creator": "Keystone View Co."},
            }
            for number in numbers
        ]
        db.session.execute(insert(Card), cards)
        ids = dict(
            db.session.execute(
                select(Card.content_hash, Card.id).where(Card.content_hash.in_([c["content_hash"] for c in cards]))
            ).all()
        )
        results, reviews = [], []
        for number, card in zip(numbers, cards):
            card_id = ids[card["content_hash"]]
            state = card["state"]
            fraction = 0.004 if state == "culled" else 0.01 if state == "review" else 0.25
            results.append(
                {
                    "card_id": card_id,
                    "stage": "filter",
                    "param_hash": BENCH_PARAM_HASH,
                    "status": "done",
                    "outcome": state,
                    "metrics": {"good_match_fraction": fraction, "matches": 400, "denominator": "keypoints in the smaller half"},
                    "artifacts": {},
                    "seconds": 0.2,
                    "code_version": "bench",
                }
            )
            if state != "pass":
                continue
            # Decided by the orientation step: a card whose orientation is undecided is never
            # accepted or released, so without it the export plan would time an empty release.
            results.append(
                {
                    "card_id": card_id,
                    "stage": "orientation",
                    "param_hash": BENCH_PARAM_HASH,
                    "status": "done",
                    "outcome": "auto",
                    "metrics": {
                        "confidence": 0.97,
                        "flags": {flag: {"value": False, "decided": True} for flag in ("upside_down", "inverted", "swapped")},
                    },
                    "artifacts": {},
                    "seconds": 0.3,
                    "code_version": "bench",
                }
            )
            results.append(
                {
                    "card_id": card_id,
                    "stage": "rectify",
                    "param_hash": BENCH_PARAM_HASH,
                    "status": "done",
                    "metrics": {
                        "dy_p95": 0.8,
                        "left_box": [20, 30, 690, 670],
                        "right_box": [710, 30, 1380, 670],
                    },
                    "artifacts": {},
                    "seconds": 0.4,
                    "code_version": "bench",
                }
            )
            results.append(
                {
                    "card_id": card_id,
                    "stage": "disparity",
                    "param_hash": BENCH_PARAM_HASH,
                    "status": "done",
                    "metrics": {"coverage": 0.97, "lr_consistency": 0.88},
                    "artifacts": {},
                    "seconds": 0.3,
                    "code_version": "bench",
                }
            )
            grade = GRADES[number % len(GRADES)]
            results.append(
                {
                    "card_id": card_id,
                    "stage": "grade",
                    "param_hash": BENCH_PARAM_HASH,
                    "status": "done",
                    "outcome": grade,
                    "metrics": _grade_metrics(number),
                    "artifacts": {},
                    "seconds": 0.05,
                    "code_version": "bench",
                }
            )
            decision = DECISIONS[number % len(DECISIONS)]
            reviews.append(
                {
                    "card_id": card_id,
                    "auto_grade": grade,
                    "auto_param_hash": BENCH_PARAM_HASH,
                    "uncertainty": _grade_metrics(number)["uncertainty"],
                    "note": "",
                    "grade": grade if decision == "accepted" else None,
                    "decision": decision,
                }
            )
        db.session.execute(insert(StageResult), results)
        if reviews:
            db.session.execute(insert(CardReview), reviews)
        db.session.commit()
        echo(f"  {min(count, start + CHUNK)} / {count} cards")
    return time.perf_counter() - clock


def drop_catalogue() -> None:
    """Delete what :func:`build_catalogue` made (its collections, their cards and dependants)."""
    from sqlalchemy import delete, select

    from core.db import db
    from core.models import Card, Collection, StageResult
    from review.models import CardReview

    bench = select(Collection.id).where(Collection.name.like("bench-catalogue-%")).scalar_subquery()
    cards = select(Card.id).where(Card.collection_id.in_(bench)).scalar_subquery()
    db.session.execute(delete(CardReview).where(CardReview.card_id.in_(cards)))
    db.session.execute(delete(StageResult).where(StageResult.card_id.in_(cards)))
    db.session.execute(delete(Card).where(Card.collection_id.in_(bench)))
    db.session.execute(delete(Collection).where(Collection.name.like("bench-catalogue-%")))
    db.session.commit()


def _median_seconds(operation: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        clock = time.perf_counter()
        operation()
        times.append(time.perf_counter() - clock)
    return round(statistics.median(times), 4)


# The child that lists cards: the real command, its output thrown away, its own peak memory last.
_CARDS_CHILD = """
import sys
from app.cli import cli
try:
    cli.main(sys.argv[1:], prog_name="keystone", standalone_mode=False)
finally:
    hwm = next(l for l in open("/proc/self/status") if l.startswith("VmHWM:"))
    sys.stderr.write("\\nPEAK_KB " + hwm.split()[1] + "\\n")
"""


def _cards_json_child(collection: str, env: dict[str, str]) -> tuple[float, float]:
    """Seconds and peak MB of ``keystone cards --json --collection C`` in its own process."""
    clock = time.perf_counter()
    with open(os.devnull, "w") as sink:
        done = subprocess.run(
            [sys.executable, "-c", _CARDS_CHILD, "cards", "--json", "--collection", collection],
            stdout=sink,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            check=False,
        )
    seconds = time.perf_counter() - clock
    if done.returncode != 0:
        raise click.ClickException(f"keystone cards failed: {done.stderr.strip()[-2000:]}")
    peak_kb = next(line.split()[1] for line in done.stderr.splitlines() if line.startswith("PEAK_KB"))
    return seconds, int(peak_kb) / 1024


def time_operations(app: Any, count: int, repeats: int, child_env: dict[str, str]) -> dict[str, Any]:
    """The operations' median seconds on the built catalogue."""
    from core.auth import LOGIN_AT_KEY, SESSION_VERSION_KEY
    from core.db import db
    from core.people import create_person
    from exports.release import plan_release
    from pipeline.records import param_hash
    from review.report import build_report
    from runs.planning import pending_cards
    from runs.specs import available_stages

    figures: dict[str, Any] = {}
    stages = available_stages()
    for name in RUN_STAGES:
        spec = stages[name]

        def plan(spec: Any = spec) -> None:  # bound now: the loop moves on before the timing ends
            pending_cards(spec, param_hash(spec.params))
            db.session.rollback()

        figures[f"plan_{name}_seconds"] = _median_seconds(plan, repeats)

    cards_times, cards_peaks = [], []
    for _ in range(repeats):
        seconds, peak = _cards_json_child("bench-catalogue-0", child_env)
        cards_times.append(seconds)
        cards_peaks.append(peak)
    figures["cards_json_seconds"] = round(statistics.median(cards_times), 4)
    figures["cards_json_peak_rss_mb"] = round(max(cards_peaks), 1)

    person = create_person("bench-curator", None, ["curator", "exporter"])
    db.session.commit()
    client = app.test_client()
    # A session as the login form makes one, without going through it: a login would leave
    # rows in the append-only sign-in trail of a database the bench must leave as it found it.
    with client.session_transaction() as session:
        session.update(
            {
                "_user_id": str(person.id),
                "_fresh": True,
                "_permanent": True,
                SESSION_VERSION_KEY: person.session_version,
                LOGIN_AT_KEY: int(time.time()),
            }
        )
    if client.get("/cards").status_code != 200:
        raise click.ClickException("the bench curator's session was refused")
    per_page = int(app.config.get("CATALOG_PAGE_SIZE", 48))
    last_page = max(1, -(-count // per_page))

    def page(url: str) -> Callable[[], None]:
        def get() -> None:
            answer = client.get(url)
            if answer.status_code != 200:
                raise click.ClickException(f"GET {url} answered {answer.status_code}")

        return get

    figures["catalogue_page_seconds"] = _median_seconds(page("/cards"), repeats)
    figures["catalogue_deep_page_seconds"] = _median_seconds(page(f"/cards?page={last_page}"), repeats)
    figures["review_queue_seconds"] = _median_seconds(page("/review/"), repeats)

    def report() -> None:
        build_report()
        db.session.rollback()

    figures["report_seconds"] = _median_seconds(report, repeats)

    planned: list[int] = []

    def export_plan() -> None:
        # How many cards the plan takes in and leaves out, so the timing is of a real plan (a
        # synthetic card the plan thought stale would be left out and cost nothing).
        report = plan_release(min_grade="some")
        planned[:] = [report.cards, len(report.excluded)]
        db.session.rollback()

    figures["export_plan_seconds"] = _median_seconds(export_plan, repeats)
    figures["export_plan_cards"], figures["export_plan_excluded"] = planned
    figures["peak_rss_mb"] = round(max(peak_rss_mb(), figures["cards_json_peak_rss_mb"]), 1)
    return figures


def benchmark_catalogue(
    count: int, *, repeats: int = 3, keep: bool = False, echo: Callable[[str], None] = lambda _m: None
) -> dict[str, Any]:
    """Build, time, clean up; one JSON-able document (runs inside the app context)."""
    from flask import current_app
    from sqlalchemy import func, select

    from core.console import ensure_database
    from core.db import db
    from core.models import Card

    ensure_database()
    existing = db.session.scalar(select(func.count()).select_from(Card)) or 0
    if existing:
        raise click.ClickException(
            f"the configured database already holds {existing} cards; point KEYSTONE_DATABASE_URL at an empty "
            "database for the bench (it builds and then deletes its own catalogue)"
        )
    app = current_app._get_current_object()  # type: ignore[attr-defined]
    child_env = {
        **os.environ,
        "KEYSTONE_DATABASE_URL": app.config["SQLALCHEMY_DATABASE_URI"],
        "KEYSTONE_DATA_DIR": str(app.config["KEYSTONE_DATA_DIR"]),
        "KEYSTONE_INSTANCE_PATH": app.instance_path,
    }
    echo(f"building a synthetic catalogue of {count} cards")
    try:
        build_seconds = build_catalogue(count, echo)
        echo("timing the operations")
        figures = time_operations(app, count, repeats, child_env)
    finally:
        db.session.rollback()
        if not keep:
            echo("deleting the synthetic catalogue")
            drop_catalogue()
            from core.models import Person

            db.session.execute(Person.__table__.delete().where(Person.username == "bench-curator"))
            db.session.commit()
    return {
        "cards": count,
        "database": db.engine.dialect.name,
        "repeats": repeats,
        "build_seconds": round(build_seconds, 2),
        **figures,
    }


@click.command("catalogue")
@click.option(
    "--cards",
    "count",
    default=25_000,
    show_default=True,
    type=click.IntRange(1, 5_000_000),
    help="Cards in the synthetic catalogue.",
)
@click.option(
    "--repeats", default=3, show_default=True, type=click.IntRange(1, 50), help="Runs of each operation; the median is reported."
)
@click.option("--keep", is_flag=True, help="Leave the synthetic catalogue in the database afterwards.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
@with_appcontext
def bench_catalogue_command(count: int, repeats: int, keep: bool, as_json: bool) -> None:
    """Time planning a run, listing cards, the catalogue and review pages, the report and planning
    an export on a synthetic catalogue of N cards in the configured (empty) database."""
    document = benchmark_catalogue(count, repeats=repeats, keep=keep, echo=lambda message: click.echo(message, err=True))
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    click.echo(f"{document['cards']} cards on {document['database']}: built in {document['build_seconds']} s")
    for key, value in document.items():
        if key.endswith("_seconds") and key != "build_seconds":
            click.echo(f"  {key[: -len('_seconds')]:<28} {value:8.3f} s")
    click.echo(f"  peak memory {document['peak_rss_mb']} MB (cards --json child {document['cards_json_peak_rss_mb']} MB)")

"""``keystone demo``: build a demo collection end to end on an embedded SQLite catalogue, then serve.

Needs nothing outside the install: the cards are made from real photographs that ship with
scikit-image (the Middlebury 2014 Motorcycle stereo pair and its single images), mounted,
toned and damaged like antique cards, plus broken ones (mono card, card back, upside-down,
inverted). Rerunning is cheap: ingest sees duplicates and the stages skip finished work.
"""

from __future__ import annotations

import os
import secrets
import time
from pathlib import Path

import click
from sqlalchemy import select

DEMO_ROLES = ("admin", "curator", "exporter", "annotator")


def _demo_logins(folder: Path) -> dict[str, str]:
    """Random passwords made on the first run, kept (mode 600) so reruns print the same ones."""
    logins_file = folder / "demo-logins.txt"
    if logins_file.exists():
        pairs = (line.split(" ", 1) for line in logins_file.read_text().splitlines() if " " in line)
        return {name: password for name, password in pairs}
    logins = {role: secrets.token_urlsafe(9) for role in DEMO_ROLES}
    fd = os.open(logins_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.writelines(f"{name} {password}\n" for name, password in logins.items())
    return logins


def build_demo(folder: Path, workers: int = 2, echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """Make the cards, ingest them, run the stages, add demo people; returns a summary."""
    from pipeline.synthetic_cards import make_demo_cards, write_demo_cards

    from .db import db
    from .ingest import ingest
    from .models import Card, Person
    from .people import create_person
    from .runs import available_stages, make_executor, run_stage
    from .schema import ensure_schema

    clock = time.perf_counter()
    scans = folder / "scans"
    cards = make_demo_cards(seed=0)
    write_demo_cards(cards, scans)
    echo(f"made {len(cards)} demo cards in {scans}")

    data_dir = folder / "data"
    data_dir.mkdir(parents=True, exist_ok=True)
    ensure_schema(db.engine)
    report = ingest([scans], data_dir=data_dir, collection_name="demo", metadata_csv=scans / "metadata.csv",
                    max_pixels=10_000_000)
    echo(f"ingested {len(report.ingested)} (duplicates {len(report.duplicates)}, rejected {len(report.rejected)})")
    for entry in report.rejected:
        echo(f"  rejected {entry['path']}: {entry['reason']}")

    stage_reports = []
    with make_executor("local", workers, None) as executor:
        for spec in available_stages().values():
            stage_report = run_stage(spec, data_dir=data_dir, executor=executor)
            stage_reports.append(stage_report.as_json())
            echo(f"{spec.name}: processed {stage_report.processed} in {stage_report.seconds:.1f} s, "
                 f"outcomes {stage_report.outcomes}, failed {stage_report.failed}")

    logins = _demo_logins(folder)
    for role in DEMO_ROLES:
        if db.session.scalar(select(Person).where(Person.username == role)) is None:
            create_person(role, logins[role], [role], display_name=f"Demo {role}")

    expected = {card.name: card.expected_filter for card in cards}
    rows = []
    for card in db.session.scalars(select(Card).order_by(Card.id)):
        stem = Path(card.source_name).stem
        filter_result = card.latest_results().get("filter")
        outcome = filter_result.outcome if filter_result else None
        rows.append({
            "id": card.id, "source": card.source_name, "outcome": outcome,
            "fraction": filter_result.metrics.get("good_match_fraction") if filter_result else None,
            "expected": list(expected.get(stem, ())), "as_expected": outcome in expected.get(stem, (outcome,)),
        })
    echo(f"{'card':<32} {'filter':<8} {'fraction':>9}  expected")
    for row in rows:
        fraction = f"{100 * row['fraction']:.2f} %" if row["fraction"] is not None else "-"
        mark = "" if row["as_expected"] else "   <- unexpected"
        echo(f"{row['source']:<32} {str(row['outcome']):<8} {fraction:>9}  {'/'.join(row['expected'])}{mark}")
    return {"cards": rows, "stages": stage_reports, "logins": logins, "seconds": time.perf_counter() - clock}


@click.command("demo")
@click.option("--no-serve", is_flag=True, help="Stop after building and processing the demo collection.")
@click.option("--dir", "folder", type=click.Path(path_type=Path, file_okay=False), default=Path("keystone-demo"),
              show_default=True, help="Folder for the demo's catalogue, store and scans.")
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=5000, show_default=True, type=int)
@click.option("--workers", default=2, show_default=True, type=click.IntRange(1, 64))
def demo_command(no_serve: bool, folder: Path, host: str, port: int, workers: int) -> None:
    """Build the demo collection end to end (embedded SQLite in --dir), then serve the app."""
    from . import create_app
    from .serving import serve

    folder = folder.resolve()
    folder.mkdir(parents=True, exist_ok=True)
    app = create_app(
        {"SQLALCHEMY_DATABASE_URI": f"sqlite:///{folder / 'keystone.sqlite3'}", "KEYSTONE_DATA_DIR": str(folder / "data")},
        instance_path=folder / "instance",
    )
    with app.app_context():
        summary = build_demo(folder, workers=workers)
    click.echo(f"demo built in {summary['seconds']:.1f} s in {folder}")
    click.echo("logins (also in demo-logins.txt): " + ", ".join(f"{k} / {v}" for k, v in summary["logins"].items()))
    unexpected = [row["source"] for row in summary["cards"] if not row["as_expected"]]
    if unexpected:
        click.echo(f"warning: {len(unexpected)} card(s) routed unexpectedly: {', '.join(unexpected)}", err=True)
    if not no_serve:
        serve(app, host=host, port=port)

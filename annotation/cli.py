"""``keystone crowd``: create batches, invite annotators, aggregate and export results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
from flask import current_app, url_for
from flask.cli import with_appcontext
from sqlalchemy import select

from core.db import db
from core.limits import RECORD_ID, RECORD_IDS, parse_positive_int
from core.spreadsheet_csv import write_spreadsheet_csv

from .batches import (
    confirm_gold,
    confirm_queue_card_ids,
    create_batch,
    orientation_queue_card_ids,
    review_queue_card_ids,
)
from .models import (
    TASK_KINDS,
    Aggregate,
    Answer,
    Batch,
    BatchItem,
    CrowdSession,
    Worker,
)
from .progress import batch_progress
from .providers import InviteProvider
from .results import aggregate_batch
from .task_errors import TaskError


def _ensure() -> None:
    from core.console import ensure_database

    ensure_database()


def _emit(document: Any, as_json: bool, human: str) -> None:
    from core.console import emit_json

    if as_json:
        emit_json(document)
    else:
        click.echo(human)


@click.group("crowd")
def crowd_group() -> None:
    """Crowd annotation: batches of judge and crop tasks, invites, aggregation, export."""


@crowd_group.command("create-batch")
@click.option(
    "--from-review",
    is_flag=True,
    help="Add the cards waiting for people: those the filter sent to review and those whose "
    "orientation the orientation step could not decide (whatever their filter band).",
)
@click.option(
    "--from-orientation",
    is_flag=True,
    help="Add only the cards whose orientation the orientation step could not decide (with --kind confirm: the "
    "cards it proposed an orientation for with a narrow margin; their grids hide gold made from decided cards).",
)
@click.option("--cards", "cards", type=RECORD_IDS, default="", help="Comma-separated card ids.")
@click.option("--kind", type=click.Choice(TASK_KINDS), default="judge", show_default=True)
@click.option("--n", "n", type=click.IntRange(min=1), default=3, show_default=True, help="Answers per item.")
@click.option("--gold-rate", type=click.FloatRange(0.0, 1.0), default=0.1, show_default=True)
@click.option(
    "--gold",
    "gold_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help='JSON file {"<card id>": <known answer>} of gold items made by curators.',
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def create_batch_command(
    from_review: bool,
    from_orientation: bool,
    cards: list[int],
    kind: str,
    n: int,
    gold_rate: float,
    gold_file: Path | None,
    as_json: bool,
) -> None:
    """Create a batch of KIND tasks over the chosen cards."""
    _ensure()
    ids = list(cards) + (review_queue_card_ids() if from_review and kind != "confirm" else [])
    if (from_review or from_orientation) and kind == "judge":
        ids = list(dict.fromkeys(ids + orientation_queue_card_ids()))
    if (from_review or from_orientation) and kind == "confirm":
        ids = list(dict.fromkeys(ids + confirm_queue_card_ids()))
    gold: dict[int, dict[str, Any]] = {}
    shown: dict[int, dict[str, bool]] = {}
    if kind == "confirm" and gold_file is None and ids:
        # Every grid hides gold: cards whose orientation is known, shown wrong on purpose.
        gold, shown = confirm_gold(exclude=ids)
    if gold_file is not None:
        try:
            gold = {parse_positive_int(k, "a card id"): v for k, v in json.loads(gold_file.read_text()).items()}
        except (ValueError, AttributeError) as exc:
            raise click.BadParameter(f"expected a JSON object of card id -> answer: {exc}", param_hint="--gold") from exc
    if not ids and not gold:
        raise click.UsageError(
            "no cards: give --cards IDS, --from-review or --from-orientation (and some card must be waiting for people)"
        )
    try:
        batch = create_batch(ids, kind, n, gold_rate, gold=gold, shown=shown)
    except TaskError as exc:
        raise click.ClickException(exc.message) from exc
    progress = batch_progress(batch)
    if kind == "confirm" and not gold:
        click.echo("warning: no card with a known orientation to make gold from: these grids hide no gold", err=True)
    _emit(progress, as_json, f"batch {batch.id}: {progress['items']} {kind} items, {progress['gold_items']} gold, N={n}")


@crowd_group.command("invite")
@click.argument("name")
@click.option("--base-url", default="http://127.0.0.1:5000", show_default=True, help="Where the app is served.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def invite_command(name: str, base_url: str, as_json: bool) -> None:
    """Invite an in-house annotator NAME and print their personal link (no password)."""
    _ensure()
    try:
        worker = InviteProvider.invite(name)
    except TaskError as exc:
        raise click.ClickException(exc.message) from exc
    with current_app.test_request_context(base_url=base_url):
        link = url_for("crowd.invite", token=worker.token, _external=True)
    _emit({"worker": worker.id, "name": name, "link": link}, as_json, link)


@crowd_group.command("aggregate")
@click.argument("batch_id", type=RECORD_ID)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def aggregate_command(batch_id: int, as_json: bool) -> None:
    """Aggregate BATCH: approved cards feed the pipeline, the rest wait for a curator."""
    _ensure()
    try:
        report = aggregate_batch(batch_id)
    except TaskError as exc:
        raise click.ClickException(exc.message) from exc
    doc = report.as_json()
    _emit(
        doc,
        as_json,
        f"batch {batch_id}: {doc['approved']} approved, {doc['needs_curator']} for a curator, "
        f"{doc['escalated']} sent on to judge tasks (a grid could not agree), "
        f"{doc['pending']} unfinished, {doc['flagged_workers']} workers flagged",
    )


ANSWER_COLUMNS: tuple[str, ...] = (
    "answer_id",
    "batch",
    "card_id",
    "is_gold",
    "worker",
    "session",
    "flagged",
    "submitted_at",
    "payload",
)
AGGREGATE_COLUMNS: tuple[str, ...] = (
    "batch",
    "card_id",
    "kind",
    "state",
    "confident",
    "answers",
    "label",
    "posterior",
    "reasons",
)


def answer_rows(batch: Batch) -> list[dict[str, Any]]:
    """One row per answer; ``session`` is the provider's session key (Prolific SESSION_ID, MTurk
    assignmentId) the answer was given in, what a researcher approves submissions by."""
    rows = db.session.execute(
        select(Answer, BatchItem, Worker, CrowdSession.external_id)
        .join(BatchItem, Answer.item_id == BatchItem.id)
        .join(Worker, Answer.worker_id == Worker.id)
        .outerjoin(CrowdSession, CrowdSession.id == Answer.session_id)
        .where(BatchItem.batch_id == batch.id)
        .order_by(Answer.id)
    )
    return [
        {
            "answer_id": a.id,
            "batch": batch.id,
            "card_id": it.card_id,
            "is_gold": it.is_gold,
            "worker": f"{w.provider}:{w.external_id}",
            "session": session or "",
            "flagged": a.flagged,
            "submitted_at": a.submitted_at.isoformat(),
            "payload": json.dumps(a.payload, sort_keys=True),
        }
        for a, it, w, session in rows
    ]


def aggregate_rows(batch: Batch) -> list[dict[str, Any]]:
    rows = db.session.scalars(select(Aggregate).where(Aggregate.batch_id == batch.id).order_by(Aggregate.card_id))
    return [
        {
            "batch": batch.id,
            "card_id": a.card_id,
            "kind": a.kind,
            "state": a.state,
            "confident": a.confident,
            "answers": a.answers,
            "label": json.dumps(a.label, sort_keys=True),
            "posterior": json.dumps(a.posterior, sort_keys=True),
            "reasons": a.reasons,
        }
        for a in rows
    ]


def _write_table(rows: list[dict[str, Any]], columns: list[str], out: Path, stem: str) -> list[str]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    with (out / f"{stem}.csv").open("w", newline="") as handle:
        write_spreadsheet_csv(handle, columns, rows)  # for people: formula-like cells neutralised
    pq.write_table(
        pa.Table.from_pylist(rows, schema=None) if rows else pa.table({c: pa.array([], pa.string()) for c in columns}),
        out / f"{stem}.parquet",
    )
    return [f"{stem}.csv", f"{stem}.parquet"]


def _box_formats(batch: Batch, out: Path) -> list[str]:
    """Approved crop consensus boxes as COCO and Label Studio JSON (original image pixels)."""
    aggregates = list(
        db.session.scalars(
            select(Aggregate).where(Aggregate.batch_id == batch.id, Aggregate.kind == "crop").order_by(Aggregate.card_id)
        )
    )
    items = {it.card_id: it.card for it in batch.items}
    coco: dict[str, Any] = {
        "images": [],
        "annotations": [],
        "categories": [{"id": 1, "name": "left"}, {"id": 2, "name": "right"}],
    }
    studio: list[dict[str, Any]] = []
    for agg in aggregates:
        card = items[agg.card_id]
        coco["images"].append({"id": card.id, "file_name": card.source_name, "width": card.width, "height": card.height})
        results = []
        for category, half in ((1, "left"), (2, "right")):
            x0, y0, x1, y1 = agg.label[half]
            coco["annotations"].append(
                {
                    "id": len(coco["annotations"]) + 1,
                    "image_id": card.id,
                    "category_id": category,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                    "keystone_state": agg.state,
                }
            )
            # Label Studio stores rectangles in percent of the image size.
            results.append(
                {
                    "from_name": "box",
                    "to_name": "image",
                    "type": "rectanglelabels",
                    "original_width": card.width,
                    "original_height": card.height,
                    "value": {
                        "x": 100 * x0 / card.width,
                        "y": 100 * y0 / card.height,
                        "width": 100 * (x1 - x0) / card.width,
                        "height": 100 * (y1 - y0) / card.height,
                        "rotation": 0,
                        "rectanglelabels": [half],
                    },
                }
            )
        studio.append(
            {
                "data": {"image": card.source_name, "card_id": card.id},
                "annotations": [{"result": results}],
                "meta": {"state": agg.state},
            }
        )
    (out / "boxes.coco.json").write_text(json.dumps(coco, indent=2))
    (out / "boxes.label-studio.json").write_text(json.dumps(studio, indent=2))
    return ["boxes.coco.json", "boxes.label-studio.json"]


@crowd_group.command("export")
@click.argument("batch_id", type=RECORD_ID)
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
@with_appcontext
def export_command(batch_id: int, out: Path, as_json: bool) -> None:
    """Write BATCH's raw answers and aggregates (CSV, Parquet; boxes also as COCO and Label Studio)."""
    _ensure()
    batch = db.session.get(Batch, batch_id)
    if batch is None:
        raise click.ClickException(f"no batch {batch_id}")
    out.mkdir(parents=True, exist_ok=True)
    files = _write_table(answer_rows(batch), list(ANSWER_COLUMNS), out, "answers")
    files += _write_table(aggregate_rows(batch), list(AGGREGATE_COLUMNS), out, "aggregates")
    if batch.kind == "crop":
        files += _box_formats(batch, out)
    _emit({"batch": batch_id, "out": str(out), "files": files}, as_json, "\n".join(str(out / f) for f in files))


def register_cli(group: click.Group) -> None:
    """Add the ``crowd`` commands to ``group`` (the ``keystone`` command)."""
    group.add_command(crowd_group)

"""``keystone bench pipeline``: CPU seconds per card for each stage, and peak memory, on real cards.

The cards are ingested into a throwaway instance (SQLite, its own data dir) and run through
the real stages (``app.runs.run_stage``, inline on one core, so each card's CPU time is this
process's): filter, rectify, disparity, grade (the default pipeline) and views. Each stage's
task is wrapped to read ``time.process_time()`` around every card. A card the filter does not
pass, or that a stage fails, has no figure for the stages it did not reach (the report says
which stages each card ran).

Cards: the real scans in ``../shared/data/stereocards`` (NYPL cards ~760 px, Keystone-Mast raw
scans ~1400 px, JPS pairs ~3000 px wide), or with ``--synthetic`` (and when that folder is not
there) the Motorcycle card of scikit-image mounted at those three widths.
"""

from __future__ import annotations

import functools
import json
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from benchmarks.export import peak_rss_mb

DEFAULT_STAGES = ("filter", "rectify", "disparity", "grade")
ALL_STAGES = (*DEFAULT_STAGES, "views")
CARD_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".jps"}
SYNTHETIC_WIDTHS = (760, 1400, 3000)
TARGET_PIPELINE_CPU_S = 1.0
TARGET_VIEWS_CPU_S = 0.5


def real_cards(shared_data: Path) -> list[Path]:
    """The stereo cards and pairs of the shared data (card backs left out: they are not stereo)."""
    root = shared_data / "stereocards"
    folders = [root / "full_cards", root / "keystone_mast_raw_scans", root / "cropped_pairs" / "jps"]
    return sorted(path for folder in folders if folder.is_dir() for path in folder.iterdir()
                  if path.suffix.lower() in CARD_SUFFIXES)


def synthetic_cards(folder: Path) -> list[Path]:
    """The Motorcycle pair mounted as a card at 760, 1400 and 3000 px wide."""
    from PIL import Image
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    gap = np.full((left.shape[0], 24, 3), (214, 200, 170), np.uint8)
    card = Image.fromarray(np.concatenate([left, gap, right], axis=1))
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for width in SYNTHETIC_WIDTHS:
        height = round(card.height * width / card.width)
        path = folder / f"motorcycle_{width}px.jpg"
        card.resize((width, height), Image.Resampling.LANCZOS).save(path, quality=92)
        paths.append(path)
    return paths


def _timed(task: Callable[[Any], Any], seconds: dict[int, float], card_task: Any) -> Any:
    clock = time.process_time()
    try:
        return task(card_task)
    finally:
        seconds[card_task.card_id] = time.process_time() - clock


def benchmark_pipeline(cards: list[Path], stages: tuple[str, ...] = ALL_STAGES,
                       echo: Callable[[str], None] = lambda _m: None, sbs_order: str | None = None) -> dict[str, Any]:
    """Ingest ``cards`` into a throwaway instance and run ``stages`` inline; per-card CPU seconds.
    ``sbs_order`` is ``keystone ingest --sbs-order`` (None: JPS files are read cross-eyed)."""
    from dataclasses import replace

    from sqlalchemy import select

    from app import create_app
    from app.db import db
    from app.ingest import ingest
    from app.models import Card
    from app.runs import available_stages, run_stage
    from app.schema import upgrade
    from app.stereo_ingest import StereoOptions

    root = Path(tempfile.mkdtemp(prefix="keystone-bench-pipeline-"))
    data_dir = root / "data"
    app = create_app({"SQLALCHEMY_DATABASE_URI": f"sqlite:///{root / 'bench.sqlite3'}",
                      "KEYSTONE_DATA_DIR": str(data_dir)}, instance_path=root / "instance")
    per_stage: dict[str, dict[int, float]] = {}
    with app.app_context():
        upgrade(db.engine)
        report = ingest(cards, data_dir=data_dir, collection_name="bench-pipeline",
                        max_pixels=app.config["KEYSTONE_MAX_PIXELS"], stereo=StereoOptions(sbs_order=sbs_order))
        rejected = [item for item in report.rejected]
        specs = available_stages()
        for name in stages:
            seconds: dict[int, float] = {}
            spec = replace(specs[name], task=functools.partial(_timed, specs[name].task, seconds))
            echo(f"{name}: running")
            run_stage(spec, data_dir=data_dir, executor=None)
            per_stage[name] = seconds
        rows = []
        for card in db.session.scalars(select(Card).order_by(Card.id)):
            latest = card.latest_results()
            costs = {name: round(per_stage[name][card.id], 4) for name in stages if card.id in per_stage[name]}
            pipeline = [costs[name] for name in DEFAULT_STAGES if name in costs]
            rows.append({
                "card": card.source_name, "width": card.width, "height": card.height,
                "filter_outcome": latest["filter"].outcome if "filter" in latest else None,
                "grade": latest["grade"].outcome if "grade" in latest else None,
                "failed": {name: result.reason for name, result in latest.items() if result.status == "failed"},
                "cpu_seconds": costs,
                "pipeline_cpu_seconds": round(sum(pipeline), 4),
                "reached_grade": "grade" in costs,
                "views_cpu_seconds": costs.get("views"),
            })
        db.session.remove()
        db.engine.dispose()
    complete = [row for row in rows if row["reached_grade"]]
    views = [row["views_cpu_seconds"] for row in rows if row["views_cpu_seconds"] is not None]
    summary = {
        "cards": len(rows), "reached_grade": len(complete),
        "median_pipeline_cpu_seconds": round(statistics.median(r["pipeline_cpu_seconds"] for r in complete), 4)
        if complete else None,
        "max_pipeline_cpu_seconds": max((r["pipeline_cpu_seconds"] for r in complete), default=None),
        "median_views_cpu_seconds": round(statistics.median(views), 4) if views else None,
        "max_views_cpu_seconds": max(views, default=None),
        "per_stage_median_cpu_seconds": {
            name: round(statistics.median(per_stage[name].values()), 4) for name in stages if per_stage[name]},
        "target_pipeline_cpu_seconds": TARGET_PIPELINE_CPU_S, "target_views_cpu_seconds": TARGET_VIEWS_CPU_S,
    }
    import shutil

    shutil.rmtree(root, ignore_errors=True)
    return {"results": rows, "summary": summary, "rejected": rejected, "peak_rss_mb": round(peak_rss_mb(), 1)}


@click.command("pipeline")
@click.option("--shared-data", type=click.Path(path_type=Path, file_okay=False),
              help="Folder with the real cards (../shared/data) [default: found next to the checkout].")
@click.option("--synthetic", is_flag=True, help="Use the Motorcycle card at 760, 1400 and 3000 px instead.")
@click.option("--stages", default=",".join(ALL_STAGES), show_default=True,
              help="Stages to run, in flow order.")
@click.option("--limit", type=click.IntRange(1), help="Only the first N cards.")
@click.option("--sbs-order", type=click.Choice(["cross", "parallel"]), default="parallel", show_default=True,
              help="Eye order of side-by-side files, as keystone ingest --sbs-order: the shared JPS files are "
                   "stored parallel (../shared/data/PROVENANCE.md, and the ingest's own eye-order check).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_pipeline_command(shared_data: Path | None, synthetic: bool, stages: str, limit: int | None,
                           sbs_order: str, as_json: bool) -> None:
    """CPU seconds per card for each stage (one core, inline) and peak memory on real cards."""
    names = tuple(name.strip() for name in stages.split(",") if name.strip())
    unknown = [name for name in names if name not in ALL_STAGES]
    if unknown or not names:
        raise click.BadParameter(f"expected stages among {', '.join(ALL_STAGES)}, got {stages!r}",
                                 param_hint="--stages")
    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = [] if synthetic or shared_data is None else real_cards(shared_data)
    if not cards:
        cards = synthetic_cards(Path(tempfile.mkdtemp(prefix="keystone-bench-cards-")))
    cards = cards[:limit] if limit else cards
    document = benchmark_pipeline(cards, names, echo=lambda m: click.echo(m, err=True), sbs_order=sbs_order)
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    click.echo(f"{'card':<52} {'size':>10} " + " ".join(f"{name:>9}" for name in names) + f" {'pipeline':>9}")
    for row in document["results"]:
        cells = " ".join(f"{row['cpu_seconds'][n]:9.3f}" if n in row["cpu_seconds"] else f"{'-':>9}" for n in names)
        click.echo(f"{row['card'][:52]:<52} {row['width']:>5}x{row['height']:<4} {cells} "
                   f"{row['pipeline_cpu_seconds']:9.3f}")
    summary = document["summary"]
    click.echo(f"median pipeline {summary['median_pipeline_cpu_seconds']} CPU-s a card (target <= "
               f"{TARGET_PIPELINE_CPU_S}), views {summary['median_views_cpu_seconds']} (target <= "
               f"{TARGET_VIEWS_CPU_S}); peak {document['peak_rss_mb']} MB")

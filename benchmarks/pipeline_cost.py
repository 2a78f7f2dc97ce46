"""``keystone bench pipeline``: CPU seconds per card for each stage, and peak memory, on real cards.

The cards are ingested into a throwaway instance (SQLite, its own data dir) and run through
the real stages (``runs.loop.run_stage``, inline on one core with one OpenCV thread as in a pool
worker, so each card's CPU time is this process's): filter, orientation, rectify, disparity,
grade (the default pipeline) and views. Each stage's
task is wrapped to read ``time.process_time()`` around every card. A card the filter does not
pass, or that a stage fails, has no figure for the stages it did not reach (the report says
which stages each card ran).

Variants, side by side in one run (``--variant``, default ``full`` and ``work``): ``full`` runs
rectification and disparity at full resolution (``work_side=None``, the behaviour before the
working resolution), ``work`` with the defaults (views stored and matched at
``RectifyParams.work_side``), both with the stages chained as ``keystone run`` chains them
(:mod:`pipeline.chains`), and ``stage-by-stage`` the defaults with every stage over all cards before
the next (``keystone run --stage-by-stage``). Each variant
runs in its own fresh process (spawned), one after the other, so its ``peak_rss_mb`` is its own;
CPU seconds (``time.process_time``) move less with other load on the machine than wall time.
Medians are given per scan size (``by_size``: the card's width, 760 px NYPL cards, ~1400 px
Keystone-Mast raw scans, ~3000 px JPS pairs).

Measured 2026-11-24 (docs/BENCHMARKS.md, "Decodes and writes on every card"): medians of each
card's best of three runs, filter to grade, 0.41 / 1.16 / 1.63 CPU-s at 760 / 1400 / ~3000 px
(main before the change: 0.44 / 1.21 / 1.79; without the orientation step's text cue 0.28 /
1.00 / 1.49); peak ~565 MB (273 MB without the cue). Measured 2026-11-25 (docs/BENCHMARKS.md,
"Where a card's CPU goes"), each stage's best of eight summed: 0.36 / 0.96 / 1.32 (main 7924c7b:
0.38 / 1.07 / 1.42).
Measured 2026-11-25 (docs/BENCHMARKS.md, "The cost of a card"), main (a1fe5eb) and the weighted
median at a quarter on 800 px maps alternately six times, median of each card's runs: 0.98 -> 0.87
at 1400 px, 1.38 -> 1.22 at ~3000 px (each card 0.88-0.91 of main). Measured 2026-11-25
(docs/BENCHMARKS.md, "A worker's threads and memory"), with the worker's one BLAS thread and
freed memory kept, alternately with ab4eb5f three times: 0.43 / 0.89 / 1.25 -> 0.35 / 0.71 / 1.03.

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
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import click
import numpy as np

from benchmarks.export import peak_rss_mb

DEFAULT_STAGES = ("filter", "orientation", "rectify", "disparity", "grade")
ALL_STAGES = (*DEFAULT_STAGES, "views")
CARD_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".jps"}
SYNTHETIC_WIDTHS = (760, 1400, 3000)
VARIANTS = ("full", "work", "stage-by-stage")
DEFAULT_VARIANTS = ("full", "work")
SIZE_CLASSES = ((0, 1000, "<1000 px"), (1000, 2000, "1000-2000 px"), (2000, 10**9, ">=2000 px"))
TARGET_PIPELINE_CPU_S = 1.0
TARGET_VIEWS_CPU_S = 0.5


def real_cards(shared_data: Path) -> list[Path]:
    """The stereo cards and pairs of the shared data (card backs left out: they are not stereo)."""
    root = shared_data / "stereocards"
    folders = [root / "full_cards", root / "keystone_mast_raw_scans", root / "cropped_pairs" / "jps"]
    return sorted(
        path for folder in folders if folder.is_dir() for path in folder.iterdir() if path.suffix.lower() in CARD_SUFFIXES
    )


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


def variant_params(variant: str) -> dict[str, Any]:
    """Stage parameters that differ from the defaults in ``variant`` (``full``: no working side)."""
    from pipeline.rectify import RectifyParams
    from pipeline.stages.disparity import DisparityStageParams

    if variant in ("work", "stage-by-stage"):
        return {}
    if variant == "full":
        return {"rectify": RectifyParams(work_side=None), "disparity": DisparityStageParams(work_side=None)}
    raise click.BadParameter(f"expected a variant among {', '.join(VARIANTS)}, got {variant!r}")


def by_size(rows: list[dict[str, Any]], stages: tuple[str, ...]) -> list[dict[str, Any]]:
    """Median pipeline and per-stage CPU seconds of the cards that reached the grade, per scan size."""
    out = []
    for low, high, label in SIZE_CLASSES:
        group = [r for r in rows if r["reached_grade"] and low <= r["width"] < high]
        if not group:
            continue
        out.append(
            {
                "size": label,
                "cards": len(group),
                "widths": sorted({r["width"] for r in group}),
                "median_pipeline_cpu_seconds": round(statistics.median(r["pipeline_cpu_seconds"] for r in group), 4),
                "max_pipeline_cpu_seconds": max(r["pipeline_cpu_seconds"] for r in group),
                "median_cpu_seconds": {
                    name: round(statistics.median(r["cpu_seconds"][name] for r in group), 4)
                    for name in stages
                    if all(name in r["cpu_seconds"] for r in group)
                },
            }
        )
    return out


def benchmark_variant(
    cards: list[Path], stages: tuple[str, ...], sbs_order: str | None, variant: str, warm_up: bool = True
) -> dict[str, Any]:
    """:func:`benchmark_pipeline` with ``variant``'s parameters (run in a fresh process by the command),
    set up as every pool worker of ``keystone run`` is (:func:`pipeline.runner.init_worker`: one
    OpenCV and one BLAS thread, freed memory kept): inner threads would add their overhead to
    the process's CPU seconds.

    ``warm_up``: the cards first go through the stages once in a throwaway instance of the same
    process, and the figures are the second pass's. A pool worker pays its one-time costs (lazy
    imports, the text recogniser's ONNX sessions, OpenCV's first calls) once for thousands of
    cards, but a single pass charges them all to the first card each stage meets (measured
    2026-11-25: 0.24 CPU-s on the first ~3000 px card, 0.31 on the first to read print). The
    first pass's medians are kept (``first_pass_by_size``) so that cost stays visible."""
    from pipeline.runner import init_worker

    init_worker()
    chain = variant != "stage-by-stage"
    first = (
        benchmark_pipeline(cards, stages, sbs_order=sbs_order, params=variant_params(variant), chain=chain) if warm_up else None
    )
    document = benchmark_pipeline(cards, stages, sbs_order=sbs_order, params=variant_params(variant), chain=chain)
    document["variant"] = variant
    document["warmed_up"] = warm_up
    document["first_pass_by_size"] = None
    if first is not None:
        document["first_pass_by_size"] = [
            {"size": g["size"], "median_pipeline_cpu_seconds": g["median_pipeline_cpu_seconds"]}
            for g in first["summary"]["by_size"]
        ]
    return document


def decide_as_stored() -> None:
    """The benchmark's cards are stored the right way up, positive, eyes in order: say so as a
    curator would (an override on every card still undecided), so the cost of the stages after
    the orientation step is measured on every card whatever the step decided."""
    from sqlalchemy import select

    from core.db import db
    from core.models import Card
    from review.models import OrientationOverride

    for card_id in db.session.scalars(select(Card.id).where(~Card.id.in_(select(OrientationOverride.card_id)))):
        db.session.add(
            OrientationOverride(
                card_id=card_id, upside_down=False, inverted=False, swapped=False, note="benchmark: cards stored upright"
            )
        )
    db.session.commit()


def benchmark_pipeline(
    cards: list[Path],
    stages: tuple[str, ...] = ALL_STAGES,
    echo: Callable[[str], None] = lambda _m: None,
    sbs_order: str | None = None,
    params: dict[str, Any] | None = None,
    chain: bool = True,
) -> dict[str, Any]:
    """Ingest ``cards`` into a throwaway instance and run ``stages`` inline; per-card CPU seconds.
    ``sbs_order`` is ``keystone ingest --sbs-order`` (None: JPS files are read cross-eyed);
    ``params``: stage name -> parameters replacing that stage's defaults; ``chain``: stages
    chained as ``keystone run`` does by default (:mod:`pipeline.chains`), else stage by stage."""
    from dataclasses import replace

    from sqlalchemy import select

    from app import create_app
    from app.schema import upgrade
    from catalogue.ingest import ingest
    from catalogue.stereo_ingest import StereoOptions
    from core.db import db
    from core.models import Card
    from pipeline.stages.spec import StageSpec
    from runs.loop import run_stage, run_stages
    from runs.report import StageReport
    from runs.specs import available_stages

    root = Path(tempfile.mkdtemp(prefix="keystone-bench-pipeline-"))
    data_dir = root / "data"
    app = create_app(
        {"SQLALCHEMY_DATABASE_URI": f"sqlite:///{root / 'bench.sqlite3'}", "KEYSTONE_DATA_DIR": str(data_dir)},
        instance_path=root / "instance",
    )
    per_stage: dict[str, dict[int, float]] = {}
    with app.app_context():
        upgrade(db.engine)
        report = ingest(
            cards,
            data_dir=data_dir,
            collection_name="bench-pipeline",
            max_pixels=app.config["KEYSTONE_MAX_PIXELS"],
            stereo=StereoOptions(sbs_order=sbs_order),
        )
        rejected = [item for item in report.rejected]
        specs = available_stages()
        for name in stages:
            per_stage[name] = {}
            spec = specs[name]
            if params and name in params:
                spec = replace(spec, params=params[name], task=functools.partial(spec.task.func, params=params[name]))
            specs[name] = replace(spec, task=functools.partial(_timed, spec.task, per_stage[name]))

        def run_one(spec: StageSpec, followers: Sequence[StageSpec], leave_out: Mapping[str, set[int]]) -> StageReport:
            if spec.name == "rectify":
                decide_as_stored()  # with or without the orientation step in the run
            echo(f"{spec.name}: running")
            return run_stage(spec, data_dir=data_dir, executor=None, followers=followers, leave_out=leave_out)

        list(run_stages([specs[name] for name in stages], run_one, chain))
        rows = []
        for card in db.session.scalars(select(Card).order_by(Card.id)):
            latest = card.latest_results()
            costs = {name: round(per_stage[name][card.id], 4) for name in stages if card.id in per_stage[name]}
            pipeline = [costs[name] for name in DEFAULT_STAGES if name in costs]
            rows.append(
                {
                    "card": card.source_name,
                    "width": card.width,
                    "height": card.height,
                    "filter_outcome": latest["filter"].outcome if "filter" in latest else None,
                    "grade": latest["grade"].outcome if "grade" in latest else None,
                    "failed": {name: result.reason for name, result in latest.items() if result.status == "failed"},
                    "cpu_seconds": costs,
                    "pipeline_cpu_seconds": round(sum(pipeline), 4),
                    "reached_grade": "grade" in costs,
                    "views_cpu_seconds": costs.get("views"),
                }
            )
        db.session.remove()
        db.engine.dispose()
    complete = [row for row in rows if row["reached_grade"]]
    views = [row["views_cpu_seconds"] for row in rows if row["views_cpu_seconds"] is not None]
    summary = {
        "cards": len(rows),
        "reached_grade": len(complete),
        "median_pipeline_cpu_seconds": round(statistics.median(r["pipeline_cpu_seconds"] for r in complete), 4)
        if complete
        else None,
        "max_pipeline_cpu_seconds": max((r["pipeline_cpu_seconds"] for r in complete), default=None),
        "median_views_cpu_seconds": round(statistics.median(views), 4) if views else None,
        "max_views_cpu_seconds": max(views, default=None),
        "per_stage_median_cpu_seconds": {
            name: round(statistics.median(per_stage[name].values()), 4) for name in stages if per_stage[name]
        },
        "target_pipeline_cpu_seconds": TARGET_PIPELINE_CPU_S,
        "target_views_cpu_seconds": TARGET_VIEWS_CPU_S,
        "by_size": by_size(rows, stages),
    }
    import shutil

    shutil.rmtree(root, ignore_errors=True)
    return {"results": rows, "summary": summary, "rejected": rejected, "peak_rss_mb": round(peak_rss_mb(), 1)}


@click.command("pipeline")
@click.option(
    "--shared-data",
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder with the real cards (../shared/data) [default: found next to the checkout].",
)
@click.option("--synthetic", is_flag=True, help="Use the Motorcycle card at 760, 1400 and 3000 px instead.")
@click.option("--stages", default=",".join(ALL_STAGES), show_default=True, help="Stages to run, in flow order.")
@click.option("--limit", type=click.IntRange(1), help="Only the first N cards.")
@click.option(
    "--sbs-order",
    type=click.Choice(["cross", "parallel"]),
    default="parallel",
    show_default=True,
    help="Eye order of side-by-side files, as keystone ingest --sbs-order: the shared JPS files are "
    "stored parallel (../shared/data/PROVENANCE.md, and the ingest's own eye-order check).",
)
@click.option(
    "--variant",
    "variants",
    multiple=True,
    type=click.Choice(VARIANTS),
    help="full (work_side None: full resolution, as before), work (the defaults) and/or stage-by-stage "
    "(the defaults, every stage over all cards before the next instead of chained as keystone run "
    "does); repeatable. Default: full and work, side by side, each in its own process.",
)
@click.option(
    "--cold",
    is_flag=True,
    help="Time the first pass of a fresh process (one-time costs charged to the first card of each "
    "stage) instead of a second pass after a warm-up one.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_pipeline_command(
    shared_data: Path | None,
    synthetic: bool,
    stages: str,
    limit: int | None,
    sbs_order: str,
    variants: tuple[str, ...],
    cold: bool,
    as_json: bool,
) -> None:
    """CPU seconds per card for each stage (one core, inline) and peak memory on real cards."""
    names = tuple(name.strip() for name in stages.split(",") if name.strip())
    unknown = [name for name in names if name not in ALL_STAGES]
    if unknown or not names:
        raise click.BadParameter(f"expected stages among {', '.join(ALL_STAGES)}, got {stages!r}", param_hint="--stages")
    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = [] if synthetic or shared_data is None else real_cards(shared_data)
    if not cards:
        cards = synthetic_cards(Path(tempfile.mkdtemp(prefix="keystone-bench-cards-")))
    cards = cards[:limit] if limit else cards
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    runs: dict[str, dict[str, Any]] = {}
    for variant in variants or DEFAULT_VARIANTS:
        click.echo(f"{variant}: running", err=True)
        # A fresh process per variant: its peak memory is its own, and nothing is cached across.
        with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
            runs[variant] = pool.submit(benchmark_variant, cards, names, sbs_order, variant, not cold).result()
    main = runs.get("work") or next(iter(runs.values()))
    document = {**main, "variants": runs, "comparison": comparison(runs) if len(runs) > 1 else None}
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    for variant, run in runs.items():
        click.echo(f"== {variant}")
        click.echo(f"{'card':<52} {'size':>10} " + " ".join(f"{name:>9}" for name in names) + f" {'pipeline':>9}")
        for row in run["results"]:
            cells = " ".join(f"{row['cpu_seconds'][n]:9.3f}" if n in row["cpu_seconds"] else f"{'-':>9}" for n in names)
            click.echo(f"{row['card'][:52]:<52} {row['width']:>5}x{row['height']:<4} {cells} {row['pipeline_cpu_seconds']:9.3f}")
        summary = run["summary"]
        for group in summary["by_size"]:
            click.echo(
                f"{group['size']:>13}: median {group['median_pipeline_cpu_seconds']} CPU-s a card "
                f"({group['cards']} cards) {group['median_cpu_seconds']}"
            )
        if run.get("first_pass_by_size"):
            first = ", ".join(f"{g['size']} {g['median_pipeline_cpu_seconds']}" for g in run["first_pass_by_size"])
            click.echo(f"  first pass of the process (one-time costs included): {first}")
        click.echo(
            f"median pipeline {summary['median_pipeline_cpu_seconds']} CPU-s a card (target <= "
            f"{TARGET_PIPELINE_CPU_S}), views {summary['median_views_cpu_seconds']} (target <= "
            f"{TARGET_VIEWS_CPU_S}); peak {run['peak_rss_mb']} MB"
        )


def comparison(runs: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scan size: the median pipeline CPU seconds of each variant side by side, and the ratio."""
    labels = [label for _, _, label in SIZE_CLASSES]
    out = []
    for label in labels:
        row: dict[str, Any] = {"size": label}
        for variant, run in runs.items():
            group = next((g for g in run["summary"]["by_size"] if g["size"] == label), None)
            row[variant] = group["median_pipeline_cpu_seconds"] if group else None
        if row.get("full") and row.get("work"):
            row["work_over_full"] = round(row["work"] / row["full"], 3)
        if row.get("stage-by-stage") and row.get("work"):
            row["chained_over_stage_by_stage"] = round(row["work"] / row["stage-by-stage"], 3)
        if any(row.get(v) is not None for v in runs):
            out.append(row)
    return out

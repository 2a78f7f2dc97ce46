"""``keystone bench views``: CPU seconds per card of the views stage, the current code against the
code before the vectorised rasteriser (a frozen copy in :mod:`benchmarks.views_frozen`), side by
side in one run, with what the change did to the output.

The cards are ingested into a throwaway instance (SQLite, its own data dir) and run through filter,
rectify, disparity and grade (``runs.loop.run_stage``, inline), so the views stage sees real rectified
views and disparities. Then, per card and repeat, the old and the new ``views_task`` run one after the
other in this process (order alternating between repeats), each timed by ``time.process_time()``.

What is compared
----------------
* ``rasteriser``: v0 of the old run (its grey picture and depth) rendered into the four corner
  cameras of its ``views.json`` by the old and the new :func:`pipeline.views.reproject` with the
  same triangle rule (the paper's relative depth step alone): the largest difference in intensity
  (0..1) and relative depth over pixels both cover, PSNR of the intensity, the fraction of pixels
  differing by more than one 8-bit level or 1e-4 in relative depth, and the pixels covered by one
  and not the other. The stated tolerance (:data:`TOLERANCE`): at most 0.01 % of the pixels differ,
  in value or in coverage (float32 fragments: a pixel centre within 1e-5 px of a triangle edge may
  land in the neighbouring triangle, at a depth edge another surface).
* ``cracks``: the fraction of each corner view in holes that do not touch the border
  (:func:`pipeline.views.crack_fraction`: holes less than 3 px across) under the paper's rule and under the stage's
  rule (relative step and a parallax stretch of more than ``max_stretch_px``).
* ``viewer_bytes``: what the viewer downloads for a card: before, the five PNGs and five float32
  ``.npy`` depth maps; now, the five JPEGs and five mesh PNGs.

Cards: the real scans in ``../shared/data/stereocards`` or, with ``--synthetic`` (and when that
folder is not there), the Motorcycle card of scikit-image mounted at three widths.
"""

from __future__ import annotations

import functools
import json
import math
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from benchmarks.pipeline_cost import DEFAULT_STAGES, decide_as_stored, real_cards, synthetic_cards

TARGET_VIEWS_CPU_S = 0.5
# At most 0.01 % of the pixels may differ by more than one 8-bit level or 1e-4 in relative depth, or
# in coverage: pixel centres within 1e-5 of a triangle edge (float32 barycentrics) may fall into the
# triangle on the other side, which at a depth edge is another surface.
TOLERANCE = {"intensity": 1 / 255, "relative_depth": 1e-4, "differing_fraction": 1e-4, "coverage_fraction": 1e-4}


def _rectified_scenes(cards: list[Path], root: Path, sbs_order: str | None) -> list[dict[str, Any]]:
    """Run ``cards`` through filter..grade in a throwaway instance under ``root``; the views
    stage's inputs for each card that was graded (not failure)."""
    from dataclasses import replace

    from sqlalchemy import select

    from app import create_app
    from app.schema import upgrade
    from catalogue.ingest import ingest
    from catalogue.stereo_ingest import StereoOptions
    from core.db import db
    from core.models import Card
    from pipeline.stages.views import views_inputs
    from runs.loop import run_stage
    from runs.specs import available_stages

    data_dir = root / "data"
    app = create_app(
        {"SQLALCHEMY_DATABASE_URI": f"sqlite:///{root / 'bench.sqlite3'}", "KEYSTONE_DATA_DIR": str(data_dir)},
        instance_path=root / "instance",
    )
    scenes = []
    with app.app_context():
        upgrade(db.engine)
        ingest(
            cards,
            data_dir=data_dir,
            collection_name="bench-views",
            max_pixels=app.config["KEYSTONE_MAX_PIXELS"],
            stereo=StereoOptions(sbs_order=sbs_order),
        )
        specs = available_stages()
        for name in DEFAULT_STAGES:
            if name == "rectify":
                decide_as_stored()  # the flow rule: nothing is rectified while its orientation is undecided
            run_stage(replace(specs[name]), data_dir=data_dir, executor=None)
        for card in db.session.scalars(select(Card).order_by(Card.id)):
            inputs = views_inputs(card, {})
            if inputs.get("left") and inputs.get("disparity_left") and inputs.get("grade") not in (None, "failure"):
                scenes.append(
                    {
                        "card_id": card.id,
                        "card": card.source_name,
                        "width": card.width,
                        "content_hash": card.content_hash,
                        "inputs": inputs,
                    }
                )
        db.session.remove()
        db.engine.dispose()
    return scenes


def _run(task_fn: Any, scene: dict[str, Any], data_dir: Path, folder: str) -> tuple[float, Any]:
    from pipeline.records import CardTask

    task = CardTask(
        card_id=scene["card_id"],
        content_hash=scene["content_hash"],
        image_path="",
        work_dir=str(data_dir / "bench-views" / folder / str(scene["card_id"])),
        data_dir=str(data_dir),
        inputs=scene["inputs"],
    )
    clock = time.process_time()
    record = task_fn(task)
    return time.process_time() - clock, record


def _file_bytes(data_dir: Path, record: Any, names: list[str]) -> int:
    return sum((data_dir / record.artifacts[name]).stat().st_size for name in names)


def compare_rasterisers(data_dir: Path, old_record: Any, max_stretch_px: float) -> dict[str, Any]:
    """The old and the new rasteriser on the old run's v0 and corner cameras (module docstring)."""
    from PIL import Image

    from benchmarks.views_frozen import geometry as old
    from pipeline import views as new

    scene = json.loads((data_dir / old_record.artifacts["scene"]).read_text())
    grey = np.asarray(Image.open(data_dir / old_record.artifacts["v0"]))
    depth = np.load(data_dir / old_record.artifacts["v0_depth"])
    h, w = depth.shape
    cams = [new.Camera(np.array(v["rotation"]), np.array(v["translation"]), float(v["focal_px"]), w, h) for v in scene["views"]]
    gd = new.make_gd_image(grey, depth, cams[0].focal_px)
    worst_i = worst_d = 0.0
    coverage = differing = 0
    squared = []
    cracks_paper, cracks_stage, seconds_old, seconds_new = [], [], 0.0, 0.0
    for cam in cams[1:]:
        clock = time.process_time()
        before = old.reproject(old.GDImage(gd.intensity, gd.depth, gd.valid, gd.focal_px), cams[0], cam)
        seconds_old += time.process_time() - clock
        clock = time.process_time()
        after = new.reproject(gd, cams[0], cam)
        seconds_new += time.process_time() - clock
        both = ~before.hole & ~after.hole
        diff = np.abs(before.intensity - after.intensity)[both]
        worst_i = max(worst_i, float(diff.max(initial=0.0)))
        rel = np.abs(before.depth - after.depth)[both] / before.depth[both]
        worst_d = max(worst_d, float(rel.max(initial=0.0)))
        coverage += int((before.hole != after.hole).sum())
        differing += int(((diff > 1 / 255) | (rel > TOLERANCE["relative_depth"])).sum())
        squared.append(float(np.mean(diff.astype(np.float64) ** 2)) if diff.size else 0.0)
        cracks_paper.append(new.crack_fraction(after.hole))
        stage = new.reproject(gd, cams[0], cam, with_boundary=False, max_stretch_px=max_stretch_px)
        cracks_stage.append(new.crack_fraction(stage.hole))
    mse = statistics.fmean(squared)
    return {
        "max_abs_intensity": worst_i,
        "max_relative_depth": worst_d,
        "coverage_differs_fraction": coverage / (4 * h * w),
        "differing_fraction": differing / (4 * h * w),
        "psnr_db": round(10 * math.log10(1.0 / mse), 2) if mse > 0 else None,
        "reproject_cpu_seconds": {"old": round(seconds_old / 4, 4), "new": round(seconds_new / 4, 4)},
        "crack_fraction": {"paper_rule": round(max(cracks_paper), 6), "stage_rule": round(max(cracks_stage), 6)},
    }


def benchmark_views(
    cards: list[Path], repeats: int = 3, sbs_order: str | None = None, echo: Any = lambda _m: None
) -> dict[str, Any]:
    from benchmarks.views_frozen.stage import views_task as old_views_task
    from benchmarks.views_frozen.synthesis import ViewsStageParams as OldParams
    from pipeline.stages.views import views_task
    from pipeline.view_synthesis import ViewsStageParams

    root = Path(tempfile.mkdtemp(prefix="keystone-bench-views-"))
    try:
        echo(f"filter, rectify, disparity, grade on {len(cards)} cards")
        scenes = _rectified_scenes(cards, root, sbs_order)
        data_dir = root / "data"
        new_params, old_params = ViewsStageParams(), OldParams()
        tasks = {
            "old": functools.partial(old_views_task, params=old_params),
            "new": functools.partial(views_task, params=new_params),
        }
        rows = []
        for scene in scenes:
            echo(f"views: {scene['card']}")
            seconds: dict[str, list[float]] = {"old": [], "new": []}
            records: dict[str, Any] = {}
            for repeat in range(repeats):
                for version in ("old", "new") if repeat % 2 == 0 else ("new", "old"):
                    spent, records[version] = _run(tasks[version], scene, data_dir, version)
                    seconds[version].append(spent)
            row: dict[str, Any] = {
                "card": scene["card"],
                "width": scene["width"],
                "status": {v: records[v].status for v in records},
                "reason": {v: records[v].reason for v in records if records[v].reason},
            }
            if all(r.status == "done" for r in records.values()):
                old_record, new_record = records["old"], records["new"]
                names = ["v0", "v1", "v2", "v3", "v4"]
                row.update(
                    {
                        "cpu_seconds": {v: round(statistics.median(s), 4) for v, s in seconds.items()},
                        "size": new_record.metrics["size"],
                        "colour": new_record.metrics["colour"],
                        "viewer_bytes": {
                            "old": _file_bytes(data_dir, old_record, [*names, *(f"{n}_depth" for n in names)]),
                            "new": _file_bytes(
                                data_dir, new_record, [*(f"{n}_web" for n in names), *(f"{n}_mesh" for n in names)]
                            ),
                        },
                        "hole_fractions": {
                            "old": old_record.metrics["hole_fractions"],
                            "new": new_record.metrics["hole_fractions"],
                        },
                        "rasteriser": compare_rasterisers(data_dir, old_record, new_params.max_stretch_px),
                    }
                )
            rows.append(row)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    done = [r for r in rows if "cpu_seconds" in r]

    def median(values: list[float]) -> float | None:
        return round(statistics.median(values), 4) if values else None

    old_s = [r["cpu_seconds"]["old"] for r in done]
    new_s = [r["cpu_seconds"]["new"] for r in done]
    within = all(
        r["rasteriser"]["differing_fraction"] <= TOLERANCE["differing_fraction"]
        and r["rasteriser"]["coverage_differs_fraction"] <= TOLERANCE["coverage_fraction"]
        for r in done
    )
    summary = {
        "cards": len(rows),
        "compared": len(done),
        "repeats": repeats,
        "median_cpu_seconds": {"old": median(old_s), "new": median(new_s)},
        "max_cpu_seconds": {"old": max(old_s, default=None), "new": max(new_s, default=None)},
        "speed_up": round(statistics.median(o / n for o, n in zip(old_s, new_s)), 2) if done else None,
        "median_viewer_bytes": {v: median([r["viewer_bytes"][v] for r in done]) for v in ("old", "new")},
        "max_viewer_bytes": {v: max((r["viewer_bytes"][v] for r in done), default=None) for v in ("old", "new")},
        "max_crack_fraction": {
            k: max((r["rasteriser"]["crack_fraction"][k] for r in done), default=None) for k in ("paper_rule", "stage_rule")
        },
        "rasteriser_max_differing_fraction": max((r["rasteriser"]["differing_fraction"] for r in done), default=None),
        "rasteriser_max_abs_intensity": max((r["rasteriser"]["max_abs_intensity"] for r in done), default=None),
        "rasteriser_max_relative_depth": max((r["rasteriser"]["max_relative_depth"] for r in done), default=None),
        "rasteriser_within_tolerance": within,
        "tolerance": TOLERANCE,
        "target_views_cpu_seconds": TARGET_VIEWS_CPU_S,
    }
    return {"results": rows, "summary": summary}


@click.command("views")
@click.option(
    "--shared-data",
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder with the real cards (../shared/data) [default: found next to the checkout].",
)
@click.option("--synthetic", is_flag=True, help="Use the Motorcycle card at 760, 1400 and 3000 px instead.")
@click.option("--limit", type=click.IntRange(1), help="Only the first N cards.")
@click.option(
    "--repeats",
    type=click.IntRange(1),
    default=3,
    show_default=True,
    help="Runs of each version per card (the median counts; order alternates).",
)
@click.option(
    "--sbs-order",
    type=click.Choice(["cross", "parallel"]),
    default="parallel",
    show_default=True,
    help="Eye order of side-by-side files, as keystone ingest --sbs-order.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_views_command(
    shared_data: Path | None, synthetic: bool, limit: int | None, repeats: int, sbs_order: str, as_json: bool
) -> None:
    """CPU seconds per card of the views stage, old code against new in one run, and the output difference."""
    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = [] if synthetic or shared_data is None else real_cards(shared_data)
    if not cards:
        cards = synthetic_cards(Path(tempfile.mkdtemp(prefix="keystone-bench-cards-")))
    cards = cards[:limit] if limit else cards
    document = benchmark_views(cards, repeats, sbs_order, echo=lambda m: click.echo(m, err=True))
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    click.echo(f"{'card':<44} {'size':>9} {'old s':>7} {'new s':>7} {'old kB':>8} {'new kB':>8} {'max dI':>9} {'cracks':>15}")
    for row in document["results"]:
        if "cpu_seconds" not in row:
            click.echo(f"{row['card'][:44]:<44} {row['status']} {row['reason']}")
            continue
        r = row["rasteriser"]
        click.echo(
            f"{row['card'][:44]:<44} {row['size'][0]:>4}x{row['size'][1]:<4} {row['cpu_seconds']['old']:7.3f} "
            f"{row['cpu_seconds']['new']:7.3f} {row['viewer_bytes']['old'] / 1e3:8.0f} "
            f"{row['viewer_bytes']['new'] / 1e3:8.0f} {r['max_abs_intensity']:9.2e} "
            f"{r['crack_fraction']['paper_rule']:7.4f}>{r['crack_fraction']['stage_rule']:.4f}"
        )
    s = document["summary"]
    click.echo(
        f"median CPU-s a card: old {s['median_cpu_seconds']['old']}, new {s['median_cpu_seconds']['new']} "
        f"(x{s['speed_up']}; target <= {TARGET_VIEWS_CPU_S}); viewer bytes a card: old "
        f"{s['median_viewer_bytes']['old']}, new {s['median_viewer_bytes']['new']}; rasteriser within "
        f"tolerance: {s['rasteriser_within_tolerance']}"
    )

"""``keystone bench views``: CPU seconds per card of the views stage, the current code against the
code before the vectorised rasteriser and the colour views (:data:`BASELINE_COMMIT`), side by side
in one run, with what the change did to the output.

The old code is that commit's ``pipeline/``, taken from git (``git archive``) into a temporary
folder and run in a subprocess whose ``pipeline`` package is that copy (:class:`OldCode`); no copy
of old code is kept in the repository. Where git or the commit is not there (an installed package,
a shallow clone: ``git fetch --unshallow`` brings the history), the benchmark says so and times the
current code alone (``--baseline`` names another commit).

The cards are ingested into a throwaway instance (SQLite, its own data dir) and run through filter,
rectify, disparity and grade (``runs.loop.run_stage``, inline), so the views stage sees real rectified
views and disparities. Then, per card and repeat, the old and the new ``views_task`` run one after the
other (order alternating between repeats), each timed by ``time.process_time()`` of the process it
runs in (the old one in its subprocess, the new one here).

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

import io
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np

from benchmarks.pipeline_cost import DEFAULT_STAGES, decide_as_stored, real_cards, synthetic_cards

TARGET_VIEWS_CPU_S = 0.5
# The views stage before the vectorised rasteriser and the colour views: the "old" of this benchmark.
BASELINE_COMMIT = "7f31cd2996f1864727152436dd3a35eb085bf141"
REPO_ROOT = Path(__file__).resolve().parents[1]
# At most 0.01 % of the pixels may differ by more than one 8-bit level or 1e-4 in relative depth, or
# in coverage: pixel centres within 1e-5 of a triangle edge (float32 barycentrics) may fall into the
# triangle on the other side, which at a depth edge is another surface.
TOLERANCE = {"intensity": 1 / 255, "relative_depth": 1e-4, "differing_fraction": 1e-4, "coverage_fraction": 1e-4}


def checkout_baseline(commit: str, into: Path, repo: Path = REPO_ROOT) -> tuple[Path | None, str | None]:
    """``commit``'s ``pipeline/`` extracted under ``into``: ``(into, None)``, or ``(None, why not)``
    when git, a checkout or the commit is not there."""
    git = shutil.which("git")
    if git is None:
        return None, "git is not installed"
    found = subprocess.run(
        [git, "-C", str(repo), "rev-parse", "--verify", "--quiet", f"{commit}^{{commit}}"], capture_output=True, text=True
    )
    if found.returncode != 0:
        if "not a git repository" in found.stderr:
            return None, f"{repo} is not a git checkout"
        shallow = subprocess.run([git, "-C", str(repo), "rev-parse", "--is-shallow-repository"], capture_output=True, text=True)
        hint = " (this is a shallow clone: git fetch --unshallow brings the history)" if shallow.stdout.strip() == "true" else ""
        return None, f"commit {commit} is not in this checkout{hint}"
    archive = subprocess.run([git, "-C", str(repo), "archive", "--format=tar", commit, "pipeline"], capture_output=True)
    if archive.returncode != 0:
        return None, f"git archive {commit} pipeline failed: {archive.stderr.decode(errors='replace').strip()}"
    into.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(into, filter="data")
    return into, None


# Runs in the subprocess whose ``pipeline`` is the old commit's: one JSON request a line on stdin,
# one reply a line on stdout after REPLY (anything else the old code prints is passed over).
OLD_WORKER = r"""
import json, sys, time
from pathlib import Path
import numpy as np
import pipeline
if not Path(pipeline.__file__).resolve().is_relative_to(Path.cwd().resolve()):
    sys.exit(f"the old code's pipeline did not load: {pipeline.__file__}")
import pipeline.inpainting, PIL.Image  # imported lazily by the stage: not part of its time
from pipeline import views as geometry
from pipeline.records import CardTask
from pipeline.stages.views import views_task
from pipeline.view_synthesis import ViewsStageParams

params = ViewsStageParams()
for line in sys.stdin:
    request = json.loads(line)
    if request["op"] == "views":
        task = CardTask(**request["task"])
        clock = time.process_time()
        record = views_task(task, params)
        spent = time.process_time() - clock
        reply = {"seconds": spent, "status": record.status, "reason": record.reason,
                 "metrics": record.metrics, "artifacts": record.artifacts}
    else:
        arrays = np.load(request["gd"])
        gd = geometry.GDImage(arrays["intensity"], arrays["depth"], arrays["valid"], float(arrays["focal_px"]))
        cams = [geometry.Camera(np.array(c["rotation"]), np.array(c["translation"]), float(c["focal_px"]),
                                int(c["width"]), int(c["height"])) for c in request["cameras"]]
        views, spent = {}, 0.0
        for i, cam in enumerate(cams[1:]):
            clock = time.process_time()
            view = geometry.reproject(gd, cams[0], cam)
            spent += time.process_time() - clock
            views.update({f"intensity{i}": view.intensity, f"depth{i}": view.depth, f"hole{i}": view.hole})
        np.savez(request["out"], **views)
        reply = {"seconds": spent}
    print("REPLY " + json.dumps(reply, default=float), flush=True)
"""


@dataclass(frozen=True)
class OldRecord:
    """The parts of the old code's StageRecord this benchmark reads."""

    status: str
    reason: str | None
    metrics: dict[str, Any] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)


class OldCode:
    """The old commit's views stage and rasteriser, in a subprocess whose ``pipeline`` is ``tree``."""

    def __init__(self, tree: Path) -> None:
        self.tree = tree
        self.process = subprocess.Popen(
            [sys.executable, "-c", OLD_WORKER],
            cwd=tree,
            env={**_environment(), "PYTHONPATH": str(tree)},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def _ask(self, request: dict[str, Any]) -> dict[str, Any]:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()
        for line in self.process.stdout:
            if line.startswith("REPLY "):
                reply: dict[str, Any] = json.loads(line[len("REPLY ") :])
                return reply
        raise RuntimeError(f"the old code's process ended (exit status {self.process.wait()})")

    def views(self, task: Any) -> tuple[float, OldRecord]:
        """The old ``views_task`` on ``task`` (a CardTask): CPU seconds and its record."""
        fields = ("card_id", "content_hash", "image_path", "work_dir", "data_dir", "inputs")
        reply = self._ask({"op": "views", "task": {name: getattr(task, name) for name in fields}})
        return reply["seconds"], OldRecord(reply["status"], reply["reason"], reply["metrics"] or {}, reply["artifacts"] or {})

    def reproject(self, gd: Any, cameras: list[dict[str, Any]], scratch: Path) -> tuple[float, list[dict[str, np.ndarray]]]:
        """The old ``reproject`` of ``gd`` from ``cameras[0]`` into each other camera: CPU seconds, views."""
        source, out = scratch / "gd.npz", scratch / "old_views.npz"
        np.savez(source, intensity=gd.intensity, depth=gd.depth, valid=gd.valid, focal_px=gd.focal_px)
        reply = self._ask({"op": "reproject", "gd": str(source), "cameras": cameras, "out": str(out)})
        with np.load(out) as arrays:
            views = [{k: arrays[f"{k}{i}"] for k in ("intensity", "depth", "hole")} for i in range(len(cameras) - 1)]
        return reply["seconds"], views

    def close(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()
        try:
            self.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()


def _environment() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


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


def _run(version: str, scene: dict[str, Any], data_dir: Path, old: OldCode | None, params: Any) -> tuple[float, Any]:
    """Run the ``old`` or ``new`` views task on one scene: CPU seconds of its own process, its record."""
    from pipeline.records import CardTask
    from pipeline.stages.views import views_task

    task = CardTask(
        card_id=scene["card_id"],
        content_hash=scene["content_hash"],
        image_path="",
        work_dir=str(data_dir / "bench-views" / version / str(scene["card_id"])),
        data_dir=str(data_dir),
        inputs=scene["inputs"],
    )
    if version == "old":
        assert old is not None
        return old.views(task)
    clock = time.process_time()
    record = views_task(task, params)
    return time.process_time() - clock, record


def _file_bytes(data_dir: Path, record: Any, names: list[str]) -> int:
    return sum((data_dir / record.artifacts[name]).stat().st_size for name in names)


def compare_rasterisers(data_dir: Path, old_record: Any, max_stretch_px: float, old: OldCode, scratch: Path) -> dict[str, Any]:
    """The old and the new rasteriser on the old run's v0 and corner cameras (module docstring)."""
    from PIL import Image

    from pipeline import views as new

    scene = json.loads((data_dir / old_record.artifacts["scene"]).read_text())
    grey = np.asarray(Image.open(data_dir / old_record.artifacts["v0"]))
    depth = np.load(data_dir / old_record.artifacts["v0_depth"])
    h, w = depth.shape
    cameras = [{**v, "width": w, "height": h} for v in scene["views"]]
    cams = [new.Camera(np.array(v["rotation"]), np.array(v["translation"]), float(v["focal_px"]), w, h) for v in cameras]
    gd = new.make_gd_image(grey, depth, cams[0].focal_px)
    seconds_old, old_views = old.reproject(gd, cameras, scratch)
    worst_i = worst_d = 0.0
    coverage = differing = 0
    squared = []
    cracks_paper, cracks_stage, seconds_new = [], [], 0.0
    for cam, before in zip(cams[1:], old_views):
        clock = time.process_time()
        after = new.reproject(gd, cams[0], cam)
        seconds_new += time.process_time() - clock
        both = ~before["hole"] & ~after.hole
        diff = np.abs(before["intensity"] - after.intensity)[both]
        worst_i = max(worst_i, float(diff.max(initial=0.0)))
        rel = np.abs(before["depth"] - after.depth)[both] / before["depth"][both]
        worst_d = max(worst_d, float(rel.max(initial=0.0)))
        coverage += int((before["hole"] != after.hole).sum())
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
    cards: list[Path],
    repeats: int = 3,
    sbs_order: str | None = None,
    echo: Any = lambda _m: None,
    baseline: str = BASELINE_COMMIT,
) -> dict[str, Any]:
    """Time the views stage per card, the ``baseline`` commit's code against the current code, and
    compare their output; the current code alone when the baseline cannot be had (it says why)."""
    from pipeline.view_synthesis import ViewsStageParams

    root = Path(tempfile.mkdtemp(prefix="keystone-bench-views-"))
    old: OldCode | None = None
    try:
        tree, unavailable = checkout_baseline(baseline, root / "baseline")
        if unavailable:
            echo(f"old code unavailable: {unavailable}; timing the current code only")
        echo(f"filter, rectify, disparity, grade on {len(cards)} cards")
        scenes = _rectified_scenes(cards, root, sbs_order)
        data_dir = root / "data"
        new_params = ViewsStageParams()
        old = OldCode(tree) if tree is not None else None
        versions = ("old", "new") if old is not None else ("new",)
        rows = []
        for scene in scenes:
            echo(f"views: {scene['card']}")
            seconds: dict[str, list[float]] = {v: [] for v in versions}
            records: dict[str, Any] = {}
            for repeat in range(repeats):
                for version in versions if repeat % 2 == 0 else versions[::-1]:
                    spent, records[version] = _run(version, scene, data_dir, old, new_params)
                    seconds[version].append(spent)
            row: dict[str, Any] = {
                "card": scene["card"],
                "width": scene["width"],
                "status": {v: records[v].status for v in records},
                "reason": {v: records[v].reason for v in records if records[v].reason},
            }
            if all(r.status == "done" for r in records.values()):
                names = ["v0", "v1", "v2", "v3", "v4"]
                new_record = records["new"]
                row.update(
                    {
                        "cpu_seconds": {v: round(statistics.median(s), 4) for v, s in seconds.items()},
                        "size": new_record.metrics["size"],
                        "colour": new_record.metrics["colour"],
                        "viewer_bytes": {
                            "new": _file_bytes(
                                data_dir, new_record, [*(f"{n}_web" for n in names), *(f"{n}_mesh" for n in names)]
                            )
                        },
                        "hole_fractions": {v: records[v].metrics["hole_fractions"] for v in versions},
                    }
                )
                if old is not None:
                    old_record = records["old"]
                    row["viewer_bytes"]["old"] = _file_bytes(data_dir, old_record, [*names, *(f"{n}_depth" for n in names)])
                    row["rasteriser"] = compare_rasterisers(data_dir, old_record, new_params.max_stretch_px, old, root)
            rows.append(row)
    finally:
        if old is not None:
            old.close()
        shutil.rmtree(root, ignore_errors=True)
    timed = [r for r in rows if "cpu_seconds" in r]
    compared = [r for r in timed if "rasteriser" in r]

    def median(values: list[float]) -> float | None:
        return round(statistics.median(values), 4) if values else None

    def seconds_of(version: str) -> list[float]:
        return [r["cpu_seconds"][version] for r in timed if version in r["cpu_seconds"]]

    old_s, new_s = seconds_of("old"), seconds_of("new")
    within = all(
        r["rasteriser"]["differing_fraction"] <= TOLERANCE["differing_fraction"]
        and r["rasteriser"]["coverage_differs_fraction"] <= TOLERANCE["coverage_fraction"]
        for r in compared
    )

    def largest(values: Any) -> Any:
        return max(values, default=None)

    summary = {
        "baseline": {"commit": baseline, "available": tree is not None, "unavailable_because": unavailable},
        "cards": len(rows),
        "timed": len(timed),
        "compared": len(compared),
        "repeats": repeats,
        "median_cpu_seconds": {"old": median(old_s), "new": median(new_s)},
        "max_cpu_seconds": {"old": largest(old_s), "new": largest(new_s)},
        "speed_up": round(statistics.median(o / n for o, n in zip(old_s, new_s)), 2) if old_s and new_s else None,
        "median_viewer_bytes": {
            v: median([r["viewer_bytes"][v] for r in timed if v in r["viewer_bytes"]]) for v in ("old", "new")
        },
        "max_viewer_bytes": {v: largest(r["viewer_bytes"][v] for r in timed if v in r["viewer_bytes"]) for v in ("old", "new")},
        "max_crack_fraction": {
            k: largest(r["rasteriser"]["crack_fraction"][k] for r in compared) for k in ("paper_rule", "stage_rule")
        },
        "rasteriser_max_differing_fraction": largest(r["rasteriser"]["differing_fraction"] for r in compared),
        "rasteriser_max_abs_intensity": largest(r["rasteriser"]["max_abs_intensity"] for r in compared),
        "rasteriser_max_relative_depth": largest(r["rasteriser"]["max_relative_depth"] for r in compared),
        "rasteriser_within_tolerance": within if compared else None,
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
@click.option(
    "--baseline",
    default=BASELINE_COMMIT,
    show_default=True,
    help="Commit whose pipeline/ is the old code (taken from git; without it the current code is timed alone).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_views_command(
    shared_data: Path | None, synthetic: bool, limit: int | None, repeats: int, sbs_order: str, baseline: str, as_json: bool
) -> None:
    """CPU seconds per card of the views stage, old code (a recorded commit) against new in one run, and the output difference."""
    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = [] if synthetic or shared_data is None else real_cards(shared_data)
    if not cards:
        cards = synthetic_cards(Path(tempfile.mkdtemp(prefix="keystone-bench-cards-")))
    cards = cards[:limit] if limit else cards
    document = benchmark_views(cards, repeats, sbs_order, echo=lambda m: click.echo(m, err=True), baseline=baseline)
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return

    def cell(values: dict[str, Any], key: str, width: int, decimals: int, scale: float = 1.0) -> str:
        value = values.get(key)
        return f"{value / scale:{width}.{decimals}f}" if value is not None else f"{'-':>{width}}"

    click.echo(f"{'card':<44} {'size':>9} {'old s':>7} {'new s':>7} {'old kB':>8} {'new kB':>8} {'max dI':>9} {'cracks':>15}")
    for row in document["results"]:
        if "cpu_seconds" not in row:
            click.echo(f"{row['card'][:44]:<44} {row['status']} {row['reason']}")
            continue
        r = row.get("rasteriser")
        raster = (
            f"{r['max_abs_intensity']:9.2e} {r['crack_fraction']['paper_rule']:7.4f}>{r['crack_fraction']['stage_rule']:.4f}"
            if r
            else ""
        )
        click.echo(
            f"{row['card'][:44]:<44} {row['size'][0]:>4}x{row['size'][1]:<4} {cell(row['cpu_seconds'], 'old', 7, 3)} "
            f"{cell(row['cpu_seconds'], 'new', 7, 3)} {cell(row['viewer_bytes'], 'old', 8, 0, 1e3)} "
            f"{cell(row['viewer_bytes'], 'new', 8, 0, 1e3)} {raster}".rstrip()
        )
    s = document["summary"]
    if not s["baseline"]["available"]:
        click.echo(f"old code ({s['baseline']['commit']}) unavailable: {s['baseline']['unavailable_because']}")
    click.echo(
        f"median CPU-s a card: old {s['median_cpu_seconds']['old']}, new {s['median_cpu_seconds']['new']} "
        f"(x{s['speed_up']}; target <= {TARGET_VIEWS_CPU_S}); viewer bytes a card: old "
        f"{s['median_viewer_bytes']['old']}, new {s['median_viewer_bytes']['new']}; rasteriser within "
        f"tolerance: {s['rasteriser_within_tolerance']}"
    )

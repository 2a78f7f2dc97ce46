"""``keystone bench grade``: does the automatic grade follow the true error of the depth it grades?

Antique cards are made from scenes with ground-truth disparity (Motorcycle from scikit-image,
and Tsukuba / Adirondack Q from ``../shared/data/stereo_gt`` when present, or MiddEval3 folders
given with ``--scene``) by the project's card simulator (:func:`simulation.cards.make_card_from_pair`)
at a range of degradations (:data:`CASES`): fading, scratches, blur, JPEG, vertical offset and
rotation between the halves, low texture, swapped eyes, and a combination. Each card goes through
the real stage tasks (filter, rectify, disparity, grade: the functions ``keystone run`` calls,
with default parameters or the thresholds given) in a throwaway folder.

The true error: every valid ground-truth pixel ``(x, y, d)`` of the source left view is mapped
to the scan by the card's placement (left eye ``A_l (x, y, 1)``, right eye ``A_r (x - d, y, 1)``),
into each crop by the boxes rectification used, and through its homographies ``H_l``/``H_r`` into
the rectified views, where the true disparity is ``x_left - x_right`` in rectified-view pixels.
``true_bad2`` is the percentage of those points where the pipeline's left disparity (sampled at
the nearest pixel, rescaled if the map is at a working size) is more than 2 px off, a missing
disparity counting as off (full coverage). When the rectified left view shows the right eye
(eyes swapped and not caught), the correct disparity is the reversed one, ``-d_true + c`` with
the constant ``c`` most favourable to the pipeline (median of ``d + d_true``): its depth is
reversed whatever its matching. A card the pipeline stops (culled, rectification or disparity
failed) delivers no depth: ``grade`` is the stage's status and ``true_bad2`` 100.

Summary: Spearman's rank correlation between the grade level (few 0, some 1, failure 2) and
``true_bad2`` over the graded cards (and over all cards, stopped ones as failure), and the median
``true_bad2`` per grade; targets: Spearman >= 0.6 and few < some < failure.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

from benchmarks.disparity import Scene, builtin_scenes, load_middeval3
from simulation.cards import Degradation, make_card_from_pair

TARGET_SPEARMAN = 0.6
BAD_PX = 2.0  # the "bad-2" tolerance, rectified-view px
LEVEL = {"few": 0, "some": 1, "failure": 2}

# (case name, degradation): each a kind of damage antique cards show, at a mild and a strong level.
CASES: tuple[tuple[str, Degradation], ...] = (
    ("clean", Degradation()),
    ("fade-0.5", Degradation(fade=0.5)),
    ("fade-0.9", Degradation(fade=0.9)),
    ("scratches-2", Degradation(scratches=2)),
    ("scratches-8", Degradation(scratches=8)),
    ("blur-2", Degradation(blur_px=2.0)),
    ("blur-5", Degradation(blur_px=5.0)),
    ("jpeg-30", Degradation(jpeg_quality=30)),
    ("jpeg-8", Degradation(jpeg_quality=8)),
    ("offset-3px", Degradation(dy_px=3.0)),
    ("offset-10px", Degradation(dy_px=10.0)),
    ("rotation-1deg", Degradation(rotation_deg=1.0)),
    ("rotation-4deg", Degradation(rotation_deg=4.0)),
    ("low-texture-0.7", Degradation(low_texture=0.7)),
    ("low-texture-1.0", Degradation(low_texture=1.0)),
    ("swapped-eyes", Degradation(swap=True)),
    ("combined", Degradation(fade=0.6, blur_px=2.5, jpeg_quality=25, dy_px=2.0, scratches=2)),
    (
        "combined-heavy",
        Degradation(fade=0.8, blur_px=4.0, jpeg_quality=12, dy_px=5.0, rotation_deg=1.5, scratches=4, low_texture=0.6),
    ),
)
QUICK_CASES = ("clean", "blur-5", "offset-10px", "swapped-eyes")


@dataclass(frozen=True)
class CardRun:
    """One card through the pipeline: what each stage recorded, and where its files are."""

    records: dict[str, Any]  # stage -> StageRecord
    data_dir: Path


def run_pipeline(card_image: np.ndarray, jpeg_quality: int, folder: Path, grade_params: Any = None) -> CardRun:
    """The stage tasks of ``keystone run`` on one card saved as a JPEG scan in ``folder``."""
    from pipeline.io import write_jpeg

    folder.mkdir(parents=True, exist_ok=True)
    scan = folder / "card.jpg"
    write_jpeg(scan, card_image, quality=jpeg_quality)
    return run_pipeline_on_scan(scan, folder, grade_params)


def run_pipeline_on_scan(scan: Path, folder: Path, grade_params: Any = None) -> CardRun:
    """The stage tasks of ``keystone run`` (filter, rectify, disparity, grade; default parameters,
    or ``grade_params``) on one scan, writing their artifacts under ``folder``."""
    from pipeline.filter import FilterParams
    from pipeline.grading import GradeParams
    from pipeline.records import CardTask
    from pipeline.rectify import RectifyParams
    from pipeline.stages.disparity import DisparityStageParams, disparity_task
    from pipeline.stages.filter import filter_task
    from pipeline.stages.grade import grade_task
    from pipeline.stages.rectify import rectify_task

    folder.mkdir(parents=True, exist_ok=True)
    records: dict[str, Any] = {}

    def task(stage: str, inputs: dict[str, Any]) -> CardTask:
        work = folder / stage
        work.mkdir(exist_ok=True)
        return CardTask(
            card_id=1, content_hash="bench", image_path=str(scan), work_dir=str(work), data_dir=str(folder), inputs=inputs
        )

    records["filter"] = filtered = filter_task(task("filter", {}), FilterParams())
    if filtered.status != "done" or filtered.outcome == "culled":
        return CardRun(records, folder)
    boxes = {"left_box": filtered.metrics["left_box"], "right_box": filtered.metrics["right_box"]}
    records["rectify"] = rectified = rectify_task(task("rectify", boxes), RectifyParams())
    if rectified.status == "failed":
        return CardRun(records, folder)
    camera = rectified.metrics.get("K") or [[None]]
    records["disparity"] = disparity = disparity_task(
        task(
            "disparity",
            {
                "left": rectified.artifacts["left"],
                "right": rectified.artifacts["right"],
                "disparity_range": [rectified.metrics.get("disparity_min"), rectified.metrics.get("disparity_max")],
                "focal_px": camera[0][0],
            },
        ),
        DisparityStageParams(),
    )
    if disparity.status != "done":
        return CardRun(records, folder)
    metrics = {name: records[name].metrics for name in ("filter", "rectify", "disparity")}
    records["grade"] = grade_task(
        task(
            "grade",
            {
                "left": rectified.artifacts["left"],
                "right": rectified.artifacts["right"],
                "disparity_left": disparity.artifacts["disparity_left"],
                "disparity_right": disparity.artifacts["disparity_right"],
                "confidence": disparity.artifacts["confidence"],
                "metrics": metrics,
            },
        ),
        grade_params or GradeParams(),
    )
    return CardRun(records, folder)


def _apply(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N, 2)`` points through a 3x3 homography (column vectors, ``x' ~ H x``)."""
    homogeneous = np.column_stack([points, np.ones(len(points))]) @ np.asarray(H, float).T
    return homogeneous[:, :2] / homogeneous[:, 2:3]


@dataclass(frozen=True)
class TruePoints:
    """Ground truth mapped into the rectified left view: integer pixels ``col``, ``row`` (on the
    photograph) and the geometric disparity ``d_true`` there (rectified-view px,
    ``x_left - x_right`` between the views as shown); ``left_eye_shown_left``: whether the
    rectified left view shows the left eye."""

    col: np.ndarray
    row: np.ndarray
    d_true: np.ndarray
    left_eye_shown_left: bool


def true_points(run: CardRun, truth: dict[str, Any], gt: np.ndarray, stride: int = 2) -> TruePoints:
    """Every ``stride``-th valid ground-truth pixel of the source left view, mapped through the
    card's placement, the crops rectification used and its homographies (module docstring)."""
    rectified = run.records["rectify"]
    camera = json.loads((run.data_dir / rectified.artifacts["rectification"]).read_text())
    H_l, H_r = np.asarray(camera["H_l"], float), np.asarray(camera["H_r"], float)
    boxes = [camera["left_box"], camera["right_box"]]  # card's left / right crops, as rectified
    ys, xs = np.nonzero(np.isfinite(gt))
    keep = (ys % stride == 0) & (xs % stride == 0)
    ys, xs = ys[keep].astype(float), xs[keep].astype(float)
    d = gt[ys.astype(int), xs.astype(int)].astype(float)
    A_l, A_r = np.asarray(truth["left_affine"], float), np.asarray(truth["right_affine"], float)
    eye_point = {
        "left": np.column_stack([xs, ys, np.ones_like(xs)]) @ A_l.T,
        "right": np.column_stack([xs - d, ys, np.ones_like(xs)]) @ A_r.T,
    }
    # Which eye each crop shows: the card's left photo is the right eye when the eyes are swapped.
    eye_of_box = ["right", "left"] if truth.get("halves_swapped") else ["left", "right"]
    shown_left_box = 1 if camera.get("swapped") else 0  # H_l maps the right crop when rectify swapped
    shown_right_box = 1 - shown_left_box
    shown_left_eye, shown_right_eye = eye_of_box[shown_left_box], eye_of_box[shown_right_box]
    q_left = _apply(H_l, eye_point[shown_left_eye] - np.asarray(boxes[shown_left_box][:2], float))
    q_right = _apply(H_r, eye_point[shown_right_eye] - np.asarray(boxes[shown_right_box][:2], float))
    d_true = q_left[:, 0] - q_right[:, 0]
    view = cv2.imread(str(run.data_dir / rectified.artifacts["left"]), cv2.IMREAD_GRAYSCALE)
    h, w = view.shape
    col, row = np.rint(q_left[:, 0]).astype(int), np.rint(q_left[:, 1]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    col, row, d_true = col[inside], row[inside], d_true[inside]
    on_photo = view[row, col] > 0
    return TruePoints(col[on_photo], row[on_photo], d_true[on_photo], shown_left_eye == "left")


def true_bad2(run: CardRun, truth: dict[str, Any], gt: np.ndarray, stride: int = 2) -> dict[str, Any]:
    """Percent of the :func:`true_points` where the pipeline's left disparity is more than 2
    rectified-view px from the true one (see the module docstring), with the number of points
    compared and whether the rectified left view shows the left eye."""
    points = true_points(run, truth, gt, stride)
    if points.col.size == 0:
        return {"true_bad2": 100.0, "points": 0, "left_eye_shown_left": points.left_eye_shown_left}
    rectified, disparity = run.records["rectify"], run.records["disparity"]
    h, w = cv2.imread(str(run.data_dir / rectified.artifacts["left"]), cv2.IMREAD_GRAYSCALE).shape
    disp = np.load(run.data_dir / disparity.artifacts["disparity_left"])
    mh, mw = disp.shape  # a map at a working size: sample it there, scale its px to view px
    d_pipe = disp[np.minimum(points.row * mh // h, mh - 1), np.minimum(points.col * mw // w, mw - 1)]
    d_pipe = d_pipe.astype(float) * (w / mw)
    d_true = points.d_true
    if not points.left_eye_shown_left:  # depth reversed: the right disparity is the mirrored one
        finite = np.isfinite(d_pipe)
        offset = float(np.median(d_pipe[finite] + d_true[finite])) if finite.any() else 0.0
        d_true = offset - d_true
    error = np.abs(np.where(np.isfinite(d_pipe), d_pipe, np.inf) - d_true)
    return {
        "true_bad2": round(100.0 * float(np.mean(error > BAD_PX)), 3),
        "points": int(points.col.size),
        "left_eye_shown_left": points.left_eye_shown_left,
    }


def _ranks(values: Sequence[float]) -> np.ndarray:
    """Ranks 1..n with ties averaged."""
    array = np.asarray(values, float)
    order = np.argsort(array, kind="mergesort")
    ranks = np.empty(len(array))
    ranks[order] = np.arange(1, len(array) + 1)
    for value in np.unique(array):
        tied = array == value
        ranks[tied] = ranks[tied].mean()
    return ranks


def spearman(a: Sequence[float], b: Sequence[float]) -> float | None:
    """Spearman's rank correlation (Pearson on tie-averaged ranks); ``None`` when either side is constant."""
    if len(a) < 3:
        return None
    ra, rb = _ranks(a), _ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return None
    return round(float(np.corrcoef(ra, rb)[0, 1]), 4)


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    graded = [r for r in results if r["grade"] in LEVEL]
    medians = {}
    counts = {}
    for name in LEVEL:
        errors = [r["true_bad2"] for r in graded if r["grade"] == name]
        counts[name] = len(errors)
        medians[name] = round(statistics.median(errors), 3) if errors else None
    present = [medians[g] for g in LEVEL if medians[g] is not None]
    everything = [(LEVEL.get(r["grade"], 2), r["true_bad2"]) for r in results]
    rho = spearman([LEVEL[r["grade"]] for r in graded], [r["true_bad2"] for r in graded])
    return {
        "cards": len(results),
        "graded": len(graded),
        "stopped": len(results) - len(graded),
        "counts": counts,
        "median_true_bad2": medians,
        "spearman": rho,
        "spearman_all_cards": spearman([level for level, _ in everything], [error for _, error in everything]),
        "ordered": len(present) == 3 and present[0] < present[1] < present[2],
        "targets": {"spearman": TARGET_SPEARMAN, "median_order": "few < some < failure"},
        "meets_targets": bool(
            rho is not None and rho >= TARGET_SPEARMAN and len(present) == 3 and present[0] < present[1] < present[2]
        ),
    }


_NOT_MEASUREMENTS = (
    "reasons",
    "notes",
    "checks",
    "nearest",
    "levels",
    "deciding",
    "uncertainty_reason",
    "thresholds_hash",
    "uncertainty",
)


def outcome_of(run: CardRun) -> dict[str, Any]:
    """The grade of a card run: ``grade`` (or, for a card the pipeline stopped, ``culled`` /
    ``"<stage> failed"``), ``uncertainty``, ``reason``, ``nearest``, ``deciding`` and the
    ``measurements`` (``None`` when not graded)."""
    graded = run.records.get("grade")
    if graded is None or graded.status != "done":
        stopped = next(name for name in ("grade", "disparity", "rectify", "filter") if name in run.records)
        record = run.records[stopped]
        status = "culled" if stopped == "filter" and record.outcome == "culled" else f"{stopped} {record.status}"
        return {
            "grade": status,
            "uncertainty": None,
            "reason": record.reason,
            "nearest": None,
            "deciding": None,
            "measurements": None,
        }
    return {
        "grade": graded.outcome,
        "uncertainty": graded.metrics["uncertainty"],
        "reason": graded.reason,
        "nearest": graded.metrics.get("nearest"),
        "deciding": graded.metrics.get("deciding"),
        "measurements": {k: v for k, v in graded.metrics.items() if k not in _NOT_MEASUREMENTS},
    }


def benchmark_grade(
    scenes: list[Scene],
    cases: Sequence[tuple[str, Degradation]] = CASES,
    seed: int = 0,
    grade_params: Any = None,
    keep: Path | None = None,
) -> dict[str, Any]:
    """Every scene x case through the pipeline; the document ``keystone bench grade --json`` prints.
    The cards' files go to ``keep`` (kept) or to a temporary folder removed at the end."""
    if keep is None:
        with tempfile.TemporaryDirectory(prefix="keystone-bench-grade-") as scratch:
            return benchmark_grade(scenes, cases, seed, grade_params, keep=Path(scratch))
    results = []
    clock = time.perf_counter()
    root = Path(keep)
    for scene_index, scene in enumerate(scenes):
        for case_index, (case, degradation) in enumerate(cases):
            started = time.perf_counter()
            card = make_card_from_pair(
                scene.left,
                scene.right,
                seed=1000 * seed + 37 * scene_index + case_index,
                degradation=degradation,
                name=f"{scene.name}-{case}",
            )
            folder = root / f"{scene.name}-{case}"
            run = run_pipeline(card.image, degradation.jpeg_quality or 92, folder, grade_params)
            entry: dict[str, Any] = {"scene": scene.name, "case": case, **outcome_of(run)}
            if entry["measurements"] is not None:
                entry.update(true_bad2(run, card.truth, scene.gt))
            else:
                entry["true_bad2"] = 100.0
            entry["seconds"] = round(time.perf_counter() - started, 3)
            results.append(entry)
    return {
        "results": results,
        "summary": {**summarise(results), "seconds": round(time.perf_counter() - clock, 2)},
        "units": "true_bad2: percent of valid ground truth more than 2 rectified-view px off, missing = off",
    }


def _load_scenes(scene_dirs: Sequence[Path], quick: bool) -> list[Scene]:
    if scene_dirs:
        return [load_middeval3(folder) for folder in scene_dirs]
    scenes = builtin_scenes()
    return scenes[:1] if quick else scenes


@click.command("grade")
@click.option(
    "--scene",
    "scene_dirs",
    multiple=True,
    type=click.Path(path_type=Path, file_okay=False, exists=True),
    help="A MiddEval3 scene folder (im0.png, im1.png, disp0GT.pfm); repeatable. Default: Motorcycle, "
    "and Tsukuba and Adirondack from ../shared/data/stereo_gt when present.",
)
@click.option("--quick", is_flag=True, help=f"Motorcycle (or the first scene) with {len(QUICK_CASES)} cases: a test-sized run.")
@click.option("--case", "case_names", multiple=True, help="Only these cases (repeatable); see the module for the list.")
@click.option("--seed", default=0, show_default=True, type=int)
@click.option(
    "--thresholds",
    "thresholds_file",
    type=click.Path(path_type=Path, dir_okay=False, exists=True),
    help="Grade with these thresholds (JSON as `keystone grade show --json` prints) instead of the defaults.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_grade_command(
    scene_dirs: tuple[Path, ...], quick: bool, case_names: tuple[str, ...], seed: int, thresholds_file: Path | None, as_json: bool
) -> None:
    """Antique cards from ground-truth scenes at a range of degradations through the real pipeline:
    the grade, its uncertainty and the true bad-2 of the disparity per card, and how well the
    grade follows the true error (Spearman, median true error per grade)."""
    from pipeline.errors import PipelineError
    from pipeline.grading import GradeParams, GradeThresholds

    known = dict(CASES)
    unknown = [name for name in case_names if name not in known]
    if unknown:
        raise click.BadParameter(f"unknown case {', '.join(unknown)}; cases: {', '.join(known)}", param_hint="--case")
    names = case_names or (QUICK_CASES if quick else tuple(known))
    params = None
    if thresholds_file is not None:
        try:
            document = json.loads(thresholds_file.read_text())
            params = GradeParams(GradeThresholds.from_dict(document.get("thresholds", document)))
        except (ValueError, PipelineError) as exc:
            raise click.ClickException(f"{thresholds_file}: {exc}") from exc
    try:
        scenes = _load_scenes(scene_dirs, quick)
        document = benchmark_grade(scenes, [(name, known[name]) for name in names], seed=seed, grade_params=params)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False))
        return
    click.echo(f"{'scene':<12} {'case':<16} {'grade':<18} {'uncert':>6} {'bad2%':>7}  nearest")
    for r in document["results"]:
        near = r.get("nearest") or {}
        shown = f"{near.get('measurement')} {near.get('value')} vs {near.get('threshold')}" if near else "-"
        uncertainty = "-" if r["uncertainty"] is None else f"{r['uncertainty']:.2f}"
        click.echo(f"{r['scene'][:12]:<12} {r['case']:<16} {r['grade']:<18} {uncertainty:>6} {r['true_bad2']:7.1f}  {shown}")
    s = document["summary"]
    medians = s["median_true_bad2"]
    click.echo(
        f"\n{s['cards']} cards, {s['graded']} graded ({s['counts']['few']} few / {s['counts']['some']} some / "
        f"{s['counts']['failure']} failure), {s['stopped']} stopped by the pipeline; {s['seconds']} s"
    )
    click.echo(
        f"Spearman(grade level, true bad-2) = {s['spearman']} over graded cards "
        f"({s['spearman_all_cards']} with stopped cards as failure); target >= {TARGET_SPEARMAN}"
    )
    click.echo(
        "median true bad-2: "
        + " / ".join(f"{g} {'-' if medians[g] is None else f'{medians[g]:.1f} %'}" for g in LEVEL)
        + f" (ordered few < some < failure: {'yes' if s['ordered'] else 'no'})"
    )

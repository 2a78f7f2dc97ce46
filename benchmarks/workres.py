"""``keystone bench workres``: disparity error against run time across working resolutions.

The disparity stage matches views longer than ``DisparityStageParams.work_side`` at that side and
brings the maps back to the views' pixels (:func:`pipeline.stages.disparity.disparity_at_work_side`).
This measures what that costs in accuracy, on ground truth:

- scenes: scikit-image's Motorcycle (741x500) and, when ``shared/data/stereo_gt`` is present,
  Tsukuba (384x288) and Adirondack Q (718x496), with the loaders of ``bench disparity``;
- each scene as given (``scan`` 1) and "scanned" at 2x (``scan`` 2: both views upsampled bicubic,
  seeded film-grain-like noise of sigma ``GRAIN_SIGMA`` grey levels added, the ground truth times 2
  on the upsampled grid). A ~3000 px card holds two ~1500 px views of a photograph whose detail is
  that of a far smaller one: the 2x scan of Motorcycle (1482x1000) stands for it;
- per working side (``--side``, default 400 ... 1000 and ``full``): the stage's own function with
  the default backend and the search range the rectifier would measure (the ground truth's range),
  the maps upsampled to the scan's resolution, errors there at full coverage (as ``bench disparity``:
  a pixel left empty counts as an error of 1000 px in the EPE): ``epe``, ``bad2`` (|d - gt| > 2 px of
  the scan), ``bad2_scene`` (> 2 px of the scene as given, i.e. 2 x scan px), and ``seconds``
  (process CPU time of the call, one OpenCV thread, median of ``--repeats``).

The summary gives, per working side, mean errors over the cases and the median seconds, for the
2x scans (where the working side matters) and over everything; ``--plot`` draws mean bad-2 against
seconds on the 2x scans with the Pareto front.
"""

from __future__ import annotations

import json
import statistics
import time
from typing import Any

import click
import cv2
import numpy as np

from benchmarks.disparity import Scene, builtin_scenes, disparity_errors, pareto_front
from pipeline.disparity import DEFAULT_BACKEND, DisparityParams
from pipeline.stages.disparity import disparity_at_work_side

DEFAULT_SIDES = ("400", "500", "600", "700", "800", "1000", "full")
SCAN_FACTORS = (1, 2)
GRAIN_SIGMA = 4.0  # grey levels: film grain and scanner noise on an oversampled scan


def scanned(scene: Scene, factor: int, seed: int = 0) -> Scene:
    """``scene`` as if scanned at ``factor`` x its resolution: views upsampled (bicubic) with
    seeded noise, ground truth upsampled (nearest: unknown stays unknown) and times ``factor``."""
    if factor == 1:
        return scene
    rng = np.random.default_rng(seed)
    h, w = scene.gt.shape
    size = (w * factor, h * factor)

    def view(image: np.ndarray) -> np.ndarray:
        up = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC).astype(np.float32)
        up += rng.normal(0.0, GRAIN_SIGMA, up.shape).astype(np.float32)
        return np.clip(np.round(up), 0, 255).astype(np.uint8)

    gt = cv2.resize(scene.gt, size, interpolation=cv2.INTER_NEAREST) * factor
    return Scene(f"{scene.name}", view(scene.left), view(scene.right), gt.astype(np.float32))


def benchmark_workres(
    scenes: list[Scene],
    sides: tuple[str, ...] = DEFAULT_SIDES,
    factors: tuple[int, ...] = SCAN_FACTORS,
    repeats: int = 1,
    backend: str = DEFAULT_BACKEND,
) -> dict[str, Any]:
    """Every scene x scan factor x working side (``"full"`` or px): errors and seconds."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    results: list[dict[str, Any]] = []
    try:
        for base in scenes:
            for factor in factors:
                scene = scanned(base, factor)
                finite = scene.gt[np.isfinite(scene.gt)]
                search = (float(finite.min()), float(finite.max()))
                params = DisparityParams(disparity_range=search)
                for side in sides:
                    work_side = None if side == "full" else int(side)
                    times, result, scale = [], None, 1.0
                    for _ in range(max(1, repeats)):
                        clock = time.process_time()
                        result, scale = disparity_at_work_side(scene.left, scene.right, backend, params, work_side)
                        times.append(time.process_time() - clock)
                    assert result is not None
                    errors = disparity_errors(result.disp_left, scene.gt)
                    valid = np.isfinite(scene.gt)
                    err = np.abs(result.disp_left[valid].astype(np.float64) - scene.gt[valid])
                    err[~np.isfinite(err)] = np.inf
                    results.append(
                        {
                            "scene": scene.name,
                            "scan": factor,
                            "side": side,
                            "size": [int(scene.left.shape[1]), int(scene.left.shape[0])],
                            "work_size": [round(scene.left.shape[1] * scale), round(scene.left.shape[0] * scale)],
                            "epe": round(errors["epe"], 4),
                            "bad2": round(errors["bad2"], 3),
                            "bad2_scene": round(float((err > 2 * factor).mean() * 100), 3),
                            "coverage": round(errors["coverage"], 3),
                            "seconds": round(float(statistics.median(times)), 4),
                        }
                    )
    finally:
        cv2.setNumThreads(threads)
    return {"results": results, "summary": summarise(results, sides), "backend": backend, "grain_sigma": GRAIN_SIGMA}


def summarise(results: list[dict[str, Any]], sides: tuple[str, ...]) -> dict[str, list[dict[str, Any]]]:
    """Per working side: mean EPE / bad-2 / bad-2 in scene px and median seconds, on the 2x scans
    (``scan2``) and on every case (``all``)."""
    out: dict[str, list[dict[str, Any]]] = {}
    for label, keep in (("scan2", lambda r: r["scan"] == 2), ("all", lambda r: True)):
        rows_out = []
        for side in sides:
            rows = [r for r in results if r["side"] == side and keep(r)]
            if not rows:
                continue
            rows_out.append(
                {
                    "side": side,
                    "cases": len(rows),
                    "epe": round(float(np.mean([r["epe"] for r in rows])), 4),
                    "bad2": round(float(np.mean([r["bad2"] for r in rows])), 3),
                    "bad2_scene": round(float(np.mean([r["bad2_scene"] for r in rows])), 3),
                    "seconds": round(float(statistics.median(r["seconds"] for r in rows)), 4),
                }
            )
        out[label] = rows_out
    return out


def plot_workres(summary: list[dict[str, Any]], path: str) -> list[str]:
    """PNG of mean bad-2 against median seconds per working side, Pareto front in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = [(row["side"], row["seconds"], row["bad2"]) for row in summary]
    front = pareto_front(points)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    for name, seconds, bad2 in points:
        ax.scatter([seconds], [bad2], s=40, color="tab:red" if name in front else "tab:grey", zorder=3)
        ax.annotate(name, (seconds, bad2), textcoords="offset points", xytext=(5, 4), fontsize=8)
    line = sorted((s, e) for n, s, e in points if n in front)
    if line:
        ax.step([p[0] for p in line], [p[1] for p in line], where="post", color="tab:red", lw=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel("CPU seconds per pair (median, one thread)")
    ax.set_ylabel("mean bad-2 at the scan's resolution (%)")
    ax.set_title("Disparity at a working side: 2x scans of ground-truth scenes")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return front


@click.command("workres")
@click.option(
    "--side", "sides", multiple=True, help="Working side in px, or 'full'; repeatable. Default: 400 500 600 700 800 1000 full."
)
@click.option(
    "--scan",
    "factors",
    multiple=True,
    type=click.IntRange(1, 4),
    help="Scan factor (1 = the scene as given, 2 = scanned at 2x); repeatable. Default: 1 and 2.",
)
@click.option(
    "--repeats", default=1, show_default=True, type=click.IntRange(1, 20), help="Runs per case; the median time is reported."
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
@click.option("--plot", type=click.Path(dir_okay=False), help="Write a PNG of bad-2 against seconds (2x scans).")
def bench_workres_command(
    sides: tuple[str, ...], factors: tuple[int, ...], repeats: int, as_json: bool, plot: str | None
) -> None:
    """Disparity error against run time across working resolutions, on ground-truth scenes."""
    chosen = sides or DEFAULT_SIDES
    for side in chosen:
        if side != "full" and not (side.isdigit() and int(side) >= 16):
            raise click.BadParameter(f"expected a side in px (>= 16) or 'full', got {side!r}", param_hint="--side")
    document = benchmark_workres(builtin_scenes(), tuple(chosen), tuple(factors) or SCAN_FACTORS, repeats)
    if plot:
        summary = document["summary"].get("scan2") or document["summary"]["all"]
        document["pareto_front"] = plot_workres(summary, plot)
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    for row in document["results"]:
        click.echo(
            f"{row['scene']:<11} x{row['scan']} side {row['side']:>5} work {row['work_size'][0]:>5}x"
            f"{row['work_size'][1]:<5} epe {row['epe']:7.3f} bad2 {row['bad2']:6.2f} % "
            f"(scene px {row['bad2_scene']:6.2f} %) {row['seconds']:.3f} s"
        )
    for label, rows in document["summary"].items():
        click.echo(f"-- {label}")
        for row in rows:
            click.echo(
                f"side {row['side']:>5}: epe {row['epe']:.3f} bad2 {row['bad2']:.2f} % "
                f"bad2_scene {row['bad2_scene']:.2f} % {row['seconds']:.3f} s ({row['cases']} cases)"
            )

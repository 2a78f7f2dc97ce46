"""Side by side with OpenCV (docs/BENCHMARKS.md): our Loop-Zhang :func:`pipeline.rectify.rectify_pair`
against ``cv2.stereoRectifyUncalibrated`` (Hartley 1999) on the same inputs.

Fairness: Hartley is given **our** fundamental matrix and inlier matches (the ones
:func:`rectify_pair` used, in its output order after a swap), so the comparison is of the
homographies alone. When our method refuses a pair, Hartley gets F and inliers from
:func:`match_features` + :func:`estimate_fundamental` on the pair as given (a typed refusal there
is Hartley's error too). Hartley's time is that front end plus its own call. Both methods then get
KeystoneDepth's translation (the right view moved along x so that the smallest inlier disparity,
along-row mismatches left out, is 0): Hartley re-centres disparity about zero, which no disparity
stage expects, and a translation changes no distortion metric nor |dy|.

Metrics per pair and method, over the inlier matches:
``dy_median`` / ``dy_p95`` (px, |y_l' - y_r'| after rectification), ``midline_deviation`` (deg,
|midline angle - 90| of the worse view, :func:`pipeline.rectify.distortion_metrics`),
``aspect_change`` (the worse view, ratio >= 1), ``seconds`` (median over repeats, one OpenCV thread).
Synthetic pairs also get ``epe`` / ``bad2`` (px / percent over valid ground truth): disparity by
``estimate_disparity(backend="keystone")`` on the rectified pair (search range: the method's
own fenced inlier disparity range, as the pipeline passes it), mapped back to the original left
view (left pixel ``p`` -> ``H_l p``, the match ``(x' - d, y')`` -> ``H_r^-1`` -> undo the synthetic
warp -> original right view; predicted disparity ``x_l - x_r``); pixels that leave the canvas count
as missing (``coverage``), and are left out of EPE / bad-2 (which are over covered valid GT).
``gt_dy_p95`` (synthetic): p95 of the row error of *every* ground-truth correspondence after
rectification (px), the geometric truth behind the inlier |dy|.

Pairs: (a) real, no ground truth, from ``shared/data/stereocards`` when present: full cards split
by :func:`pipeline.filter.filter_card`, the Keystone-Mast raw scans (same), the JPS pairs (halved)
and the depthy 7995 pair; (b) synthetic: Motorcycle (always), Tsukuba and Adirondack (when
``shared/data/stereo_gt`` is present), right view warped by rotation (up to 3 deg), vertical shift
(up to 20 px) and a keystone (projective) term.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

from benchmarks.disparity import Scene, builtin_scenes, disparity_errors, motorcycle_scene
from pipeline.disparity import DisparityParams, estimate_disparity
from pipeline.errors import PipelineError
from pipeline.rectify import (
    Rectification,
    RectifyParams,
    distortion_metrics,
    estimate_fundamental,
    match_features,
    rectify_pair,
)

__all__ = [
    "METHODS",
    "SYNTHETIC_WARPS",
    "BenchPair",
    "benchmark_rectify",
    "default_pairs",
    "keystone_warp",
    "real_pairs",
    "summarise",
    "synthetic_pairs",
]

METHODS = ("keystone", "hartley")
# name: (rotation deg, vertical shift px, keystone per px of the centred x). 1e-4 at 741 px wide
# scales the right edge ~3.7 % against the left edge.
SYNTHETIC_WARPS: dict[str, tuple[float, float, float]] = {
    "rot1-dy5": (1.0, 5.0, 0.0),
    "rot3-dy20-keystone": (3.0, 20.0, 1e-4),
    "rot-2-up10-keystone": (-2.0, -10.0, -1.5e-4),
}
QUICK_WARPS = ("rot3-dy20-keystone",)


@dataclass
class BenchPair:
    name: str
    kind: str  # "real" | "synthetic"
    left: np.ndarray
    right: np.ndarray
    gt: np.ndarray | None = None  # left-view disparity of the unwarped pair, NaN = unknown
    warp: np.ndarray | None = None  # 3x3: original right pixel -> warped right pixel


# ------------------------------------------------------------------------------------ inputs


def keystone_warp(width: int, height: int, degrees: float, dy: float, keystone: float) -> np.ndarray:
    """3x3 homography: rotate about the centre, a keystone term ``w = 1 + k (x - cx)``, then down ``dy``."""
    c = np.array([[1, 0, -(width - 1) / 2.0], [0, 1, -(height - 1) / 2.0], [0, 0, 1.0]])
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    ks = np.array([[1, 0, 0], [0, 1, 0], [keystone, 0, 1.0]])
    return np.array([[1, 0, 0], [0, 1, dy], [0, 0, 1.0]]) @ np.linalg.inv(c) @ ks @ rot @ c


def synthetic_pairs(scenes: list[Scene], warps: tuple[str, ...] | None = None, scale: float = 1.0) -> list[BenchPair]:
    out = []
    for scene in scenes:
        left, right, gt = scene.left, scene.right, scene.gt
        if scale != 1.0:
            size = (round(left.shape[1] * scale), round(left.shape[0] * scale))
            left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
            right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
            gt = cv2.resize(gt, size, interpolation=cv2.INTER_NEAREST) * scale
        h, w = left.shape[:2]
        for name in warps or tuple(SYNTHETIC_WARPS):
            deg, dy, ks = SYNTHETIC_WARPS[name]
            M = keystone_warp(w, h, deg, dy * scale, ks / scale)
            warped = cv2.warpPerspective(right, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out.append(BenchPair(f"{scene.name}/{name}", "synthetic", left, warped, gt, M))
    return out


def real_pairs(shared_data: str | Path | None) -> list[BenchPair]:
    """The real pairs under ``shared_data/stereocards`` (none when absent)."""
    if shared_data is None:
        return []
    root = Path(shared_data) / "stereocards"
    if not root.is_dir():
        return []
    from pipeline.filter import filter_card
    from pipeline.io import read_image
    from pipeline.split import crop_halves

    out = []
    for folder in ("full_cards", "keystone_mast_raw_scans"):
        for path in sorted((root / folder).glob("*.jpg")):
            try:
                card = read_image(path)
                split, _ = filter_card(card)
                left, right = crop_halves(card, split)
            except PipelineError:
                continue  # no split: nothing to rectify (the filter records why)
            out.append(BenchPair(f"{folder}/{path.stem}", "real", np.ascontiguousarray(left), np.ascontiguousarray(right)))
    for path in sorted((root / "cropped_pairs" / "jps").glob("*.jps")):
        try:
            card = read_image(path)
        except PipelineError:
            continue
        half = card.shape[1] // 2
        out.append(
            BenchPair(
                f"jps/{path.stem}", "real", np.ascontiguousarray(card[:, :half]), np.ascontiguousarray(card[:, half : 2 * half])
            )
        )
    depthy = root / "cropped_pairs" / "depthy_7995"
    if (depthy / "7995l-image.jpg").is_file() and (depthy / "7995r-image.jpg").is_file():
        try:
            out.append(
                BenchPair("depthy/7995", "real", read_image(depthy / "7995l-image.jpg"), read_image(depthy / "7995r-image.jpg"))
            )
        except PipelineError:
            pass
    return out


def default_shared_data() -> Path | None:
    candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
    return candidate if candidate.is_dir() else None


def default_pairs(shared_data: str | Path | None = None, quick: bool = False) -> list[BenchPair]:
    """Quick: Motorcycle at half size with the hardest warp only. Else real pairs (when present)
    and every synthetic warp of every built-in Middlebury scene."""
    if quick:
        return synthetic_pairs([motorcycle_scene()], QUICK_WARPS, scale=0.5)
    root = Path(shared_data) if shared_data is not None else default_shared_data()
    stereo_gt = root / "stereo_gt" if root is not None and (root / "stereo_gt").is_dir() else None
    scenes = builtin_scenes(stereo_gt) if stereo_gt is not None else [motorcycle_scene()]
    return real_pairs(root) + synthetic_pairs(scenes)


# ---------------------------------------------------------------------------------- methods


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    xh = np.c_[pts, np.ones(len(pts))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return xh[:, :2] / xh[:, 2:3]


def _translate_no_negative(H_l: np.ndarray, H_r: np.ndarray, il: np.ndarray, ir: np.ndarray, width: int) -> np.ndarray:
    """KeystoneDepth's translation for Hartley: smallest fenced inlier disparity -> 0."""
    disp = _apply(H_l, il)[:, 0] - _apply(H_r, ir)[:, 0]
    med = float(np.median(disp))
    sigma = max(1.4826 * float(np.median(np.abs(disp - med))), 0.01 * width)
    keep = np.abs(disp - med) <= 5.0 * sigma
    shift = float(disp[keep].min()) if keep.any() else 0.0
    return np.array([[1, 0, shift], [0, 1, 0], [0, 0, 1.0]]) @ H_r


def _canvas(H_l: np.ndarray, H_r: np.ndarray, shapes: list[tuple[int, int]], cap: float = 2.0):
    """Union of both warped views, at most ``cap`` x the input, moved to the origin."""
    quads = []
    for H, (h, w) in zip((H_l, H_r), shapes):
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
        quads.append(_apply(H, corners))
    allq = np.vstack(quads)
    if not np.all(np.isfinite(allq)):
        return None
    lo, hi = allq.min(axis=0), allq.max(axis=0)
    limit = cap * np.array([max(s[1] for s in shapes), max(s[0] for s in shapes)], float)
    span = np.minimum(hi - lo, limit)
    lo = (lo + hi) / 2 - span / 2
    move = np.array([[1, 0, -lo[0] - 0.5], [0, 1, -lo[1] - 0.5], [0, 0, 1.0]])
    return move @ H_l, move @ H_r, (max(1, math.ceil(span[0])), max(1, math.ceil(span[1])))


def _metrics(H_l, H_r, il, ir, shapes) -> dict[str, float]:
    a, b = _apply(H_l, il), _apply(H_r, ir)
    dy = np.abs(a[:, 1] - b[:, 1])
    ms = [distortion_metrics(H, w, h) for H, (h, w) in zip((H_l, H_r), shapes)]
    return {
        "dy_median": float(np.median(dy)),
        "dy_p95": float(np.percentile(dy, 95)),
        "midline_deviation": float(max(abs(m["midline_angle"] - 90.0) for m in ms)),
        "aspect_change": float(max(m["aspect_change"] for m in ms)),
    }


def _run_keystone(pair: BenchPair, params: RectifyParams) -> tuple[Rectification, float]:
    clock = time.perf_counter()
    rect = rectify_pair(pair.left, pair.right, params)
    return rect, time.perf_counter() - clock


def _front_end(pair: BenchPair, params: RectifyParams, rect: Rectification | None):
    """(F, il, ir, swapped, seconds): ours when available, else a fresh estimate on the pair as given."""
    if rect is not None:
        il, ir = rect.inlier_points
        return rect.F, il, ir, rect.swapped, 0.0
    clock = time.perf_counter()
    pts_l, pts_r = match_features(pair.left, pair.right, params)
    scale = max(1.0, max(*pair.left.shape[:2], *pair.right.shape[:2]) / params.max_side)
    F, mask, _ = estimate_fundamental(pts_l, pts_r, params, scale)
    return F, pts_l[mask], pts_r[mask], False, time.perf_counter() - clock


def _run_hartley(F, il, ir, shape_l, shape_r) -> tuple[np.ndarray, np.ndarray, float]:
    clock = time.perf_counter()
    h, w = shape_l[:2]
    ok, H1, H2 = cv2.stereoRectifyUncalibrated(
        np.ascontiguousarray(il, np.float64), np.ascontiguousarray(ir, np.float64), F, (w, h)
    )
    if not ok or H1 is None or H2 is None or not (np.all(np.isfinite(H1)) and np.all(np.isfinite(H2))):
        raise PipelineError("stereoRectifyUncalibrated returned no finite homographies")
    H2 = _translate_no_negative(H1, H2, il, ir, max(w, shape_r[1]))
    return H1, H2, time.perf_counter() - clock


def _inlier_range(H_l: np.ndarray, H_r: np.ndarray, il: np.ndarray, ir: np.ndarray, width: int) -> tuple[float, float]:
    """(min, max) inlier disparity after rectification, along-row mismatches fenced out (as ours)."""
    disp = _apply(H_l, il)[:, 0] - _apply(H_r, ir)[:, 0]
    med = float(np.median(disp))
    sigma = max(1.4826 * float(np.median(np.abs(disp - med))), 0.01 * width)
    keep = np.abs(disp - med) <= 5.0 * sigma
    return float(disp[keep].min()), float(disp[keep].max())


def _disparity_error(
    pair: BenchPair,
    left: np.ndarray,
    right: np.ndarray,
    H_l: np.ndarray,
    H_r: np.ndarray,
    size: tuple[int, int],
    swapped: bool,
    drange: tuple[float, float],
) -> dict[str, float]:
    """Disparity on the rectified pair (search range: the method's own inlier disparity range, as
    the pipeline passes it), mapped back to the original left view, against GT."""
    if swapped:  # H_l applies to the view given as right: no GT for that orientation
        return {"epe": math.nan, "bad2": math.nan, "coverage": 0.0}
    width, height = size
    rl = cv2.warpPerspective(left, H_l, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    rr = cv2.warpPerspective(right, H_r, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    disp = estimate_disparity(rl, rr, "keystone", DisparityParams(disparity_range=drange)).disp_left.astype(np.float32)
    h, w = left.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    pts = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
    p = _apply(H_l, pts)
    inside = np.all(np.isfinite(p), axis=1) & (p[:, 0] >= 0) & (p[:, 0] <= width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= height - 1)
    mx = np.where(inside, p[:, 0], -1).reshape(h, w).astype(np.float32)
    my = np.where(inside, p[:, 1], -1).reshape(h, w).astype(np.float32)
    d = cv2.remap(disp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
    q = np.c_[p[:, 0] - d, p[:, 1]]
    back = _apply(np.linalg.inv(H_r), q)
    if pair.warp is not None:
        back = _apply(np.linalg.inv(pair.warp), back)
    pred = (pts[:, 0] - back[:, 0]).reshape(h, w)
    pred[~inside.reshape(h, w)] = np.nan
    gt = pair.gt
    valid = np.isfinite(gt)
    # Geometric truth: row error of the ground-truth correspondences after rectification.
    truth_r = np.c_[pts[:, 0] - gt.ravel(), pts[:, 1]][valid.ravel()]
    if pair.warp is not None:
        truth_r = _apply(pair.warp, truth_r)
    gt_dy = np.abs(p[valid.ravel(), 1] - _apply(H_r, truth_r)[:, 1])
    gt_dy = gt_dy[np.isfinite(gt_dy)]
    gt_dy_p95 = float(np.percentile(gt_dy, 95)) if gt_dy.size else math.nan
    covered = valid & np.isfinite(pred)
    coverage = float(covered.sum() / max(valid.sum(), 1) * 100)
    if not covered.any():
        return {"epe": math.nan, "bad2": math.nan, "coverage": coverage, "gt_dy_p95": gt_dy_p95}
    gt_cov = np.where(covered, gt, np.nan).astype(np.float32)
    err = disparity_errors(pred, gt_cov)
    return {"epe": err["epe"], "bad2": err["bad2"], "coverage": coverage, "gt_dy_p95": gt_dy_p95}


# ---------------------------------------------------------------------------------- benchmark


def _row(pair: BenchPair, method: str) -> dict[str, Any]:
    return {
        "pair": pair.name,
        "kind": pair.kind,
        "method": method,
        "dy_median": None,
        "dy_p95": None,
        "midline_deviation": None,
        "aspect_change": None,
        "epe": None,
        "bad2": None,
        "coverage": None,
        "gt_dy_p95": None,
        "seconds": None,
        "error": None,
    }


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def benchmark_rectify(
    pairs: list[BenchPair], repeats: int = 1, params: RectifyParams | None = None, disparity: bool = True
) -> dict[str, Any]:
    """Run both methods on every pair (one OpenCV thread). A typed failure is a row with ``error``."""
    params = params or RectifyParams()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    results: list[dict[str, Any]] = []
    try:
        for pair in pairs:
            ours, theirs = _row(pair, "keystone"), _row(pair, "hartley")
            rect, times = None, []
            try:
                for _ in range(max(1, repeats)):
                    rect, seconds = _run_keystone(pair, params)
                    times.append(seconds)
            except PipelineError as exc:
                ours["error"] = exc.reason() if hasattr(exc, "reason") else str(exc)
                rect = None
            views = (pair.right, pair.left) if rect is not None and rect.swapped else (pair.left, pair.right)
            shapes = [views[0].shape[:2], views[1].shape[:2]]
            if rect is not None:
                il, ir = rect.inlier_points
                ours.update(_metrics(rect.H_l, rect.H_r, il, ir, shapes))
                ours["seconds"] = float(statistics.median(times))
                ours["warp_needed"] = bool(rect.warp_needed)
                if disparity and pair.gt is not None:
                    try:
                        ours.update(
                            _disparity_error(
                                pair, pair.left, pair.right, rect.H_l, rect.H_r, rect.size, rect.swapped, rect.disparity_range
                            )
                        )
                    except PipelineError as exc:
                        ours["error"] = f"disparity: {exc.reason()}"
                    except (np.linalg.LinAlgError, cv2.error) as exc:
                        ours["error"] = f"disparity: numerical failure ({type(exc).__name__})"
            try:
                F, il, ir, swapped, front = _front_end(pair, params, rect)
                if rect is not None:
                    front = _front_seconds(pair, params)  # the same front end, timed once for Hartley
                h_times = []
                for _ in range(max(1, repeats)):
                    H1, H2, seconds = _run_hartley(F, il, ir, shapes[0], shapes[1])
                    h_times.append(front + seconds)
                theirs.update(_metrics(H1, H2, il, ir, shapes))
                theirs["seconds"] = float(statistics.median(h_times))
                if disparity and pair.gt is not None:
                    canvas = _canvas(H1, H2, shapes)
                    if canvas is None:
                        theirs["error"] = "unbounded_warp: a corner maps to infinity"
                    else:
                        G1, G2, size = canvas
                        drange = _inlier_range(G1, G2, il, ir, size[0])
                        theirs.update(_disparity_error(pair, pair.left, pair.right, G1, G2, size, swapped, drange))
            except PipelineError as exc:
                theirs["error"] = exc.reason()
            except cv2.error as exc:
                theirs["error"] = f"opencv_error: {str(exc).strip().splitlines()[-1][:120]}"
            except (np.linalg.LinAlgError, ValueError, ZeroDivisionError) as exc:
                theirs["error"] = f"numerical_failure: {type(exc).__name__}: {str(exc)[:120]}"
            results.append({k: _clean(v) for k, v in ours.items()})
            results.append({k: _clean(v) for k, v in theirs.items()})
    finally:
        cv2.setNumThreads(threads)
    return {"results": results, "summary": summarise(results)}


def _front_seconds(pair: BenchPair, params: RectifyParams) -> float:
    """Time of the shared front end (SIFT matches + MAGSAC F) that Hartley needs as input."""
    clock = time.perf_counter()
    pts_l, pts_r = match_features(pair.left, pair.right, params)
    scale = max(1.0, max(*pair.left.shape[:2], *pair.right.shape[:2]) / params.max_side)
    try:
        estimate_fundamental(pts_l, pts_r, params, scale)
    except PipelineError:
        pass
    return time.perf_counter() - clock


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method and kind (real / synthetic / all): medians over the pairs both methods handled,
    failures counted, and the acceptance criterion (better distortion with equal or better |dy|)."""
    out: dict[str, Any] = {}
    both = {r["pair"] for r in results if r["error"] is None} & {
        r["pair"] for r in results if r["method"] == "hartley" and r["error"] is None
    }
    both = {p for p in both if all(r["error"] is None for r in results if r["pair"] == p)}
    for method in METHODS:
        rows = [r for r in results if r["method"] == method]
        entry: dict[str, Any] = {"pairs": len(rows), "failures": sum(r["error"] is not None for r in rows)}
        for kind in ("real", "synthetic", "all"):
            sel = [r for r in rows if r["pair"] in both and (kind == "all" or r["kind"] == kind)]
            stats: dict[str, Any] = {
                "pairs": len(sel),
                "failures": sum(r["error"] is not None for r in rows if kind == "all" or r["kind"] == kind),
            }
            for key in ("dy_median", "dy_p95", "midline_deviation", "aspect_change", "epe", "bad2", "gt_dy_p95", "seconds"):
                vals = [r[key] for r in sel if r[key] is not None]
                stats[key] = float(np.median(vals)) if vals else None
            entry[kind] = stats
        out[method] = entry
    wins = 0
    compared = 0
    for pair in sorted(both):
        k = next(r for r in results if r["pair"] == pair and r["method"] == "keystone")
        h = next(r for r in results if r["pair"] == pair and r["method"] == "hartley")
        compared += 1
        wins += int(k["midline_deviation"] <= h["midline_deviation"] + 1e-9 and k["dy_p95"] <= h["dy_p95"] + 0.1)
    out["compared_pairs"] = compared
    out["keystone_beats_hartley"] = wins
    out["criterion"] = "midline deviation <= Hartley's and |dy| p95 <= Hartley's + 0.1 px"
    return out


def _fmt(value, spec: str) -> str:
    width = int(spec.split(".")[0] or 0)
    return "-".rjust(width) if value is None else format(value, spec)


@click.command("rectify")
@click.option(
    "--shared-data",
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder with the real pairs and stereo_gt (../shared/data); default: found next to the "
    "checkout, else the Motorcycle synthetic pairs only.",
)
@click.option(
    "--repeats",
    default=1,
    show_default=True,
    type=click.IntRange(1, 100),
    help="Runs per pair and method; the median time is reported.",
)
@click.option("--quick", is_flag=True, help="Motorcycle at half size, one synthetic warp (a few seconds).")
@click.option("--no-disparity", is_flag=True, help="Skip the disparity error on the synthetic pairs.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_rectify_command(shared_data: Path | None, repeats: int, quick: bool, no_disparity: bool, as_json: bool) -> None:
    """Residual |dy|, distortion, disparity error (synthetic) and seconds per pair: keystone vs hartley."""
    from benchmarks.rectify import benchmark_rectify, default_pairs
    from pipeline.errors import PipelineError

    try:
        pairs = default_pairs(shared_data, quick=quick)
        document = benchmark_rectify(pairs, repeats=repeats, disparity=not no_disparity)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False))
        return
    click.echo(
        f"{'pair':<44} {'method':<9} {'dy med':>7} {'dy p95':>7} {'midline':>8} {'aspect':>7} "
        f"{'epe':>6} {'bad2%':>6} {'gt dy95':>7} {'seconds':>8}  error"
    )
    for r in document["results"]:
        click.echo(
            f"{r['pair'][:44]:<44} {r['method']:<9} {_fmt(r['dy_median'], '7.2f')} {_fmt(r['dy_p95'], '7.2f')} "
            f"{_fmt(r['midline_deviation'], '8.2f')} {_fmt(r['aspect_change'], '7.3f')} "
            f"{_fmt(r['epe'], '6.2f')} {_fmt(r['bad2'], '6.1f')} {_fmt(r['gt_dy_p95'], '7.2f')} "
            f"{_fmt(r['seconds'], '8.3f')}  {r['error'] or ''}"
        )
    summary = document["summary"]
    click.echo("")
    click.echo(
        f"medians over the {summary['compared_pairs']} pairs both methods rectified "
        "(midline = |midline angle - 90| deg, worse view):"
    )
    click.echo(
        f"{'method':<9} {'kind':<10} {'pairs':>5} {'dy med':>7} {'dy p95':>7} {'midline':>8} {'aspect':>7} "
        f"{'epe':>6} {'bad2%':>6} {'seconds':>8} {'failures':>8}"
    )
    for method in ("keystone", "hartley"):
        entry = summary[method]
        for kind in ("real", "synthetic"):
            s = entry[kind]
            click.echo(
                f"{method:<9} {kind:<10} {s['pairs']:>5} {_fmt(s['dy_median'], '7.2f')} {_fmt(s['dy_p95'], '7.2f')} "
                f"{_fmt(s['midline_deviation'], '8.2f')} {_fmt(s['aspect_change'], '7.3f')} "
                f"{_fmt(s['epe'], '6.2f')} {_fmt(s['bad2'], '6.1f')} {_fmt(s['seconds'], '8.3f')} "
                f"{s['failures']:>8}"
            )
    click.echo(
        f"keystone beats hartley on {summary['keystone_beats_hartley']} of {summary['compared_pairs']} pairs "
        f"({summary['criterion']})"
    )

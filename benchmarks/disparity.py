"""Error against run time of the disparity backends, for ``keystone bench disparity``.

Scenes: Middlebury MiddEval3 folders (``im0.png``, ``im1.png``, ``disp0GT.pfm`` with non-finite =
unknown, optional ``mask0nocc.png`` where 255 = non-occluded) or the built-in ones: Motorcycle from
scikit-image (always) and, when ``shared/data/stereo_gt`` is present, Tsukuba (``disp_left_x16.png``,
d = value / 16, 0 = unknown) and Adirondack Q (``disp_left_int.png`` + ``mask_nonocc.png``).

Each right view is also perturbed the way antique pairs are off: 2 and 4 px down, rotated 0.5 deg
about its centre. Metrics per scene x perturbation x backend, over valid ground truth:
``epe``, ``bad1``, ``bad2`` (percent of |d - gt| > 1 / 2 px) at full coverage (a pixel a backend left
empty counts as an error, with error 1000 px in the EPE), the same on the backend's confident pixels
(confidence >= 0.5) with their ``confident_coverage``, and ``seconds``: the median over repeats on one
OpenCV thread.

Tuning split (issue #17): the default backend's choices were made on the **tuned** scenes,
``motorcycle`` and ``tsukuba`` (:data:`TUNING_SCENES`); every other scene is **held-out**:
Adirondack Q, the same Adirondack with the right view from the other exposure
(``adirondack-exposure``, Middlebury's ``AdirondackE`` right view: a photometric test on the same
geometry, so not an independent scene), and any ``--scene`` folder. Rows carry their ``split``;
``summary_by_split`` gives the means per backend and split, with each backend's time as a ratio
to DIS medium measured in the same run. Target: held-out mean bad-2 <= 8 % at <= 10x DIS medium.
"""

from __future__ import annotations

import re
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

from pipeline.disparity import BACKENDS, DEFAULT_BACKEND, DisparityParams, estimate_disparity
from pipeline.errors import ImageReadError, InvalidInputError

PERTURBATIONS = ("none", "down2", "down4", "rot0.5")
MISSING_ERROR_PX = 1000.0
TARGET_BAD2 = 8.0
TARGET_SECONDS = 0.3
TARGET_RATIO_TO_DIS_MEDIUM = 10.0
TUNING_SCENES = ("motorcycle", "tsukuba")  # everything else is held out (see the module docstring)
SPLITS = ("tuned", "held-out")


class PFMError(ImageReadError):
    code = "bad_pfm"


@dataclass
class Scene:
    name: str
    left: np.ndarray  # RGB or grey uint8
    right: np.ndarray
    gt: np.ndarray  # float32 disparity of the left view, NaN = unknown

    @property
    def split(self) -> str:
        """``tuned`` for the scenes the default backend was tuned on, else ``held-out``."""
        return "tuned" if self.name in TUNING_SCENES else "held-out"


# ------------------------------------------------------------------------------------------- PFM
def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM (``Pf`` grey or ``PF`` colour) as float32, top row first."""
    with open(path, "rb") as fh:
        data = fh.read()
    m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if not m:
        raise PFMError(f"{path}: not a PFM file")
    channels = 3 if m.group(1) == b"PF" else 1
    width, height, scale = int(m.group(2)), int(m.group(3)), float(m.group(4))
    dtype = "<f4" if scale < 0 else ">f4"
    count = width * height * channels
    body = data[m.end() :]
    if len(body) < 4 * count:
        raise PFMError(f"{path}: truncated ({len(body)} bytes for {count} floats)")
    arr = np.frombuffer(body, dtype=dtype, count=count).astype(np.float32)
    arr = arr.reshape((height, width, channels) if channels == 3 else (height, width))
    return np.ascontiguousarray(arr[::-1])


def write_pfm(path: str | Path, image: np.ndarray) -> None:
    """Write a float32 HxW (``Pf``) or HxWx3 (``PF``) PFM, little-endian, bottom row first."""
    a = np.asarray(image, dtype="<f4")
    if a.ndim == 2:
        header = b"Pf"
    elif a.ndim == 3 and a.shape[2] == 3:
        header = b"PF"
    else:
        raise InvalidInputError(f"PFM needs HxW or HxWx3, got {a.shape}")
    with open(path, "wb") as fh:
        fh.write(header + f"\n{a.shape[1]} {a.shape[0]}\n-1.0\n".encode())
        fh.write(np.ascontiguousarray(a[::-1]).tobytes())


# ---------------------------------------------------------------------------------------- scenes
def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ImageReadError(f"cannot read {path}")
    return img[..., ::-1].copy()


def load_middeval3(folder: str | Path) -> Scene:
    folder = Path(folder)
    for name in ("im0.png", "im1.png", "disp0GT.pfm"):
        if not (folder / name).is_file():
            raise ImageReadError(f"{folder}: missing {name} (MiddEval3 layout: im0.png, im1.png, disp0GT.pfm)")
    gt = read_pfm(folder / "disp0GT.pfm")
    gt = gt[..., 0] if gt.ndim == 3 else gt
    gt = gt.astype(np.float32)
    gt[~np.isfinite(gt)] = np.nan
    mask_path = folder / "mask0nocc.png"
    if mask_path.is_file():
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if mask is not None and mask.shape == gt.shape:
            gt[mask != 255] = np.nan
    left, right = _read_rgb(folder / "im0.png"), _read_rgb(folder / "im1.png")
    if left.shape != right.shape or left.shape[:2] != gt.shape:
        raise InvalidInputError(f"{folder}: im0 {left.shape}, im1 {right.shape}, GT {gt.shape} differ")
    return Scene(folder.name, left, right, gt)


def motorcycle_scene() -> Scene:
    from skimage import data

    left, right, disp = data.stereo_motorcycle()
    gt = np.asarray(disp, np.float32).copy()
    gt[~np.isfinite(gt)] = np.nan  # scikit-image marks unknown with +inf
    return Scene("motorcycle", left, right, gt)


def default_shared_gt() -> Path | None:
    candidate = Path(__file__).resolve().parents[2] / "shared" / "data" / "stereo_gt"
    return candidate if candidate.is_dir() else None


def builtin_scenes(stereo_gt: str | Path | None = None) -> list[Scene]:
    """Motorcycle, plus Tsukuba, Adirondack Q and Adirondack Q with the other exposure's right
    view (``adirondack-exposure``) from ``stereo_gt`` when present."""
    scenes = [motorcycle_scene()]
    root = Path(stereo_gt) if stereo_gt is not None else default_shared_gt()
    if root is None:
        return scenes
    tsu = root / "middlebury2001_tsukuba"
    if (tsu / "disp_left_x16.png").is_file():
        raw = cv2.imread(str(tsu / "disp_left_x16.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        gt = raw / 16.0
        gt[raw == 0] = np.nan
        scenes.append(Scene("tsukuba", _read_rgb(tsu / "left.png"), _read_rgb(tsu / "right.png"), gt))
    adi = root / "middlebury2014_adirondack_Q"
    if (adi / "disp_left_int.png").is_file():
        gt = cv2.imread(str(adi / "disp_left_int.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        mask_path = adi / "mask_nonocc.png"
        if mask_path.is_file():
            gt[cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) != 255] = np.nan
        left = _read_rgb(adi / "left.png")
        scenes.append(Scene("adirondack", left, _read_rgb(adi / "right.png"), gt))
        if (adi / "right_E_exposure.png").is_file():
            scenes.append(Scene("adirondack-exposure", left, _read_rgb(adi / "right_E_exposure.png"), gt))
    return scenes


# ---------------------------------------------------------------------------------- perturbation
def perturb(right: np.ndarray, kind: str) -> np.ndarray:
    """The right view moved ``down2``/``down4`` px, or rotated ``rot0.5`` deg about its centre."""
    h, w = right.shape[:2]
    if kind == "none":
        return right
    if kind.startswith("down"):
        M = np.float32([[1, 0, 0], [0, 1, float(kind[4:])]])
    elif kind.startswith("rot"):
        M = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), float(kind[3:]), 1.0)
    else:
        raise InvalidInputError(f"unknown perturbation {kind!r}; choose from {', '.join(PERTURBATIONS)}")
    return cv2.warpAffine(right, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# --------------------------------------------------------------------------------------- metrics
def disparity_errors(disp: np.ndarray, gt: np.ndarray, confidence: np.ndarray | None = None) -> dict[str, float]:
    valid = np.isfinite(gt)
    n = int(valid.sum())
    if n == 0:
        raise InvalidInputError("ground truth has no valid pixel")
    err = np.abs(disp[valid].astype(np.float64) - gt[valid])
    err[~np.isfinite(err)] = MISSING_ERROR_PX
    out = {
        "epe": float(err.mean()),
        "bad1": float((err > 1).mean() * 100),
        "bad2": float((err > 2).mean() * 100),
        "coverage": float(np.isfinite(disp[valid]).mean() * 100),
    }
    if confidence is not None:
        conf = (confidence[valid] >= 0.5) & np.isfinite(disp[valid])
        out["confident_coverage"] = float(conf.mean() * 100)
        ce = err[conf]
        out["confident_epe"] = float(ce.mean()) if ce.size else None
        out["confident_bad1"] = float((ce > 1).mean() * 100) if ce.size else None
        out["confident_bad2"] = float((ce > 2).mean() * 100) if ce.size else None
    return out


# ------------------------------------------------------------------------------------- benchmark
def benchmark_disparity(
    scenes: list[Scene],
    backends: list[str] | tuple[str, ...] = BACKENDS,
    perturbations: tuple[str, ...] = PERTURBATIONS,
    repeats: int = 3,
    params: DisparityParams | None = None,
) -> dict[str, Any]:
    """Run every backend on every scene x perturbation on one OpenCV thread."""
    for b in backends:
        if b not in BACKENDS:
            raise InvalidInputError(f"unknown backend {b!r}; choose from {', '.join(BACKENDS)}")
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    results: list[dict[str, Any]] = []
    try:
        for scene in scenes:
            for kind in perturbations:
                right = perturb(scene.right, kind)
                for backend in backends:
                    times, res = [], None
                    for _ in range(max(1, repeats)):
                        res = estimate_disparity(scene.left, right, backend, params or DisparityParams())
                        times.append(res.seconds)
                    row: dict[str, Any] = {"scene": scene.name, "split": scene.split, "perturbation": kind, "backend": backend}
                    row.update(disparity_errors(res.disp_left, scene.gt, res.confidence))
                    row["seconds"] = float(statistics.median(times))
                    row["size"] = [int(scene.left.shape[1]), int(scene.left.shape[0])]
                    results.append(row)
    finally:
        cv2.setNumThreads(threads)
    return {
        "results": results,
        "summary": summarise(results),
        "summary_by_split": summarise_by_split(results),
        "tuning_scenes": list(TUNING_SCENES),
        "default_backend": DEFAULT_BACKEND,
        "target": {
            "mean_bad2": TARGET_BAD2,
            "split": "held-out",
            "seconds_741x500": TARGET_SECONDS,
            "ratio_to_dis_medium": TARGET_RATIO_TO_DIS_MEDIUM,
        },
    }


def _means(rows: list[dict[str, Any]]) -> dict[str, Any]:
    scaled = [r["seconds"] * (741 * 500) / (r["size"][0] * r["size"][1]) for r in rows]
    return {
        "epe": float(np.mean([r["epe"] for r in rows])),
        "bad1": float(np.mean([r["bad1"] for r in rows])),
        "bad2": float(np.mean([r["bad2"] for r in rows])),
        "coverage": float(np.mean([r["coverage"] for r in rows])),
        "seconds": float(statistics.median(r["seconds"] for r in rows)),
        "seconds_741x500": float(statistics.median(scaled)),
        "rows": len(rows),
    }


def _ratio_to_dis_medium(results: list[dict[str, Any]], rows: list[dict[str, Any]]) -> float | None:
    """Median over the rows' cases of seconds / DIS medium's seconds on the same case (same run),
    or None when DIS medium did not run."""
    dis = {(r["scene"], r["perturbation"]): r["seconds"] for r in results if r["backend"] == "dis-medium"}
    ratios = [
        r["seconds"] / dis[(r["scene"], r["perturbation"])] for r in rows if dis.get((r["scene"], r["perturbation"]), 0) > 0
    ]
    return float(statistics.median(ratios)) if ratios else None


def summarise(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per backend: mean EPE / bad-1 / bad-2 / coverage over all rows, median seconds, the
    seconds scaled to a 741x500 pair (time grows about linearly with pixels) and the median ratio
    of its time to DIS medium's on the same cases (``ratio_to_dis_medium``, None without it)."""
    out = []
    for backend in dict.fromkeys(r["backend"] for r in results):
        rows = [r for r in results if r["backend"] == backend]
        out.append({"backend": backend, **_means(rows), "ratio_to_dis_medium": _ratio_to_dis_medium(results, rows)})
    return out


def summarise_by_split(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The same means per backend and split (``tuned`` / ``held-out``), splits without rows left out."""
    out = []
    for backend in dict.fromkeys(r["backend"] for r in results):
        for split in SPLITS:
            rows = [r for r in results if r["backend"] == backend and r.get("split") == split]
            if rows:
                out.append(
                    {
                        "backend": backend,
                        "split": split,
                        **_means(rows),
                        "ratio_to_dis_medium": _ratio_to_dis_medium(results, rows),
                    }
                )
    return out


def pareto_front(points: list[tuple[str, float, float]]) -> list[str]:
    """Names of the (name, seconds, error) points no other point beats on both (lower is better)."""
    front = []
    for name, s, e in points:
        dominated = any((s2 <= s and e2 <= e) and (s2 < s or e2 < e) for n2, s2, e2 in points if n2 != name)
        if not dominated:
            front.append(name)
    return front


def plot_pareto(summary: list[dict[str, Any]], path: str | Path, by_split: list[dict[str, Any]] | None = None) -> list[str]:
    """PNG of mean bad-2 against seconds per backend (log time axis) with the Pareto front.

    With ``by_split`` holding held-out rows, the front and the filled points are the held-out
    means and the tuned scenes' means are drawn hollow beside them; otherwise all rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    held = [s for s in (by_split or []) if s["split"] == "held-out"]
    tuned = [s for s in (by_split or []) if s["split"] == "tuned"] if held else []
    main = held or summary
    pts = [(s["backend"], s["seconds"], s["bad2"]) for s in main]
    front = pareto_front(pts)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
    for name, sec, err in pts:
        ax.scatter([sec], [err], s=40, color="tab:red" if name in front else "tab:grey", zorder=3)
        ax.annotate(name, (sec, err), textcoords="offset points", xytext=(5, 4), fontsize=8)
    if tuned:
        ax.scatter(
            [s["seconds"] for s in tuned],
            [s["bad2"] for s in tuned],
            s=40,
            facecolors="none",
            edgecolors="tab:blue",
            zorder=3,
            label="tuned scenes (" + ", ".join(TUNING_SCENES) + ")",
        )
    fp = sorted((sec, err) for n, sec, err in pts if n in front)
    if fp:
        label = "Pareto front, held-out scenes" if held else "Pareto front"
        ax.step([p[0] for p in fp], [p[1] for p in fp], where="post", color="tab:red", lw=1, label=label)
    ax.axhline(TARGET_BAD2, color="tab:green", ls="--", lw=0.8, label=f"target bad-2 {TARGET_BAD2:g} %")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per pair (median, one core)")
    ax.set_ylabel("mean bad-2 at full coverage (%)")
    ax.set_title("Disparity backends: error against run time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(str(path))
    plt.close(fig)
    return front


@click.command("disparity")
@click.option(
    "--scene",
    "scenes",
    multiple=True,
    type=click.Path(path_type=Path, file_okay=False, exists=True),
    help="MiddEval3 scene folder (im0.png, im1.png, disp0GT.pfm, optional mask0nocc.png); repeatable. "
    "Default: Motorcycle (scikit-image) plus Tsukuba and Adirondack (both exposures) from "
    "../shared/data/stereo_gt when present. Scenes other than motorcycle and tsukuba are held out.",
)
@click.option(
    "--backend", "backends", multiple=True, type=click.Choice(BACKENDS), help="Backend to run; repeatable. Default: all."
)
@click.option(
    "--perturbation",
    "perturbations",
    multiple=True,
    type=click.Choice(("none", "down2", "down4", "rot0.5")),
    help="Right-view perturbation; repeatable. Default: all four.",
)
@click.option(
    "--repeats", default=3, show_default=True, type=click.IntRange(1, 100), help="Runs per case; the median time is reported."
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
@click.option(
    "--plot",
    type=click.Path(path_type=Path, dir_okay=False),
    help="Write a PNG of mean bad-2 against seconds with the Pareto front (needs matplotlib).",
)
def bench_disparity_command(
    scenes: tuple[Path, ...],
    backends: tuple[str, ...],
    perturbations: tuple[str, ...],
    repeats: int,
    as_json: bool,
    plot: Path | None,
) -> None:
    """EPE, bad-1, bad-2 and coverage over valid ground truth at full coverage, and seconds (one core)."""
    import json

    from benchmarks.disparity import (
        PERTURBATIONS,
        benchmark_disparity,
        builtin_scenes,
        load_middeval3,
        plot_pareto,
    )
    from pipeline.errors import PipelineError

    try:
        loaded = [load_middeval3(s) for s in scenes] if scenes else builtin_scenes()
        document = benchmark_disparity(
            loaded, backends=backends or BACKENDS, perturbations=perturbations or PERTURBATIONS, repeats=repeats
        )
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if plot is not None:
        try:
            document["pareto_front"] = plot_pareto(document["summary"], plot, document["summary_by_split"])
        except ImportError as exc:
            raise click.ClickException(f"--plot needs matplotlib ({exc})") from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False, default=_nan_safe))
        return
    click.echo(
        f"{'scene':<14} {'perturbation':<12} {'backend':<14} {'epe':>7} {'bad1%':>7} {'bad2%':>7} "
        f"{'cover%':>7} {'conf%':>7} {'seconds':>8}"
    )
    for r in document["results"]:
        click.echo(
            f"{r['scene'][:14]:<14} {r['perturbation']:<12} {r['backend']:<14} {r['epe']:7.2f} "
            f"{r['bad1']:7.1f} {r['bad2']:7.1f} {r['coverage']:7.1f} {r['confident_coverage']:7.1f} "
            f"{r['seconds']:8.3f}"
        )
    click.echo("")
    click.echo(f"{'backend':<14} {'mean epe':>9} {'mean bad2%':>11} {'cover%':>7} {'median s':>9} {'s@741x500':>10}")
    for s in document["summary"]:
        click.echo(
            f"{s['backend']:<14} {s['epe']:9.2f} {s['bad2']:11.1f} {s['coverage']:7.1f} {s['seconds']:9.3f} "
            f"{s['seconds_741x500']:10.3f}"
        )
    click.echo("")
    click.echo(
        f"{'backend':<14} {'split':<9} {'epe':>6} {'bad1%':>7} {'bad2%':>7} {'cover%':>7} {'median s':>9} {'x dis-medium':>12}"
    )
    for s in document["summary_by_split"]:
        ratio = "-" if s["ratio_to_dis_medium"] is None else f"{s['ratio_to_dis_medium']:.1f}"
        click.echo(
            f"{s['backend']:<14} {s['split']:<9} {s['epe']:6.2f} {s['bad1']:7.1f} {s['bad2']:7.1f} "
            f"{s['coverage']:7.1f} {s['seconds']:9.3f} {ratio:>12}"
        )
    target = document["target"]
    click.echo(
        f"default backend: {document['default_backend']} (target: {target['split']} mean bad-2 <= "
        f"{target['mean_bad2']} % at <= {target['ratio_to_dis_medium']:g}x DIS medium's time; "
        f"tuned on {', '.join(document['tuning_scenes'])})"
    )
    if plot is not None:
        click.echo(f"plot: {plot} (Pareto front: {', '.join(document['pareto_front'])})")


def _nan_safe(value):  # pragma: no cover - numpy scalars only
    return float(value)

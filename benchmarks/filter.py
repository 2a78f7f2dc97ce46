"""Timing of the filter stage (split + SIFT + matching) on one core, for ``keystone bench filter``.

The pipeline parallelises by card (one OpenCV thread per worker process, see
:func:`pipeline.runner.init_worker`), so the figure that matters is seconds per card on one core;
the target is 0.35 s for halves of about 600 x 570 px.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

from pipeline.filter import FilterParams, good_match_fraction
from pipeline.io import read_image
from pipeline.split import crop_halves, split_card

TARGET_SECONDS = 0.35

MOUNT_RGB = (214, 201, 170)  # buff card stock, for synthetic cards


def benchmark_filter(
    cards: list[tuple[str, np.ndarray]], repeats: int = 3, params: FilterParams = FilterParams()
) -> dict[str, Any]:
    """Median seconds per card of each filter step on one OpenCV thread.

    ``cards``: ``(name, uint8 image)`` pairs. Each card is filtered ``repeats`` times; the
    result holds per card the median split, detect and match seconds, the median total (the
    whole :func:`pipeline.filter.filter_card` work: split, crop, grey + downscale, SIFT,
    matching), the halves' sizes as given to SIFT (``[w, h]``), the outcome and the fraction.
    OpenCV's thread count is set to 1 for the run and restored afterwards.
    """
    if repeats < 1:
        raise ValueError(f"Expected repeats >= 1, got {repeats}")
    previous_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    results = []
    try:
        for name, card in cards:
            split_s, detect_s, match_s, total_s = [], [], [], []
            for _ in range(repeats):
                start = time.perf_counter()
                split = split_card(card, params.split)
                split_s.append(time.perf_counter() - start)
                left, right = crop_halves(card, split)
                result = good_match_fraction(left, right, params)
                total_s.append(time.perf_counter() - start)
                detect_s.append(result.detect_seconds)
                match_s.append(result.match_seconds)
            results.append(
                {
                    "card": name,
                    "card_size": [int(card.shape[1]), int(card.shape[0])],
                    "half_size": list(result.left_size),
                    "right_half_size": list(result.right_size),
                    "keypoints": [result.keypoints_left, result.keypoints_right],
                    "outcome": result.outcome,
                    "good_match_fraction": round(result.good_match_fraction, 6),
                    "split_seconds": round(statistics.median(split_s), 6),
                    "detect_seconds": round(statistics.median(detect_s), 6),
                    "match_seconds": round(statistics.median(match_s), 6),
                    "total_seconds": round(statistics.median(total_s), 6),
                }
            )
    finally:
        cv2.setNumThreads(previous_threads)
    totals = [r["total_seconds"] for r in results]
    median_total = round(statistics.median(totals), 6) if totals else None
    return {
        "results": results,
        "median_total_seconds": median_total,
        "max_total_seconds": max(totals) if totals else None,
        "target_seconds": TARGET_SECONDS,
        "within_target": None if median_total is None else median_total <= TARGET_SECONDS,
        "threads": 1,
        "repeats": repeats,
    }


def default_bench_cards(shared_data: Path | None) -> list[tuple[str, np.ndarray]]:
    """The real full cards and Keystone-Mast raw scans under ``shared_data/stereocards`` when
    present (names relative to that folder); otherwise three synthetic cards built from
    scikit-image's Middlebury Motorcycle pair, so the benchmark runs on any install."""
    if shared_data is not None:
        root = Path(shared_data) / "stereocards"
        paths = sorted((root / "full_cards").glob("*.jpg")) + sorted((root / "keystone_mast_raw_scans").glob("*.jpg"))
        if paths:
            return [(str(path.relative_to(root)), read_image(path)) for path in paths]
    return synthetic_bench_cards()


def synthetic_bench_cards() -> list[tuple[str, np.ndarray]]:
    """Three cards from the Motorcycle pair (741 x 500 each view): on a mount at full size, on a
    mount at a 760 px web-scan scale, and as a greyscale raw-scan-like pair with film edges."""
    from skimage import data  # imported here: only the synthetic fallback needs it

    left, right, _ = data.stereo_motorcycle()
    small = [cv2.resize(view, (356, 240), interpolation=cv2.INTER_AREA) for view in (left, right)]
    grey = [cv2.cvtColor(view, cv2.COLOR_RGB2GRAY) for view in (left, right)]
    return [
        ("synthetic/motorcycle_mounted.png", mounted_pair(left, right, margin=(40, 30, 60, 50), gutter=24)),
        ("synthetic/motorcycle_web_card.png", mounted_pair(small[0], small[1], margin=(18, 14, 26, 40), gutter=12)),
        ("synthetic/motorcycle_raw_scan.png", film_strip_pair(grey[0], grey[1])),
    ]


def mounted_pair(
    left: np.ndarray,
    right: np.ndarray,
    margin: tuple[int, int, int, int] = (40, 30, 40, 50),
    gutter: int = 24,
    colour: tuple[int, int, int] = MOUNT_RGB,
) -> np.ndarray:
    """Two equal-size RGB views on a plain mount: ``margin`` = (left, top, right, bottom) px,
    ``gutter`` px of mount between the photos. Returns the uint8 ``(H, W, 3)`` card."""
    height, width = left.shape[:2]
    m_left, m_top, m_right, m_bottom = margin
    card = np.empty((m_top + height + m_bottom, m_left + 2 * width + gutter + m_right, 3), dtype=np.uint8)
    card[:] = colour
    card[m_top : m_top + height, m_left : m_left + width] = left
    x = m_left + width + gutter
    card[m_top : m_top + height, x : x + width] = right
    return card


def film_strip_pair(left: np.ndarray, right: np.ndarray, edge: int = 12) -> np.ndarray:
    """Two equal-size grey views side by side like a raw negative scan: a black film edge of
    ``edge`` px around and between the frames. Returns the uint8 ``(H, W)`` card."""
    height, width = left.shape[:2]
    card = np.zeros((height + 2 * edge, 2 * width + 3 * edge), dtype=np.uint8)
    card[edge : edge + height, edge : edge + width] = left
    card[edge : edge + height, 2 * edge + width : 2 * edge + 2 * width] = right
    return card


@click.command("filter")
@click.option(
    "--repeats", default=3, show_default=True, type=click.IntRange(1, 100), help="Runs per card; the median is reported."
)
@click.option(
    "--shared-data",
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder with the real test cards (../shared/data); default: found next to the checkout, "
    "else synthetic cards from scikit-image's Motorcycle pair.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def bench_filter_command(repeats: int, shared_data: Path | None, as_json: bool) -> None:
    """Seconds per card on one core for the split + SIFT filter, split into detect and match."""
    from core.console import emit_json

    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = default_bench_cards(shared_data)
    document = benchmark_filter(cards, repeats=repeats)
    if as_json:
        emit_json(document)
        return
    click.echo(f"{'card':<56} {'half':>10} {'split':>7} {'detect':>7} {'match':>7} {'total':>7}")
    for row in document["results"]:
        size = "x".join(str(v) for v in row["half_size"])
        click.echo(
            f"{row['card'][:56]:<56} {size:>10} {row['split_seconds']:7.3f} {row['detect_seconds']:7.3f} "
            f"{row['match_seconds']:7.3f} {row['total_seconds']:7.3f}"
        )
    click.echo(
        f"median total {document['median_total_seconds']:.3f} s per card (target <= {document['target_seconds']} s, one core)"
    )

"""``keystone bench export``: release throughput and peak memory on a synthetic catalogue.

The catalogue is N accepted cards on a throwaway SQLite database. To build it fast, the cards
share a few real stored originals and stage artifacts (Middlebury Motorcycle, as shipped with
scikit-image, at several crops) but each has its own id, content hash and review, so the
release writes N distinct cards. By default maps are kept small (160 x 108 views, the "512"
depth map at 128 x 128) so 10,000 cards fit on a shared disk; ``map_size=512`` gives real-size
cards instead (512 x 512 depth, 800 x 600 rectified views and disparity maps: about 9 MB of
release per card and format), to show that peak memory does not grow with the card count.
The export runs in a child process: its peak RSS (``getrusage``) is the export's own.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from exports.formats import default_format_names, format_names

VARIANTS = 4
VIEW_SIZE = (160, 108)  # (width, height) of each half in the default (small) synthetic cards
DEPTH_SIZE = 128
REAL_MAP_SIZE = 512  # the paper's depth maps
TARGET_RSS_MB = 500


def view_size_for(map_size: int | None) -> tuple[int, int]:
    """(width, height) of the synthetic rectified views: the small default, or 4:3 views scaled
    with the depth map (800 x 600 at 512, the size of one rectified half of a 1,600 px scan)."""
    if map_size is None:
        return VIEW_SIZE
    if map_size < 16:
        raise ValueError(f"Expected a map size of at least 16 px, got {map_size}")
    return (map_size * 25 // 16, map_size * 75 // 64)


def _variant_arrays(variant: int, view_size: tuple[int, int] = VIEW_SIZE, depth_size: int = DEPTH_SIZE) -> dict[str, np.ndarray]:
    """A real stereo card (Motorcycle halves side by side) and plausible maps for it: views
    ``view_size`` (W, H) RGB uint8, disparity (H, W) float32 px (NaN unknown), depth
    ``depth_size`` square float32 (f / d, baseline 1)."""
    from PIL import Image
    from skimage import data

    left, right, disp = data.stereo_motorcycle()
    x0 = 40 * variant  # a different crop per variant: distinct pixels, same kind of scene
    views = [np.asarray(Image.fromarray(v[:, x0 : x0 + 600]).resize(view_size, Image.Resampling.BOX)) for v in (left, right)]
    gutter = np.full((view_size[1], 8, 3), 200, np.uint8)
    scale = view_size[0] / 600
    truth = np.asarray(disp[:, x0 : x0 + 600], np.float32)
    truth = np.where(np.isfinite(truth), truth, np.nan)
    small = np.asarray(Image.fromarray(truth).resize(view_size, Image.Resampling.NEAREST), np.float32) * scale
    depth = np.asarray(
        Image.fromarray(1.2071 * view_size[1] / np.where(small > 0, small, np.nan)).resize(
            (depth_size, depth_size), Image.Resampling.NEAREST
        ),
        np.float32,
    )
    return {
        "card": np.concatenate([views[0], gutter, views[1]], axis=1),
        "left": views[0],
        "right": views[1],
        "disparity_left": small,
        "disparity_right": small,
        "depth_512": depth,
    }


SYNTHETIC_ORIENTATION = {
    "decision": "auto",
    "confidence": 0.99,
    "flags": {
        flag: {"p": 0.01, "decided": True, "value": False, "evidence": ["synthetic card"]}
        for flag in ("upside_down", "inverted", "swapped")
    },
}


def build_synthetic_catalogue(
    count: int, data_dir: Path, echo: Callable[[str], None] = print, map_size: int | None = None
) -> None:
    """Insert ``count`` accepted, graded cards with stage results pointing at shared artifacts
    (``map_size``: see :func:`view_size_for`; None keeps the small default maps)."""
    from sqlalchemy import insert

    from core.db import db
    from core.models import Card, Collection, StageResult
    from pipeline.io import write_json, write_npy, write_png
    from review.models import CardReview

    clock = time.perf_counter()
    view_size = view_size_for(map_size)
    shared: list[dict[str, Any]] = []
    for variant in range(VARIANTS):
        arrays = _variant_arrays(variant, view_size, map_size or DEPTH_SIZE)
        work = Path("derived") / "bench" / f"v{variant}"
        write_png(data_dir / work / "card.png", arrays["card"])
        write_png(data_dir / work / "left.png", arrays["left"])
        write_png(data_dir / work / "right.png", arrays["right"])
        for name in ("disparity_left", "disparity_right", "depth_512"):
            write_npy(data_dir / work / f"{name}.npy", arrays[name])
        width = view_size[0]
        write_json(
            data_dir / work / "rectification.json",
            {
                "convention": "column vectors, x' ~ H x; disparity d = x_left - x_right >= 0",
                "H_l": np.eye(3).tolist(),
                "H_r": np.eye(3).tolist(),
                "K": [[1.2071 * view_size[1], 0, width / 2], [0, 1.2071 * view_size[1], view_size[1] / 2], [0, 0, 1]],
                "R": np.eye(3).tolist(),
                "t": [1.0, 0.0, 0.0],
                "size": list(view_size),
                "left_box": [0, 0, width, view_size[1]],
                "right_box": [width + 8, 0, 2 * width + 8, view_size[1]],
            },
        )
        shared.append({"card": str(work / "card.png"), "work": work, "bytes": (data_dir / work / "card.png").stat().st_size})
    collection = Collection(name="bench-synthetic")
    db.session.add(collection)
    db.session.flush()
    grades = ("few", "some", "some")
    for start in range(0, count, 1000):
        chunk = range(start, min(count, start + 1000))
        card_rows = []
        for number in chunk:
            variant = shared[number % VARIANTS]
            card_rows.append(
                {
                    "collection_id": collection.id,
                    "content_hash": hashlib.sha256(f"bench-{number}".encode()).hexdigest(),
                    "stored_path": variant["card"],
                    "source_name": f"bench-{number:06d}.png",
                    "source_path": "(synthetic)",
                    "accession": f"2026.0001.{number:05d}",
                    "width": 2 * view_size[0] + 8,
                    "height": view_size[1],
                    "image_format": "PNG",
                    "byte_size": variant["bytes"],
                    "state": "pass",
                    "source_metadata": {"title": f"Synthetic card {number}", "url": f"https://example.org/cards/{number}"},
                }
            )
        ids = list(db.session.scalars(insert(Card).returning(Card.id), card_rows))
        results, reviews = [], []
        for number, card_id in zip(chunk, ids):
            work = shared[number % VARIANTS]["work"]
            # The orientation step decided each synthetic card upright (the flow rule releases
            # no card whose orientation is undecided).
            results.append(
                {
                    "card_id": card_id,
                    "stage": "orientation",
                    "param_hash": "bench0orientati0",
                    "status": "done",
                    "outcome": "auto",
                    "metrics": SYNTHETIC_ORIENTATION,
                    "artifacts": {},
                    "code_version": "0.1.0",
                }
            )
            results.append(
                {
                    "card_id": card_id,
                    "stage": "rectify",
                    "param_hash": "bench0rectify000",
                    "status": "done",
                    "metrics": {
                        "orientation": {"applied": []},
                        # no inputs_digest: a made-up one would make every card stale (runs.card_state)
                        "orientation_used": {"upside_down": False, "inverted": False, "swapped": False},
                    },
                    "artifacts": {
                        "left": str(work / "left.png"),
                        "right": str(work / "right.png"),
                        "rectification": str(work / "rectification.json"),
                    },
                    "code_version": "0.1.0",
                }
            )
            results.append(
                {
                    "card_id": card_id,
                    "stage": "disparity",
                    "param_hash": "bench0disparity0",
                    "status": "done",
                    "metrics": {},
                    "code_version": "0.1.0",
                    "artifacts": {name: str(work / f"{name}.npy") for name in ("disparity_left", "disparity_right", "depth_512")},
                }
            )
            grade = grades[number % len(grades)]
            results.append(
                {
                    "card_id": card_id,
                    "stage": "grade",
                    "param_hash": "bench0grade00000",
                    "status": "done",
                    "outcome": grade,
                    "metrics": {},
                    "artifacts": {},
                    "code_version": "0.1.0",
                }
            )
            reviews.append({"card_id": card_id, "auto_grade": grade, "grade": grade, "decision": "accepted"})
        db.session.execute(insert(StageResult), results)
        db.session.execute(insert(CardReview), reviews)
        db.session.commit()
    echo(f"built a synthetic catalogue of {count} accepted cards in {time.perf_counter() - clock:.1f} s")


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB since it started its program.

    Linux's ``getrusage`` ``ru_maxrss`` survives ``exec``: a child forked from a big process (a
    long test run) reports the parent's high-water mark. ``VmHWM`` in /proc belongs to the
    exec'd program's own memory map, so it is read first."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child_export(database_url: str, data_dir: str, out_dir: str, formats: str) -> dict[str, Any]:
    """Runs in the child process: export, then report time and this process's peak RSS."""
    from app import create_app
    from core.db import db
    from exports.release import publish_release

    app = create_app({"SQLALCHEMY_DATABASE_URI": database_url, "KEYSTONE_DATA_DIR": data_dir})
    with app.app_context():
        baseline = peak_rss_mb()
        clock = time.perf_counter()
        report = publish_release(out_dir, formats=formats, notes="benchmark", actor_label="bench")
        seconds = time.perf_counter() - clock
        db.session.remove()
    peak = peak_rss_mb()
    return {
        "path": report.path,
        "cards": report.cards,
        "files": report.files,
        "bytes": report.bytes,
        "export_seconds": seconds,
        "peak_rss_mb": peak,
        "rss_before_export_mb": baseline,
    }


def benchmark_export(
    count: int,
    *,
    formats: str = "keystonedepth,parquet",
    folder: Path | None = None,
    echo: Callable[[str], None] = print,
    map_size: int | None = None,
) -> dict[str, Any]:
    """Build the catalogue, export it in a child process, verify the release; the figures."""
    from app import create_app
    from app.schema import upgrade
    from core.db import db
    from exports.verify import verify_release

    root = Path(folder) if folder else Path(tempfile.mkdtemp(prefix="keystone-bench-export-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        database_url = f"sqlite:///{root / 'bench.sqlite3'}"
        data_dir = root / "data"
        app = create_app(
            {"SQLALCHEMY_DATABASE_URI": database_url, "KEYSTONE_DATA_DIR": str(data_dir)}, instance_path=root / "instance"
        )
        with app.app_context():
            upgrade(db.engine)
            build_synthetic_catalogue(count, data_dir, echo, map_size)
            db.session.remove()
            db.engine.dispose()
        code = "import json, sys; from benchmarks.export import _child_export; print(json.dumps(_child_export(*sys.argv[1:])))"
        env = {**os.environ, "KEYSTONE_INSTANCE_PATH": str(root / "instance")}
        done = subprocess.run(
            [sys.executable, "-c", code, database_url, str(data_dir), str(root / "releases"), formats],
            capture_output=True,
            text=True,
            env=env,
            check=False,
            cwd=Path(__file__).resolve().parents[1],
        )
        if done.returncode != 0:
            raise RuntimeError(f"the export child failed: {done.stderr.strip()[-2000:]}")
        child = json.loads(done.stdout.strip().splitlines()[-1])
        clock = time.perf_counter()
        verified = verify_release(child["path"], validate_croissant=count <= 2000)
        verify_seconds = time.perf_counter() - clock
        seconds = child["export_seconds"]
        return {
            "benchmark": "export",
            "cards": child["cards"],
            "formats": formats.split(","),
            "files": child["files"],
            "bytes": child["bytes"],
            "export_seconds": round(seconds, 3),
            "cards_per_second": round(child["cards"] / seconds, 2),
            "mb_per_second": round(child["bytes"] / 1e6 / seconds, 2),
            "peak_rss_mb": round(child["peak_rss_mb"], 1),
            "rss_before_export_mb": round(child["rss_before_export_mb"], 1),
            "target_rss_mb": TARGET_RSS_MB,
            "verified": verified.ok,
            "verify_seconds": round(verify_seconds, 3),
            "view_size": list(view_size_for(map_size)),
            "depth_size": [map_size or DEPTH_SIZE] * 2,
        }
    finally:
        if folder is None:
            shutil.rmtree(root, ignore_errors=True)


@click.command("export")
@click.option(
    "--cards",
    "card_count",
    default=10_000,
    show_default=True,
    type=click.IntRange(1, 1_000_000),
    help="Synthetic accepted cards in the catalogue.",
)
@click.option(
    "--format",
    "formats",
    default=",".join(default_format_names()),
    show_default=True,
    help=f"Comma-separated layouts: {', '.join(format_names())}.",
)
@click.option(
    "--dir",
    "folder",
    type=click.Path(path_type=Path, file_okay=False),
    help="Work folder (catalogue, store, release); default a temporary folder, removed after.",
)
@click.option(
    "--map-size",
    type=click.IntRange(16, 4096),
    default=None,
    help="Real-size cards: depth maps MAP_SIZE x MAP_SIZE, rectified views and disparity 4:3 at "
    "MAP_SIZE*25/16 wide (512 gives 800 x 600, ~9 MB per card and format). "
    "Default: small maps (160 x 108 views, 128 x 128 depth).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def bench_export_command(card_count: int, formats: str, folder: Path | None, map_size: int | None, as_json: bool) -> None:
    """Release throughput (cards/s) and peak memory on a synthetic catalogue of accepted cards.

    The export runs in a child process so its peak resident memory is its own."""
    from core.console import emit_json

    document = benchmark_export(
        card_count,
        formats=formats,
        folder=folder,
        map_size=map_size,
        echo=(lambda m: click.echo(m, err=True)) if as_json else click.echo,
    )
    if as_json:
        emit_json(document)
        return
    click.echo(
        f"{document['cards']} cards in {document['export_seconds']:.1f} s: {document['cards_per_second']:.1f} "
        f"cards/s, {document['mb_per_second']:.1f} MB/s; peak RSS {document['peak_rss_mb']:.0f} MB "
        f"(target < {document['target_rss_mb']} MB); verify {document['verify_seconds']:.1f} s, ok={document['verified']}"
    )

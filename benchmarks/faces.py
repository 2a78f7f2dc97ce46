"""Measure the ``face_upright`` cue (:mod:`pipeline.faces`) on real photos, one photo at a time.

Sets (all stored the right way up):

* ``cards``: the photos of the shared real cards (``/work/shared/data/stereocards``): the nine
  full NYPL cards and the two Keystone-Mast raw scans split with
  :func:`pipeline.split.split_card` (left and right box), the three JPS pairs cut in half, the
  depthy 7995 left and right images: 30 photos. Thresholds are chosen here.
* ``cards_negative``: the same photos as negatives (``255 - v``).
* ``keystonedepth``: the 100 KeystoneDepth rectified left views
  (``keystonedepth/rectified_left_vis/train/<label>/*.png``). TEST ONLY: reported, never tuned on.

Each photo, as stored and turned 180 deg, is scored by :func:`pipeline.faces.faces_both_ways`
(which itself searches it as given and turned). Per set and variant: ``fired`` (photos whose
value is not 0), ``right`` (value > 0 for an upright photo, < 0 for a turned one), ``wrong``.
``sweep`` recounts the same searches at other ``min_score`` values, with and without the
landmark check (eyes above mouth). Seconds: median wall and CPU time of one photo's two searches
on one OpenCV thread (as in a pipeline worker), and of reading the nets once.

    python -m benchmarks.faces [--json] [--data DIR] [--max-side 640] [--min-face 20] [--photos] [--sets cards,...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.faces import Face, FaceParams, PhotoFaces, detect_faces, faces_both_ways
from pipeline.io import read_image
from pipeline.split import split_card

DEFAULT_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SWEEP_SCORES = (0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)


def card_photos(data: Path) -> list[tuple[str, np.ndarray]]:
    """The 30 photos of the shared real cards, as stored (upright)."""
    root = data / "stereocards"
    photos = []
    for sub in ("full_cards", "keystone_mast_raw_scans"):
        for path in sorted((root / sub).glob("*.jpg")):
            card = read_image(path)
            split = split_card(card)
            for side, (x0, y0, x1, y1) in (("left", split.left_box), ("right", split.right_box)):
                photos.append((f"{path.stem}:{side}", np.ascontiguousarray(card[y0:y1, x0:x1])))
    for path in sorted((root / "cropped_pairs" / "jps").glob("*.jps")):
        pair = read_image(path)
        half = pair.shape[1] // 2
        photos += [(f"{path.stem}:left", pair[:, :half].copy()), (f"{path.stem}:right", pair[:, half : 2 * half].copy())]
    pair_dir = root / "cropped_pairs" / "depthy_7995"
    for name in ("7995l-image.jpg", "7995r-image.jpg"):
        if (pair_dir / name).exists():
            photos.append((f"depthy_7995:{name[:5]}", read_image(pair_dir / name)))
    return photos


def keystonedepth_photos(data: Path) -> list[tuple[str, np.ndarray]]:
    root = data / "keystonedepth" / "rectified_left_vis" / "train"
    return [(f"{p.parent.name}/{p.stem}", read_image(p)) for p in sorted(root.glob("*/*.png"))]


def _value(searched: PhotoFaces, min_score: float, landmark_check: bool) -> float:
    def count(faces: tuple[Face, ...]) -> int:
        return sum(f.score >= min_score and (f.eyes_above_mouth or not landmark_check) for f in faces)

    up, down = count(searched.upright), count(searched.turned)
    return (up - down) / (up + down + 1.0)


def _tally(values: list[float], upright: bool) -> dict[str, int]:
    return {
        "photos": len(values),
        "fired": sum(v != 0 for v in values),
        "right": sum(v > 0 if upright else v < 0 for v in values),
        "wrong": sum(v < 0 if upright else v > 0 for v in values),
    }


def measure_variant(photos: list[tuple[str, np.ndarray]], params: FaceParams, upright: bool) -> dict[str, Any]:
    rows, wall, cpu = [], [], []
    for name, photo in photos:
        image = photo if upright else np.ascontiguousarray(photo[::-1, ::-1])
        clock, cpu_clock = time.perf_counter(), time.process_time()
        searched = faces_both_ways(image, params)
        wall.append(time.perf_counter() - clock)
        cpu.append(time.process_time() - cpu_clock)
        rows.append((name, searched))
    values = [_value(s, params.min_score, True) for _, s in rows]
    return {
        **_tally(values, upright),
        "seconds_per_photo_median": round(statistics.median(wall), 4),
        "cpu_seconds_per_photo_median": round(statistics.median(cpu), 4),
        "seconds_per_photo_max": round(max(wall), 4),
        "sweep": {
            f"{score}{'' if check else ' no landmark check'}": _tally([_value(s, score, check) for _, s in rows], upright)
            for check in (True, False)
            for score in SWEEP_SCORES
        },
        "photos_fired": {
            name: {"value": round(v, 3), **s.as_dict(), "all_upright": [f.as_dict() for f in s.upright]}
            for (name, s), v in zip(rows, values)
            if any(f.score >= SWEEP_SCORES[0] for f in (*s.upright, *s.turned))
        },
    }


def measure(photos: list[tuple[str, np.ndarray]], params: FaceParams, negative: bool = False) -> dict[str, Any]:
    if negative:
        photos = [(name, 255 - photo) for name, photo in photos]
    return {"as_given": measure_variant(photos, params, True), "turned": measure_variant(photos, params, False)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--max-side", type=int, default=FaceParams().max_side)
    parser.add_argument("--min-face", type=float, default=FaceParams().min_face_px, help="min_face_px")
    parser.add_argument("--photos", action="store_true", help="list every photo where a face was found")
    parser.add_argument("--sets", default="cards,cards_negative,keystonedepth")
    args = parser.parse_args(argv)
    if not (args.data / "stereocards").is_dir():
        print(f"no shared data at {args.data}", file=sys.stderr)
        return 2
    params = dataclasses.replace(FaceParams(), max_side=args.max_side, min_face_px=args.min_face)
    cv2.setNumThreads(1)  # as pipeline.runner.init_worker: one core per worker
    clock = time.perf_counter()
    detect_faces(np.zeros((64, 64, 3), np.uint8), params)  # reads the nets once
    report: dict[str, Any] = {"params": dataclasses.asdict(params), "seconds_first_call": round(time.perf_counter() - clock, 3)}
    sets = args.sets.split(",")
    if "cards" in sets or "cards_negative" in sets:
        cards = card_photos(args.data)
        if "cards" in sets:
            report["cards"] = measure(cards, params)
        if "cards_negative" in sets:
            report["cards_negative"] = measure(cards, params, negative=True)
    if "keystonedepth" in sets:
        report["keystonedepth"] = measure(keystonedepth_photos(args.data), params)
    keys = [(key, variant) for key in ("cards", "cards_negative", "keystonedepth") if key in report for variant in report[key]]
    if not args.photos:
        for key, variant in keys:
            report[key][variant]["photos_fired"] = sorted(report[key][variant]["photos_fired"])
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    for key, variant in keys:
        r = report[key][variant]
        print(
            f"{key:15s} {variant:9s} {r['photos']:3d} photos: fired {r['fired']}, right {r['right']}, wrong {r['wrong']}; "
            f"{r['seconds_per_photo_median']:.3f} s, {r['cpu_seconds_per_photo_median']:.3f} CPU-s a photo (median)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

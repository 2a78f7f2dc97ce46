"""The orientation decision on distorted pairs and on one card at many sizes and formats (issue 35.4).

Each upright real card (``/work/shared/data/stereocards/full_cards``, NYPL mounted prints) is
made into variants a scanner, a printer or a bad crop could give: one photo enlarged 1.3x
about its centre and cut back to its box, the two photos turned by a few degrees (the same
way and opposite ways), one photo cut unevenly and stretched back, the whole card at 0.25x to
4x, and round trips through JPEG (quality 75 and 95) and PNG. Every variant is split and its
orientation estimated as the pipeline would; a variant is *confident-wrong* when it is decided
automatically on flags other than upright, positive, in eye order (the truth for every card).
A cue that cannot read a photo must give no evidence: people are asked instead.

    python -m benchmarks.orientation_distorted [--json] [--data DIR] [--cards demo1,pima]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from pipeline.io import read_image
from pipeline.orientation import OrientationParams, estimate_orientation
from pipeline.split import split_card

Box = tuple[int, int, int, int]
DEFAULT_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
UPRIGHT = {"upside_down": False, "inverted": False, "swapped": False}


def _photo(card: np.ndarray, box: Box, change: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``card`` with the photo in ``box`` replaced by ``change(photo)`` (same size)."""
    x0, y0, x1, y1 = box
    out = card.copy()
    out[y0:y1, x0:x1] = change(np.ascontiguousarray(card[y0:y1, x0:x1]))
    return out


def enlarged(photo: np.ndarray, factor: float) -> np.ndarray:
    """The photo enlarged about its centre and cut back to its size."""
    h, w = photo.shape[:2]
    big = cv2.resize(photo, None, fx=factor, fy=factor, interpolation=cv2.INTER_LINEAR)
    top, left = (big.shape[0] - h) // 2, (big.shape[1] - w) // 2
    return np.ascontiguousarray(big[top : top + h, left : left + w])


def turned_by(photo: np.ndarray, degrees: float) -> np.ndarray:
    """The photo turned about its centre (counter-clockwise for positive degrees), edges reflected."""
    h, w = photo.shape[:2]
    matrix = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), degrees, 1.0)
    return cv2.warpAffine(photo, matrix, (w, h), borderMode=cv2.BORDER_REFLECT)


def cut_unevenly(photo: np.ndarray, sides: tuple[float, float, float, float]) -> np.ndarray:
    """The photo less the fractions ``(left, top, right, bottom)`` of it, stretched back to its size."""
    h, w = photo.shape[:2]
    left, top, right, bottom = sides
    kept = photo[int(top * h) : h - int(bottom * h), int(left * w) : w - int(right * w)]
    return cv2.resize(kept, (w, h), interpolation=cv2.INTER_AREA)


def rescaled(card: np.ndarray, factor: float) -> np.ndarray:
    return cv2.resize(card, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC)


def round_trip(card: np.ndarray, extension: str, quality: int = 0) -> np.ndarray:
    """``card`` (RGB or grey) written as ``extension`` (".jpg" at ``quality``, ".png") and read back."""
    colour = card.ndim == 3
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if quality else []
    ok, data = cv2.imencode(extension, cv2.cvtColor(card, cv2.COLOR_RGB2BGR) if colour else card, params)
    if not ok:
        raise ValueError(f"could not encode the card as {extension}")
    back = cv2.imdecode(data, cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    return cv2.cvtColor(back, cv2.COLOR_BGR2RGB) if colour else back


DISTORTIONS = ("right_x1.3", "left_x1.3", "turned_L+4_R-3", "turned_L-5_R+5", "right_cut_unevenly", "left_cut_unevenly")
SIZES_AND_FORMATS = ("x0.25", "x0.5", "x2", "x4", "jpeg75", "jpeg95", "png")


def variants(
    card: np.ndarray, names: tuple[str, ...] = ("original", *DISTORTIONS, *SIZES_AND_FORMATS)
) -> Iterator[tuple[str, np.ndarray]]:
    """``(name, image)`` for each named variant of an upright card (the split's boxes are the photos)."""
    split = split_card(card)
    lb, rb = split.left_box, split.right_box
    made: dict[str, Callable[[], np.ndarray]] = {
        "original": lambda: card,
        "right_x1.3": lambda: _photo(card, rb, lambda p: enlarged(p, 1.3)),
        "left_x1.3": lambda: _photo(card, lb, lambda p: enlarged(p, 1.3)),
        "turned_L+4_R-3": lambda: _photo(_photo(card, lb, lambda p: turned_by(p, 4.0)), rb, lambda p: turned_by(p, -3.0)),
        "turned_L-5_R+5": lambda: _photo(_photo(card, lb, lambda p: turned_by(p, -5.0)), rb, lambda p: turned_by(p, 5.0)),
        "right_cut_unevenly": lambda: _photo(card, rb, lambda p: cut_unevenly(p, (0.08, 0.02, 0.0, 0.10))),
        "left_cut_unevenly": lambda: _photo(card, lb, lambda p: cut_unevenly(p, (0.0, 0.10, 0.06, 0.0))),
        "x0.25": lambda: rescaled(card, 0.25),
        "x0.5": lambda: rescaled(card, 0.5),
        "x2": lambda: rescaled(card, 2.0),
        "x4": lambda: rescaled(card, 4.0),
        "jpeg75": lambda: round_trip(card, ".jpg", 75),
        "jpeg95": lambda: round_trip(card, ".jpg", 95),
        "png": lambda: round_trip(card, ".png"),
    }
    for name in names:
        yield name, made[name]()


def decide(image: np.ndarray, params: OrientationParams | None = None) -> dict:
    """The orientation step's outcome on one variant: decision, proposal, its probability, the
    cues that gave evidence and why the stereo cues or the arches were not read."""
    split = split_card(image)
    estimate = estimate_orientation(image, split.left_box, split.right_box, params or OrientationParams())
    proposed = estimate.proposed_orientation()
    return {
        "decision": estimate.decision,
        "proposed": proposed,
        "probability": round(estimate.combination_probability, 3),
        "confident_wrong": estimate.decision == "auto" and proposed != UPRIGHT,
        "cues": {cue.name: round(cue.value, 3) for cue in estimate.cues if cue.value != 0.0},
        "arches": estimate.details.get("arches"),
        "stereo_unread": estimate.details.get("stereo_unread"),
        "undecidable": estimate.undecidable,
    }


def measure(data: Path, cards: list[str] | None = None) -> dict:
    rows = []
    for path in sorted((data / "stereocards" / "full_cards").glob("*.jpg")):
        if cards and not any(name in path.stem for name in cards):
            continue
        for name, image in variants(read_image(path)):
            rows.append({"card": path.stem, "variant": name, **decide(image)})
    summary = {
        group: {
            "variants": len(chosen := [r for r in rows if r["variant"] in names]),
            "auto": sum(r["decision"] == "auto" for r in chosen),
            "asked_or_confirm": sum(r["decision"] != "auto" for r in chosen),
            "confident_wrong": sum(r["confident_wrong"] for r in chosen),
        }
        for group, names in (("original", ("original",)), ("distorted", DISTORTIONS), ("sizes_and_formats", SIZES_AND_FORMATS))
    }
    return {"summary": summary, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--cards", help="comma-separated parts of card names (default: every full card)")
    args = parser.parse_args(argv)
    if not (args.data / "stereocards" / "full_cards").is_dir():
        print(f"no shared data at {args.data}", file=sys.stderr)
        return 2
    report = measure(args.data, args.cards.split(",") if args.cards else None)
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    for row in report["rows"]:
        flags = ",".join(k for k, v in (row["proposed"] or {}).items() if v) or "upright"
        wrong = "  CONFIDENT-WRONG" if row["confident_wrong"] else ""
        print(f"{row['card'][:40]:40s} {row['variant']:18s} {row['decision']:7s} {flags:22s} P={row['probability']:.3f}{wrong}")
    print(json.dumps(report["summary"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

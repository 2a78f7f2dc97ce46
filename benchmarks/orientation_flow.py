"""The orientation flow on real cards, end to end through ``keystone`` on a fresh instance.

Each card (taken as correctly oriented as stored) becomes four scans: the original, the card
turned 180 deg, its negative, and the card with its two photos exchanged (the split's boxes,
:func:`pipeline.orientation.orient_variant`). They are ingested into a fresh catalogue (a temp
folder: SQLite and a data dir) and run with ``keystone run --stages
filter,orientation,rectify,disparity,grade``; ``keystone cards --json`` is read back. Measured:

* ``wrong_graded``: cards graded with an orientation other than the truth (must be 0);
* ``auto_right`` / ``auto_wrong``: decided automatically (``decided_by == "auto"``) and right /
  wrong, over all variants (target: auto_right >= 85 %);
* ``decision``: the step's own outcome per variant (``auto``, ``confirm``: a proposal people
  confirm in a grid, ``ask``: a one-card judge task), with ``proposal_right`` for the confirms;
* ``sent_to_people``: variants waiting for people; ``originals_sent_to_people`` of the originals
  (sent needlessly: target at most one in seven);
* per flag, the share right among the flags the step decided (``flag_accuracy``), with the
  split the cue weights were tuned on (``benchmarks.orientation.TUNE``) kept apart;
* ``crop``: every crop box the pipeline would use (photo area, else the filter split) against
  the hand-drawn photo (``tests/pipeline/data/photo_area_truth.csv``, mapped onto each variant):
  inside, and IoU;
* ``seconds_per_card``: each stage's seconds per card in this run (one worker).

    python -m benchmarks.orientation --flow [--json] [--data DIR] [--scans DIR [--truth CSV]]

``--scans DIR`` measures other cards (every image in DIR, taken as correctly oriented; hand
boxes from ``--truth`` in the CSV format above, paths relative to DIR).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image

from pipeline.io import read_image
from pipeline.orientation import orient_variant
from pipeline.split import split_card

from .orientation_split import TUNE
from .photo_area import TRUTH, inside, iou, read_truth

Box = tuple[int, int, int, int]
FLAGS = ("upside_down", "inverted", "swapped")
VARIANT_FLAGS: dict[str, tuple[bool, bool, bool]] = {
    "original": (False, False, False),
    "rotated_180": (True, False, False),
    "negative": (False, True, False),
    "swapped": (False, False, True),
    # the original at another size (0.6x when wider than 1200 px, else 1.5x): the cues and the
    # network must not depend on the scan's resolution
    "rescaled": (False, False, False),
}
STAGES = "filter,orientation,rectify,disparity,grade"


def _variant_truth(
    name: str, shape: tuple[int, int], split: tuple[Box, Box], truth: tuple[Box, Box] | None
) -> tuple[Box, Box] | None:
    """The hand boxes (left photo, right photo on the scan) mapped onto a variant."""
    if truth is None:
        return None
    left, right = truth
    height, width = shape
    if name == "rotated_180":

        def turn(b: Box) -> Box:
            return (width - b[2], height - b[3], width - b[0], height - b[1])

        return turn(right), turn(left)
    if name == "swapped":
        lb, rb = split
        dx, dy = rb[0] - lb[0], rb[1] - lb[1]
        return (
            (right[0] - dx, right[1] - dy, right[2] - dx, right[3] - dy),
            (left[0] + dx, left[1] + dy, left[2] + dx, left[3] + dy),
        )
    return left, right


def make_variants(cards: list[tuple[str, Path, tuple[Box, Box] | None]], out: Path) -> dict[str, dict[str, Any]]:
    """Write the four variants of each card as PNG into ``out``; returns file name -> truth."""
    out.mkdir(parents=True, exist_ok=True)
    truths: dict[str, dict[str, Any]] = {}
    for stem, path, boxes in cards:
        card = read_image(path)
        split = split_card(card)
        lb, rb = split.left_box, split.right_box
        width = min(lb[2] - lb[0], rb[2] - rb[0])
        height = min(lb[3] - lb[1], rb[3] - rb[1])
        same = ((lb[0], lb[1], lb[0] + width, lb[1] + height), (rb[0], rb[1], rb[0] + width, rb[1] + height))
        for name, flags in VARIANT_FLAGS.items():
            if name == "rotated_180":
                image = np.ascontiguousarray(card[::-1, ::-1])
            elif name == "negative":
                image = 255 - card
            elif name == "swapped":
                image, _, _ = orient_variant(card, same[0], same[1], False, False, True)
            elif name == "rescaled":
                factor = 0.6 if card.shape[1] > 1200 else 1.5
                size = (round(card.shape[1] * factor), round(card.shape[0] * factor))
                image = cv2.resize(card, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_CUBIC)
            else:
                image = card
            file_name = f"{stem}__{name}.png"
            Image.fromarray(image).save(out / file_name)
            truths[file_name] = {
                "card": stem,
                "variant": name,
                "flags": dict(zip(FLAGS, flags)),
                "split": "tune" if stem in TUNE else "held_out",
                "boxes": None if name == "rescaled" else _variant_truth(name, card.shape[:2], same, boxes),
            }
    return truths


def _keystone(args: list[str], env: dict[str, str]) -> dict[str, Any]:
    result = subprocess.run([sys.executable, "-m", "app", *args], env=env, capture_output=True, text=True, check=False)
    if result.returncode not in (0, 1):
        raise RuntimeError(f"keystone {' '.join(args)} exited {result.returncode}: {result.stderr[-2000:]}")
    return json.loads(result.stdout)


def run_flow(scans: Path, instance: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Ingest and run on a fresh instance; the run report and ``keystone cards --json``."""
    env = {
        **os.environ,
        "KEYSTONE_DATABASE_URL": f"sqlite:///{instance / 'keystone.sqlite3'}",
        "KEYSTONE_DATA_DIR": str(instance / "data"),
        "KEYSTONE_INSTANCE_PATH": str(instance / "instance"),
        "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
    }
    _keystone(["ingest", str(scans), "--json"], env)
    report = _keystone(["run", "--stages", STAGES, "--json"], env)
    cards = _keystone(["cards", "--json"], env)["cards"]
    return report, cards


def evaluate(truths: dict[str, dict[str, Any]], report: dict[str, Any], cards: list[dict[str, Any]]) -> dict[str, Any]:
    rows = []
    for card in cards:
        truth = truths.get(card["source"])
        if truth is None:
            continue
        stages = card["stages"]
        orientation = card["orientation"]
        step = stages.get("orientation", {})
        metrics = step.get("metrics") or {}
        right = all(orientation[f] == truth["flags"][f] for f in FLAGS)
        filter_box = stages["filter"].get("metrics") or {}
        fallback = metrics.get("photo_area_fallback") or not metrics.get("photo_left_box")
        used = (
            (filter_box.get("left_box"), filter_box.get("right_box"))
            if fallback
            else (metrics.get("photo_left_box"), metrics.get("photo_right_box"))
        )
        crop: dict[str, Any] = {"source": "filter split" if fallback else "photo area"}
        if truth["boxes"] is not None and used[0] is not None:
            crop.update(
                inside=[inside(tuple(b), tuple(t)) for b, t in zip(used, truth["boxes"])],
                iou=[round(iou(tuple(b), tuple(t)), 4) for b, t in zip(used, truth["boxes"])],
            )
        rows.append(
            {
                "source": card["source"],
                "card": truth["card"],
                "variant": truth["variant"],
                "split": truth["split"],
                "filter": stages["filter"].get("outcome"),
                "decision": step.get("outcome"),
                "step_status": step.get("status"),
                "orientation": orientation,
                "truth": truth["flags"],
                "right": right,
                "flags_step": {f: (metrics.get("flags") or {}).get(f, {}).get("value") for f in FLAGS},
                "proposal_right": (metrics.get("proposed") or {}) == truth["flags"],
                "graded": stages["grade"]["status"] == "done",
                "grade": stages["grade"].get("outcome"),
                "crop": crop,
            }
        )
    return summarise(rows, report)


def summarise(rows: list[dict[str, Any]], report: dict[str, Any]) -> dict[str, Any]:
    n = len(rows)
    auto = [r for r in rows if r["orientation"]["decided_by"] == "auto"]
    originals = [r for r in rows if r["variant"] == "original" and r["filter"] in ("pass", "review")]
    flag_accuracy: dict[str, dict[str, Any]] = {}
    for split in ("tune", "held_out", "all"):
        chosen = [r for r in rows if split == "all" or r["split"] == split]
        flag_accuracy[split] = {}
        for flag in FLAGS:
            decided = [r for r in chosen if r["flags_step"][flag] is not None]
            flag_accuracy[split][flag] = {
                "decided": len(decided),
                "of": len(chosen),
                "right": sum(r["flags_step"][flag] == r["truth"][flag] for r in decided),
            }
    boxes = [r["crop"] for r in rows if "inside" in r["crop"]]
    halves_inside = sum(sum(c["inside"]) for c in boxes)
    ious = [v for c in boxes for v in c["iou"]]
    seconds = {
        s["stage"]: (round(s["seconds"] / s["processed"], 3) if s["processed"] else None) for s in report.get("stages", [])
    }
    return {
        "variants": n,
        "wrong_graded": [r["source"] for r in rows if r["graded"] and not r["right"]],
        "graded": sum(r["graded"] for r in rows),
        "auto_right": sum(r["right"] for r in auto),
        "auto_wrong": [r["source"] for r in auto if not r["right"]],
        "auto_right_fraction": round(sum(r["right"] for r in auto) / n, 4) if n else None,
        "sent_to_people": sum(r["orientation"]["decided_by"] is None for r in rows),
        "decisions": {d: sum(r["decision"] == d for r in rows) for d in ("auto", "confirm", "ask")},
        "confirm_proposals_right": sum(r["decision"] == "confirm" and r["proposal_right"] for r in rows),
        "per_variant": {
            v: {
                "n": sum(r["variant"] == v for r in rows),
                "auto_right": sum(r["variant"] == v and r["right"] and r["orientation"]["decided_by"] == "auto" for r in rows),
                "sent_to_people": sum(r["variant"] == v and r["orientation"]["decided_by"] is None for r in rows),
            }
            for v in VARIANT_FLAGS
        },
        "originals_sent_to_people": sum(r["orientation"]["decided_by"] is None for r in originals),
        "originals": len(originals),
        "waiting_for_people": report.get("waiting_for_people"),
        "flag_accuracy": flag_accuracy,
        "crop": {
            "halves": 2 * len(boxes),
            "inside": halves_inside,
            "photo_area_used": sum(c["source"] == "photo area" for c in boxes),
            "mean_iou": round(float(np.mean(ious)), 4) if ious else None,
            "not_inside": [r["source"] for r in rows if "inside" in r["crop"] and not all(r["crop"]["inside"])],
        },
        "seconds_per_card": seconds,
        "rows": rows,
    }


def shared_cards(data: Path) -> list[tuple[str, Path, tuple[Box, Box] | None]]:
    """The real cards with hand-drawn photo areas (full cards and Keystone-Mast raw scans)."""
    root = data / "stereocards"
    return [(Path(name).stem, root / name, (left, right)) for name, left, right in read_truth(TRUTH) if (root / name).is_file()]


def folder_cards(folder: Path, truth_csv: Path | None) -> list[tuple[str, Path, tuple[Box, Box] | None]]:
    boxes = {name: (left, right) for name, left, right in read_truth(truth_csv)} if truth_csv else {}
    return [
        (path.stem, path, boxes.get(str(path.relative_to(folder))))
        for path in sorted(folder.rglob("*"))
        if path.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff")
    ]


def main_flow(data: Path, scans: Path | None, truth_csv: Path | None, as_json: bool, keep: Path | None) -> int:
    cards = folder_cards(scans, truth_csv) if scans is not None else shared_cards(data)
    if not cards:
        print("no cards to measure", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="keystone-flow-") as tmp:
        root = keep or Path(tmp)
        truths = make_variants(cards, root / "scans")
        report, listing = run_flow(root / "scans", root)
        result = evaluate(truths, report, listing)
    if as_json:
        print(json.dumps(result, indent=1, default=float))
    else:
        for key, value in result.items():
            if key != "rows":
                print(f"{key}: {value}")
    return 0

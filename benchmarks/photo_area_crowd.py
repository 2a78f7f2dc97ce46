"""Photo-area proposals against the simulated crowd's consensus crop boxes (IoU).

The crowd's crop task asks each annotator for the artifact-free rectangle of each photo; the
proposal (:func:`pipeline.photo_area.find_photo_areas`) is what the crop tool opens on and the
default crop when nobody draws. Here the simulated crowd draws on simulated cards whose prints
are known exactly (:func:`simulation.cards.make_stereo_card`: arched and square prints, printed
titles and captions, stains and scratches): each of four annotators answers with
:func:`annotation.simulate.simulated_answer` (three honest, HONEST_ACCURACY, and one spammer)
around the true print box shrunk by ``CROP_INSET_FRACTION`` a side (the print's own edge is not
artifact-free), and :func:`annotation.aggregation.consensus_box` makes the consensus as the
crowd's aggregation does. Measured per half: IoU(proposal, consensus), IoU(proposal, truth),
IoU(consensus, truth) and whether the proposal lies inside the print; CPU seconds per card.

    python -m benchmarks.photo_area_crowd [--cards N] [--seed S] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np

from .photo_area import inside, iou

Box = tuple[float, float, float, float]


def measure(cards: int, seed: int) -> dict[str, Any]:
    from annotation.aggregation import consensus_box
    from annotation.simulate import CROP_INSET_FRACTION, HONEST_ACCURACY, SimulatedWorker, simulated_answer
    from pipeline.photo_area import find_photo_areas
    from simulation.cards import make_stereo_card

    workers = [SimulatedWorker(k, f"honest-{k}", a, False) for k, a in enumerate(HONEST_ACCURACY[:3])]
    workers.append(SimulatedWorker(9, "spammer", 0.5, True))
    rng = np.random.default_rng(seed)
    rows = []
    for index in range(cards):
        card = make_stereo_card(seed, index)
        height, width = card.image.shape[:2]
        prints = [tuple(float(v) for v in b) for b in card.truth["photo_boxes"]]
        truth = {}
        for half, (x0, y0, x1, y1) in zip(("left", "right"), prints, strict=True):
            dx, dy = max(2.0, CROP_INSET_FRACTION * (x1 - x0)), max(2.0, CROP_INSET_FRACTION * (y1 - y0))
            truth[half] = [x0 + dx, y0 + dy, x1 - dx, y1 - dy]
        answers = [simulated_answer("crop", truth, w, (width, height), rng) for w in workers]
        clock = time.process_time()
        areas = find_photo_areas(card.image)
        seconds = time.process_time() - clock
        for half, proposal, print_box in zip(("left", "right"), (areas.left_box, areas.right_box), prints, strict=True):
            consensus = consensus_box([a[half] for a in answers], image_size=(width, height)).box
            proposal_f = tuple(float(v) for v in proposal)
            rows.append(
                {
                    "card": card.name,
                    "half": half,
                    "photo_shape": card.truth.get("photo_shape"),
                    "proposal": list(proposal_f),
                    "consensus": [round(v, 1) for v in consensus],
                    "truth": truth[half],
                    "iou_proposal_consensus": round(iou(proposal_f, consensus), 4),
                    "iou_proposal_truth": round(iou(proposal_f, tuple(truth[half])), 4),
                    "iou_consensus_truth": round(iou(consensus, tuple(truth[half])), 4),
                    "proposal_inside_print": inside(proposal_f, print_box, tolerance=1),
                    "fallback": areas.fallback_reason,
                    "seconds": round(seconds, 4),
                }
            )

    def summary(key: str) -> dict[str, float]:
        values = np.array([r[key] for r in rows])
        return {
            "mean": round(float(values.mean()), 4),
            "median": round(float(np.median(values)), 4),
            "min": round(float(values.min()), 4),
        }

    return {
        "cards": cards,
        "halves": len(rows),
        "iou_proposal_consensus": summary("iou_proposal_consensus"),
        "iou_proposal_truth": summary("iou_proposal_truth"),
        "iou_consensus_truth": summary("iou_consensus_truth"),
        "proposal_inside_print": sum(r["proposal_inside_print"] for r in rows),
        "fallbacks": sum(r["fallback"] is not None for r in rows) // 2,
        "cpu_seconds_per_card_median": round(float(np.median([r["seconds"] for r in rows[::2]])), 4),
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cards", type=int, default=24)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--rows", action="store_true", help="include every half's boxes")
    args = parser.parse_args(argv)
    if args.cards < 1:
        parser.error("--cards must be at least 1")
    report = measure(args.cards, args.seed)
    if not args.rows:
        report.pop("rows")
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Calibrate and measure :mod:`pipeline.orientation` on variants of the shared real cards.

Each real card (``/work/shared/data/stereocards``: full cards, Keystone-Mast raw scans, cropped
pairs, the depthy pair set side by side) is taken as correctly oriented as stored (checked by
eye and by near/far disparity, see the report), split with :func:`pipeline.split.split_card`,
and turned into its eight variants (upside_down x inverted x swapped, made by
:func:`pipeline.orientation.orient_variant`). Each variant is split again, as the pipeline
would, and its cues measured. The cue weights are fitted (multinomial log-likelihood over the
eight hypotheses, L2-regularised, the L2 strength chosen by leave-one-card-out within the tune
cards with the one-standard-error rule) on the TUNE cards only and the accuracy is reported on
the HELD-OUT cards: per flag, the share right among decided flags; whole variants decided
automatically (the most probable flag combination at ``auto_probability``) and how many of those
are wrong; the same for the acceptance test's four variants per card (original, turned,
negative, halves swapped) with the originals sent to people; seconds per card. The defaults in :class:`OrientationParams` are this fit, rounded;
``held_out`` evaluates them, ``held_out_with_refitted_weights`` a fresh fit (should match).

    python -m benchmarks.orientation [--json] [--data DIR] [--rows]
    python -m benchmarks.orientation --scales 0.6,0.8,1,1.3,1.7
    python -m benchmarks.orientation --flow [--json] [--scans DIR [--truth CSV]] [--keep DIR]

Truth. Every card is taken as correct as stored. The NYPL cards are mounted prints; the JPS
pairs were checked parallel in PROVENANCE.md; for the two Keystone-Mast raw scans (one was said
to be eye-swapped as scanned) the near/far order was measured by template matching at full
resolution: 09995's foreground bush has x_left - x_right = 82 px against 55-57 px for the trees
behind the statue and 58-59 px for the statue (near = larger: left half is the left eye), and
the detector's occlusion side agrees (+0.33: 838 bands ending at near edges, 420 starting);
09997 is nearly all at infinity (within 1 px over the building, lawn and trees), but in the
same columns the road and car at the bottom are 2-3 px larger than the lawn (again left = left
eye; ground plane +0.49); its occlusion side is uninformative (150 vs 147 bands). Neither scan
reads as swapped; if one is, it would be 09997, which the geometry here does not support.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import minimize

from pipeline.io import read_image
from pipeline.orientation import (
    CUE_CONDITIONS,
    CUE_FLAGS,
    FLAGS,
    HYPOTHESES,
    OrientationParams,
    decided_combination,
    estimate_orientation,
    flag_probabilities,
    hypothesis_probabilities,
    orient_variant,
    parity,
)
from pipeline.split import split_card

from .orientation_split import TUNE

DEFAULT_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def load_cards(data: Path) -> list[tuple[str, np.ndarray]]:
    root = data / "stereocards"
    cards = []
    for sub in ("full_cards", "keystone_mast_raw_scans"):
        for path in sorted((root / sub).glob("*.jpg")):
            cards.append((path.stem, read_image(path)))
    for path in sorted((root / "cropped_pairs" / "jps").glob("*.jps")):
        cards.append((path.stem, read_image(path)))
    pair = root / "cropped_pairs" / "depthy_7995"
    if (pair / "7995l-image.jpg").exists():
        left, right = read_image(pair / "7995l-image.jpg"), read_image(pair / "7995r-image.jpg")
        h = min(left.shape[0], right.shape[0])
        cards.append(("depthy_7995", np.concatenate([left[:h], right[:h]], axis=1)))
    return cards


def cue_table(rows: list[dict]) -> dict[str, dict[str, dict[str, int]]]:
    """Each cue's fire rate, right and wrong, per split: a cue fires on a variant when its value
    is not 0, and is right when its sign says the parity of its flags that the truth has. A cue
    read under one tone hypothesis (CUE_CONDITIONS) counts only on variants of that tone."""
    table: dict[str, dict[str, dict[str, int]]] = {}
    for cue, flags in CUE_FLAGS.items():
        table[cue] = {}
        for split in ("tune", "held_out"):
            chosen = [r for r in rows if r["split"] == split]
            if cue in CUE_CONDITIONS:
                flag, value = CUE_CONDITIONS[cue]
                chosen = [r for r in chosen if r["truth"][flag] == value]
            fired = [r for r in chosen if abs(r["values"].get(cue, 0.0)) > 1e-9]
            right = sum((r["values"][cue] > 0) == (sum(r["truth"][f] for f in flags) % 2 == 0) for r in fired)
            table[cue][split] = {"variants": len(chosen), "fired": len(fired), "right": right, "wrong": len(fired) - right}
    return table


def measure(cards: list[tuple[str, np.ndarray]], params: OrientationParams) -> list[dict]:
    rows = []
    for name, card in cards:
        split = split_card(card)
        for flags in itertools.product((False, True), repeat=3):
            variant, _, _ = orient_variant(card, split.left_box, split.right_box, *flags)
            clock = time.perf_counter()
            vsplit = split_card(variant)
            split_seconds = time.perf_counter() - clock
            cpu = time.process_time()
            estimate = estimate_orientation(variant, vsplit.left_box, vsplit.right_box, params)
            cpu = time.process_time() - cpu
            rows.append(
                {
                    "card": name,
                    "truth": dict(zip(FLAGS, flags)),
                    "split": "tune" if name in TUNE else "held_out",
                    "values": {c.name: c.value for c in estimate.cues},
                    "undecidable": estimate.undecidable,
                    "tie_decided": estimate.tie_decided,
                    "tie_right": (estimate.same_turn_and_swap >= 0.5) == (flags[0] == flags[2]),
                    "seconds": estimate.seconds,
                    "cpu_seconds": cpu,
                    "split_seconds": split_seconds,
                    "decided_by": estimate.orientation()["decided_by"],
                }
            )
    return rows


def single_view_caps(data: Path) -> dict[str, float]:
    """Upper bounds for the weights of the single-photo cues that need no stereo, no colour and
    no mount (``sky_top``, ``detail_bottom``, ``smooth_bright``, ``dark_detail``), from the 100
    KeystoneDepth rectified left views (upright positives of Keystone-Mast photos, the kind of
    card this project grades): each cue's one-parameter logistic weight on them.

    Each view (its central 70 %, clear of the homography's black fill) is halved into a pseudo
    pair and measured as the module measures a pair. Turning (or inverting) a photo negates
    these cues exactly, so the view gives ``x`` for the right answer and ``-x`` for the wrong one
    and ``P(right) = sigmoid(2 w x)`` under the parity model. Measured: the tune cards alone
    fitted ``smooth_bright`` and ``detail_bottom`` about five times heavier than these 100
    photos support (right sign on 63 and 50 of them)."""
    from scipy.optimize import minimize_scalar

    from pipeline.orientation import (
        _dark_detail,
        _detail_bottom,
        _grey,
        _sky_top,
        _smooth_bright,
    )

    cues = {"sky_top": _sky_top, "detail_bottom": _detail_bottom, "smooth_bright": _smooth_bright, "dark_detail": _dark_detail}
    values: dict[str, list[float]] = {c: [] for c in cues}
    for path in sorted((data / "keystonedepth" / "rectified_left_vis" / "train").glob("*/*.png")):
        grey = _grey(read_image(path))
        h, w = grey.shape
        grey = grey[int(0.15 * h) : int(0.85 * h), int(0.15 * w) : int(0.85 * w)]
        scale = min(1.0, 512 / grey.shape[1])
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        half = grey.shape[1] // 2
        left, right = np.ascontiguousarray(grey[:, :half]), np.ascontiguousarray(grey[:, half : 2 * half])
        for name, measure_cue in cues.items():
            values[name].append(measure_cue(left, right))
    caps = {}
    for name, vs in values.items():
        if not vs:
            continue
        x = np.array(vs)

        def loss(w: float, x: np.ndarray = x) -> float:
            return float(np.mean(np.logaddexp(0.0, -2.0 * w * x)))

        best = minimize_scalar(loss, bounds=(0.0, 20.0), method="bounded")
        caps[name] = round(float(best.x), 3)
    return caps


def fit_weights(rows: list[dict], l2: float, caps: dict[str, float] | None = None) -> dict[str, float]:
    """Weights maximising the log-likelihood of the true hypothesis (softmax over eight), >= 0
    and at most ``caps[cue]`` where given."""
    names = list(CUE_FLAGS)
    usable = [r for r in rows if r["undecidable"] is None]
    signs = np.array([[1 - 2 * parity(h, CUE_FLAGS[c]) for c in names] for h in HYPOTHESES], float)  # (8, C)
    X = np.array([[r["values"][c] for c in names] for r in usable])  # (N, C)
    truth = np.array([HYPOTHESES.index(tuple(r["truth"][f] for f in FLAGS)) for r in usable])

    def loss(w: np.ndarray) -> float:
        scores = (X * w) @ signs.T  # (N, 8)
        scores -= scores.max(axis=1, keepdims=True)
        log_p = scores - np.log(np.exp(scores).sum(axis=1, keepdims=True))
        return float(-log_p[np.arange(len(truth)), truth].mean() + l2 * (w**2).sum() / len(names))

    caps = caps or {}
    bounds = [(0.0, caps.get(c)) for c in names]
    start = np.array([min(1.0, caps.get(c, 1.0)) for c in names])
    result = minimize(loss, start, method="L-BFGS-B", bounds=bounds)
    return {c: round(float(w), 3) for c, w in zip(names, result.x)}


def log_loss(rows: list[dict], weights: dict[str, float]) -> float:
    """Mean negative log-probability of the true hypothesis."""
    names = list(CUE_FLAGS)
    usable = [r for r in rows if r["undecidable"] is None]
    signs = np.array([[1 - 2 * parity(h, CUE_FLAGS[c]) for c in names] for h in HYPOTHESES], float)
    X = np.array([[r["values"][c] for c in names] for r in usable])
    truth = np.array([HYPOTHESES.index(tuple(r["truth"][f] for f in FLAGS)) for r in usable])
    scores = (X * np.array([weights[c] for c in names])) @ signs.T
    scores -= scores.max(axis=1, keepdims=True)
    log_p = scores - np.log(np.exp(scores).sum(axis=1, keepdims=True))
    return float(-log_p[np.arange(len(truth)), truth].mean())


def choose_l2(
    rows: list[dict], candidates: tuple[float, ...] = (1e-4, 1e-3, 3e-3, 1e-2, 3e-2), caps: dict[str, float] | None = None
) -> dict:
    """Leave-one-card-out within the tune cards (the held-out cards play no part): the
    strongest L2 whose held-back log-loss is within one standard error (over the left-out cards)
    of the smallest. (The one-standard-error rule: with seven tune cards the smallest loss alone
    chose the weakest L2 on the grid and weights up to 15 per cue unit, trusting cues such as
    the occlusion side far beyond their record across cards.)"""
    cards = sorted({r["card"] for r in rows})
    losses, errors = {}, {}
    for l2 in candidates:
        per_card = [
            log_loss([r for r in rows if r["card"] == card], fit_weights([r for r in rows if r["card"] != card], l2, caps))
            for card in cards
        ]
        losses[l2] = float(np.mean(per_card))
        errors[l2] = float(np.std(per_card, ddof=1) / np.sqrt(len(per_card))) if len(per_card) > 1 else 0.0
    best = min(losses, key=losses.get)
    chosen = max(l2 for l2 in candidates if losses[l2] <= losses[best] + errors[best])
    return {
        "l2": chosen,
        "smallest_loss_l2": best,
        "leave_one_card_out_log_loss": {str(k): round(v, 4) for k, v in losses.items()},
        "standard_error": {str(k): round(v, 4) for k, v in errors.items()},
    }


def evaluate(rows: list[dict], weights: dict[str, float], auto_probability: float) -> dict:
    out: dict = {"variants": len(rows), "cards": len({r["card"] for r in rows})}
    doubtful = 0
    per_flag = {f: {"decided": 0, "right": 0, "right_at_0.5": 0} for f in FLAGS}
    for r in rows:
        if r["undecidable"] is not None:
            doubtful += 1
            continue
        p = flag_probabilities(r["values"], weights)
        any_doubt = False
        for f in FLAGS:
            guess = p[f] >= 0.5
            per_flag[f]["right_at_0.5"] += guess == r["truth"][f]
            if p[f] >= auto_probability or p[f] <= 1 - auto_probability:
                per_flag[f]["decided"] += 1
                per_flag[f]["right"] += guess == r["truth"][f]
            else:
                any_doubt = True
        doubtful += any_doubt
    # Whole cards decided automatically (every flag confident), and whether all three are right;
    # "acceptance" counts the four variants of the acceptance test (original, turned, negative,
    # halves swapped) only.
    auto = {"decided": 0, "right": 0, "wrong": 0}
    acceptance = {"variants": 0, "decided_and_right": 0, "wrong": 0, "originals": 0, "originals_to_people": 0}
    for r in rows:
        truth = tuple(r["truth"][f] for f in FLAGS)
        single = sum(truth) <= 1
        acceptance["variants"] += single
        acceptance["originals"] += not any(truth)
        if r["undecidable"] is not None:
            acceptance["originals_to_people"] += not any(truth)
            continue
        best, _ = decided_combination(r["values"], weights, auto_probability)
        if best is not None:
            right = best == truth
            auto["decided"] += 1
            auto["right" if right else "wrong"] += 1
            acceptance["decided_and_right"] += single and right
            acceptance["wrong"] += single and not right
        else:
            acceptance["originals_to_people"] += not any(truth)
    out["decided_automatically"] = auto
    out["acceptance_variants"] = acceptance
    ties = [r for r in rows if r["undecidable"] is None and r["tie_decided"]]
    out["upside_down_equals_swapped"] = {"decided": len(ties), "right": sum(r["tie_right"] for r in ties)}
    # cards people settle with one answer (is it upside down?): tie and inverted both confident
    out["doubtful_needing_one_answer"] = sum(
        1
        for r in rows
        if r["undecidable"] is None
        and r["tie_decided"]
        and max(p := flag_probabilities(r["values"], weights)["inverted"], 1 - p) >= auto_probability
    )
    for s in per_flag.values():
        s["accuracy_decided"] = round(s["right"] / s["decided"], 4) if s["decided"] else None
        s["accuracy_all"] = round(s["right_at_0.5"] / len(rows), 4)
    out["per_flag"] = per_flag
    out["doubtful_cards"] = doubtful
    out["seconds_per_card_mean"] = round(float(np.mean([r["seconds"] for r in rows])), 4)
    out["seconds_per_card_max"] = round(float(np.max([r["seconds"] for r in rows])), 4)
    # CPU seconds of this process (OpenCV's threads included): less skewed by a busy machine.
    out["cpu_seconds_per_card_mean"] = round(float(np.mean([r["cpu_seconds"] for r in rows])), 4)
    return out


SWEEP = (0.95, 0.9, 0.85, 0.8, 0.75, 0.7, 0.65, 0.6)
THRESHOLD_MARGIN = 0.05


def threshold_sweep(tune: list[dict], held: list[dict], weights: dict[str, float]) -> dict:
    """Whole variants decided, and wrong, at each candidate ``auto_probability``, per split; and
    the rule that chose the default: the lowest threshold at which no tune variant is decided
    wrongly, plus ``THRESHOLD_MARGIN`` (rounded up to the sweep's grid). The held-out split only
    checks it. (The text cue is read where the step would read it, at the configured threshold.)"""
    table = {}
    for threshold in SWEEP:
        table[str(threshold)] = {
            name: {
                "decided": (e := evaluate(rows, weights, threshold))["decided_automatically"]["decided"],
                "wrong": e["decided_automatically"]["wrong"],
                "acceptance_decided_and_right": e["acceptance_variants"]["decided_and_right"],
                "acceptance_wrong": e["acceptance_variants"]["wrong"],
            }
            for name, rows in (("tune", tune), ("held_out", held))
        }
    clean = [t for t in SWEEP if all(table[str(u)]["tune"]["wrong"] == 0 for u in SWEEP if u >= t)]
    lowest = min(clean) if clean else max(SWEEP)
    chosen = min((t for t in SWEEP if t >= lowest + THRESHOLD_MARGIN - 1e-9), default=max(SWEEP))
    return {"table": table, "lowest_clean_on_tune": lowest, "chosen": chosen}


def scale_check(cards: list[tuple[str, np.ndarray]], scales: tuple[float, ...], params: OrientationParams) -> dict:
    """The acceptance test's four variants of every card with the card rescaled first (area
    filter down, cubic up): whole variants decided, and wrong, at each candidate threshold per
    split, and the most probable wrong answers seen. A scan's resolution is the collection's
    choice, so a threshold that holds only at the stored size would not hold on cards unseen."""
    acceptance = [(False, False, False), (True, False, False), (False, True, False), (False, False, True)]
    weights = params.weights()
    outcomes = []
    for scale in scales:
        for name, card in cards:
            method = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
            scaled = card if scale == 1 else cv2.resize(card, None, fx=scale, fy=scale, interpolation=method)
            split = split_card(scaled)
            for flags in acceptance:
                variant, _, _ = orient_variant(scaled, split.left_box, split.right_box, *flags)
                vsplit = split_card(variant)
                estimate = estimate_orientation(variant, vsplit.left_box, vsplit.right_box, params)
                if estimate.undecidable is not None:
                    continue
                values = {c.name: c.value for c in estimate.cues}
                joint = hypothesis_probabilities(values, weights)
                best = max(joint, key=joint.__getitem__)
                # a swapped call the occlusion cues lean against goes to people whatever its P
                vetoed = decided_combination(values, weights, 0.0)[0] is None
                outcomes.append(
                    {
                        "scale": scale,
                        "card": name,
                        "split": "tune" if name in TUNE else "held_out",
                        "truth": flags,
                        "probability": 0.0 if vetoed else joint[best],
                        "right": best == flags,
                    }
                )
    table = {
        str(t): {
            split: {
                "decided": sum(o["probability"] >= t for o in outcomes if o["split"] == split),
                "wrong": sum(o["probability"] >= t and not o["right"] for o in outcomes if o["split"] == split),
            }
            for split in ("tune", "held_out")
        }
        for t in SWEEP
    }
    wrong = sorted((o for o in outcomes if not o["right"]), key=lambda o: -o["probability"])[:5]
    return {
        "scales": list(scales),
        "variants": len(outcomes),
        "table": table,
        "most_probable_wrong": [
            {**o, "probability": round(o["probability"], 3), "truth": dict(zip(FLAGS, o["truth"]))} for o in wrong
        ],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--rows", action="store_true", help="include every variant's cue values")
    parser.add_argument(
        "--flow",
        action="store_true",
        help="measure the whole flow instead: four variants per card through keystone ingest/run "
        "on a fresh instance (benchmarks.orientation_flow)",
    )
    parser.add_argument("--scans", type=Path, help="with --flow: measure the images in this folder instead")
    parser.add_argument("--truth", type=Path, help="with --scans: hand-drawn photo boxes (photo_area_truth.csv format)")
    parser.add_argument("--keep", type=Path, help="with --flow: keep the instance in this folder")
    parser.add_argument(
        "--scales",
        help="instead: the acceptance variants with every card rescaled by each of these factors "
        "(comma-separated, e.g. 0.6,0.8,1,1.3,1.7), decided and wrong at each threshold",
    )
    parser.add_argument(
        "--head",
        type=Path,
        help="the learned cue's head to use (a JSON file of `python -m benchmarks.upright --out`), e.g. one trained "
        "without the held-out cards, for a held-out figure of the whole step",
    )
    args = parser.parse_args(argv)
    if args.flow:
        from .orientation_flow import main_flow

        return main_flow(args.data, args.scans, args.truth, args.json, args.keep)
    if not (args.data / "stereocards").is_dir():
        print(f"no shared data at {args.data}", file=sys.stderr)
        return 2
    # Every cue measured on every variant (the step leaves out the second stereo pass where it
    # could not change the outcome at its own threshold; the fit and the sweep need its value).
    params = OrientationParams(fill_only_when_it_could_matter=False)
    if args.head is not None:
        from pipeline.upright import load_head

        params = replace(params, learned_head=str(args.head), learned_head_version=load_head(str(args.head)).version)
    if args.scales:
        scales = tuple(float(v) for v in args.scales.split(","))
        if not scales or any(not 0.1 <= v <= 4.0 for v in scales):
            parser.error(f"--scales: expected factors between 0.1 and 4, got {args.scales!r}")
        print(json.dumps(scale_check(load_cards(args.data), scales, params), indent=1, default=float))
        return 0
    rows = measure(load_cards(args.data), params)
    tune = [r for r in rows if r["split"] == "tune"]
    held = [r for r in rows if r["split"] == "held_out"]
    caps = single_view_caps(args.data)
    selection = choose_l2(tune, caps=caps)
    fitted = fit_weights(tune, selection["l2"], caps)
    report = {
        "tune_cards": sorted(TUNE),
        "held_out_cards": sorted({r["card"] for r in held}),
        "default_weights": params.weights(),
        "single_view_caps": caps,
        "l2_selection": selection,
        "fitted_on_tune": fitted,
        "held_out": evaluate(held, params.weights(), params.auto_probability),
        "tune": evaluate(tune, params.weights(), params.auto_probability),
        "held_out_with_refitted_weights": evaluate(held, fitted, params.auto_probability),
        "auto_probability": params.auto_probability,
        "threshold_sweep": threshold_sweep(tune, held, params.weights()),
        "split_seconds_mean": round(float(np.mean([r["split_seconds"] for r in rows])), 4),
        "cues": cue_table(rows),
    }
    if args.rows:
        report["rows"] = rows
    if args.json:
        print(json.dumps(report, indent=1, default=float))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A simulated crowd for the demo: workers with known accuracies answer through the real use cases.

The demo needs approved crowd annotations for the rest of the flow to consume, and a disputed
one for the curators' review queue. This module makes them the way a real crowd would: a batch
over the cards, invited workers, each fetching and submitting through
:func:`annotation.reservations.next_tasks` and :func:`annotation.answers.submit` (every rule of
assignment, N, validation and idempotency applies), then :func:`annotation.results.aggregate_batch`.

Noise model (all draws from one seeded generator, so a seed gives one outcome):
- honest workers have an accuracy ``a`` (0.93-0.98): a judgement is right with probability
  ``a``, else one of its questions (the judge table, :data:`annotation.questions.JUDGE`:
  stereo, upside-down, inverted, swapped eyes) is answered wrong; a crop box is the true box with
  each coordinate jittered by a
  Gaussian of sigma 1.5 px, or, with probability ``1 - a``, a sloppy box off by up to 8 % of
  the box size;
- the last worker is a spammer: coin-flip judgements, random boxes (caught on gold, when the
  caller gives gold cards: Dawid-Skene on a handful of cards and no gold cannot tell whom to
  trust, so judge aggregates then mostly wait for a curator);
- with three or more cards, one card is *hard* (a faint, low-contrast scan): honest workers
  guess whether it is inverted, and their boxes spread by 10 % of the box size. Real crowds
  disagree on such cards; it is the card that should wait for a curator.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from flask import current_app
from sqlalchemy import select

from core.db import db, read_only
from core.models import Card, StageResult

from .aggregation import HALVES
from .answers import submit
from .batches import create_batch
from .crowd_settings import DEFAULT_MIN_BOX_PX
from .questions import judge_questions, keys
from .reservations import next_tasks
from .results import aggregate_batch
from .task_errors import TaskError
from .workers import get_or_create_worker

HONEST_ACCURACY = (0.98, 0.97, 0.96, 0.95, 0.93)
BOX_SIGMA_PX = 1.5
SLOPPY_FRACTION = 0.08  # of the box size, for a careless honest box
HARD_FRACTION = 0.10  # of the box size: how far honest boxes spread on the hard card
CROP_INSET_FRACTION = 0.03  # the filter's split box shrunk by this much per side (at least 2 px)


@dataclass(frozen=True)
class SimulatedWorker:
    worker_id: int
    name: str
    accuracy: float  # probability of a right judgement / a careful box; 0.5 and random boxes: spammer
    spammer: bool


def crop_truth_from_filter(card_id: int) -> dict[str, list[float]] | None:
    """The filter's split boxes (latest filter result), each shrunk a little; None without a split.

    Boxes are ``[x0, y0, x1, y1]`` in original image pixels. Shrinking keeps the gutter and the
    mount's edge out of the crop, as an annotator asked for the artifact-free part would.
    """
    metrics = db.session.scalar(
        select(StageResult.metrics)
        .where(StageResult.card_id == card_id, StageResult.stage == "filter", StageResult.status == "done")
        .order_by(StageResult.created_at.desc(), StageResult.id.desc())
        .limit(1)
    )
    if not metrics or "left_box" not in metrics or "right_box" not in metrics:
        return None
    truth = {}
    for half, key in (("left", "left_box"), ("right", "right_box")):
        x0, y0, x1, y1 = (float(v) for v in metrics[key])
        dx = max(2.0, round(CROP_INSET_FRACTION * (x1 - x0)))
        dy = max(2.0, round(CROP_INSET_FRACTION * (y1 - y0)))
        truth[half] = [x0 + dx, y0 + dy, x1 - dx, y1 - dy]
    return truth


def _clamp_box(box: Sequence[float], size: tuple[int, int], minimum: float) -> list[float]:
    """Inside the image and at least ``minimum`` px per side (the submit rules), rounded to 0.1 px."""
    width, height = size
    x0, y0, x1, y1 = box
    x0, y0 = min(max(0.0, x0), width - minimum), min(max(0.0, y0), height - minimum)
    x1, y1 = max(min(float(width), x1), x0 + minimum), max(min(float(height), y1), y0 + minimum)
    return [round(v, 1) for v in (x0, y0, x1, y1)]


def simulated_answer(
    kind: str,
    truth: Mapping[str, Any],
    worker: SimulatedWorker,
    size: tuple[int, int],
    rng: np.random.Generator,
    *,
    hard: bool = False,
    min_box: float = DEFAULT_MIN_BOX_PX,
) -> dict[str, Any]:
    """One worker's answer for one card, by the noise model in the module docstring."""
    if kind == "judge":
        questions = keys(judge_questions())
        if worker.spammer:
            return {q: bool(rng.random() < 0.5) for q in questions}
        answer = {q.key: bool(truth.get(q.key, q.default)) for q in judge_questions()}
        if hard and "inverted" in answer:  # a faint, low-contrast scan: is it a negative? honest workers guess
            answer["inverted"] = bool(rng.random() < 0.5)
        if rng.random() >= worker.accuracy:  # a slip: one question answered wrong
            slip = questions[int(rng.integers(len(questions)))]
            answer[slip] = not answer[slip]
        return answer
    answer = {}
    for half in HALVES:
        x0, y0, x1, y1 = truth[half]
        w, h = x1 - x0, y1 - y0
        if worker.spammer:
            bx, by = rng.uniform(0, size[0] - min_box), rng.uniform(0, size[1] - min_box)
            box = [bx, by, bx + rng.uniform(min_box, size[0] - bx), by + rng.uniform(min_box, size[1] - by)]
        elif hard:
            box = [x0, y0, x1, y1] + rng.normal(0, HARD_FRACTION, 4) * [w, h, w, h]
        elif rng.random() < worker.accuracy:
            box = [x0, y0, x1, y1] + rng.normal(0, BOX_SIGMA_PX, 4)
        else:
            box = [x0, y0, x1, y1] + rng.uniform(-SLOPPY_FRACTION, SLOPPY_FRACTION, 4) * [w, h, w, h]
        answer[half] = _clamp_box([float(v) for v in box], size, min_box)
    return answer


def _truths(
    card_ids: Sequence[int], kind: str, given: Mapping[int, Mapping[str, Any]]
) -> tuple[dict[int, dict[str, Any]], list[dict[str, Any]]]:
    truths: dict[int, dict[str, Any]] = {}
    skipped: list[dict[str, Any]] = []
    for card_id in dict.fromkeys(card_ids):
        if kind == "judge":
            extra = set(given.get(card_id, {})) - set(keys(judge_questions()))
            if extra:
                raise TaskError(f"Unexpected judgement fields in the truth of card {card_id}: {', '.join(sorted(extra))}")
            # Unless said otherwise, the answer of an untouched page: a stereo pair, upright, ...
            truths[card_id] = {**{q.key: q.default for q in judge_questions()}, **given.get(card_id, {})}
        elif card_id in given:
            truths[card_id] = {h: [float(v) for v in given[card_id][h]] for h in HALVES}
        else:
            boxes = crop_truth_from_filter(card_id)
            if boxes is None:
                skipped.append({"card": card_id, "reason": "no filter split boxes (left_box/right_box) and no truth given"})
            else:
                truths[card_id] = boxes
    return truths, skipped


def seed_simulated_crowd(
    card_ids: Sequence[int],
    *,
    kind: str,
    workers: int = 6,
    seed: int = 0,
    truth: dict[int, dict[str, Any]] | None = None,
    n: int | None = None,
    gold: Mapping[int, dict[str, Any]] | None = None,
    gold_rate: float = 0.3,
) -> dict[str, Any]:
    """Create a batch over ``card_ids``, let ``workers`` simulated workers answer it, aggregate it.

    Args:
        card_ids: cards to annotate (unknown ids: TaskError 404, nothing is created).
        kind: ``"judge"`` or ``"crop"``.
        workers: how many workers (at least ``n`` + 1: the last one is the spammer). Six by
            default: with gold, one slip in a worker's first three gold answers flags them
            (threshold 0.7, KEYSTONE_CROWD_MIN_GOLD 3), and the batch still needs N usable workers.
        seed: seeds the noise and names the workers (``sim-<seed>-<i>``, invite provider), so
            a rerun with the same seed reuses them.
        truth: card id -> the true answer. Judge: defaults to each question's ``default``
            (a stereo pair, upright, not inverted, eyes in order), per question overridable. Crop: defaults to the filter's split boxes
            shrunk a little (:func:`crop_truth_from_filter`); cards with neither are skipped.
        n: answers per item; default 4 for judge, 3 for crop. Why more for judge: on a handful
            of cards, three binary answers per question rarely reach the 0.95 posterior that
            approval needs (measured: 0 of 6 cards approved with n=3, 5 of 6 with n=4 and gold).
        gold: card id -> known answer, for cards (not in ``card_ids``) mixed in as gold items
            at ``gold_rate``; they seed Dawid-Skene and catch the spammer (flagged on gold).
            Judge batches need them, covering the rare answers (an upside-down, an inverted
            and a non-stereo card): measured on 6 cards, 3-5 approved for every seed 0-7 with
            such gold, 0-4 with all-ordinary gold, about none without gold.

    Returns:
        ``{"batch", "kind", "cards", "gold_cards", "hard_card", "skipped", "workers", "answers",
        "approved", "needs_curator", "pending", "flagged_workers", "agreement"}``; ``batch`` is
        None when every card was skipped. ``answers`` counts gold answers too.
    """
    if kind not in ("judge", "crop"):
        raise TaskError(f"Expected kind judge or crop, got {kind!r}")
    n = (4 if kind == "judge" else 3) if n is None else n
    if n < 1 or workers < n + 1:
        raise TaskError(f"Expected n >= 1 and at least n + 1 = {n + 1} workers (one is the spammer), got {workers}")
    rng = np.random.default_rng(seed)
    with read_only():
        gold = dict(gold or {})
        overlap = sorted(set(gold) & set(card_ids))
        if overlap:
            raise TaskError(f"A card cannot be gold and annotated in one batch: {', '.join(map(str, overlap))}")
        wanted = [*card_ids, *gold]
        found = set(db.session.scalars(select(Card.id).where(Card.id.in_(wanted))))
        missing = [c for c in wanted if c not in found]
        if missing:
            raise TaskError(f"No card with id {', '.join(map(str, missing))}", 404)
        truths, skipped = _truths(card_ids, kind, truth or {})
        sizes = {c.id: (c.width, c.height) for c in db.session.scalars(select(Card).where(Card.id.in_([*truths, *gold])))}
    summary: dict[str, Any] = {
        "batch": None,
        "kind": kind,
        "cards": sorted(truths),
        "gold_cards": sorted(gold),
        "hard_card": None,
        "skipped": skipped,
        "workers": [],
        "answers": 0,
        "approved": 0,
        "needs_curator": 0,
        "pending": 0,
        "flagged_workers": 0,
        "agreement": {},
    }
    if not truths:
        return summary
    hard = int(rng.choice(sorted(truths))) if len(truths) >= 3 else None
    min_box = float(current_app.config.get("KEYSTONE_CROWD_MIN_BOX_PX", DEFAULT_MIN_BOX_PX))
    crowd = [
        SimulatedWorker(
            get_or_create_worker("invite", f"sim-{seed}-{i}").id,
            f"sim-{seed}-{i}",
            HONEST_ACCURACY[i % len(HONEST_ACCURACY)] if i < workers - 1 else 0.5,
            i == workers - 1,
        )
        for i in range(workers)
    ]
    batch_id = create_batch(sorted(truths), kind, n, gold_rate if gold else 0.0, gold=gold).id
    known = {**truths, **gold}
    answers, step, progress = 0, 0, True
    while progress:  # rounds until nobody could answer anything more
        progress = False
        for worker in crowd:
            tasks, _why = next_tasks(worker.worker_id, kind, hold=1)
            if not tasks:
                continue
            task = tasks[0]
            answer = simulated_answer(
                kind, known[task.card_id], worker, sizes[task.card_id], rng, hard=task.card_id == hard, min_box=min_box
            )
            step += 1
            result = submit(worker.worker_id, task.reservation_token, answer, f"sim-{seed}-{batch_id}-{step:06d}")
            answers += not result.duplicate
            progress = True
    report = aggregate_batch(batch_id)
    summary.update(
        {
            "batch": batch_id,
            "hard_card": hard,
            "answers": answers,
            "approved": report.approved,
            "needs_curator": report.needs_curator,
            "pending": report.pending,
            "flagged_workers": report.flagged_workers,
            "agreement": report.agreement,
            "workers": [{"worker": w.worker_id, "name": w.name, "accuracy": w.accuracy, "spammer": w.spammer} for w in crowd],
        }
    )
    return summary

"""Turning redundant crowd answers into one answer per card: votes, Dawid-Skene, boxes.

Pure functions over plain records and numpy arrays; no database, no Flask.

Judgements
----------
A judge answer is a few binary questions about a card (the table :data:`annotation.questions.JUDGE`:
stereo pair, upside-down, inverted, photos in the wrong order). They are
aggregated *separately*, one binary Dawid-Skene per question, not as one 8-class joint label:
for three questions a joint confusion matrix has 8 x 7 = 56 free parameters per worker, far more than the few
dozen answers a worker gives per batch, while per question it has 2. The questions' errors
are also largely independent (misreading orientation says little about spotting a negative).
What is lost is the dependency "not a stereo card => the others are moot"; the caller
handles that by ignoring the other questions when a ``gate`` question (``is_stereo``) comes out false.

Label convention: class indices ``0..K-1``; for the binary questions ``1`` means "yes"
(is a stereo pair / is upside-down / is inverted).

Confusion matrices are row = true class, column = answered class, rows sum to 1.

Boxes
-----
Boxes are ``(x0, y0, x1, y1)`` in original image pixels, ``x0 < x1`` and ``y0 < y1``,
aggregated per card half by :func:`consensus_box`.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import questions as question_table

__all__ = [
    "ALL_QUESTIONS",
    "HALVES",
    "OPTIONAL_QUESTIONS",
    "QUESTIONS",
    "BoxConsensus",
    "ConfidenceRules",
    "DawidSkeneResult",
    "GoldScore",
    "InvalidBoxError",
    "Judgement",
    "JudgementAnswer",
    "LabelAnswer",
    "MajorityVote",
    "aggregate_judgements",
    "box_iou",
    "consensus_box",
    "dawid_skene",
    "flag_workers",
    "gold_accuracy",
    "is_confident",
    "majority_vote",
    "unconfident_reasons",
    "validate_box",
]

# The judge table's keys as they were at import, for callers that only read them (the demo's
# gold, the simulations in tests); code that must follow the table reads annotation.questions.
QUESTIONS: tuple[str, ...] = question_table.required_keys(question_table.JUDGE)
OPTIONAL_QUESTIONS: tuple[str, ...] = tuple(q.key for q in question_table.JUDGE if q.optional)
ALL_QUESTIONS: tuple[str, ...] = question_table.keys(question_table.JUDGE)
# A crop answer: one box per half of the card.
HALVES: tuple[str, ...] = ("left", "right")


@dataclass(frozen=True)
class LabelAnswer:
    """One worker's answer to one question about one item: a class index in ``0..K-1``."""

    item_id: Hashable
    worker_id: Hashable
    label: int


@dataclass(frozen=True, init=False)
class Judgement:
    """One worker's (or gold's) answers to the judge questions about one card, by question key:
    ``Judgement(is_stereo=True, upside_down=False, ...)`` or ``Judgement(payload)``. A question
    not asked is absent (None counts as absent)."""

    answers: tuple[tuple[str, bool], ...]

    def __init__(self, given: Mapping[str, bool | None] | None = None, /, **by_key: bool | None) -> None:
        merged = {**(given or {}), **by_key}
        object.__setattr__(self, "answers", tuple(sorted((k, bool(v)) for k, v in merged.items() if v is not None)))

    def get(self, key: str) -> bool | None:
        """The answer to question ``key``, None where it was not asked."""
        return dict(self.answers).get(key)


@dataclass(frozen=True)
class JudgementAnswer:
    item_id: Hashable
    worker_id: Hashable
    judgement: Judgement


# ---------------------------------------------------------------------------------------------
# Majority vote


@dataclass(frozen=True)
class MajorityVote:
    """``label`` is None on a tie; ``tied`` lists the labels sharing the top count."""

    label: int | None
    tied: tuple[int, ...]
    votes: tuple[int, ...]  # votes per class, length K


def majority_vote(answers: Iterable[LabelAnswer], n_classes: int) -> dict[Hashable, MajorityVote]:
    """Plain vote per item; ties are reported, not broken, so the caller decides (curator)."""
    counts: dict[Hashable, list[int]] = {}
    for a in answers:
        _check_label(a.label, n_classes)
        counts.setdefault(a.item_id, [0] * n_classes)[a.label] += 1
    out: dict[Hashable, MajorityVote] = {}
    for item, votes in counts.items():
        top = max(votes)
        tied = tuple(k for k, v in enumerate(votes) if v == top)
        out[item] = MajorityVote(tied[0] if len(tied) == 1 else None, tied, tuple(votes))
    return out


def _check_label(label: int, n_classes: int) -> None:
    if not 0 <= label < n_classes:
        raise ValueError(f"Expected a label in 0..{n_classes - 1}, got {label}")


# ---------------------------------------------------------------------------------------------
# Dawid-Skene


@dataclass(frozen=True)
class DawidSkeneResult:
    """Dawid & Skene (1979), "Maximum likelihood estimation of observer error-rates using the
    EM algorithm", Applied Statistics 28(1), with Dirichlet-smoothed (MAP) M-steps.

    Shapes: I items, W workers, K classes.
    """

    item_ids: tuple[Hashable, ...]  # (I,) row order of ``posteriors``
    worker_ids: tuple[Hashable, ...]  # (W,) order of ``confusion``
    posteriors: NDArray[np.float64]  # (I, K) P(true class | answers); gold rows are one-hot
    labels: NDArray[np.int64]  # (I,) MAP class
    confidence: NDArray[np.float64]  # (I,) posterior of the MAP class
    confusion: NDArray[np.float64]  # (W, K, K) row = true class, column = answered
    worker_accuracy: NDArray[np.float64]  # (W,) sum_k prior_k * confusion[w, k, k]
    class_prior: NDArray[np.float64]  # (K,) estimated on the non-gold items
    iterations: int
    converged: bool
    log_likelihood: float  # of the non-gold answers under the final parameters
    # Id -> row lookups, built once so per-item access stays O(1) on large batches.
    _item_row: dict[Hashable, int] = field(init=False, repr=False, compare=False)
    _worker_row: dict[Hashable, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_item_row", {it: i for i, it in enumerate(self.item_ids)})
        object.__setattr__(self, "_worker_row", {w: j for j, w in enumerate(self.worker_ids)})

    def posterior(self, item_id: Hashable) -> NDArray[np.float64]:
        """(K,) posterior of one item; KeyError for an item with no answers."""
        return self.posteriors[self._item_row[item_id]]

    def label_of(self, item_id: Hashable) -> int:
        return int(self.labels[self._item_row[item_id]])

    def accuracy_of(self, worker_id: Hashable) -> float:
        return float(self.worker_accuracy[self._worker_row[worker_id]])


def _logsumexp_rows(a: NDArray[np.float64]) -> NDArray[np.float64]:
    m = a.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(a - m).sum(axis=1, keepdims=True)))[:, 0]


def dawid_skene(
    answers: Sequence[LabelAnswer],
    n_classes: int,
    gold: Mapping[Hashable, int] | None = None,
    *,
    smoothing: float = 1.0,
    tol: float = 1e-6,
    max_iter: int = 200,
) -> DawidSkeneResult:
    """Estimate true labels and per-worker confusion matrices by EM, seeded with gold.

    Args:
        answers: the answers of one batch for one question.
        n_classes: K; classes nobody ever answered are allowed (smoothing keeps them finite).
        gold: item -> known true class. Gold posteriors are clamped to one-hot for the whole
            run, so gold both anchors the confusion matrices and is never "re-estimated".
            Gold items without answers are ignored.
        smoothing: Dirichlet pseudo-count added to every confusion cell and to the class
            prior (1.0 = Laplace). Why: a worker with three answers would otherwise get a
            matrix of exact 0s and 1s, and a single answer of theirs could veto every other
            worker on an item (log 0).
        tol: stop when no posterior moves by more than ``tol``.
        max_iter: hard cap on EM iterations.

    Initialisation: confusion matrices of workers with gold answers come from those answers
    alone (smoothed): that is the one thing we know for sure about them, and it keeps
    colluding spammers from defining "truth" at the start. Workers without gold start from a
    soft majority vote over the non-gold items.

    Never NaN: the E-step works in log space with strictly positive (smoothed) parameters.
    """
    if n_classes < 2:
        raise ValueError(f"Expected n_classes >= 2, got {n_classes}")
    if smoothing <= 0:
        raise ValueError(f"Expected smoothing > 0, got {smoothing}")
    if not answers:
        raise ValueError("Expected at least one answer, got none")
    gold = dict(gold or {})
    K = n_classes
    item_ids = tuple(dict.fromkeys(a.item_id for a in answers))
    worker_ids = tuple(dict.fromkeys(a.worker_id for a in answers))
    item_index = {it: i for i, it in enumerate(item_ids)}
    worker_index = {w: j for j, w in enumerate(worker_ids)}
    for a in answers:
        _check_label(a.label, K)
    for lab in gold.values():
        _check_label(lab, K)
    ai = np.array([item_index[a.item_id] for a in answers], dtype=np.int64)  # (M,)
    aw = np.array([worker_index[a.worker_id] for a in answers], dtype=np.int64)  # (M,)
    al = np.array([a.label for a in answers], dtype=np.int64)  # (M,)
    I, W = len(item_ids), len(worker_ids)

    is_gold = np.zeros(I, dtype=bool)
    gold_T = np.zeros((I, K))
    for it, lab in gold.items():
        if it in item_index:
            is_gold[item_index[it]] = True
            gold_T[item_index[it], lab] = 1.0

    prior_rows = ~is_gold if (~is_gold).any() else np.ones(I, dtype=bool)

    def m_step(T: NDArray[np.float64], use: NDArray[np.bool_]) -> tuple[NDArray, NDArray]:
        # counts[w, k, l] = sum over answers (i, w, l) of T[i, k]
        counts = np.full((W, K, K), smoothing)
        np.add.at(counts, (aw[use], slice(None), al[use]), T[ai[use]])
        confusion = counts / counts.sum(axis=2, keepdims=True)
        # The class prior comes from the open items only: curators pick gold to over-represent
        # rare classes (that is what catches an always-"valid" spammer), so gold is not a sample
        # of the batch.
        prior = T[prior_rows].sum(axis=0) + smoothing
        return confusion, prior / prior.sum()

    # Soft majority vote, then gold clamped on top.
    T = np.zeros((I, K))
    np.add.at(T, (ai, al), 1.0)
    T /= T.sum(axis=1, keepdims=True)
    T[is_gold] = gold_T[is_gold]
    has_gold = np.zeros(W, dtype=bool)
    has_gold[aw[is_gold[ai]]] = True
    # Workers with gold: count only their gold answers; others: all their answers vs soft MV.
    use = is_gold[ai] | ~has_gold[aw]
    confusion, prior = m_step(T, use)

    everything = np.ones(len(answers), dtype=bool)
    converged = False
    iterations = 0
    log_lik = 0.0
    for iterations in range(1, max_iter + 1):  # noqa: B007 (read after the loop: how many ran)
        # E-step in log space: log P(k) + sum over the item's answers of log C[w, k, l].
        log_T = np.tile(np.log(prior), (I, 1))
        np.add.at(log_T, ai, np.log(confusion[aw, :, al]))
        norm = _logsumexp_rows(log_T)
        new_T = np.exp(log_T - norm[:, None])
        new_T[is_gold] = gold_T[is_gold]
        log_lik = float(norm[~is_gold].sum())
        delta = float(np.abs(new_T - T).max())
        T = new_T
        confusion, prior = m_step(T, everything)
        if delta < tol:
            converged = True
            break

    labels = T.argmax(axis=1).astype(np.int64)
    confidence = T[np.arange(I), labels]
    accuracy = np.einsum("k,wkk->w", prior, confusion)
    return DawidSkeneResult(
        item_ids=item_ids,
        worker_ids=worker_ids,
        posteriors=T,
        labels=labels,
        confidence=confidence,
        confusion=confusion,
        worker_accuracy=accuracy,
        class_prior=prior,
        iterations=iterations,
        converged=converged,
        log_likelihood=log_lik,
    )


def aggregate_judgements(
    answers: Sequence[JudgementAnswer],
    gold: Mapping[Hashable, Judgement] | None = None,
    *,
    smoothing: float = 1.0,
    tol: float = 1e-6,
    max_iter: int = 200,
    questions: Sequence[question_table.Question] | None = None,
) -> dict[str, DawidSkeneResult]:
    """One binary Dawid-Skene per question of ``questions`` (default: the judge table), keyed by
    its key; an optional question (``swapped``) only when any answer has it, over the answers and
    gold that have it.

    See the module docstring for why not one joint label; parameters as in :func:`dawid_skene`.
    """
    gold = gold or {}
    out: dict[str, DawidSkeneResult] = {}
    for question in question_table.judge_questions() if questions is None else questions:
        q = question.key
        labelled = [LabelAnswer(a.item_id, a.worker_id, int(said)) for a in answers if (said := a.judgement.get(q)) is not None]
        if not labelled and question.optional:
            continue
        gold_q = {it: int(said) for it, j in gold.items() if (said := j.get(q)) is not None}
        out[q] = dawid_skene(labelled, 2, gold_q, smoothing=smoothing, tol=tol, max_iter=max_iter)
    return out


# ---------------------------------------------------------------------------------------------
# Worker quality on gold


@dataclass(frozen=True)
class GoldScore:
    correct: int
    total: int

    @property
    def accuracy(self) -> float:
        """Fraction correct; 0 answers give NaN-free 0.0 (flagging also needs ``min_gold``)."""
        return self.correct / self.total if self.total else 0.0


def gold_accuracy(answers: Iterable[LabelAnswer], gold: Mapping[Hashable, int]) -> dict[Hashable, GoldScore]:
    """Per worker: how many gold answers were right, out of how many. Non-gold answers ignored.

    For judge tasks pass per-question labels, or encode a whole judgement as one label
    (e.g. ``4*is_stereo + 2*upside_down + inverted``) to count a card right only when all
    three questions are.
    """
    tally: dict[Hashable, list[int]] = {}
    for a in answers:
        if a.item_id in gold:
            t = tally.setdefault(a.worker_id, [0, 0])
            t[0] += int(a.label == gold[a.item_id])
            t[1] += 1
    return {w: GoldScore(c, n) for w, (c, n) in tally.items()}


def flag_workers(accuracies: Mapping[Hashable, GoldScore], threshold: float, min_gold: int) -> frozenset[Hashable]:
    """Workers to stop serving: gold accuracy below ``threshold`` on at least ``min_gold`` golds.

    ``min_gold`` exists because one unlucky gold answer is 0 % accuracy: nobody is flagged
    before the evidence is worth acting on.
    """
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"Expected 0 <= threshold <= 1, got {threshold}")
    if min_gold < 1:
        raise ValueError(f"Expected min_gold >= 1, got {min_gold}")
    return frozenset(w for w, s in accuracies.items() if s.total >= min_gold and s.accuracy < threshold)


# ---------------------------------------------------------------------------------------------
# Box consensus


class InvalidBoxError(ValueError):
    """A box that is not four finite numbers with x0 < x1 and y0 < y1 (and inside the image)."""


Box = tuple[float, float, float, float]


def _short_repr(value: Any, limit: int = 120) -> str:
    """``repr`` cut to ``limit`` characters; an integer past Python's 4,300-digit limit is described, not printed."""
    try:
        text = repr(value)
    except ValueError:
        return f"<a {type(value).__name__} too large to print>"
    return text if len(text) <= limit else text[:limit] + "..."


def validate_box(box: Sequence[float], image_size: tuple[int, int] | None = None) -> Box:
    """Check one box ``(x0, y0, x1, y1)`` in pixels; ``image_size`` is ``(width, height)``."""
    try:
        b = np.asarray(box, dtype=np.float64)
    except (OverflowError, TypeError, ValueError):
        # A 400-digit integer overflows a float64, a string or a nested list is no coordinate.
        raise InvalidBoxError(f"Expected four finite numbers (x0, y0, x1, y1), got {_short_repr(box)}") from None
    if b.shape != (4,):
        raise InvalidBoxError(f"Expected a box (x0, y0, x1, y1), got shape {b.shape}")
    if not np.isfinite(b).all():
        raise InvalidBoxError(f"Expected finite coordinates, got {tuple(b.tolist())}")
    x0, y0, x1, y1 = (float(v) for v in b)
    if x1 <= x0 or y1 <= y0:
        raise InvalidBoxError(f"Expected x0 < x1 and y0 < y1 (positive width and height), got {(x0, y0, x1, y1)}")
    if image_size is not None:
        w, h = image_size
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            raise InvalidBoxError(f"Expected a box inside the {w}x{h} image, got {(x0, y0, x1, y1)}")
    return (x0, y0, x1, y1)


def box_iou(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pairwise intersection over union. ``a`` (N, 4), ``b`` (M, 4) -> (N, M) in [0, 1]."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    ix = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = ix * iy
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


@dataclass(frozen=True)
class BoxConsensus:
    """Consensus of one half's boxes. ``mad`` is per coordinate (x0, y0, x1, y1), in pixels."""

    box: Box
    kept: int
    dropped: int
    kept_mask: tuple[bool, ...]  # in input order
    mad: Box  # median absolute deviation of the kept boxes from ``box``
    mean_iou: float  # mean IoU of the kept boxes to ``box``; 0.0 when none kept


def _as_box(values: NDArray[np.float64]) -> Box:
    """Four coordinates (x0, y0, x1, y1) as plain floats."""
    x0, y0, x1, y1 = (float(v) for v in values)
    return (x0, y0, x1, y1)


def consensus_box(
    boxes: Sequence[Sequence[float]],
    min_iou: float = 0.5,
    image_size: tuple[int, int] | None = None,
) -> BoxConsensus:
    """Robust consensus: coordinate-wise median, drop boxes with IoU < ``min_iou`` to it, redo.

    Why the median: one careless or hostile box moves a mean arbitrarily far but a median of
    3+ boxes not at all; the IoU cut then removes that box from the spread figures too.
    When no box reaches ``min_iou`` (all disagree), the first median is returned with
    ``kept == 0`` so the confidence rules send the card to a curator.
    """
    if len(boxes) == 0:
        raise InvalidBoxError("Expected at least one box, got none")
    B = np.array([validate_box(b, image_size) for b in boxes])  # (N, 4)
    median = np.median(B, axis=0)
    keep = box_iou(B, median)[:, 0] >= min_iou
    if not keep.any():
        return BoxConsensus(
            box=_as_box(median),
            kept=0,
            dropped=len(B),
            kept_mask=tuple(False for _ in B),
            mad=_as_box(np.median(np.abs(B - median), axis=0)),
            mean_iou=0.0,
        )
    K = B[keep]
    box = np.median(K, axis=0)
    return BoxConsensus(
        box=_as_box(box),
        kept=int(keep.sum()),
        dropped=int((~keep).sum()),
        kept_mask=tuple(bool(k) for k in keep),
        mad=_as_box(np.median(np.abs(K - box), axis=0)),
        mean_iou=float(box_iou(K, box).mean()),
    )


# ---------------------------------------------------------------------------------------------
# Approved vs waits-for-curator


@dataclass(frozen=True)
class ConfidenceRules:
    """Thresholds for auto-approval. ``max_box_mad_px`` is in original image pixels."""

    min_posterior: float = 0.95
    min_boxes_kept: int = 2
    max_box_mad_px: float = 8.0
    min_box_mean_iou: float = 0.8


def unconfident_reasons(
    posteriors: Mapping[str, float] | None = None,
    boxes: Mapping[str, BoxConsensus] | None = None,
    rules: ConfidenceRules = ConfidenceRules(),
) -> tuple[str, ...]:
    """Why a card must wait for a curator; empty when it can be approved.

    Args:
        posteriors: question (or any name) -> posterior of the MAP label.
        boxes: half name ("left"/"right") -> its consensus.
    """
    reasons: list[str] = []
    for name, p in (posteriors or {}).items():
        if not p >= rules.min_posterior:  # also catches NaN
            reasons.append(f"{name}: posterior {p:.3f} < {rules.min_posterior}")
    for half, c in (boxes or {}).items():
        if c.kept < rules.min_boxes_kept:
            reasons.append(f"{half} box: {c.kept} boxes kept < {rules.min_boxes_kept}")
            continue
        if max(c.mad) > rules.max_box_mad_px:
            reasons.append(f"{half} box: spread {max(c.mad):.1f} px > {rules.max_box_mad_px} px")
        if c.mean_iou < rules.min_box_mean_iou:
            reasons.append(f"{half} box: mean IoU {c.mean_iou:.2f} < {rules.min_box_mean_iou}")
    return tuple(reasons)


def is_confident(
    posteriors: Mapping[str, float] | None = None,
    boxes: Mapping[str, BoxConsensus] | None = None,
    rules: ConfidenceRules = ConfidenceRules(),
) -> bool:
    """True: store as an approved annotation; False: the card waits for a curator."""
    return not unconfident_reasons(posteriors, boxes, rules)

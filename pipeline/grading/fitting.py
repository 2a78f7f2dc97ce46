"""Fitting the thresholds: :func:`fit_thresholds` refits them to labels (coordinate descent over
candidate thresholds at the measurements' quantiles, maximising macro-F1) and reports the
agreement on labels the thresholds were not fitted on (stratified k-fold cross-validation with
:func:`pipeline.cross_validation.stratified_folds`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import grade_agreement
from ..cross_validation import stratified_folds
from ..errors import InvalidInputError, PipelineError
from .measurements import GradeMeasurements
from .verdict import GRADES, RULES, GradeThresholds, Threshold

__all__ = ["FitReport", "NotEnoughLabelsError", "TrueErrorBands", "agreement", "fit_thresholds", "labels_from_true_error"]

MIN_LABELS = 10  # fewer labels cannot be cross-validated meaningfully
DEFAULT_THRESHOLDS = GradeThresholds()


class NotEnoughLabelsError(PipelineError):
    """Too few curator labels (or a single class) to fit and cross-validate thresholds."""

    code = "not_enough_labels"


def agreement(truth: Sequence[int] | np.ndarray, predicted: Sequence[int] | np.ndarray) -> dict[str, Any]:
    """:func:`pipeline.grade_agreement.agreement` over :data:`GRADES` (indices into it)."""
    return grade_agreement.agreement(truth, predicted, GRADES)


def _f1_of(truth: np.ndarray, predicted: np.ndarray) -> float:
    matrix = np.zeros((3, 3), np.int64)
    np.add.at(matrix, (truth, predicted), 1)
    return grade_agreement.macro_f1(matrix)


@dataclass(frozen=True)
class FitReport:
    """Thresholds fitted to all labels, and how well fitted thresholds agree with curators.

    ``held_out``: :func:`agreement` pooled over the k held-out folds, each predicted by thresholds
    fitted on the other folds only (so every label is predicted exactly once, by thresholds not
    fitted on it). ``baseline``: the ``base`` thresholds on all labels. ``training``: the fitted
    thresholds on the labels they were fitted on (optimistic; for comparison only).
    ``changed``: the thresholds that moved from ``base``, in words."""

    thresholds: GradeThresholds
    held_out: dict[str, Any]
    baseline: dict[str, Any]
    training: dict[str, Any]
    labels: int
    folds: int
    seed: int
    changed: list[str]
    objective: str = "macro_f1"

    def as_dict(self) -> dict[str, Any]:
        return {
            "thresholds": self.thresholds.to_dict(),
            "held_out": self.held_out,
            "baseline": self.baseline,
            "training": self.training,
            "labels": self.labels,
            "folds": self.folds,
            "seed": self.seed,
            "changed": list(self.changed),
            "objective": self.objective,
        }


def _matrix_of(rows: Sequence[GradeMeasurements]) -> np.ndarray:
    """(N, rules) float values, NaN where missing (a missing value never raises the grade)."""
    out = np.full((len(rows), len(RULES)), np.nan)
    for i, m in enumerate(rows):
        for j, name in enumerate(RULES):
            value = getattr(m, name)
            if value is not None:
                out[i, j] = float(value)
    return out


def _levels(column: np.ndarray, threshold: Threshold) -> np.ndarray:
    """Vectorised :meth:`Threshold.level`; NaN is level 0."""
    level = np.zeros(column.shape, np.int64)
    with np.errstate(invalid="ignore"):
        for value, limit in ((1, threshold.some), (2, threshold.failure)):
            if limit is None:
                continue
            beyond = column > limit if threshold.direction == "above" else column < limit
            level = np.where(beyond, np.maximum(level, value), level)
    return level


def _predict(values: np.ndarray, thresholds: GradeThresholds) -> np.ndarray:
    if values.shape[0] == 0:
        return np.zeros(0, np.int64)
    return np.max(np.stack([_levels(values[:, j], getattr(thresholds, name)) for j, name in enumerate(RULES)], axis=1), axis=1)


def _candidates(column: np.ndarray, name: str) -> list[float | None]:
    """Thresholds to try: None (rule level off), and midpoints between the distinct values at the
    column's 2nd..98th percentiles (25 of them), so a threshold never sits on a labelled value."""
    if RULES[name].scale == "flag":
        return [None, 0.5]
    finite = column[np.isfinite(column)]
    if finite.size == 0:
        return [None]
    distinct = np.unique(finite)
    if distinct.size == 1:
        return [None, float(distinct[0])]
    midpoints = (distinct[:-1] + distinct[1:]) / 2
    picks = np.unique(np.percentile(midpoints, np.linspace(2, 98, 25), method="nearest"))
    return [None, *(float(p) for p in picks)]


def _fit(values: np.ndarray, truth: np.ndarray, base: GradeThresholds, sweeps: int = 6) -> GradeThresholds:
    """Coordinate descent from ``base``: for each rule in turn, for its some and failure levels,
    take the candidate (or None) with the best macro-F1 given every other threshold; keep the
    current one unless another is strictly better; stop when a sweep changes nothing."""
    names = list(RULES)
    current = {name: getattr(base, name) for name in names}
    levels = np.stack([_levels(values[:, j], current[name]) for j, name in enumerate(names)], axis=1)
    best = _f1_of(truth, levels.max(axis=1))
    candidates = {name: _candidates(values[:, j], name) for j, name in enumerate(names)}
    for _ in range(sweeps):
        improved = False
        for j, name in enumerate(names):
            others = np.delete(levels, j, axis=1).max(axis=1) if len(names) > 1 else np.zeros(len(truth), np.int64)
            for level_name in ("some", "failure"):
                rule = current[name]
                for candidate in candidates[name]:
                    trial = replace(rule, **{level_name: candidate})
                    if (
                        trial.some is not None
                        and trial.failure is not None
                        and ((trial.failure < trial.some) if trial.direction == "above" else (trial.failure > trial.some))
                    ):
                        continue  # a failure threshold short of the some threshold
                    column = _levels(values[:, j], trial)
                    score = _f1_of(truth, np.maximum(others, column))
                    if score > best + 1e-12:
                        best, rule, improved = score, trial, True
                        levels[:, j] = column
                current[name] = rule
        if not improved:
            break
    return GradeThresholds(**current)


def _changes(base: GradeThresholds, fitted: GradeThresholds) -> list[str]:
    out = []
    for name in RULES:
        before, after = getattr(base, name), getattr(fitted, name)
        for level in ("some", "failure"):
            a, b = getattr(before, level), getattr(after, level)
            if a != b:
                out.append(f"{name} {level}: {_threshold_text(a)} -> {_threshold_text(b)}")
    return out


def fit_thresholds(
    rows: Sequence[tuple[GradeMeasurements | Mapping[str, Any], str]],
    base: GradeThresholds = DEFAULT_THRESHOLDS,
    folds: int = 5,
    seed: int = 0,
) -> FitReport:
    """Fit the thresholds to curator labels and report held-out agreement.

    ``rows``: (measurements, curator grade in few / some / failure). The fit is coordinate descent
    from ``base`` over candidate thresholds at the measurements' quantiles (or a level switched
    off), maximising macro-F1, so the result is still a readable set of thresholds. Agreement is
    estimated by stratified ``folds``-fold cross-validation: thresholds are refitted on k-1 folds
    and grade the fold left out; the pooled confusion matrix covers every label exactly once.

    Raises :class:`NotEnoughLabelsError` for fewer than 10 labels, a single class, or fewer
    labels than folds; :class:`InvalidInputError` for an unknown grade or ``folds < 2``.
    """
    if folds < 2:
        raise InvalidInputError(f"Expected folds >= 2, got {folds}")
    index = {g: i for i, g in enumerate(GRADES)}
    measured: list[GradeMeasurements] = []
    truth_list: list[int] = []
    for position, row in enumerate(rows):
        try:
            values, label = row
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"row {position}: expected (measurements, label), got {row!r}") from exc
        if label not in index:
            raise InvalidInputError(f"row {position}: unknown grade {label!r}; expected one of {', '.join(GRADES)}")
        measured.append(GradeMeasurements.from_dict(values))
        truth_list.append(index[label])
    n = len(measured)
    needed = max(MIN_LABELS, folds)
    if n < needed:
        raise NotEnoughLabelsError(
            f"{n} curator labels; at least {needed} are needed to fit and cross-validate ({needed - n} more)"
        )
    truth = np.array(truth_list, np.int64)
    classes = sorted({GRADES[t] for t in truth_list})
    if len(classes) < 2:
        raise NotEnoughLabelsError(
            f"all {n} curator labels are {classes[0]!r}: grade at least one card of another class "
            "(few, some, failure) before fitting"
        )
    matrix = _matrix_of(measured)
    rng = np.random.default_rng(seed)
    predicted = np.full(n, -1, np.int64)
    for test in stratified_folds(truth, folds, rng):
        if test.size == 0:
            continue
        train = np.setdiff1d(np.arange(n), test)
        fold_thresholds = _fit(matrix[train], truth[train], base)
        predicted[test] = _predict(matrix[test], fold_thresholds)
    fitted = _fit(matrix, truth, base)
    return FitReport(
        thresholds=fitted,
        held_out=agreement(truth, predicted),
        baseline=agreement(truth, _predict(matrix, base)),
        training=agreement(truth, _predict(matrix, fitted)),
        labels=n,
        folds=folds,
        seed=seed,
        changed=_changes(base, fitted),
    )


@dataclass(frozen=True)
class TrueErrorBands:
    """Which grade a measured true error calls for: ``true_bad2`` (percent of ground-truth pixels
    more than 2 px off) under ``few_below`` is few, above ``failure_above`` failure, between them
    some. Defaults: the default backend on clean Middlebury pairs is 8-19 % bad-2 (docs/BENCHMARKS.md, disparity), so
    under 25 % is as good as the matcher gets; over 50 % most of the depth map is wrong."""

    few_below: float = 25.0
    failure_above: float = 50.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.few_below <= self.failure_above <= 100.0):
            raise InvalidInputError(
                f"Expected 0 <= few_below <= failure_above <= 100 (percent), got {self.few_below}, {self.failure_above}"
            )

    def label(self, true_bad2: float) -> str:
        return "few" if true_bad2 < self.few_below else "failure" if true_bad2 > self.failure_above else "some"


def labels_from_true_error(
    results: Sequence[Mapping[str, Any]], bands: TrueErrorBands = TrueErrorBands()
) -> list[tuple[Mapping[str, Any], str]]:
    """``(measurements, grade the true error calls for)`` for every graded card of a
    ``keystone bench grade --json`` document's ``results`` (cards the pipeline stopped have no
    measurements and are left out). Raises :class:`InvalidInputError` for an entry without a
    numeric ``true_bad2``."""
    rows: list[tuple[Mapping[str, Any], str]] = []
    for position, entry in enumerate(results):
        if not isinstance(entry, Mapping):
            raise InvalidInputError(f"result {position}: expected an object, got {type(entry).__name__}")
        measurements = entry.get("measurements")
        if not measurements:
            continue
        error = entry.get("true_bad2")
        if isinstance(error, bool) or not isinstance(error, (int, float)):
            raise InvalidInputError(f"result {position}: expected a numeric true_bad2, got {error!r}")
        rows.append((measurements, bands.label(float(error))))
    return rows


def _threshold_text(threshold: float | None) -> str:
    return "off" if threshold is None else f"{threshold:.6g}"

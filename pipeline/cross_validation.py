"""Stratified k-fold splits, shared by every fit in the pipeline that reports held-out figures
(the grade thresholds, the homography verdict)."""

from __future__ import annotations

import numpy as np

__all__ = ["stratified_folds"]


def stratified_folds(labels: np.ndarray, k: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``k`` disjoint, sorted int64 index arrays covering ``range(len(labels))``, each class dealt
    round-robin after a shuffle by ``rng`` (so class shares per fold differ by at most one item;
    the round-robin continues across classes so small classes do not all land in fold 0)."""
    folds: list[list[int]] = [[] for _ in range(k)]
    offset = 0
    for cls in np.unique(labels):
        members = rng.permutation(np.flatnonzero(labels == cls))
        for n, i in enumerate(members):
            folds[(n + offset) % k].append(int(i))
        offset += len(members)
    return [np.array(sorted(f), np.int64) for f in folds]

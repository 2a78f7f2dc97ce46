"""Agreement between annotators of one batch: raw agreement, Krippendorff's alpha, Gwet's AC1.

Why three figures. Most cards are valid and upright, so two workers agree by chance most of
the time. Kappa-style coefficients (and alpha) subtract that chance agreement with the
*observed* class marginals; on skewed classes the expected agreement approaches the observed
one and the coefficient collapses towards 0, or below, even when workers almost always agree
(the "kappa paradox", Feinstein & Cicchetti 1990). Gwet's AC1 models chance agreement as the
share of ratings that could be random and stays stable there. Raw agreement shows what the
others correct for. Report all three; read AC1 on skewed questions.

Missing answers are the rule (not every worker sees every item): every function takes a
reliability matrix ``(raters, units)`` with NaN for "no answer", or a list of units each with
its own variable number of values. Units with fewer than two values carry no agreement
information and are skipped, as all three definitions prescribe.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from annotation.aggregation import box_iou

__all__ = [
    "PairwiseDistance",
    "box_distance",
    "gwet_ac1",
    "krippendorff_alpha",
    "krippendorff_alpha_boxes",
    "krippendorff_alpha_nominal",
    "nominal_distance",
    "percent_agreement",
    "units_from_reliability",
]

# (N, d) values x (M, d) values -> (N, M) differences, 0 on identical values, symmetric.
PairwiseDistance = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


def nominal_distance(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """0 when two values are equal, 1 otherwise (Krippendorff's nominal metric)."""
    return np.any(a[:, None, :] != b[None, :, :], axis=2).astype(np.float64)


def box_distance(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``1 - IoU`` between boxes ``(x0, y0, x1, y1)``: 0 for identical boxes, 1 for disjoint."""
    return 1.0 - box_iou(a, b)


def units_from_reliability(reliability: ArrayLike) -> list[NDArray[np.float64]]:
    """A ``(raters, units)`` matrix with NaN for missing -> per unit an array ``(m_u, 1)``."""
    R = np.asarray(reliability, dtype=np.float64)
    if R.ndim != 2:
        raise ValueError(f"Expected a (raters, units) matrix, got shape {R.shape}")
    return [col[~np.isnan(col)][:, None] for col in R.T]


def krippendorff_alpha(units: Sequence[ArrayLike], distance: PairwiseDistance) -> float:
    """Krippendorff's alpha with any difference function.

    Krippendorff (2011), "Computing Krippendorff's Alpha-Reliability", eqs. for the general
    form: with n pairable values (values in units with m_u >= 2),

        D_o = 1/n * sum_u 1/(m_u - 1) * sum_{i != j in u} delta(v_i, v_j)
        D_e = 1/(n (n - 1)) * sum_{i != j over all pairable values} delta(v_i, v_j)
        alpha = 1 - D_o / D_e

    Args:
        units: per unit an array ``(m_u, d)`` of its values (a 1-D array is read as d = 1).
        distance: pairwise difference function (see :data:`PairwiseDistance`). For nominal
            data it is 0/1; for boxes we use ``1 - IoU`` directly as the difference.

    Returns:
        alpha in (-inf, 1]; NaN when D_e = 0 (every value identical: alpha is undefined).
        Cost O(n^2) in the pairable values: fine for a batch (a few thousand values).
    """
    pairable = []
    for u in units:
        v = np.asarray(u, dtype=np.float64)
        v = v[:, None] if v.ndim == 1 else v
        if len(v) >= 2:
            pairable.append(v)
    if not pairable:
        raise ValueError("Expected at least one unit with two or more values, got none")
    n = sum(len(v) for v in pairable)
    D_o = sum(distance(v, v).sum() / (len(v) - 1) for v in pairable) / n
    allv = np.concatenate(pairable)
    D_e = distance(allv, allv).sum() / (n * (n - 1))
    if D_e == 0:
        return float("nan")
    return float(1.0 - D_o / D_e)


def krippendorff_alpha_nominal(reliability: ArrayLike) -> float:
    """Nominal alpha from a ``(raters, units)`` matrix of class codes, NaN = missing."""
    return krippendorff_alpha(units_from_reliability(reliability), nominal_distance)


def krippendorff_alpha_boxes(units: Sequence[ArrayLike]) -> float:
    """Alpha for crop boxes with difference ``1 - IoU``; per unit an array ``(m_u, 4)``."""
    return krippendorff_alpha(units, box_distance)


def _category_counts(reliability: ArrayLike) -> tuple[NDArray[np.float64], int]:
    """``(units, K)`` counts r_ik of raters putting unit i in category k, and K."""
    R = np.asarray(reliability, dtype=np.float64)
    if R.ndim != 2:
        raise ValueError(f"Expected a (raters, units) matrix, got shape {R.shape}")
    cats = np.unique(R[~np.isnan(R)])
    counts = np.stack([(R == c).sum(axis=0) for c in cats], axis=1).astype(np.float64)
    return counts.reshape(R.shape[1], len(cats)), len(cats)


def percent_agreement(reliability: ArrayLike) -> float:
    """Raw agreement: the share of agreeing rater pairs within a unit, averaged over units
    rated at least twice (Gwet 2008's p_a; equals the plain percent agreement for 2 raters).
    """
    r_ik, _ = _category_counts(reliability)
    r_i = r_ik.sum(axis=1)
    multi = r_i >= 2
    if not multi.any():
        raise ValueError("Expected at least one unit with two or more answers, got none")
    return float(((r_ik[multi] * (r_ik[multi] - 1)).sum(axis=1) / (r_i[multi] * (r_i[multi] - 1))).mean())


def gwet_ac1(reliability: ArrayLike, n_categories: int | None = None) -> float:
    """Gwet's AC1 for nominal data, any number of raters, missing answers allowed.

    Gwet (2008), "Computing inter-rater reliability and its variance in the presence of high
    agreement", Br. J. Math. Stat. Psychol. 61, 29-48, multi-rater form (also Gwet,
    Handbook of Inter-Rater Reliability, 4th ed., ch. 2):

        p_a  = mean over units with r_i >= 2 of sum_k r_ik (r_ik - 1) / (r_i (r_i - 1))
        pi_k = mean over units with r_i >= 1 of r_ik / r_i
        p_e  = 1/(K - 1) * sum_k pi_k (1 - pi_k)
        AC1  = (p_a - p_e) / (1 - p_e)

    ``n_categories`` is K, the number of categories raters *could* choose; it defaults to
    the number observed, which understates K when a category was never used.
    """
    r_ik, seen = _category_counts(reliability)
    K = seen if n_categories is None else n_categories
    if K < 2:
        raise ValueError(f"Expected at least 2 categories, got {K}")
    if K < seen:
        raise ValueError(f"Expected n_categories >= {seen} observed categories, got {K}")
    p_a = percent_agreement(reliability)
    r_i = r_ik.sum(axis=1)
    rated = r_i >= 1
    pi_k = (r_ik[rated] / r_i[rated, None]).mean(axis=0)
    p_e = float((pi_k * (1 - pi_k)).sum() / (K - 1))
    return float((p_a - p_e) / (1 - p_e))

"""Agreement of the automatic grade with curator labels: confusion matrix, accuracy, Cohen's kappa,
macro-F1 and per-class precision / recall.

Its own module, with numpy alone, so the report page can compute it without importing the grading
package (whose measurements import rectification and with it SciPy: 1.5-3 s the first time a
server process drew the report).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

# The grades in the order of the matrix' rows and columns (pipeline.grading.verdict.GRADES).
GRADE_ORDER: tuple[str, ...] = ("few", "some", "failure")


def agreement(
    truth: Sequence[int] | np.ndarray, predicted: Sequence[int] | np.ndarray, grades: Sequence[str] = GRADE_ORDER
) -> dict[str, Any]:
    """Confusion matrix (rows = curator label, columns = automatic grade, order ``grades``),
    accuracy, Cohen's kappa, macro-F1 and per-class precision / recall / support. Labels and
    grades are indices into ``grades``. Undefined figures (no such class) are ``None``."""
    k = len(grades)
    matrix = np.zeros((k, k), np.int64)
    np.add.at(matrix, (np.asarray(truth, np.int64), np.asarray(predicted, np.int64)), 1)
    n = int(matrix.sum())
    out: dict[str, Any] = {
        "labels": n,
        "order": list(grades),
        "confusion": matrix.tolist(),
        "accuracy": None,
        "cohen_kappa": None,
        "macro_f1": None,
        "per_class": {},
    }
    if n == 0:
        return out
    rows, columns = matrix.sum(1), matrix.sum(0)
    observed = float(np.trace(matrix)) / n
    expected = float(rows @ columns) / (n * n)
    out["accuracy"] = round(observed, 4)
    # kappa is undefined when chance agreement is total (one class on both sides).
    out["cohen_kappa"] = round((observed - expected) / (1 - expected), 4) if expected < 1 else None
    out["macro_f1"] = round(macro_f1(matrix), 4)
    for i, name in enumerate(grades):
        out["per_class"][name] = {
            "precision": round(int(matrix[i, i]) / int(columns[i]), 4) if columns[i] else None,
            "recall": round(int(matrix[i, i]) / int(rows[i]), 4) if rows[i] else None,
            "support": int(rows[i]),
        }
    return out


def macro_f1(matrix: np.ndarray) -> float:
    """Mean F1 over the classes the curators used (a class nobody labelled has no recall)."""
    scores = []
    for i in range(matrix.shape[0]):
        support, predicted, hit = matrix[i].sum(), matrix[:, i].sum(), matrix[i, i]
        if support == 0:
            continue
        scores.append(2.0 * hit / (support + predicted))
    return float(np.mean(scores)) if scores else 0.0

"""The automatic quality grade of a card: few artifacts / some artifacts / failure, with reasons.

The paper (KeystoneDepth, Luo et al.) graded a sample of 711 cards by hand into these three
categories (:func:`paper_distribution`). Here every card gets the grade automatically from
measurements, each compared with two thresholds ("some" and "failure"); the worst level any
measurement reaches is the grade, and every grade carries its reasons in words and names the
measurement nearest its threshold.

One concept per module, all pure:

* :mod:`.measurements`: :func:`measure_card` -> :class:`GradeMeasurements`.
* :mod:`.verdict`: :class:`GradeThresholds`, :func:`grade` -> :class:`GradeResult` (reasons,
  nearest measurement, uncertainty).
* :mod:`.fitting`: :func:`fit_thresholds` with cross-validated agreement, to curator labels or
  to the true error measured by ``keystone bench grade`` (:func:`labels_from_true_error`).

:func:`pipeline.stages.grade.grade_task` is the per-card stage task the runner calls.
"""

from .fitting import (
    FitReport,
    NotEnoughLabelsError,
    TrueErrorBands,
    agreement,
    fit_thresholds,
    labels_from_true_error,
)
from .measurements import GradeMeasurements, measure_card
from .verdict import (
    GRADES,
    GradeParams,
    GradeResult,
    GradeThresholds,
    Threshold,
    grade,
    paper_distribution,
)

__all__ = [
    "GRADES",
    "FitReport",
    "GradeMeasurements",
    "GradeParams",
    "GradeResult",
    "GradeThresholds",
    "NotEnoughLabelsError",
    "Threshold",
    "TrueErrorBands",
    "agreement",
    "fit_thresholds",
    "grade",
    "labels_from_true_error",
    "measure_card",
    "paper_distribution",
]

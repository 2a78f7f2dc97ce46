"""Agreement figures against published values (irrCAC README, Krippendorff 2011) and by hand."""

from __future__ import annotations

import numpy as np
import pytest

from annotation.agreement import (
    gwet_ac1,
    krippendorff_alpha,
    krippendorff_alpha_boxes,
    krippendorff_alpha_nominal,
    nominal_distance,
    percent_agreement,
)

nan = np.nan

# Krippendorff (2011), "Computing Krippendorff's Alpha-Reliability", section C: 4 observers,
# 12 units, values 1..5, missing answers. Nominal alpha = 0.743. The same data ships with
# Gwet's R package irrCAC as `cac.raw4raters` (transposed); its README reports
# pa = 0.8181818, AC1 = 0.77544, Krippendorff's alpha = 0.74342.
KRIPPENDORFF_2011 = np.array(
    [
        [1, 2, 3, 3, 2, 1, 4, 1, 2, nan, nan, nan],
        [1, 2, 3, 3, 2, 2, 4, 1, 2, 5, nan, 3],
        [nan, 3, 3, 3, 2, 3, 4, 2, 2, 5, 1, nan],
        [1, 2, 3, 3, 2, 4, 4, 1, 2, 5, 1, nan],
    ]
)

# Krippendorff (2011), section A: two observers, binary data, 10 units; alpha = 0.095.
BINARY_TWO_CODERS = np.array(
    [
        [0, 1, 0, 0, 0, 0, 0, 0, 1, 0],
        [1, 1, 1, 0, 0, 1, 0, 0, 0, 0],
    ]
)


def test_alpha_nominal_textbook_value_with_missing_answers() -> None:
    assert krippendorff_alpha_nominal(KRIPPENDORFF_2011) == pytest.approx(0.74342, abs=5e-6)


def test_alpha_nominal_binary_textbook_value() -> None:
    assert krippendorff_alpha_nominal(BINARY_TWO_CODERS) == pytest.approx(0.095, abs=5e-4)


def test_alpha_nominal_matches_krippendorff_package() -> None:
    krippendorff = pytest.importorskip("krippendorff")
    rng = np.random.default_rng(7)
    R = rng.choice([0.0, 1.0, 2.0], size=(6, 40), p=[0.7, 0.2, 0.1])
    R[rng.random(R.shape) < 0.4] = nan  # not every worker sees every item
    for data in (KRIPPENDORFF_2011, BINARY_TWO_CODERS, R):
        expected = krippendorff.alpha(reliability_data=data, level_of_measurement="nominal")
        assert krippendorff_alpha_nominal(data) == pytest.approx(expected, abs=1e-12)


def test_gwet_ac1_textbook_value_with_missing_answers() -> None:
    assert percent_agreement(KRIPPENDORFF_2011) == pytest.approx(0.8181818, abs=1e-7)
    assert gwet_ac1(KRIPPENDORFF_2011) == pytest.approx(0.77544, abs=5e-6)


def test_gwet_ac1_six_raters_distribution() -> None:
    # irrCAC README, `distrib.6raters` (15 patients x 5 diagnoses, 6 psychiatrists each):
    # gwet.ac1.dist -> AC1 0.4448007, pa 0.5511111; krippen.alpha.dist -> 0.4204384.
    distribution = [
        [0, 0, 0, 6, 0],
        [0, 3, 0, 0, 3],
        [0, 1, 4, 0, 1],
        [0, 0, 0, 0, 6],
        [0, 3, 0, 3, 0],
        [2, 0, 4, 0, 0],
        [0, 0, 4, 0, 2],
        [2, 0, 3, 1, 0],
        [2, 0, 0, 4, 0],
        [0, 0, 0, 0, 6],
        [1, 0, 0, 5, 0],
        [1, 1, 0, 4, 0],
        [0, 3, 3, 0, 0],
        [1, 0, 0, 5, 0],
        [0, 2, 0, 3, 1],
    ]
    # Rater identity does not enter either coefficient, so any raters-by-units layout of the
    # counts will do: column u lists the diagnoses given to patient u.
    R = np.array([np.repeat(np.arange(5.0), row) for row in distribution]).T
    assert percent_agreement(R) == pytest.approx(0.5511111, abs=1e-7)
    assert gwet_ac1(R) == pytest.approx(0.4448007, abs=1e-7)
    assert krippendorff_alpha_nominal(R) == pytest.approx(0.4204384, abs=1e-7)


def test_gwet_ac1_two_raters_by_hand() -> None:
    # BINARY_TWO_CODERS: 6 of 10 units agree -> pa = 0.6; "1" is 6 of 20 ratings -> pi_1 = 0.3,
    # pe = (0.3*0.7 + 0.7*0.3) / (2 - 1) = 0.42; AC1 = (0.6 - 0.42) / (1 - 0.42) = 0.3103448.
    assert percent_agreement(BINARY_TWO_CODERS) == pytest.approx(0.6)
    assert gwet_ac1(BINARY_TWO_CODERS) == pytest.approx(0.18 / 0.58)


def test_skewed_classes_alpha_collapses_ac1_does_not() -> None:
    # The kappa paradox on a skewed judge question, by hand: 100 cards, 2 workers; both say
    # "valid" on 96, each says "invalid" alone on 2 different cards. pa = 0.96.
    # Alpha: n = 200 values, 4 of them "invalid": D_o = 2 * 4 / 200 = 0.04,
    # D_e = 2 * 196 * 4 / (200 * 199) = 0.0394; alpha = 1 - 0.04 / 0.0394 = -0.0152.
    # AC1: pi_invalid = 0.02, pe = 2 * 0.02 * 0.98 = 0.0392; AC1 = 0.9208 / 0.9608 = 0.9584.
    R = np.zeros((2, 100))
    R[0, [0, 1]] = 1
    R[1, [2, 3]] = 1
    assert percent_agreement(R) == pytest.approx(0.96)
    assert krippendorff_alpha_nominal(R) == pytest.approx(1 - 0.04 / (2 * 196 * 4 / (200 * 199)))
    assert krippendorff_alpha_nominal(R) < 0
    assert gwet_ac1(R) == pytest.approx((0.96 - 0.0392) / (1 - 0.0392))


def test_gwet_ac1_counts_unused_categories_when_told() -> None:
    # 3 possible answers, only 2 used: K = 3 lowers pe and raises AC1.
    assert gwet_ac1(BINARY_TWO_CODERS, n_categories=3) > gwet_ac1(BINARY_TWO_CODERS)
    with pytest.raises(ValueError, match="Expected n_categories >= 5 observed"):
        gwet_ac1(KRIPPENDORFF_2011, n_categories=2)


def test_units_with_a_single_answer_are_ignored() -> None:
    extra = np.full((2, 3), nan)
    extra[0] = [1, 0, 1]  # answered by one worker only: no pair, no information
    R = np.concatenate([BINARY_TWO_CODERS, extra], axis=1)
    assert krippendorff_alpha_nominal(R) == pytest.approx(krippendorff_alpha_nominal(BINARY_TWO_CODERS))
    assert gwet_ac1(R) != gwet_ac1(BINARY_TWO_CODERS)  # pi_k uses every rated unit (Gwet 2008)
    assert percent_agreement(R) == pytest.approx(0.6)


def test_no_pairable_unit_is_an_error() -> None:
    with pytest.raises(ValueError, match="two or more"):
        krippendorff_alpha_nominal([[1, nan], [nan, 0]])
    with pytest.raises(ValueError, match="two or more"):
        percent_agreement([[1, nan], [nan, 0]])


def test_alpha_is_nan_when_every_value_is_identical() -> None:
    assert np.isnan(krippendorff_alpha_nominal(np.ones((3, 4))))


def test_alpha_boxes_by_hand() -> None:
    # Unit 1: two identical boxes (delta 0). Unit 2: a 10x10 box and a 10x20 box sharing its
    # top half: IoU = 100 / 200 = 0.5, delta = 0.5. n = 4 values.
    # D_o = (1/4) * [0 + 2 * 0.5 / 1] = 0.25.
    # All values: A A B C with A = (0,0,10,10) twice, B = (100,100,110,110), C = (100,100,110,120).
    # Ordered pairs: A-A 0 (x2), A-B 1 (x4), A-C 1 (x4), B-C 0.5 (x2) -> sum = 9.
    # D_e = 9 / (4 * 3) = 0.75; alpha = 1 - 0.25 / 0.75 = 2/3.
    units = [
        np.array([[0, 0, 10, 10], [0, 0, 10, 10]], dtype=float),
        np.array([[100, 100, 110, 110], [100, 100, 110, 120]], dtype=float),
    ]
    assert krippendorff_alpha_boxes(units) == pytest.approx(2 / 3)


def test_general_alpha_with_nominal_distance_equals_nominal_alpha() -> None:
    units = [col[~np.isnan(col)] for col in KRIPPENDORFF_2011.T]
    assert krippendorff_alpha(units, nominal_distance) == pytest.approx(0.743421052631579)

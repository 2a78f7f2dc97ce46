"""Majority vote, Dawid-Skene seeded with gold, worker quality, box consensus, approval rules."""

from __future__ import annotations

import numpy as np
import pytest

from annotation.aggregation import (
    BoxConsensus,
    ConfidenceRules,
    GoldScore,
    InvalidBoxError,
    Judgement,
    JudgementAnswer,
    LabelAnswer,
    aggregate_judgements,
    box_iou,
    consensus_box,
    dawid_skene,
    flag_workers,
    gold_accuracy,
    is_confident,
    majority_vote,
    unconfident_reasons,
    validate_box,
)


def answers_from(table: dict[str, dict[str, int]]) -> list[LabelAnswer]:
    """``{worker: {item: label}}`` -> answers."""
    return [LabelAnswer(item, worker, label) for worker, row in table.items() for item, label in row.items()]


# --- majority vote ---------------------------------------------------------------------------


def test_majority_vote_reports_ties_instead_of_breaking_them() -> None:
    votes = majority_vote(
        answers_from({"a": {"c1": 1, "c2": 0}, "b": {"c1": 1, "c2": 1}, "c": {"c1": 0}}),
        n_classes=2,
    )
    assert votes["c1"].label == 1 and votes["c1"].votes == (1, 2) and votes["c1"].tied == (1,)
    assert votes["c2"].label is None and votes["c2"].tied == (0, 1)


def test_majority_vote_rejects_labels_outside_the_classes() -> None:
    with pytest.raises(ValueError, match="Expected a label in 0..1, got 2"):
        majority_vote([LabelAnswer("c1", "a", 2)], n_classes=2)


# --- Dawid-Skene -----------------------------------------------------------------------------


def colluding_spammers_case() -> tuple[list[LabelAnswer], dict[str, int], dict[str, int]]:
    """Two careful workers against three spammers who all answer "0" on everything.

    20 cards, truth alternates 0/1. On every true-1 card the vote is 3 x "0" vs 2 x "1", so
    majority vote gets exactly half wrong. Cards g0..g3 are gold.
    """
    truth = {f"c{i}": i % 2 for i in range(16)} | {f"g{i}": i % 2 for i in range(4)}
    table = {w: dict(truth) for w in ("careful1", "careful2")}
    table |= {w: {item: 0 for item in truth} for w in ("spam1", "spam2", "spam3")}
    gold = {k: v for k, v in truth.items() if k.startswith("g")}
    return answers_from(table), gold, truth


def test_dawid_skene_beats_majority_vote_against_colluding_spammers() -> None:
    answers, gold, truth = colluding_spammers_case()
    mv = majority_vote(answers, 2)
    assert sum(mv[i].label == t for i, t in truth.items()) == 10  # half: every true 1 is lost

    ds = dawid_skene(answers, 2, gold)
    assert ds.converged
    assert all(ds.label_of(i) == t for i, t in truth.items())
    # Spammers' answers carry no information: both rows of their matrix say "0".
    spam = ds.confusion[ds.worker_ids.index("spam1")]
    assert spam[0, 0] > 0.9 and spam[1, 0] > 0.9
    assert ds.accuracy_of("careful1") > 0.9
    assert ds.accuracy_of("spam1") == pytest.approx(0.5, abs=0.1)
    assert np.all(ds.confidence > 0.95)


def test_gold_posteriors_are_clamped_even_against_every_answer() -> None:
    answers = answers_from({"a": {"x": 0, "y": 1}, "b": {"x": 0, "y": 1}, "c": {"x": 0, "y": 1}})
    ds = dawid_skene(answers, 2, gold={"x": 1})
    np.testing.assert_array_equal(ds.posterior("x"), [0.0, 1.0])
    assert ds.label_of("x") == 1


def test_initial_confusion_comes_from_gold_so_a_flipper_is_read_inverted() -> None:
    # "flip" answers the opposite of the truth on all four gold cards; on the open card it
    # says 0 and the unreliable "one" says 1: trust the flip, reversed.
    table = {
        "flip": {"g0": 1, "g1": 0, "g2": 1, "g3": 0, "open": 0},
        "one": {"g0": 1, "g1": 0, "g2": 0, "g3": 1, "open": 1},
    }
    ds = dawid_skene(answers_from(table), 2, gold={"g0": 0, "g1": 1, "g2": 0, "g3": 1}, max_iter=1)
    C = ds.confusion[ds.worker_ids.index("flip")]
    assert C[0, 1] > 0.5 and C[1, 0] > 0.5
    assert ds.label_of("open") == 1


def test_single_answers_unseen_classes_and_workers_without_gold_stay_finite() -> None:
    answers = [
        LabelAnswer("lonely", "w1", 2),  # one answer, and class 2 appears nowhere else
        LabelAnswer("c1", "w2", 0),
        LabelAnswer("c1", "w3", 0),
        LabelAnswer("c2", "w2", 1),
        LabelAnswer("g", "w3", 0),
    ]
    ds = dawid_skene(answers, 4, gold={"g": 0})  # class 3 never answered
    for arr in (ds.posteriors, ds.confusion, ds.worker_accuracy, ds.class_prior, ds.confidence):
        assert np.isfinite(arr).all()
    np.testing.assert_allclose(ds.posteriors.sum(axis=1), 1.0)
    np.testing.assert_allclose(ds.confusion.sum(axis=2), 1.0)
    # One answer of a rare class from a worker nobody knows: not enough to approve the card.
    assert 0.0 < ds.posterior("lonely")[2] < 0.95
    assert ds.confidence[ds.item_ids.index("lonely")] < 0.95
    assert 0.0 < ds.posterior("lonely")[3] < 0.5
    assert np.isfinite(ds.log_likelihood)


def test_smoothing_keeps_a_three_answer_worker_from_vetoing_an_item() -> None:
    # Without smoothing "rookie" (3 answers, all agreeing with the crowd) would get a 0/1
    # matrix and a single contrary answer would force the posterior to 1.0 against four others.
    table = {w: {"a": 0, "b": 1, "c": 0, "d": 0} for w in ("w1", "w2", "w3", "w4")}
    table["rookie"] = {"a": 0, "b": 1, "c": 0, "d": 1}
    ds = dawid_skene(answers_from(table), 2)
    assert ds.label_of("d") == 0
    assert 0.0 < ds.posterior("d")[1] < 0.5


def test_iteration_cap_and_tolerance_are_honoured() -> None:
    answers, gold, _ = colluding_spammers_case()
    capped = dawid_skene(answers, 2, gold, max_iter=1, tol=0.0)
    assert capped.iterations == 1 and not capped.converged
    loose = dawid_skene(answers, 2, gold, tol=0.5)
    strict = dawid_skene(answers, 2, gold, tol=1e-10)
    assert loose.iterations < strict.iterations


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_classes": 1}, "n_classes >= 2"),
        ({"smoothing": 0.0}, "smoothing > 0"),
    ],
)
def test_dawid_skene_bad_parameters(kwargs: dict[str, float], message: str) -> None:
    params = {"n_classes": 2} | kwargs
    with pytest.raises(ValueError, match=message):
        dawid_skene([LabelAnswer("c", "w", 0)], **params)  # type: ignore[arg-type]


def test_dawid_skene_needs_answers() -> None:
    with pytest.raises(ValueError, match="at least one answer"):
        dawid_skene([], 2)


def test_aggregate_judgements_runs_one_model_per_question() -> None:
    upright_valid = Judgement(is_stereo=True, upside_down=False, inverted=False)
    flipped = Judgement(is_stereo=True, upside_down=True, inverted=False)
    answers = [
        JudgementAnswer("card1", "a", upright_valid),
        JudgementAnswer("card1", "b", upright_valid),
        JudgementAnswer("card1", "c", upright_valid),
        JudgementAnswer("gold1", "a", flipped),
        JudgementAnswer("gold1", "c", flipped),
    ]
    out = aggregate_judgements(answers, gold={"gold1": flipped})
    assert set(out) == {"is_stereo", "upside_down", "inverted"}
    assert out["is_stereo"].label_of("card1") == 1
    assert out["upside_down"].label_of("card1") == 0
    assert out["upside_down"].label_of("gold1") == 1


def test_swapped_is_aggregated_over_the_answers_that_asked_it() -> None:
    def judged(swapped: bool | None) -> Judgement:
        return Judgement(is_stereo=True, upside_down=False, inverted=False, swapped=swapped)

    answers = [
        JudgementAnswer("card1", "a", judged(True)),
        JudgementAnswer("card1", "b", judged(True)),
        JudgementAnswer("card1", "c", judged(None)),  # an older page: not asked
        JudgementAnswer("card2", "a", judged(False)),
        JudgementAnswer("card2", "b", judged(False)),
        JudgementAnswer("card2", "c", judged(False)),
        JudgementAnswer("gold1", "a", judged(True)),
        JudgementAnswer("gold1", "b", judged(True)),
    ]
    out = aggregate_judgements(answers, gold={"gold1": judged(True)})
    assert set(out) == {"is_stereo", "upside_down", "inverted", "swapped"}
    assert out["swapped"].label_of("card1") == 1 and out["swapped"].posterior("card1")[1] > 0.7
    assert out["swapped"].label_of("card2") == 0 and out["swapped"].posterior("card2")[0] > 0.8
    # Without any answer that asked it, there is no swapped model at all (older batches).
    older = [JudgementAnswer(a.item_id, a.worker_id, judged(None)) for a in answers]
    assert set(aggregate_judgements(older)) == {"is_stereo", "upside_down", "inverted"}


# --- worker quality --------------------------------------------------------------------------


def test_gold_accuracy_counts_only_gold_answers() -> None:
    answers = answers_from({"a": {"g1": 1, "g2": 0, "x": 1}, "b": {"g1": 0, "x": 0}, "c": {"x": 1}})
    scores = gold_accuracy(answers, gold={"g1": 1, "g2": 1})
    assert scores == {"a": GoldScore(1, 2), "b": GoldScore(0, 1)}
    assert scores["a"].accuracy == 0.5
    assert GoldScore(0, 0).accuracy == 0.0


def test_flag_workers_needs_enough_gold_before_flagging() -> None:
    scores = {"good": GoldScore(9, 10), "bad": GoldScore(3, 10), "unlucky": GoldScore(0, 1)}
    assert flag_workers(scores, threshold=0.7, min_gold=5) == {"bad"}
    assert flag_workers(scores, threshold=0.7, min_gold=1) == {"bad", "unlucky"}
    with pytest.raises(ValueError, match="min_gold >= 1"):
        flag_workers(scores, threshold=0.7, min_gold=0)
    with pytest.raises(ValueError, match="threshold"):
        flag_workers(scores, threshold=1.5, min_gold=1)


# --- boxes -----------------------------------------------------------------------------------


def test_box_iou_by_hand() -> None:
    # Two 10x10 boxes overlapping by half: intersection 50, union 150.
    iou = box_iou(np.array([[0, 0, 10, 10]]), np.array([[5, 0, 15, 10], [20, 20, 30, 30]]))
    np.testing.assert_allclose(iou, [[1 / 3, 0.0]])


def test_consensus_box_ignores_an_outlier() -> None:
    boxes = [(10, 20, 110, 220), (12, 18, 112, 222), (11, 21, 109, 219), (300, 300, 400, 400)]
    c = consensus_box(boxes)
    # First median (11.5, 20.5, 111, 221) has IoU 0 with the outlier -> dropped; the median of
    # the three kept is (11, 20, 110, 220); absolute deviations per coordinate are {1, 1, 0},
    # {0, 2, 1}, {0, 2, 1}, {0, 2, 1} -> MAD 1 px each.
    assert c.box == (11.0, 20.0, 110.0, 220.0)
    assert (c.kept, c.dropped) == (3, 1)
    assert c.kept_mask == (True, True, True, False)
    assert c.mad == (1.0, 1.0, 1.0, 1.0)
    assert 0.95 < c.mean_iou < 1.0


def test_consensus_box_when_nobody_agrees_keeps_nothing() -> None:
    c = consensus_box([(0, 0, 10, 10), (100, 100, 110, 110), (200, 0, 210, 10)])
    assert c.kept == 0 and c.mean_iou == 0.0
    assert not is_confident(boxes={"left": c})


@pytest.mark.parametrize(
    ("box", "message"),
    [
        ((0, 0, float("nan"), 10), "finite"),
        ((10, 0, 0, 10), "x0 < x1"),
        ((0, 10, 10, 10), "positive width and height"),
        ((0, 0, 10), "shape"),
        ((-1, 0, 10, 10), "inside the 100x50 image"),
        ((0, 0, 10, 60), "inside the 100x50 image"),
    ],
)
def test_invalid_boxes_are_refused(box: tuple[float, ...], message: str) -> None:
    with pytest.raises(InvalidBoxError, match=message):
        validate_box(box, image_size=(100, 50))
    with pytest.raises(InvalidBoxError):
        consensus_box([(0, 0, 5, 5), box], image_size=(100, 50))


def test_empty_box_list_is_refused() -> None:
    with pytest.raises(InvalidBoxError, match="at least one box"):
        consensus_box([])


# --- approved vs waits for a curator ---------------------------------------------------------


def tight_box() -> BoxConsensus:
    return consensus_box([(10, 20, 110, 220), (11, 21, 111, 221), (10, 20, 110, 220)])


def test_confident_card_is_approved() -> None:
    assert is_confident({"is_stereo": 0.99, "upside_down": 0.97}, {"left": tight_box(), "right": tight_box()})


def test_each_rule_sends_the_card_to_a_curator() -> None:
    rules = ConfidenceRules(min_posterior=0.95, min_boxes_kept=2, max_box_mad_px=8.0, min_box_mean_iou=0.8)
    assert unconfident_reasons({"inverted": 0.9}, rules=rules) == ("inverted: posterior 0.900 < 0.95",)
    assert unconfident_reasons({"inverted": float("nan")}, rules=rules)
    single = consensus_box([(10, 20, 110, 220)])
    assert unconfident_reasons(boxes={"left": single}, rules=rules) == ("left box: 1 boxes kept < 2",)
    loose = consensus_box([(0, 0, 100, 100), (20, 20, 100, 100), (10, 10, 100, 100)])
    reasons = unconfident_reasons(boxes={"right": loose}, rules=rules)
    assert reasons == ("right box: spread 10.0 px > 8.0 px",)
    assert not is_confident(boxes={"right": loose}, rules=rules)


def test_core_modules_import_no_web_or_database_code() -> None:
    # The pure core must stay usable from the pipeline, the CLI and tests without the app.
    import json
    import subprocess
    import sys

    code = (
        "import json, sys\n"
        "import annotation.assignment, annotation.aggregation, annotation.agreement\n"
        "print(json.dumps(sorted(m for m in sys.modules"
        " if m.split('.')[0] in ('flask', 'sqlalchemy', 'torch', 'app', 'krippendorff'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == []

"""The confirm grid's pure part: what a tap means, the gold a batch hides, the vote over taps."""

from __future__ import annotations

import itertools

import pytest

from annotation.confirm import (
    FLAGS,
    GOLD_FLIPS,
    TapAnswer,
    aggregate_taps,
    apply_taps,
    as_flags,
    gold_shown,
    grid_order,
    pick_gold,
    taps_between,
)

ALL = [dict(zip(FLAGS, values, strict=True)) for values in itertools.product((False, True), repeat=3)]


@pytest.mark.parametrize("shown", ALL)
def test_a_tap_flips_one_flag_and_taps_between_undoes_them(shown):  # type: ignore[no-untyped-def]
    assert apply_taps(shown, {}) == shown  # no tap confirms what was shown
    for flag in FLAGS:
        assert apply_taps(shown, {flag: True}) == {**shown, flag: not shown[flag]}
    for truth in ALL:
        assert apply_taps(shown, taps_between(shown, truth)) == truth


def test_gold_shows_each_flag_wrong_in_turn_and_once_right():  # type: ignore[no-untyped-def]
    truth = {"upside_down": True, "inverted": False, "swapped": False}
    shown = [gold_shown(truth, turn) for turn in range(len(GOLD_FLIPS))]
    taps = [taps_between(s, truth) for s in shown]
    assert [tuple(f for f in FLAGS if t[f]) for t in taps] == [("upside_down",), ("inverted",), ("swapped",), ()]
    assert gold_shown(truth, 4) == shown[0]


def test_as_flags_needs_all_three():  # type: ignore[no-untyped-def]
    assert as_flags({"upside_down": 1, "inverted": 0, "swapped": True}) == {
        "upside_down": True,
        "inverted": False,
        "swapped": True,
    }
    with pytest.raises(KeyError):
        as_flags({"upside_down": True})


def test_the_vote_follows_reliable_workers_over_a_spammer_who_taps_everything():  # type: ignore[no-untyped-def]
    gold = {100 + g: {f: f == FLAGS[g % 3] for f in FLAGS} for g in range(6)}
    truth = {i: {f: (i % 10 == 1 and f == "upside_down") for f in FLAGS} for i in range(30)}
    answers = []
    for worker in ("good-1", "good-2"):
        answers += [TapAnswer(i, worker, t) for i, t in truth.items()]
        answers += [TapAnswer(g, worker, t) for g, t in gold.items()]
    answers += [TapAnswer(i, "spammer", dict.fromkeys(FLAGS, True)) for i in [*truth, *gold]]
    votes = aggregate_taps(answers, gold)
    for i, t in truth.items():
        assert {f: bool(votes[f].label_of(i)) for f in FLAGS} == t
        assert min(max(votes[f].posterior(i)) for f in FLAGS) > 0.95
    assert votes["inverted"].accuracy_of("spammer") < 0.6 < 0.9 < votes["inverted"].accuracy_of("good-1")


def test_grid_order_is_the_tokens_order_not_the_items():  # type: ignore[no-untyped-def]
    assert grid_order([(1, "b"), (2, "a"), (3, "c")]) == [2, 1, 3]


def test_a_grids_gold_has_one_card_shown_right_and_the_rest_wrong_on_different_flags():  # type: ignore[no-untyped-def]
    def taps(*flags: str) -> dict[str, bool]:
        return {f: f in flags for f in FLAGS}

    candidates = [
        (1, 0, taps("upside_down")),
        (2, 0, taps("upside_down")),
        (3, 1, taps("inverted")),
        (4, 2, taps()),
        (5, 0, taps("swapped")),
        (6, 0, taps()),
    ]
    assert pick_gold(candidates, 3) == [6, 1, 5]  # right, then least answered of two flags
    assert pick_gold(candidates, 4) == [6, 1, 5, 3]
    assert pick_gold(candidates, 6) == [6, 1, 5, 3, 2, 4]
    assert pick_gold(candidates, 0) == [] and pick_gold([], 3) == []

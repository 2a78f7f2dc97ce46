"""Confirm grids, the pure part: what a tap means, the gold a grid hides, the vote over taps.

A confirm card is shown as the pipeline would use it: the orientation flags it is shown with
(``shown``, the card as scanned: ``upside_down``, ``inverted``, ``swapped``, :mod:`pipeline.orientation`) are
applied to the scan before the picture is made. A worker taps only what looks wrong:
"upside down", "negative" or "inside-out depth". Each tap flips one flag, independently of
the others, because the three fixes commute where it matters: turning the whole card and
exchanging its photos commute, a negative is a negative either way up, and a correct pair
turned 180 deg keeps its depth right (both photos turn and trade places). So the orientation
a grid answer says is ``shown`` XOR ``taps``, flag by flag.

Gold: a card whose orientation people (or the step, with a wide margin) already decided,
shown deliberately wrong on one flag (or right), so the right answer is known: one tap on
that flag (or none). No Flask or SQLAlchemy here.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from .aggregation import DawidSkeneResult, LabelAnswer, dawid_skene
from .questions import GRID, keys

# The keys of a grid answer: the grid's questions (annotation.questions.GRID, where each one's
# button words, hotkey and help are), which are the orientation flags of pipeline.decided_orientation.
FLAGS: tuple[str, ...] = keys(GRID)
# What gold shows wrong, in turn: one flag flipped, or none (a gold card shown right keeps a
# worker who taps everything from passing).
GOLD_FLIPS: tuple[tuple[str, ...], ...] = (("upside_down",), ("inverted",), ("swapped",), ())

Flags = Mapping[str, bool]


def as_flags(values: Mapping[str, object]) -> dict[str, bool]:
    """The three flags of ``values`` as booleans; KeyError when one is missing."""
    return {flag: bool(values[flag]) for flag in FLAGS}


def apply_taps(shown: Flags, taps: Flags) -> dict[str, bool]:
    """The card's orientation (as scanned) that an answer says: each tapped flag flipped."""
    return {flag: bool(shown[flag]) != bool(taps.get(flag, False)) for flag in FLAGS}


def taps_between(shown: Flags, truth: Flags) -> dict[str, bool]:
    """The taps that turn what is shown into the truth: the flags where they differ."""
    return {flag: bool(shown[flag]) != bool(truth[flag]) for flag in FLAGS}


def gold_shown(truth: Flags, turn: int) -> dict[str, bool]:
    """What the ``turn``-th gold card of a batch is shown with: its truth with
    :data:`GOLD_FLIPS` ``[turn % 4]`` flipped (so a batch's gold covers every tap and no tap)."""
    flips = GOLD_FLIPS[turn % len(GOLD_FLIPS)]
    return {flag: bool(truth[flag]) != (flag in flips) for flag in FLAGS}


@dataclass(frozen=True)
class TapAnswer:
    item_id: Hashable
    worker_id: Hashable
    taps: Mapping[str, bool]


def aggregate_taps(answers: Sequence[TapAnswer], gold: Mapping[Hashable, Flags] | None = None) -> dict[str, DawidSkeneResult]:
    """One binary Dawid-Skene per flag over "tapped" (1) / "left alone" (0), seeded with the
    gold taps, so a worker's reliability (their confusion on gold and on the crowd's consensus)
    weighs their taps. Why per flag and not one joint label: the flags are independent
    questions (see the module docstring), and 8 joint classes would need far more answers."""
    gold = gold or {}
    return {
        flag: dawid_skene(
            [LabelAnswer(a.item_id, a.worker_id, int(bool(a.taps.get(flag, False)))) for a in answers],
            2,
            {item: int(bool(taps[flag])) for item, taps in gold.items()},
        )
        for flag in FLAGS
    }


def pick_gold(candidates: Sequence[tuple[Hashable, int, Flags]], k: int) -> list[Hashable]:
    """Which ``k`` gold items a grid hides, from ``(item, answers so far, gold taps)``: one
    shown right (no tap is the answer: a worker who taps everything fails it) and the rest
    shown wrong on as many different flags as there are, least answered first within each
    (so every gold card gathers evidence on workers)."""
    pool = sorted(candidates, key=lambda c: (c[1], str(c[0])))
    right = [c for c in pool if not any(c[2].get(f) for f in FLAGS)]
    wrong = [c for c in pool if any(c[2].get(f) for f in FLAGS)]
    picked: list[tuple[Hashable, int, Flags]] = right[:1] if k > 0 else []
    seen: set[str] = set()
    for c in wrong:  # one of each wrong flag first, then the least answered of the rest
        flag = next(f for f in FLAGS if c[2].get(f))
        if len(picked) < k and flag not in seen:
            picked.append(c)
            seen.add(flag)
    rest = [c for c in pool if c not in picked]
    picked += rest[: max(0, k - len(picked))]
    return [c[0] for c in picked]


def grid_order(items: Iterable[tuple[Hashable, str]]) -> list[Hashable]:
    """The order a grid shows its cards in: by each reservation token (random, never stored
    order), so gold items sit anywhere among the regular ones."""
    return [item for item, _ in sorted(items, key=lambda pair: pair[1])]

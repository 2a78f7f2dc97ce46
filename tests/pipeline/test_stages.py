"""Per-card stage tasks: orientation corrections apply to derived images only, and say so."""

from __future__ import annotations

import numpy as np

from pipeline.stages.rectify import orient_card


def test_upright_card_skips_the_orientation_step_and_says_why():
    card = np.arange(24, dtype=np.uint8).reshape(4, 6)
    same, record = orient_card(card, {})
    assert same is card and record["status"] == "skipped" and record["reason"].startswith("not needed")
    _, judged = orient_card(card, {"upside_down": False, "inverted": False})
    assert judged["reason"] == "not needed: judged upright and not inverted"


def test_corrections_are_applied_to_a_copy():
    card = np.arange(24, dtype=np.uint8).reshape(4, 6)
    before = card.copy()
    fixed, record = orient_card(card, {"upside_down": True, "inverted": True})
    assert np.array_equal(card, before)  # the original array is untouched
    assert np.array_equal(fixed, 255 - before[::-1, ::-1])
    assert record == {"status": "done", "applied": ["rotated 180 deg", "intensities inverted"], "source": "judgement"}

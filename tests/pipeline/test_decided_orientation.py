"""resolve_orientation with the grid's confirm aggregate: the crowd's taps decide a ``confirm``
card, a curator's override still wins flag by flag, and a card waiting for a grid says so."""

from __future__ import annotations

from types import SimpleNamespace

from pipeline.decided_orientation import resolve_orientation

FLAGS = ("upside_down", "inverted", "swapped")
PROPOSED = {"upside_down": True, "inverted": False, "swapped": False}


def _step(outcome: str = "confirm") -> SimpleNamespace:
    flags = {f: {"p": 0.7, "decided": False, "value": v} for f, v in PROPOSED.items()}
    metrics = {"decision": outcome, "proposed": PROPOSED, "flags": flags, "confidence": 0.7}
    return SimpleNamespace(status="done", outcome=outcome, metrics=metrics, param_hash="p" * 16, reason=None)


def _confirm(tapped: dict[str, bool]) -> SimpleNamespace:
    label = {f: PROPOSED[f] != tapped[f] for f in FLAGS} | {"shown": PROPOSED, "tapped": tapped}
    return SimpleNamespace(label=label, posterior={"upside_down": 0.99, "inverted": 0.999, "swapped": 0.98}, batch_id=7)


def _override(**flags: bool | None) -> SimpleNamespace:
    return SimpleNamespace(**{f: flags.get(f) for f in FLAGS}, curator_name="cora")


def test_a_confirm_card_without_a_grid_answer_waits_for_one():  # type: ignore[no-untyped-def]
    used = resolve_orientation(_step(), None, None)
    assert [used[f] for f in FLAGS] == [None, None, None] and used["decided_by"] is None
    assert used["waiting_for"] == "people (a grid confirmation)"


def test_untapped_flags_confirm_the_proposal_and_tapped_ones_flip_it():  # type: ignore[no-untyped-def]
    confirmed = resolve_orientation(_step(), None, None, confirm=_confirm(dict.fromkeys(FLAGS, False)))
    assert {f: confirmed[f] for f in FLAGS} == PROPOSED
    assert confirmed["decided_by"] == "crowd" and confirmed["confidence"] == 0.98 and confirmed["waiting_for"] is None
    assert "crowd confirmation (batch 7)" in confirmed["source"]
    flipped = resolve_orientation(
        _step(), None, None, confirm=_confirm({"upside_down": True, "inverted": False, "swapped": True})
    )
    assert {f: flipped[f] for f in FLAGS} == {"upside_down": False, "inverted": False, "swapped": True}


def test_a_curators_override_wins_flag_by_flag():  # type: ignore[no-untyped-def]
    used = resolve_orientation(_step(), None, _override(inverted=True), confirm=_confirm(dict.fromkeys(FLAGS, False)))
    assert {f: used[f] for f in FLAGS} == {**PROPOSED, "inverted": True} and used["decided_by"] == "curator"


def test_without_a_confirm_source_the_old_sources_are_unchanged():  # type: ignore[no-untyped-def]
    auto = resolve_orientation(_step("auto"), None, None)
    assert {f: auto[f] for f in FLAGS} == PROPOSED and auto["decided_by"] == "auto"
    asked = resolve_orientation(_step("ask"), None, None)
    assert asked["decided_by"] is None and "not sure" in asked["waiting_for"]

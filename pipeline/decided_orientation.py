"""The orientation the pipeline uses for a card: the step's, the crowd's, an operator's or a curator's.

Four sources, each flag taken from the strongest that speaks to it:

1. a curator's override (``review.models.OrientationOverride``), flag by flag;
2. an operator's word for the card's whole collection (``core.models.CollectionOrientation``):
   known prints, known to be scanned in eye order, flag by flag;
3. the crowd's approved confirm aggregate (a grid: the flags the card was shown with, each
   flag the crowd's vote says was tapped flipped; ``annotation.confirm``), all three flags;
   then the crowd's approved judge aggregate: ``upside_down`` and ``inverted`` always;
   ``swapped`` when the judge task asked it (``label["swapped"]``), else the step's own value
   when the step was confident on that flag, else undecided (a person answers it);
4. the orientation stage's result, when it decided the card automatically (``outcome ==
   "auto"``); a step that asked, or that only proposes an orientation for people to confirm
   (``outcome == "confirm"``), contributes nothing on its own (given the operator's word as
   ``known_flags``, the step decides the remaining flags itself when it can).

``decided_by`` names the strongest source used (``curator`` > ``operator`` > ``crowd`` >
``auto``); any flag still null means the card is undecided: it waits for people, and it is not
rectified, graded, accepted or released (the flow rule of docs/PIPELINE.md, Orientation).
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from typing import Any, Protocol

from .results import CardResults, StageResultLike

__all__ = [
    "FLAGS",
    "ApprovedAggregate",
    "CuratorOverride",
    "OperatorWord",
    "card_orientation",
    "is_decided",
    "public_orientation",
    "resolve_orientation",
    "said_flags",
    "word_phrase",
    "word_sentence",
    "word_source",
]

FLAGS: tuple[str, ...] = ("upside_down", "inverted", "swapped")
# What an operator's word on one flag says of a collection, in words (flag -> value -> phrase).
WORD_PHRASES: dict[str, dict[bool, str]] = {
    "upside_down": {False: "scanned upright", True: "scanned upside down"},
    "inverted": {False: "known prints", True: "known negatives"},
    "swapped": {False: "scanned in eye order", True: "scanned with the eyes exchanged"},
}


class ApprovedAggregate(Protocol):
    """The crowd's approved aggregate of one task kind for a card (``annotation.models.Aggregate``):
    the answer (``label``), how sure the aggregation is (``posterior``) and the batch it came from."""

    @property
    def label(self) -> Mapping[str, Any] | None: ...

    @property
    def posterior(self) -> Any: ...

    @property
    def batch_id(self) -> int: ...


class CuratorOverride(Protocol):
    """A curator's orientation override for one card (``review.models.OrientationOverride``):
    each flag set, or None where the curator left it to the other sources."""

    @property
    def upside_down(self) -> bool | None: ...

    @property
    def inverted(self) -> bool | None: ...

    @property
    def swapped(self) -> bool | None: ...

    @property
    def curator_name(self) -> str | None: ...


class OperatorWord(Protocol):
    """An operator's word for a whole collection (``core.models.CollectionOrientation``)."""

    @property
    def upside_down(self) -> bool | None: ...

    @property
    def inverted(self) -> bool | None: ...

    @property
    def swapped(self) -> bool | None: ...

    @property
    def collection_name(self) -> str: ...

    @property
    def set_by_name(self) -> str: ...

    @property
    def set_at(self) -> datetime: ...


def _as_flag(value: Any) -> bool | None:
    return None if value is None else bool(value)


def said_flags(word: OperatorWord | None) -> dict[str, bool]:
    """The flags an operator's word (a CollectionOrientation row, or None) sets: flag -> value."""
    if word is None:
        return {}
    return {flag: bool(value) for flag in FLAGS if (value := getattr(word, flag)) is not None}


def word_phrase(word: OperatorWord) -> str:
    """What the word says, e.g. ``known prints, scanned in eye order``."""
    return ", ".join(WORD_PHRASES[flag][value] for flag, value in said_flags(word).items())


def word_source(word: OperatorWord) -> str:
    """The word as a source of a card's orientation, in words."""
    return f"operator's word for collection {word.collection_name} (by {word.set_by_name}, {word.set_at:%Y-%m-%d})"


def word_sentence(word: OperatorWord) -> str:
    """The word as a card page shows it: ``Collection X: known prints, said by NAME on DATE``."""
    return f"Collection {word.collection_name}: {word_phrase(word)}, said by {word.set_by_name} on {word.set_at:%Y-%m-%d}"


def resolve_orientation(
    step: StageResultLike | None,
    judge: ApprovedAggregate | None,
    override: CuratorOverride | None,
    operator: OperatorWord | None = None,
    *,
    confirm: ApprovedAggregate | None = None,
) -> dict[str, Any]:
    """The ``orientation`` field of ``keystone cards --json`` plus ``source`` (in words),
    ``waiting_for`` (why it is undecided, or null), ``operator_word`` (the collection's word as
    a sentence, or null) and ``operator_overridden`` (the flags of that word a curator's
    override replaces on this card).

    ``step``: the latest ``orientation`` StageResult (or None); ``judge``: the latest APPROVED
    judge Aggregate (or None); ``override``: the card's OrientationOverride row (or None);
    ``operator``: the card's collection's CollectionOrientation row (or None); ``confirm``: the
    latest APPROVED confirm Aggregate (or None).
    """
    flags: dict[str, bool | None] = dict.fromkeys(FLAGS)
    sources: list[str] = []
    decided_by: str | None = None
    confidence: float | None = None
    done_step = step if step is not None and step.status == "done" else None
    step_flags = (done_step.metrics.get("flags") or {}) if done_step is not None else {}
    if done_step is not None and done_step.outcome == "auto":
        flags = {flag: _as_flag((step_flags.get(flag) or {}).get("value")) for flag in FLAGS}
        decided_by, confidence = "auto", done_step.metrics.get("confidence")
        sources.append(f"orientation step ({done_step.param_hash})")
    if confirm is not None:
        # The label's flags are what the grid showed with the crowd's taps applied: the shown
        # flags are kept on the batch item, so a rerun of the step that proposes something
        # else cannot turn a confirmation into its opposite.
        flags = {flag: _as_flag((confirm.label or {}).get(flag)) for flag in FLAGS}
        decided_by = "crowd"
        sure = [float(v) for v in (confirm.posterior or {}).values() if isinstance(v, (int, float))]
        confidence = min(sure) if sure else 1.0
        sources.append(f"crowd confirmation (batch {confirm.batch_id})")
    if judge is not None:
        label = judge.label or {}
        flags["upside_down"] = bool(label.get("upside_down"))
        flags["inverted"] = bool(label.get("inverted"))
        if label.get("swapped") is not None:
            flags["swapped"] = bool(label["swapped"])
        elif (step_flags.get("swapped") or {}).get("decided"):
            flags["swapped"] = bool(step_flags["swapped"]["value"])
        elif decided_by != "auto":
            # Not the step's tie P(upside_down == swapped) either: in the demo it turned a
            # crowd's right "not upside down" into a wrong "swapped" on the negative card.
            flags["swapped"] = None
        decided_by = "crowd"
        # The aggregate's posterior is question -> P(its MAP answer); the least sure one counts.
        posterior = judge.posterior if isinstance(judge.posterior, dict) else {}
        sure = [float(v) for k, v in posterior.items() if k in FLAGS and isinstance(v, (int, float))]
        confidence = min(sure) if sure else 1.0
        sources.append(f"crowd judgement (batch {judge.batch_id})")
    said = said_flags(operator)
    if said and operator is not None:
        flags.update(said)
        decided_by = "operator"
        # The operator is sure of what was said; the flags left to the step or the crowd keep
        # their confidence.
        confidence = 1.0 if len(said) == len(FLAGS) else confidence
        sources.append(word_source(operator))
    overridden: list[str] = []
    if override is not None:
        touched = False
        for flag in FLAGS:
            value = getattr(override, flag)
            if value is not None:
                flags[flag] = bool(value)
                touched = True
                if flag in said:
                    overridden.append(flag)
        if touched:
            decided_by, confidence = "curator", 1.0
            sources.append(f"curator override (by {override.curator_name or 'a curator'})")
    undecided = [flag for flag in FLAGS if flags[flag] is None]
    waiting_for = None
    if undecided:
        if step is None:
            waiting_for = "the orientation step (not run yet)"
        elif step.status == "failed":
            waiting_for = f"people (the orientation step failed: {step.reason})"
        elif judge is None and confirm is None and step.outcome == "confirm":
            waiting_for = "people (a grid confirmation)"
        elif judge is None and step.metrics.get("undecidable"):
            waiting_for = f"people (the orientation step cannot tell: {step.metrics['undecidable']})"
        elif judge is None:
            unsure = [flag for flag in FLAGS if not (step_flags.get(flag) or {}).get("decided") and flag not in said]
            waiting_for = f"people (the orientation step is not sure of {', '.join(unsure or undecided)})"
        else:
            waiting_for = f"people ({', '.join(undecided)} undecided)"
    return {
        **flags,
        "decided_by": decided_by if not undecided else None,
        "confidence": None if confidence is None else round(float(confidence), 4),
        "source": "; ".join(sources) or None,
        "waiting_for": waiting_for,
        "operator_word": word_sentence(operator) if said and operator is not None else None,
        "operator_overridden": overridden,
    }


def card_orientation(card: CardResults, approved: Mapping[str, Any]) -> dict[str, Any]:
    """The orientation the pipeline uses for ``card`` (:func:`resolve_orientation`) from its latest
    orientation result and people's approved decisions about it (``approved``: ``judge``,
    ``confirm``, ``orientation_override``, ``operator_orientation``, as the driver gathers them
    through ``core.hooks.approved_decisions``; absent kinds are None)."""
    return resolve_orientation(
        card.latest_results().get("orientation"),
        approved.get("judge"),
        approved.get("orientation_override"),
        approved.get("operator_orientation"),
        confirm=approved.get("confirm"),
    )


def is_decided(orientation: Mapping[str, Any]) -> bool:
    return all(orientation.get(flag) is not None for flag in FLAGS)


def public_orientation(orientation: Mapping[str, Any]) -> dict[str, Any]:
    """The five keys of ``keystone cards --json``'s ``orientation`` (README.md)."""
    return {key: orientation.get(key) for key in (*FLAGS, "decided_by", "confidence")}

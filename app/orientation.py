"""The orientation the pipeline uses for a card: the step's, the crowd's, or a curator's.

Three sources, each flag taken from the strongest that speaks to it:

1. a curator's override (``review.models.OrientationOverride``), flag by flag;
2. the crowd's approved confirm aggregate (a grid: the flags the card was shown with, each
   flag the crowd's vote says was tapped flipped; ``annotation.confirm``), all three flags;
   then the crowd's approved judge aggregate: ``upside_down`` and ``inverted`` always;
   ``swapped`` when the judge task asked it (``label["swapped"]``), else the step's own value
   when the step was confident on that flag, else undecided (a person answers it);
3. the orientation stage's result, when it decided the card automatically (``outcome ==
   "auto"``); a step that asked, or that only proposes an orientation for people to confirm
   (``outcome == "confirm"``), contributes nothing on its own.

``decided_by`` names the strongest source used (``curator`` > ``crowd`` > ``auto``); any
flag still null means the card is undecided: it waits for people, and it is not rectified,
graded, accepted or released (the flow rule of DESIGN.md).
"""

from __future__ import annotations

from typing import Any

FLAGS: tuple[str, ...] = ("upside_down", "inverted", "swapped")


def _as_flag(value: Any) -> bool | None:
    return None if value is None else bool(value)


def resolve_orientation(
    step: Any | None, judge: Any | None, override: Any | None, *, confirm: Any | None = None
) -> dict[str, Any]:
    """The ``orientation`` field of ``keystone cards --json`` plus ``source`` (in words) and
    ``waiting_for`` (why it is undecided, or null).

    ``step``: the latest ``orientation`` StageResult (or None); ``judge``: the latest APPROVED
    judge Aggregate (or None); ``override``: the card's OrientationOverride row (or None);
    ``confirm``: the latest APPROVED confirm Aggregate (or None).
    """
    flags: dict[str, bool | None] = dict.fromkeys(FLAGS)
    sources: list[str] = []
    decided_by: str | None = None
    confidence: float | None = None
    step_ok = step is not None and step.status == "done"
    step_flags = (step.metrics.get("flags") or {}) if step_ok else {}
    if step_ok and step.outcome == "auto":
        flags = {flag: _as_flag((step_flags.get(flag) or {}).get("value")) for flag in FLAGS}
        decided_by, confidence = "auto", step.metrics.get("confidence")
        sources.append(f"orientation step ({step.param_hash})")
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
    if override is not None:
        touched = False
        for flag in FLAGS:
            value = getattr(override, flag)
            if value is not None:
                flags[flag] = bool(value)
                touched = True
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
            unsure = [flag for flag in FLAGS if not (step_flags.get(flag) or {}).get("decided")]
            waiting_for = f"people (the orientation step is not sure of {', '.join(unsure or FLAGS)})"
        else:
            waiting_for = f"people ({', '.join(undecided)} undecided)"
    return {
        **flags,
        "decided_by": decided_by if not undecided else None,
        "confidence": None if confidence is None else round(float(confidence), 4),
        "source": "; ".join(sources) or None,
        "waiting_for": waiting_for,
    }


def is_decided(orientation: dict[str, Any]) -> bool:
    return all(orientation.get(flag) is not None for flag in FLAGS)


def public_orientation(orientation: dict[str, Any]) -> dict[str, Any]:
    """The five keys DESIGN.md fixes for ``keystone cards --json``."""
    return {key: orientation.get(key) for key in (*FLAGS, "decided_by", "confidence")}

"""What the card review page says in a curator's words; the numbers stay behind its "details".

The grader, the orientation step and the crowd's aggregation write their findings for
engineers: measurement names (``dy_p95_px``), cue names with weights (``ground_plane: ...
(+0.28 x 3.5)``), posteriors against thresholds (``inverted: posterior 0.722 < 0.95``). These
functions turn each into a sentence; they take the stored strings and numbers (no database, no
Flask) and pass through anything they do not recognise, so a new cue or reason is shown as
written rather than lost.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

__all__ = [
    "MEASUREMENT_WORDS",
    "certainty_words",
    "crowd_reason_words",
    "cue_words",
    "flag_words",
    "grade_reason_words",
    "measurement_words",
    "orientation_evidence_words",
]

# The grade's measurements (pipeline.grading.measurements.GradeMeasurements) as a curator names them.
MEASUREMENT_WORDS: dict[str, str] = {
    "good_match_fraction": "points matched between the two photos",
    "dy_p95_px": "vertical misalignment after rectification",
    "shear_deg": "shear of the rectified views",
    "aspect_change": "change of shape in rectification",
    "rotation_deg": "rotation in rectification",
    "kept_fraction": "share of the photo kept by rectification",
    "swapped": "photos exchanged",
    "row_misalignment_px": "vertical parallax seen in the pair",
    "coverage": "share of the photo with depth",
    "lr_consistency": "agreement of the left and right depth maps",
    "confident_fraction": "share of the depth that is confident",
    "disparity_range_px": "depth range",
    "disparity_range_rel": "depth range (share of the width)",
    "texture_gradient": "texture",
    "textured_fraction": "share of the photo with texture",
    "photometric_error": "difference between the photos once matched",
    "photometric_error_rel": "difference between the photos once matched (relative)",
    "depth_order": "depth order (bottom nearer than top)",
    "streak_fraction": "streaks in the depth",
    "sky_near_fraction": "sky read as near",
    "reflection_symmetry": "mirror symmetry (a reflection)",
    "border_line": "card edge or mount left in the crop",
    "border_strokes": "writing left in the crop",
}

# The orientation step's cues (pipeline.stages.orientation) as a curator names them.
CUE_WORDS: dict[str, str] = {
    "text_upright": "printed text",
    "ground_plane": "the ground",
    "detail_bottom": "where the detail is",
    "learned_upright": "the trained network",
    "learned_upright_inverse": "the trained network, reading it as a negative",
    "sky_top": "the sky",
    "arched_top": "arched photo tops",
    "face_upright": "faces",
    "warm_tone": "the tone",
    "smooth_bright": "plain areas",
    "learned_tone": "the trained network's reading of the tone",
    "occlusion_side": "edges hidden from one eye",
    "occlusion_fill": "edges hidden from one eye",
}

FLAG_WORDS: dict[str, str] = {
    "upside_down": "upside down",
    "inverted": "a negative",
    "swapped": "photos in the wrong eye order",
    "is_stereo": "a stereo pair",
}

_WEIGHT = re.compile(r"\s*\(([+-]?\d+(?:\.\d+)?) x (\d+(?:\.\d+)?)\)\s*$")
_CUE = re.compile(r"^([a-z][a-z0-9_]*): (.*)$", re.S)


def percent(p: float) -> str:
    """A probability as a curator reads it: whole percent, never 100 % or 0 % unless exact."""
    value = 100.0 * p
    if 99.0 < value < 100.0:
        return "99%"
    if 0.0 < value < 1.0:
        return "1%"
    return f"{value:.0f}%"


def measurement_words(name: str) -> str:
    return MEASUREMENT_WORDS.get(name, name.replace("_", " "))


def flag_words(flag: str, p_yes: float, who: str = "the orientation step") -> str:
    """``p_yes`` (probability that ``flag`` holds) as "upside down: the orientation step is 99% sure it is not"."""
    name = FLAG_WORDS.get(flag, flag.replace("_", " "))
    if p_yes >= 0.5:
        return f"{name}: {who} is {percent(p_yes)} sure it is"
    return f"{name}: {who} is {percent(1.0 - p_yes)} sure it is not"


def cue_words(evidence: str) -> str:
    """One piece of the orientation step's evidence in words, its cue named as a curator would
    and its weight left out: "ground_plane: disparity grows towards the top: ... (-0.22 x 2.95)"
    becomes "the ground tilts the wrong way: it comes nearer towards the top"."""
    text = evidence.strip()
    weight_match = _WEIGHT.search(text)
    weight = float(weight_match.group(1)) if weight_match else 0.0
    text = _WEIGHT.sub("", text)
    match = _CUE.match(text)
    if match is None:
        return text
    cue, said = match.groups()
    if cue == "ground_plane" and weight != 0.0:
        # The cue's own words talk of disparity; a curator sees where the ground comes nearer.
        if weight > 0:
            return "the ground comes nearer towards the bottom, as in an upright picture"
        return "the ground tilts the wrong way: it comes nearer towards the top"
    said = said.replace("disparity", "depth")
    return f"{CUE_WORDS.get(cue, cue.replace('_', ' '))}: {said}"


def orientation_evidence_words(flags: Mapping[str, Any], cues: int = 2) -> list[str]:
    """The orientation step's per-flag result (``{"upside_down": {"p": .., "evidence": [..]}}``)
    as one sentence per flag with its strongest ``cues`` pieces of evidence."""
    lines = []
    for flag, info in flags.items():
        if not isinstance(info, Mapping) or not isinstance(info.get("p"), (int, float)):
            continue
        line = flag_words(flag, float(info["p"]))
        evidence = [cue_words(str(e)) for e in (info.get("evidence") or [])[:cues]]
        if evidence:
            line += " (" + "; ".join(evidence) + ")"
        lines.append(line)
    return lines


def certainty_words(uncertainty: float | None) -> str:
    """The grader's uncertainty (0 = far from every threshold, 1 = on one) in words."""
    if uncertainty is None:
        return ""
    if uncertainty >= 0.75:
        return "a close call: a measurement is right at its limit"
    if uncertainty >= 0.4:
        return "fairly sure"
    return "sure"


_POSTERIOR = re.compile(r"^(\w+): posterior (\d*\.?\d+) < (\d*\.?\d+)$")
_SPREAD = re.compile(r"^(left|right) box: spread (\d*\.?\d+) px > (\d*\.?\d+) px$")
_IOU = re.compile(r"^(left|right) box: mean IoU (\d*\.?\d+) < (\d*\.?\d+)$")
_KEPT = re.compile(r"^(left|right) box: (\d+) boxes kept < (\d+)$")


def crowd_reason_words(reasons: str, label: Mapping[str, Any] | None = None) -> list[str]:
    """Why the crowd's answer waits for a curator (:func:`annotation.aggregation.unconfident_reasons`,
    joined with "; "), one sentence per reason: "inverted: posterior 0.722 < 0.95" becomes
    "a negative? the crowd says no; the model is 72% sure (it decides alone from 95%)"."""
    label = label or {}
    out = []
    for part in (p.strip() for p in (reasons or "").split(";")):
        if not part:
            continue
        if m := _POSTERIOR.match(part):
            question, p, needed = m.group(1), float(m.group(2)), float(m.group(3))
            said = label.get(question)
            answer = "yes" if said is True else "no" if said is False else None
            name = FLAG_WORDS.get(question, question.replace("_", " "))
            said_words = f"the crowd says {answer}; " if answer else ""
            out.append(f"{name}? {said_words}the model is {percent(p)} sure (it decides alone from {percent(needed)})")
        elif m := _SPREAD.match(part):
            out.append(
                f"{m.group(1)} box: the annotators' boxes differ by up to {float(m.group(2)):.0f} px "
                f"(it decides alone within {float(m.group(3)):.0f} px)"
            )
        elif m := _IOU.match(part):
            out.append(
                f"{m.group(1)} box: the annotators' boxes overlap {percent(float(m.group(2)))} on average "
                f"(it decides alone from {percent(float(m.group(3)))})"
            )
        elif m := _KEPT.match(part):
            out.append(f"{m.group(1)} box: only {m.group(2)} answers agree (it needs {m.group(3)})")
        else:
            out.append(part)
    return out


GRADE_WORDS = {"few": "few artifacts", "some": "some artifacts", "failure": "failure"}
# Only identifiers (with an underscore): "swapped" and "coverage" are also plain English in the
# grader's sentences ("eyes swapped" read "eyes photos exchanged").
_MEASUREMENT_NAME = re.compile(
    r"\b(" + "|".join(sorted((re.escape(n) for n in MEASUREMENT_WORDS if "_" in n), key=len, reverse=True)) + r")\b"
)


def grade_reason_words(reason: str) -> str:
    """One of the grader's reasons with its measurement names in words and its grade spelled
    out: "few: ...; nearest: dy_p95_px 1.9 px is 0.14 px from its some threshold (> 2 px)"
    becomes "few artifacts: ...; nearest: vertical misalignment after rectification 1.9 px ..."."""
    grade, sep, rest = reason.partition(": ")
    if sep and grade in GRADE_WORDS:
        reason = f"{GRADE_WORDS[grade]}: {rest}"
    return _MEASUREMENT_NAME.sub(lambda m: MEASUREMENT_WORDS[m.group(1)], reason)

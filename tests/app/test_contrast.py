"""Text and badge colours of the stylesheet meet WCAG 2.1 AA contrast (4.5:1 for normal text),
computed from the colours ``app/static/keystone.css`` declares (issue 33.10: the culled and
skipped badges were 3.0:1, the left and right eye names 2.9-3.6:1)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

CSS = Path(__file__).resolve().parents[2] / "app" / "static" / "keystone.css"
AA_NORMAL_TEXT = 4.5


def relative_luminance(colour: str) -> float:
    """WCAG 2.1 relative luminance of a ``#rrggbb`` colour."""
    channels = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
    linear = [c / 12.92 if c <= 0.03928 else ((c + 0.055) / 1.055) ** 2.4 for c in channels]
    return 0.2126 * linear[0] + 0.7152 * linear[1] + 0.0722 * linear[2]


def contrast(first: str, second: str) -> float:
    high, low = sorted((relative_luminance(first), relative_luminance(second)), reverse=True)
    return (high + 0.05) / (low + 0.05)


def variables() -> dict[str, str]:
    root = CSS.read_text().split(":root {", 1)[1].split("}", 1)[0]
    return dict(re.findall(r"--([\w-]+):\s*(#[0-9a-fA-F]{6})", root))


def test_contrast_is_computed_as_wcag_defines_it() -> None:
    assert contrast("#000000", "#ffffff") == pytest.approx(21.0)
    assert contrast("#777777", "#ffffff") == pytest.approx(4.48, abs=0.01)


@pytest.mark.parametrize(
    ("what", "text", "background"),
    [
        ("body text", "ink", "paper"),
        ("muted text", "muted", "paper"),
        ("links", "accent", "paper"),
        ("the left eye named in text", "left-text", "paper"),
        ("the right eye named in text", "right-text", "paper"),
        ("a pass / done badge", "#ffffff", "pass"),
        ("a review badge", "#ffffff", "review"),
        ("a culled / skipped badge", "#ffffff", "culled"),
        ("a failed badge", "#ffffff", "failed"),
        ("an ingested badge", "#ffffff", "ingested"),
        ("a pending badge", "muted", "#ffffff"),
    ],
)
def test_text_meets_wcag_aa(what: str, text: str, background: str) -> None:
    found = variables()
    fg, bg = (value if value.startswith("#") else found[value] for value in (text, background))
    ratio = contrast(fg, bg)
    assert ratio >= AA_NORMAL_TEXT, f"{what}: {ratio:.2f}:1 < {AA_NORMAL_TEXT}:1 ({fg} on {bg})"

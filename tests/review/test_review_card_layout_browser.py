"""The curator's card page in headless Chromium at 1366 x 800 and 390 x 844 (issue 33.1): the
picture first (the scan and its anaglyph near the top, the decision buttons right by them), the
numbers behind a closed "details" disclosure, the page in words a curator uses, no sideways
scroll, the keys discoverable, and the buttons still working without JavaScript.

Measured on `keystone demo` (card 7) before this layout: the photo's top at y = 836 and the
anaglyph's at 2011 on the laptop, 1834 and 2784 on the phone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import select

# The orientation step's record as pipeline/stages/orientation.py writes it (p = P(flag holds)).
STEP_FLAGS = {
    "upside_down": {
        "p": 0.72,
        "evidence": [
            "ground_plane: disparity grows towards the top: turned, or upright and swapped (-0.22 x 2.95)",
            "arched_top: no arched photo tops found (+0.00 x 2.33)",
        ],
    },
    "inverted": {"p": 0.01, "evidence": ["warm_tone: warm (sepia/buff) tones: a positive (+0.98 x 2.23)"]},
}


@pytest.fixture
def card_to_review(app, make_card, add_stage_result, card_image, decide_orientation, data_dir: Path) -> int:  # type: ignore[no-untyped-def]
    """A graded card (auto grade few) with rectified previews (so an anaglyph) and the orientation step's evidence."""
    from review.tasks import sync_reviews

    card_id = make_card(card_image(), state="pass")
    rng = np.random.default_rng(3)
    left = rng.integers(0, 256, (280, 300, 3), dtype=np.uint8)
    folder = data_dir / "derived" / "rect-layout"
    folder.mkdir(parents=True)
    for name, image in (("left_preview", left), ("right_preview", np.roll(left, -5, axis=1))):
        Image.fromarray(image).save(folder / f"{name}.png")
    add_stage_result(
        card_id,
        "rectify",
        outcome=None,
        artifacts={
            "left_preview": "derived/rect-layout/left_preview.png",
            "right_preview": "derived/rect-layout/right_preview.png",
        },
    )
    add_stage_result(card_id, "orientation", outcome=None, metrics={"flags": STEP_FLAGS})
    add_stage_result(
        card_id,
        "grade",
        outcome="few",
        metrics={
            "dy_p95_px": 1.9,
            "uncertainty": 0.95,
            "reasons": ["few: every measurement within thresholds (1 of 1 measured); nearest: dy_p95_px 1.9 px"],
        },
    )
    decide_orientation([card_id])
    with app.app_context():
        sync_reviews()
    return card_id


def decision(app, card_id: int) -> str:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    with app.app_context():
        return db.session.scalar(select(CardReview.decision).where(CardReview.card_id == card_id))


def top_and_bottom(page, selector: str) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    box = page.locator(selector).bounding_box()
    assert box is not None, f"{selector} is not on the page"
    return box["y"], box["y"] + box["height"]


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_the_picture_comes_first_and_the_numbers_wait_behind_details(  # type: ignore[no-untyped-def]
    app, server, screen_page, make_person, card_to_review, look, wait_until, screen
) -> None:
    page = screen_page(screen, make_person("curator"))
    page.goto(f"{server}/review/cards/{card_to_review}")
    page.wait_for_selector(f"#review-card[data-card='{card_to_review}'][data-ready]")
    wait_until(page, "[...document.querySelectorAll('.review-main img')].every(i => i.complete && i.naturalWidth > 0)")
    look(page, f"review-card-layout-{screen}")
    fold = 800 if screen == "desktop" else 844

    photo_top, photo_bottom = top_and_bottom(page, ".overlay-frame img")
    anaglyph_top, anaglyph_bottom = top_and_bottom(page, "#anaglyph")
    accept_top, accept_bottom = top_and_bottom(page, "#decision-form button[value=accept]")
    assert photo_top < 400
    assert anaglyph_top < (400 if screen == "desktop" else fold)
    if screen == "desktop":
        # the whole decision on the first screen, beside the pictures
        assert anaglyph_bottom <= fold and accept_bottom <= fold
    else:
        # right under the pictures: only the grader's one-line verdict between them
        assert anaglyph_bottom < accept_top < anaglyph_bottom + 200

    # The numbers are one click away, not in the way; what is shown is said in words.
    assert page.get_attribute("#review-details", "open") is None and not page.is_visible("#review-details .two-columns")
    shown = page.inner_text(".review-main") + page.inner_text("#orientation-words")
    for jargon in ("posterior", "ground_plane", "dy_p95_px", "P 0.", "x 2.95"):
        assert jargon not in shown, f"{jargon!r} shown outside the details"
    assert "the ground tilts the wrong way" in shown and "72% sure it is" in shown
    assert "vertical misalignment after rectification 1.9 px" in shown
    assert "a close call" in page.inner_text("#review-state")
    page.click("#review-details > summary")
    assert page.is_visible("#review-details .two-columns")

    if screen == "desktop":
        # The keys are written beside the buttons, and the full list is a click away.
        assert "accept" in page.inner_text("#key-line")
        page.click("#show-keys")
        assert page.is_visible("#review-help")
        page.keyboard.press("Escape")
        assert not page.is_visible("#review-help")
        page.keyboard.press("a")
        page.wait_for_url(f"{server}/review/", timeout=10_000)  # the queue's only card: back to the queue
        assert decision(app, card_to_review) == "accepted"


def test_the_card_page_decides_without_javascript(app, server, screen_page, make_person, card_to_review) -> None:  # type: ignore[no-untyped-def]
    page = screen_page("phone", make_person("curator"), java_script_enabled=False)
    page.goto(f"{server}/review/cards/{card_to_review}")
    assert page.is_visible("#anaglyph") and page.is_visible("#decision-form button[value=accept]")
    page.click("#review-details > summary")  # a plain <details>: opens without script
    assert page.is_visible("#review-details .two-columns")
    page.click("#decision-form button[value=reject]")
    page.wait_for_load_state()
    assert decision(app, card_to_review) == "rejected"

"""The crop page in headless Chromium (issue 33.3): the help's words about the buttons are true at
1366 x 800 and 390 x 844 (Delete box and Undo edit above the card, Submit under it), the task
starts from boxes grown out to the photos' edges, and the selected box moves with the arrow
keys, resizes with Shift + arrows, ten times as far with Alt, one Undo edit step per run."""

from __future__ import annotations

import numpy as np
import pytest
from sqlalchemy import select

from annotation.models import Answer
from core.db import db


@pytest.fixture
def crop_task(app, make_card, card_image, add_stage_result):  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch
    from annotation.providers import InviteProvider

    # two 296 x 200 photos with a 12 px gutter on a buff mount 40 px wide: 684 x 280 px
    card_id = make_card(np.pad(card_image(), ((40, 40), (40, 40), (0, 0)), constant_values=200), state="pass")
    add_stage_result(card_id, "filter")
    with app.app_context():
        create_batch([card_id], "crop", 1, 0.0)
        return card_id, InviteProvider.invite("cropper").token


def stored(app) -> list[dict]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return [a.payload for a in db.session.scalars(select(Answer).order_by(Answer.id))]


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_the_help_says_where_the_buttons_are(app, server, screen_page, crop_task, wait_until, screen) -> None:  # type: ignore[no-untyped-def]
    _, token = crop_task
    page = screen_page(screen)
    page.goto(f"{server}/crowd/invite/{token}?kind=crop")
    page.wait_for_selector("#status:has-text('Card 1')", timeout=15_000)
    help_text = page.inner_text("#help")
    assert "Delete box and Undo edit are above the card, Submit and Undo last answer under it" in help_text
    assert "Shift + an arrow resizes it" in page.text_content("#help")
    assert page.evaluate("document.getElementById('help').scrollTop") == 0
    page.keyboard.press("Escape")
    wait_until(page, "document.getElementById('card-image').naturalWidth > 0")
    card = page.locator("#card-image").bounding_box()
    for button in ("#delete-box", "#undo-edit"):
        box = page.locator(button).bounding_box()
        assert box["y"] + box["height"] <= card["y"], button
    assert page.locator("#submit-answer").bounding_box()["y"] >= card["y"] + card["height"]


def test_arrow_keys_move_and_resize_the_selected_box(app, server, screen_page, crop_task, wait_until) -> None:  # type: ignore[no-untyped-def]
    from annotation.proposals import proposed_boxes, proposed_crop_boxes
    from core.models import Card

    card_id, token = crop_task
    with app.app_context():
        card = db.session.get(Card, card_id)
        safe, proposal, width = proposed_boxes(card), proposed_crop_boxes(card), card.width
    assert proposal.grown and proposal.source == safe.source
    # never smaller than the safe boxes, never past the middle of the gutter (x = 342); how far
    # they grow on mounted cards is tests/pipeline/test_photo_edges.py's
    assert proposal.left[0] <= safe.left[0] and proposal.left[3] >= safe.left[3] and proposal.left[2] <= 342
    assert proposal.right[0] >= 342 and proposal.right[2] >= safe.right[2]

    page = screen_page("desktop")
    page.goto(f"{server}/crowd/invite/{token}?kind=crop")
    page.wait_for_selector("#status:has-text('Card 1')", timeout=15_000)
    page.keyboard.press("Escape")
    wait_until(page, "document.getElementById('card-image').naturalWidth > 0")
    step = width / page.locator("#card-image").bounding_box()["width"]  # original px per screen px

    page.keyboard.press("l")
    for key in ("ArrowRight", "ArrowRight", "ArrowRight", "ArrowDown", "ArrowDown", "Alt+ArrowLeft", "Shift+ArrowUp"):
        page.keyboard.press(key)
    assert page.inner_text("#coords").startswith("left: ")
    page.keyboard.press("r")
    for key in ("ArrowUp", "ArrowUp", "Shift+ArrowLeft"):
        page.keyboard.press(key)
    page.keyboard.press("z")  # one Undo edit step takes back the right box's whole run
    page.keyboard.press("Enter")
    for _ in range(100):
        if stored(app):
            break
        page.wait_for_timeout(100)
    answer = stored(app)[0]
    x0, y0, x1, y1 = proposal.left
    moved_x, moved_y = (3 - 10) * step, 2 * step  # three right, two down, ten left (Alt)
    expected = [x0 + moved_x, y0 + moved_y, x1 + moved_x, y1 + moved_y - step]  # Shift+Up: one shorter
    expected[0], expected[2] = max(expected[0], 0.0), expected[2] - min(x0 + moved_x, 0.0)  # kept on the card
    assert answer["left"] == pytest.approx(expected, abs=0.2)
    assert answer["right"] == pytest.approx(proposal.right, abs=0.1)

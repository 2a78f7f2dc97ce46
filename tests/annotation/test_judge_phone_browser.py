"""The judge page on a 390 x 844 phone and a 1366 x 800 laptop (issue 33.2): Submit is on the first
screen of every card (a bar along the bottom edge), the first-time help opens at its top with its
example pictures loaded, and Undo brings the card back with the answer that was given, so a quick
Enter sends that answer again rather than a blank one.

Measured on `keystone demo` before: the help opened scrolled to its end (scrollTop 688 px on the
phone), Submit's top at y = 799 of 844 with the card's pictures loaded, and Undo left every box
unticked.
"""

from __future__ import annotations

import pytest
from sqlalchemy import select

from annotation.models import Answer
from core.db import db


@pytest.fixture
def judge_batch(app, make_card, card_image):  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    base = card_image()
    ids = []
    for index in range(3):
        image = base.copy()
        image[0, 0, 0] = index  # distinct content, distinct cards
        ids.append(make_card(image, state="review"))
    with app.app_context():
        create_batch(ids, "judge", 1, 0.0)
    return ids


def stored(app) -> list[dict]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return [a.payload for a in db.session.scalars(select(Answer).order_by(Answer.id))]


def wait_for_count(page, app, count: int) -> None:  # type: ignore[no-untyped-def]
    for _ in range(150):
        if len(stored(app)) == count:
            return
        page.wait_for_timeout(100)
    raise AssertionError(f"expected {count} stored answers, have {stored(app)}")


PICTURES_LOADED = (
    "['card-image', 'eye-order-as-is', 'eye-order-swapped']"
    ".every(id => { const i = document.getElementById(id); return i.complete && i.naturalWidth > 0; })"
)


@pytest.mark.parametrize("screen", ["phone", "desktop"])
def test_submit_stays_on_screen_help_opens_at_its_top_and_undo_brings_the_answer_back(  # type: ignore[no-untyped-def]
    app, server, screen_page, judge_batch, wait_until, look, screen
) -> None:
    from annotation.providers import InviteProvider

    with app.app_context():
        link = f"{server}/crowd/invite/{InviteProvider.invite(f'judge-{screen}').token}"
    page = screen_page(screen)
    height = page.viewport_size["height"]
    page.goto(link)
    page.wait_for_selector("#status:has-text('Card 1 of 3')", timeout=15_000)

    # The first-time help: at its top, its example pictures there without scrolling to them.
    assert page.is_visible("#help")
    wait_until(page, "[...document.querySelectorAll('#help img')].every(i => i.complete && i.naturalWidth === 480)")
    assert page.evaluate("document.getElementById('help').scrollTop") == 0
    title = page.locator("#help-title").bounding_box()
    assert title is not None and 0 <= title["y"] < height / 3
    (page.tap if screen == "phone" else page.click)("#help button[type=submit]")
    assert not page.is_visible("#help")

    # Submit on the first screen, once the card and its eye-order pictures have taken their room.
    for card in (1, 2):
        page.wait_for_selector(f"#status:has-text('Card {card} of 3')", timeout=15_000)
        wait_until(page, PICTURES_LOADED)
        page.evaluate("window.scrollTo(0, 0)")
        submit = page.locator("#submit-answer").bounding_box()
        assert submit is not None and submit["y"] >= 0 and submit["y"] + submit["height"] <= height, (card, submit)
        look(page, f"judge-{screen}-card-{card}")
        if card == 1:
            page.keyboard.press("f")  # upside-down
            page.keyboard.press("Enter")
            wait_for_count(page, app, 1)

    # Undo: the card comes back with its answer ticked; Enter sends that answer again.
    page.keyboard.press("u")
    page.wait_for_selector("#status:has-text('judge this card again')", timeout=10_000)
    wait_for_count(page, app, 0)
    assert page.is_checked("input[name=upside_down]") and not page.is_checked("input[name=is_stereo]")
    page.keyboard.press("Enter")
    wait_for_count(page, app, 1)
    assert stored(app) == [{"is_stereo": True, "upside_down": True, "inverted": False, "swapped": False}]

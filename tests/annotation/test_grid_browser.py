"""The confirm grid in a real browser (headless Debian Chromium, a real WSGI server): a laptop
walk with the keyboard and a phone walk with taps, each marking only the wrong cards and
sending the grid once; the layout has 4-6 columns on a 1366 px desk and 2-3 on a 390 px phone.
With ``KEYSTONE_SHOTS=DIR`` the pages are saved as screenshots to look at."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from annotation.models import Answer, BatchItem
from core.db import db

FLAGS = ("upside_down", "inverted", "swapped")
NONE = dict.fromkeys(FLAGS, False)
KEYS = {"upside_down": "u", "inverted": "n", "swapped": "d"}


@pytest.fixture
def grid_batch(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    """A confirm batch of ten cards and three gold cards; grids of 13 (all of it) with 3 gold."""
    from annotation.batches import confirm_gold, create_batch

    base = card_image()
    confirm, known = [], []
    for i in range(13):
        image = base.copy()
        image[0, 0, 0] = i
        card_id = make_card(image, state="pass")
        add_stage_result(card_id, "filter", outcome="pass")
        outcome = "confirm" if i < 10 else "auto"
        metrics = {
            "decision": outcome,
            "confidence": 0.7 if outcome == "confirm" else 0.999,
            "proposed": NONE,
            "flags": {f: {"p": 0.0, "decided": outcome == "auto", "value": False} for f in FLAGS},
        }
        add_stage_result(card_id, "orientation", outcome=outcome, metrics=metrics, param_hash="orient0123456789")
        (confirm if i < 10 else known).append(card_id)
    app.config.update(KEYSTONE_CROWD_GRID_SIZE=13, KEYSTONE_CROWD_GRID_GOLD=3)
    with app.app_context():
        gold, shown = confirm_gold(exclude=confirm)
        create_batch(confirm, "confirm", 2, 0.0, gold=gold, shown=shown)
    return confirm


def _link(app, server: str, name: str) -> str:  # type: ignore[no-untyped-def]
    from annotation.providers import InviteProvider

    with app.app_context():
        return f"{server}/crowd/invite/{InviteProvider.invite(name).token}"


def _grid(page, wait_until) -> list[dict]:  # type: ignore[no-untyped-def]
    """The grid on screen once every picture has loaded: per card, its token's item."""
    wait_until(page, "document.querySelectorAll('#grid .grid-card').length > 0")
    wait_until(page, "[...document.querySelectorAll('#grid img')].every(i => i.complete && i.naturalWidth > 0)", 60)
    return page.evaluate("[...document.querySelectorAll('#grid img')].map(i => i.src)")


def _items_on_screen(app, sources: list[str]) -> list[BatchItem]:  # type: ignore[no-untyped-def]
    from annotation.models import Reservation

    tokens = [src.split("/task/")[1].split("/")[0] for src in sources]
    with app.app_context():
        by_token = {
            r.token: (r.item.card_id, r.item.is_gold, r.item.gold_answer)
            for r in db.session.scalars(select(Reservation).where(Reservation.token.in_(tokens)))
        }
    return [by_token[t] for t in tokens]


def _stored(app) -> dict[int, dict]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return {
            item.card_id: answer.payload
            for answer, item in db.session.execute(select(Answer, BatchItem).join(BatchItem, Answer.item_id == BatchItem.id))
        }


def _columns(page) -> int:  # type: ignore[no-untyped-def]
    return page.evaluate(
        "(() => { const c = [...document.querySelectorAll('#grid .grid-card')];"
        " return c.filter(e => e.offsetTop === c[0].offsetTop).length; })()"
    )


def _wanted(items, wrong: dict[int, str]) -> list[dict]:  # type: ignore[no-untyped-def]
    """The taps a careful worker makes: gold as its answer says, ``wrong`` cards on one flag."""
    taps = []
    for card_id, is_gold, gold_answer in items:
        taps.append(dict(gold_answer) if is_gold else {**NONE, **({wrong[card_id]: True} if card_id in wrong else {})})
    return taps


def test_a_laptop_walk_with_the_keyboard_marks_only_the_wrong_cards(  # type: ignore[no-untyped-def]
    app, server, screen_page, grid_batch, look, wait_until
):
    page = screen_page("desktop")
    page.goto(_link(app, server, "kim") + "?kind=confirm")
    page.keyboard.press("Escape")  # the first-time instructions
    items = _items_on_screen(app, _grid(page, wait_until))
    assert 4 <= _columns(page) <= 6
    wrong = {grid_batch[1]: "upside_down", grid_batch[4]: "inverted"}
    wanted = _wanted(items, wrong)
    columns = _columns(page)
    presses = 0
    here = 0
    for index, taps in enumerate(wanted):
        for flag in FLAGS:
            if taps[flag]:
                # Along the cards with the right arrow: the walk does not depend on where the
                # layout breaks its rows (under load the test once measured other columns than
                # the page moved by); up and down are checked on their own below.
                for _ in range(index - here):
                    page.keyboard.press("ArrowRight")
                    presses += 1
                here = index
                page.keyboard.press(KEYS[flag])
                presses += 1
    look(page, "confirm-grid-desktop-marked")
    # A row up and back down lands on the same card, a row's width of cards away in between.
    label = "document.activeElement.getAttribute('aria-label')"
    before = page.evaluate(label)
    page.keyboard.press("ArrowUp")
    middle = page.evaluate(label)
    page.keyboard.press("ArrowDown")
    assert here >= columns and page.evaluate(label) == before
    assert int(before.split()[1]) - int(middle.split()[1]) == _columns(page)
    page.keyboard.press("Enter")
    presses += 1
    wait_until(page, "!document.getElementById('finished').hidden")
    stored = _stored(app)
    assert [stored[card_id] for card_id, _, _ in items] == wanted
    # Two wrong cards and three gold among 13 (38 % to mark, not the 10 % of a real grid):
    # still about one key press a card, Enter included.
    assert presses <= 1.5 * len(items)
    look(page, "confirm-grid-desktop-finished")


def test_a_phone_walk_taps_the_wrong_cards_and_a_double_submit_stores_once(  # type: ignore[no-untyped-def]
    app, server, screen_page, grid_batch, look, wait_until
):
    page = screen_page("phone")
    page.goto(_link(app, server, "pat") + "?kind=confirm")
    # The first-time help opens at its top with its example pictures (it opened scrolled to the
    # Start button at its end, the pictures still blank, as the judge page's did).
    assert page.is_visible("#help")
    wait_until(page, "[...document.querySelectorAll('#help img')].every(i => i.complete && i.naturalWidth > 0)")
    assert page.evaluate("document.getElementById('help').scrollTop") == 0
    page.tap("#help button[type=submit]")
    items = _items_on_screen(app, _grid(page, wait_until))
    assert 2 <= _columns(page) <= 3
    look(page, "confirm-grid-phone")
    wanted = _wanted(items, {grid_batch[7]: "swapped"})
    for index, taps in enumerate(wanted):
        for flag in FLAGS:
            if taps[flag]:
                button = page.locator(f"#grid .grid-card >> nth={index}").locator(f"[data-flag={flag}]")
                box = button.bounding_box()
                assert box["height"] >= 44 and box["width"] >= 44  # a finger's width
                button.tap()
    look(page, "confirm-grid-phone-marked")
    page.evaluate("document.getElementById('submit-answer').click(); document.getElementById('submit-answer').click()")
    wait_until(page, "!document.getElementById('finished').hidden")
    stored = _stored(app)
    assert len(stored) == len(items) and [stored[card_id] for card_id, _, _ in items] == wanted

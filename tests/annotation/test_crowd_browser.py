"""The crowd pages in a real browser: headless Chromium driven by Playwright against a real WSGI server.

Annotators judge with the keyboard, submit, undo; a second annotator never gets the first
one's assignment; MTurk's preview disables submit and an accepted HIT posts back to
externalSubmit; Prolific participants are redirected with the completion code.
"""

from __future__ import annotations

import re
from urllib.parse import parse_qs, urlsplit

import pytest
from sqlalchemy import select

from annotation.models import Answer, Reservation
from core.db import db


@pytest.fixture(autouse=True)
def prolific_completion_code(app) -> None:  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "C0DE42"


@pytest.fixture
def batch(app, make_card, card_image):  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    base = card_image()
    ids = []
    for index in range(4):
        image = base.copy()
        image[0, 0, 0] = index  # distinct content, distinct cards
        ids.append(make_card(image, state="review"))
    with app.app_context():
        return create_batch(ids, "judge", 2, 0.0).id


def invite_link(app, server: str, name: str) -> str:  # type: ignore[no-untyped-def]
    from annotation.providers import InviteProvider

    with app.app_context():
        return f"{server}/crowd/invite/{InviteProvider.invite(name).token}"


def answers(app) -> list[tuple[int, int, dict]]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return [(a.worker_id, a.item_id, a.payload) for a in db.session.scalars(select(Answer).order_by(Answer.id))]


def wait_for_answers(page, app, count: int) -> None:  # type: ignore[no-untyped-def]
    for _ in range(100):
        if len(answers(app)) == count:
            return
        page.wait_for_timeout(100)
    raise AssertionError(f"expected {count} stored answers, have {answers(app)}")


def test_annotator_judges_with_the_keyboard_submits_and_undoes(app, server, browser, batch):
    page = browser.new_page()
    page.goto(invite_link(app, server, "alice"))
    page.wait_for_selector("#status:has-text('Card 1')", timeout=15_000)
    page.keyboard.press("Escape")  # the first-time instructions
    page.keyboard.press("f")  # upside-down
    page.keyboard.press("Enter")
    wait_for_answers(page, app, 1)
    page.wait_for_selector("#status:has-text('Card 2')", timeout=10_000)  # the next card is shown
    page.keyboard.press("n")  # not a stereo pair
    page.keyboard.press("i")  # inverted
    page.keyboard.press("Enter")
    wait_for_answers(page, app, 2)
    stored = [payload for _, _, payload in answers(app)]
    assert stored == [
        {"is_stereo": True, "upside_down": True, "inverted": False, "swapped": False},
        {"is_stereo": False, "upside_down": False, "inverted": True, "swapped": False},
    ]
    page.wait_for_selector("#status:has-text('Card 3')", timeout=10_000)
    page.keyboard.press("u")  # undo the last answer
    wait_for_answers(page, app, 1)
    page.wait_for_selector("#status:has-text('judge this card again')", timeout=10_000)
    page.close()


def test_a_second_annotator_never_gets_the_same_assignment(app, server, browser, batch):
    first, second = browser.new_page(), browser.new_page()
    first.goto(invite_link(app, server, "alice"))
    second.goto(invite_link(app, server, "bob"))
    for page in (first, second):
        page.wait_for_selector("#status:has-text('Card')", timeout=15_000)
    with app.app_context():
        held = [
            (r.worker_id, r.item_id) for r in db.session.scalars(select(Reservation).where(Reservation.answered_at.is_(None)))
        ]
    by_worker: dict[int, set[int]] = {}
    for worker, item in held:
        by_worker.setdefault(worker, set()).add(item)
    assert len(by_worker) == 2 and len(held) == sum(len(items) for items in by_worker.values())
    first.keyboard.press("Escape")
    first.keyboard.press("Enter")
    wait_for_answers(first, app, 1)
    worker, item, _ = answers(app)[0]
    with app.app_context():
        again = db.session.scalars(
            select(Reservation).where(
                Reservation.worker_id == worker, Reservation.item_id == item, Reservation.answered_at.is_(None)
            )
        ).all()
    assert again == []  # alice is never given the card she answered


def test_mturk_preview_disables_submit_and_an_accepted_hit_posts_back(app, server, browser, batch):
    page = browser.new_page()
    preview = f"{server}/crowd/mturk?assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE&hitId=H1"
    page.goto(preview)
    assert page.is_disabled("#submit-answer")
    page.keyboard.press("Enter")
    page.wait_for_timeout(300)
    assert answers(app) == []

    posted: list[str] = []

    def external_submit(route, request):  # type: ignore[no-untyped-def]
        posted.append(request.post_data or "")
        route.fulfill(status=200, body="ok")

    page.route("https://workersandbox.mturk.com/**", external_submit)
    page.goto(f"{server}/crowd/mturk?assignmentId=A77&hitId=H1&workerId=W9&turkSubmitTo=https%3A%2F%2Fworkersandbox.mturk.com")
    page.wait_for_selector("#status:has-text('Card')", timeout=15_000)
    page.keyboard.press("Escape")
    page.keyboard.press("Enter")
    for _ in range(100):
        if posted:
            break
        page.wait_for_timeout(100)
    assert len(answers(app)) == 1
    assert posted and parse_qs(posted[0]).get("assignmentId") == ["A77"]


def test_prolific_participants_are_redirected_with_the_completion_code(app, server, browser, batch):
    page = browser.new_page()
    landed: list[str] = []
    page.route(
        "https://app.prolific.com/**",
        lambda route, request: (landed.append(request.url), route.fulfill(status=200, body="thanks")),
    )
    page.goto(f"{server}/crowd/prolific?PROLIFIC_PID=P123&STUDY_ID=S1&SESSION_ID=X1")
    page.wait_for_selector("#status:has-text('Card')", timeout=15_000)
    page.keyboard.press("Escape")
    page.click("#finish-link")
    for _ in range(100):
        if landed:
            break
        page.wait_for_timeout(100)
    assert landed and parse_qs(urlsplit(landed[0]).query).get("cc") == ["C0DE42"]
    assert re.match(r"https://app\.prolific\.com/submissions/complete", landed[0])


def test_annotator_draws_both_boxes_with_the_mouse_in_original_pixels(app, server, browser, make_card, card_image, wait_until):
    from annotation.batches import create_batch

    card_id = make_card(card_image(), state="pass")
    with app.app_context():
        create_batch([card_id], "crop", 1, 0.0)
    page = browser.new_page(viewport={"width": 1300, "height": 900})
    page.goto(invite_link(app, server, "carol") + "?kind=crop")
    page.wait_for_selector("#status:has-text('Card 1')", timeout=15_000)
    page.keyboard.press("Escape")
    wait_until(page, "document.getElementById('card-image').naturalWidth > 0")
    frame = page.locator("#card-image").bounding_box()

    def drag(fx0: float, fy0: float, fx1: float, fy1: float) -> None:
        page.mouse.move(frame["x"] + fx0 * frame["width"], frame["y"] + fy0 * frame["height"])
        page.mouse.down()
        page.mouse.move(frame["x"] + fx1 * frame["width"], frame["y"] + fy1 * frame["height"], steps=8)
        page.mouse.up()

    # The task starts from proposed boxes; remove both to draw from scratch (L/R pick, Delete removes).
    for key in ("l", "Delete", "r", "Delete"):
        page.keyboard.press(key)
    assert page.is_hidden(".box-left") and page.is_hidden(".box-right")
    drag(0.05, 0.10, 0.45, 0.90)  # on the left photo: the left box, whichever box was selected
    drag(0.55, 0.10, 0.95, 0.90)  # on the right photo: the right box
    page.keyboard.press("Enter")
    wait_for_answers(page, app, 1)
    payload = answers(app)[0][2]
    width, height = 604, 200  # the card's pixels, whatever size the page shows it at
    expected = {
        "left": [0.05 * width, 0.10 * height, 0.45 * width, 0.90 * height],
        "right": [0.55 * width, 0.10 * height, 0.95 * width, 0.90 * height],
    }
    for half in ("left", "right"):
        assert payload[half] == pytest.approx(expected[half], abs=3.0)

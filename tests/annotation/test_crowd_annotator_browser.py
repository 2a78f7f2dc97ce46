"""The annotator's main path in headless Chromium, on a laptop (1366 x 800, mouse) and a phone
(390 x 844, touch): one invite link, a judge card with its two eye-order pictures side by side (each
at least 170 px wide on the phone), then a crop card that starts from the proposed photo boxes,
adjusted and submitted (stored in original pixels), "n of N" progress, and a finished screen
without controls; no page scrolls sideways. Screenshots go to /tmp/shots-annotate/.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select

from annotation.models import Answer, BatchItem
from core.db import db

SHOTS = Path("/tmp/shots-annotate")
NO_SIDEWAYS_SCROLL = "document.documentElement.scrollWidth <= window.innerWidth"


def stored(app) -> list[tuple[int, dict]]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return [
            (card, payload)
            for card, payload in db.session.execute(
                select(BatchItem.card_id, Answer.payload).join(Answer, Answer.item_id == BatchItem.id).order_by(Answer.id)
            )
        ]


def wait_for_answers(page, app, count: int) -> None:  # type: ignore[no-untyped-def]
    for _ in range(150):
        if len(stored(app)) >= count:
            return
        page.wait_for_timeout(100)
    raise AssertionError(f"expected {count} stored answers, have {stored(app)}")


def touch_drag(page, cdp, start: tuple[float, float], end: tuple[float, float], steps: int = 6) -> None:  # type: ignore[no-untyped-def]
    """One finger, through Chromium's touch input (pointerType 'touch' on the page)."""
    cdp.send("Input.dispatchTouchEvent", {"type": "touchStart", "touchPoints": [{"x": start[0], "y": start[1]}]})
    for i in range(1, steps + 1):
        x = start[0] + (end[0] - start[0]) * i / steps
        y = start[1] + (end[1] - start[1]) * i / steps
        cdp.send("Input.dispatchTouchEvent", {"type": "touchMove", "touchPoints": [{"x": x, "y": y}]})
    cdp.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": []})


def pinch(cdp, centre: tuple[float, float], from_gap: float, to_gap: float, steps: int = 6) -> None:  # type: ignore[no-untyped-def]
    def points(gap: float) -> list[dict]:
        return [{"x": centre[0] - gap / 2, "y": centre[1], "id": 1}, {"x": centre[0] + gap / 2, "y": centre[1], "id": 2}]

    cdp.send("Input.dispatchTouchEvent", {"type": "touchStart", "touchPoints": points(from_gap)})
    for i in range(1, steps + 1):
        cdp.send(
            "Input.dispatchTouchEvent", {"type": "touchMove", "touchPoints": points(from_gap + (to_gap - from_gap) * i / steps)}
        )
    cdp.send("Input.dispatchTouchEvent", {"type": "touchEnd", "touchPoints": []})


@pytest.fixture
def two_batches(app, make_card, card_image, add_stage_result):  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    base = card_image()
    judge_card = make_card(base, state="review")
    crop_image = base.copy()
    crop_image[0, 0, 0] = 7
    crop_card = make_card(crop_image, state="pass")
    add_stage_result(crop_card, "filter")
    with app.app_context():
        create_batch([judge_card], "judge", 1, 0.0)
        create_batch([crop_card], "crop", 1, 0.0)
    return judge_card, crop_card


@pytest.mark.parametrize("device", ["laptop", "phone"])
def test_annotator_walks_the_invite_link_through_judge_and_crop(app, server, browser, two_batches, wait_until, device):
    from annotation.proposals import proposed_boxes
    from annotation.providers import InviteProvider
    from core.models import Card

    judge_card, crop_card = two_batches
    phone = device == "phone"
    SHOTS.mkdir(parents=True, exist_ok=True)
    with app.app_context():
        link = f"{server}/crowd/invite/{InviteProvider.invite(f'walker-{device}').token}"
        card = db.session.get(Card, crop_card)
        proposal = proposed_boxes(card)
        width, height = card.width, card.height
    options = (
        {"viewport": {"width": 390, "height": 844}, "has_touch": True, "is_mobile": True, "device_scale_factor": 2}
        if phone
        else {"viewport": {"width": 1366, "height": 800}}
    )
    context = browser.new_context(**options)
    page = context.new_page()
    click = page.tap if phone else page.click

    # Judge: the instructions open first (pictures, reachable by tap later); then one card of one.
    page.goto(link)
    page.wait_for_selector("#status:has-text('Card 1 of 1')", timeout=15_000)
    assert page.is_visible("#help") and page.is_visible("#help img[alt='An upside-down stereo card']")
    wait_until(page, "[...document.querySelectorAll('#help img')].every(img => img.naturalWidth === 480)")
    page.screenshot(path=str(SHOTS / f"{device}-1-judge-help.png"))
    click("#help button[type=submit]")
    assert page.inner_text("#position") == "Card 1 of 1" and page.evaluate(NO_SIDEWAYS_SCROLL)
    # The eye-order pictures (depth in colour), side by side, each about half a phone's width;
    # tapping one picks it, the same answer as the S box.
    wait_until(page, "['eye-order-as-is', 'eye-order-swapped'].every(id => document.getElementById(id).naturalWidth === 360)")
    as_scanned, exchanged = (page.locator(f"#eye-order-{order}").bounding_box() for order in ("as-is", "swapped"))
    assert page.is_visible("#eye-order-as-is") and page.is_visible("#eye-order-swapped")
    assert as_scanned["width"] >= (170 if phone else 200) and exchanged["width"] == pytest.approx(as_scanned["width"], abs=1)
    if not phone:  # beside the card, on the first screen: no scroll for every card
        assert as_scanned["y"] + as_scanned["height"] <= 800
    assert as_scanned["y"] == pytest.approx(exchanged["y"], abs=1) and as_scanned["x"] + as_scanned["width"] < exchanged["x"]
    assert "warm = near, cool = far; pick the one where near things are warm" in page.inner_text(".eye-order-key")
    click(".eye-order-pick[data-swapped=true]")
    assert page.is_checked("input[name=swapped]")
    assert page.get_attribute(".eye-order-pick[data-swapped=true]", "aria-pressed") == "true"
    click(".eye-order-pick[data-swapped=false]")
    assert not page.is_checked("input[name=swapped]")
    assert page.get_attribute(".eye-order-pick[data-swapped=false]", "aria-pressed") == "true"
    click("#show-help")  # help by tap or click, not only by key
    assert page.is_visible("#help")
    click("#help button[type=submit]")
    click("label:has(input[name=upside_down])")
    page.screenshot(path=str(SHOTS / f"{device}-2-judge.png"), full_page=True)
    click("#submit-answer")
    wait_for_answers(page, app, 1)
    assert stored(app)[0] == (judge_card, {"is_stereo": True, "upside_down": True, "inverted": False, "swapped": False})

    # The same link moves on to the crop batch, starting from the proposed photo boxes.
    page.wait_for_url("**kind=crop", timeout=15_000)
    page.wait_for_selector("#status:has-text('Card 1 of 1')", timeout=15_000)
    click("#help button[type=submit]")
    wait_until(page, "document.getElementById('card-image').naturalWidth > 0")
    frame = page.locator("#card-image").bounding_box()
    scale = width / frame["width"]  # original px per CSS px
    left_box = page.locator(".box-left").bounding_box()
    assert left_box["x"] == pytest.approx(frame["x"] + proposal.left[0] / scale, abs=2)
    handle = page.locator(".box-left .handle.br").bounding_box()
    assert handle["width"] >= 44 and handle["height"] >= 44  # a finger's target
    if phone:
        assert frame["width"] >= 360  # the screen's width less room for the edge handles (14 px a side)
    assert page.evaluate(NO_SIDEWAYS_SCROLL)

    # Delete the box, try to submit: the error sits beside Submit, on screen; Undo edit brings it back.
    click(".box-left")
    click("#delete-box")
    click("#submit-answer")
    error = page.locator("#error")
    error.wait_for(state="visible")
    submit = page.locator("#submit-answer").bounding_box()
    box = error.bounding_box()
    assert box["y"] + box["height"] <= options["viewport"]["height"] and abs(box["y"] - submit["y"]) < 80
    page.screenshot(path=str(SHOTS / f"{device}-3-crop-error.png"))
    click("#undo-edit")
    assert page.is_visible(".box-left") and page.is_hidden("#error")  # the box is back, the message gone

    # Pull the left box's bottom-right corner up and left: one finger on a phone, the mouse on a laptop.
    cx, cy = handle["x"] + handle["width"] / 2 - 4, handle["y"] + handle["height"] / 2 - 4
    ex, ey = cx - 20, cy - 20
    if phone:
        cdp = context.new_cdp_session(page)
        touch_drag(page, cdp, (cx, cy), (ex, ey))
    else:
        page.mouse.move(cx, cy)
        page.mouse.down()
        page.mouse.move(ex, ey, steps=6)
        page.mouse.up()
    assert page.get_attribute(".half-button[data-half=left]", "aria-pressed") == "true"
    page.screenshot(path=str(SHOTS / f"{device}-4-crop.png"))
    if phone:
        before = page.locator("#crop-stage").bounding_box()["width"]
        viewport = page.locator("#crop-viewport").bounding_box()
        pinch(cdp, (viewport["x"] + viewport["width"] / 2, viewport["y"] + viewport["height"] / 2), 60, 160)
        assert page.locator("#crop-stage").bounding_box()["width"] > 1.8 * before  # two fingers zoom
        page.screenshot(path=str(SHOTS / f"{device}-5-crop-zoomed.png"))
    click("#submit-answer")
    wait_for_answers(page, app, 2)
    card_id, payload = stored(app)[1]
    assert card_id == crop_card
    # The corner went where the pointer let go, in the card's original pixels (not screen pixels).
    expected_left = [proposal.left[0], proposal.left[1], (ex - frame["x"]) * scale, (ey - frame["y"]) * scale]
    assert payload["left"] == pytest.approx(expected_left, abs=1.5 * scale)
    assert payload["left"][2] < proposal.left[2] - 10 * scale
    assert payload["right"] == pytest.approx(proposal.right, abs=0.2)
    assert all(0 <= v <= width for v in payload["left"][::2]) and all(0 <= v <= height for v in payload["left"][1::2])

    # Finished: a screen that says so, without the controls, and how to come back.
    page.wait_for_selector("#finished:has-text('All done')", timeout=15_000)
    assert page.is_hidden("#task-controls") and page.is_hidden("#submit-answer")
    assert page.evaluate(NO_SIDEWAYS_SCROLL)
    page.screenshot(path=str(SHOTS / f"{device}-6-finished.png"), full_page=True)
    page.goto(link)  # coming back later: the same link, the finished screen, nothing to press
    assert (
        page.is_visible("#finished") and page.is_hidden("#submit-answer") and "keeps your place" in page.inner_text("#finished")
    )
    context.close()


# On a phone only (the narrow layout is the one that can break; the suite's time is short).
@pytest.mark.parametrize("device", ["phone"])
def test_a_curator_makes_a_batch_and_an_invite_link_on_the_web(app, server, browser, make_person, make_card, card_image, device):
    phone = device == "phone"
    card_id = make_card(card_image(), state="review")
    person = make_person("curator", username=f"cur-{device}")
    options = (
        {"viewport": {"width": 390, "height": 844}, "has_touch": True, "is_mobile": True}
        if phone
        else {"viewport": {"width": 1366, "height": 800}}
    )
    context = browser.new_context(**options)
    page = context.new_page()
    page.goto(f"{server}/auth/login")
    page.fill("input[name=username]", person.username)
    page.fill("input[name=password]", person.password)
    page.click("input[type=submit], button[type=submit]")
    page.wait_for_load_state()
    page.goto(f"{server}/crowd/batches")
    assert "(judge: 1, crop: 1, confirm: 0 cards)" in page.inner_text("#new-batch")
    page.click("#new-batch button[type=submit]")  # the review queue is ticked by default
    page.wait_for_selector(".flash:has-text('Batch 1 created: 1 judge cards, 3 answers each')")
    assert "0 of 3" in page.inner_text("#batch-1")
    page.fill("#new-invite input[name=name]", "Ada")
    page.click("#new-invite button[type=submit]")
    assert "Invite link for Ada made" in page.locator(".flash").inner_text()
    link = page.locator("#invites code.invite-url").inner_text()
    assert "/crowd/invite/" in link
    assert page.evaluate(NO_SIDEWAYS_SCROLL)
    page.screenshot(path=str(SHOTS / f"{device}-7-batches.png"), full_page=True)
    page.goto(link)  # the invite works at once: Ada gets the card
    page.wait_for_selector("#status:has-text('Card 1 of 1')", timeout=15_000)
    with app.app_context():
        assert db.session.scalar(select(BatchItem.card_id)) == card_id
    context.close()

"""The crowd batches page in headless Chromium (issue 33.6): a curator makes an invite link and
copies it with the Copy button; without script the button stays hidden and the link is plain,
selectable text; a bad card id comes back beside its field; a batch is paused; at 1366 x 800 and
390 x 844 nothing scrolls sideways. ``KEYSTONE_SHOTS=DIR`` keeps screenshots to look at."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from annotation.models import Worker
from core.db import db


@pytest.fixture
def review_cards(make_card, card_image):  # type: ignore[no-untyped-def]
    base = card_image()
    ids = []
    for index in range(3):
        image = base.copy()
        image[0, 0, 0] = index
        ids.append(make_card(image, state="review"))
    return ids


def invite_url(app, name: str) -> str:  # type: ignore[no-untyped-def]
    with app.app_context():
        token = db.session.scalar(select(Worker.token).where(Worker.external_id == name))
    return f"/crowd/invite/{token}"


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_a_curator_makes_an_invite_link_and_copies_it(app, server, screen_page, make_person, look, wait_until, screen):
    curator = make_person("curator")
    page = screen_page(screen, curator)
    page.context.grant_permissions(["clipboard-read", "clipboard-write"], origin=server)
    page.goto(f"{server}/crowd/batches")
    page.fill("#new-invite input[name=name]", "Ada Lovelace")
    page.fill("#new-invite input[name=days]", "7")
    page.click("#new-invite button[type=submit]")
    page.wait_for_load_state()
    link = server + invite_url(app, "Ada Lovelace")
    code = page.locator("code.invite-url")
    assert code.inner_text() == link
    assert "works until" in page.locator(".invite-head").inner_text()
    button = page.locator("button.copy-link")
    assert button.is_visible()
    button.click()
    wait_until(page, "document.querySelector('.copy-status').textContent !== ''")
    assert page.locator(".copy-status").inner_text() == "Copied"
    assert page.evaluate("navigator.clipboard.readText()") == link
    page.locator(".invite-qr-box summary").click()
    box = page.locator("svg.invite-qr").bounding_box()
    assert box is not None and 100 <= box["width"] <= 200 and box["width"] == box["height"]
    look(page, f"crowd-batches-invite-{screen}")


def test_without_script_the_link_is_selectable_text_and_no_dead_button(app, server, browser, make_person):
    curator = make_person("curator")
    page = browser.new_context(java_script_enabled=False, viewport={"width": 1366, "height": 800}).new_page()
    page.goto(f"{server}/auth/login")
    page.fill("input[name=username]", curator.username)
    page.fill("input[name=password]", curator.password)
    page.click("input[type=submit], button[type=submit]")
    page.goto(f"{server}/crowd/batches")
    page.fill("#new-invite input[name=name]", "Grace")
    page.click("#new-invite button[type=submit]")
    page.wait_for_load_state()
    assert not page.locator("button.copy-link").is_visible()
    code = page.locator("code.invite-url")
    code.click(click_count=3)  # a triple click selects the link, as a person copying it would
    assert page.evaluate("window.getSelection().toString().trim()") == server + invite_url(app, "Grace")


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_a_bad_card_id_comes_back_beside_its_field_and_a_batch_pauses(
    app, server, screen_page, make_person, look, review_cards, screen
):
    page = screen_page(screen, make_person("curator"))
    page.goto(f"{server}/crowd/batches")
    assert page.locator("#new-batch input[name=from_review]").is_checked()
    page.locator("#new-batch input[name=from_review]").uncheck()
    page.fill("#new-batch-cards", f"{review_cards[0]}, 99999")
    page.fill("#new-batch input[name=name]", "first try")
    page.click("#new-batch button[type=submit]")
    page.wait_for_load_state()
    assert page.locator("#error-cards").inner_text() == "No card with id 99999"
    assert page.input_value("#new-batch-cards") == f"{review_cards[0]}, 99999"
    assert page.input_value("#new-batch input[name=name]") == "first try"
    look(page, f"crowd-batches-error-{screen}")
    page.fill("#new-batch-cards", f"{review_cards[0]}")
    page.click("#new-batch button[type=submit]")
    page.wait_for_load_state()
    heading = page.locator("section.batch h2").first
    assert heading.inner_text().startswith("Batch 1: first try · judge")
    page.locator("section.batch button[value=paused]").click()
    page.wait_for_load_state()
    assert "paused" in page.locator("section.batch h2").first.inner_text()
    look(page, f"crowd-batches-paused-{screen}")

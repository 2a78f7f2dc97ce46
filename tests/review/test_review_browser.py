"""The review flow in a real browser: headless Chromium driven by Playwright against a real WSGI server.

A curator logs in, opens the queue and its first card, decides with the keyboard (the next card
loads after each decision), and a tab left open on a card a colleague changed gets the
conflict message instead of overwriting the colleague's decision. An annotator cannot reach review.
"""

from __future__ import annotations

from typing import Any

import pytest
from sqlalchemy import select


@pytest.fixture
def queue_cards(app, make_card, add_stage_result, card_image, decide_orientation) -> list[int]:  # type: ignore[no-untyped-def]
    """Three graded cards in queue order (most uncertain first): auto grades some, few, failure."""
    from review.tasks import sync_reviews

    ids = []
    for index, (grade, uncertainty) in enumerate([("some", 0.8), ("few", 0.5), ("failure", 0.2)]):
        card_id = make_card(card_image()[:, index:], state="pass")
        add_stage_result(
            card_id,
            "grade",
            outcome=grade,
            reason=f"because {grade}",
            metrics={"uncertainty": uncertainty, "reasons": [f"because {grade}"]},
        )
        ids.append(card_id)
    decide_orientation(ids)
    with app.app_context():
        sync_reviews()
    return ids


def decision_of(app, card_id: int) -> tuple[str, str | None]:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    with app.app_context():
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
        return review.decision, review.grade


def log_in(browser, server: str, person) -> Any:  # type: ignore[no-untyped-def]
    context = browser.new_context()  # its own cookies: a second person, a second session
    page = context.new_page()
    page.goto(f"{server}/auth/login")
    page.fill("input[name=username]", person.username)
    page.fill("input[name=password]", person.password)
    page.click("input[type=submit], button[type=submit]")
    page.wait_for_load_state()
    return page


def test_a_curator_reviews_with_the_keyboard(app, server, browser, make_person, queue_cards) -> None:  # type: ignore[no-untyped-def]
    first, second, third = queue_cards
    page = log_in(browser, server, make_person("curator", username="carol"))
    page.goto(f"{server}/review/")
    page.click("a.card-link >> nth=0")
    page.wait_for_selector(f"#review-card[data-card='{first}'][data-ready]")

    page.keyboard.press("j")  # next and previous card in the queue
    page.wait_for_selector(f"#review-card[data-card='{second}'][data-ready]", timeout=10_000)
    page.keyboard.press("k")
    page.wait_for_selector(f"#review-card[data-card='{first}'][data-ready]", timeout=10_000)

    page.keyboard.press("?")
    assert page.is_visible("#review-help")
    page.keyboard.press("a")  # ignored while the help is open
    page.keyboard.press("Escape")
    assert not page.is_visible("#review-help") and decision_of(app, first) == ("pending", None)

    page.keyboard.press("a")
    page.wait_for_selector(f"#review-card[data-card='{second}'][data-ready]", timeout=10_000)
    assert decision_of(app, first) == ("accepted", "some")

    page.keyboard.press("3")
    page.wait_for_selector(f"#review-card[data-card='{third}'][data-ready]", timeout=10_000)
    assert decision_of(app, second) == ("changed", "failure")
    # Decided cards have left the pending queue: the third is now its first card.
    assert page.get_attribute("#review-card", "data-prev-url") == ""


def test_a_stale_tab_gets_the_conflict_message(app, server, browser, make_person, queue_cards) -> None:  # type: ignore[no-untyped-def]
    third = queue_cards[2]
    alice = log_in(browser, server, make_person("curator", username="alice"))
    bob = log_in(browser, server, make_person("curator", username="bob"))
    for page in (alice, bob):
        page.goto(f"{server}/review/cards/{third}")
        page.wait_for_selector(f"#review-card[data-card='{third}'][data-ready]")
    alice.keyboard.press("r")
    alice.wait_for_url(f"{server}/review/", timeout=10_000)  # the last card in the queue: back to the queue
    assert decision_of(app, third) == ("rejected", None)

    bob.keyboard.press("2")
    bob.wait_for_selector("#review-alert.review-alert-conflict", timeout=10_000)
    message = bob.text_content("#review-alert")
    assert f"Card {third} was changed by alice at " in message and "Nothing was saved" in message
    assert bob.url == f"{server}/review/cards/{third}"  # stays put so bob can read and reload
    assert decision_of(app, third) == ("rejected", None)


@pytest.fixture
def disputed_in_queue(app, make_card, add_stage_result, card_image, decide_orientation, add_crop_dispute) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    """A graded card in the queue whose crop boxes the crowd disputes; (card, aggregate) ids."""
    from review.tasks import sync_reviews

    card_id = make_card(card_image(), state="pass")  # 604 x 200 px
    add_stage_result(card_id, "grade", outcome="some", metrics={"uncertainty": 0.7, "reasons": ["fringes"]})
    decide_orientation([card_id])
    with app.app_context():
        sync_reviews()
    _, aggregate_id = add_crop_dispute(card_id)
    return card_id, aggregate_id


def test_a_curator_settles_a_dispute_from_the_queue_and_comes_back_to_the_card(  # type: ignore[no-untyped-def]
    app, server, browser, make_person, disputed_in_queue, wait_until
) -> None:
    card_id, aggregate_id = disputed_in_queue
    page = log_in(browser, server, make_person("curator", username="carol"))
    page.goto(f"{server}/review/cards/{card_id}")
    page.wait_for_selector(f"#review-card[data-card='{card_id}'][data-ready]")
    assert page.is_disabled("button[value=accept]") and page.is_disabled("button[value='change:few']")
    page.keyboard.press("a")  # the key says why instead of posting
    wait_until(page, "!document.getElementById('review-alert').hidden")
    assert "Not accepted now: the crowd disagrees on its crop" in page.text_content("#review-alert")
    assert page.locator("#review-alert a", has_text=f"Resolve dispute {aggregate_id}").count() == 1
    assert decision_of(app, card_id) == ("pending", None)

    page.goto(f"{server}/review/")
    marker = page.locator(f"tr[data-card='{card_id}'] .held-dispute")
    assert marker.is_visible() and marker.text_content().startswith("Disputed: the crowd disagrees on its crop")
    marker.locator("a.dispute-link").click()
    page.wait_for_selector("#resolve-form")
    assert page.url.startswith(f"{server}/review/disputes/{aggregate_id}?next=")
    page.click(".use-answer >> nth=0")  # the first annotator's boxes, 310..600 on the right
    page.click("#resolve-form button[type=submit]")

    page.wait_for_selector(f"#review-card[data-card='{card_id}'][data-ready]", timeout=10_000)
    assert page.url == f"{server}/review/cards/{card_id}"
    assert "your crop answer is now the card's truth" in page.text_content(".flash-success")
    assert page.is_enabled("button[value=accept]") and page.locator("#card-blockers").count() == 0
    page.keyboard.press("a")
    page.wait_for_url(f"{server}/review/", timeout=10_000)  # the only card in the queue: back to it
    assert decision_of(app, card_id) == ("accepted", "some")


def test_an_annotator_cannot_reach_review(server, browser, make_person) -> None:  # type: ignore[no-untyped-def]
    page = log_in(browser, server, make_person("annotator", username="anna"))
    response = page.goto(f"{server}/review/")
    assert response is not None and response.status == 403
    assert "This page is for curators and admins" in page.text_content("main")
    assert page.locator("nav.mainnav a", has_text="Review").count() == 0

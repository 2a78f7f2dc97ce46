"""The cards list's search box and bulk form in headless Chromium (issue 33.7): a curator finds a
card by a word of its title, a hostile search shows an empty list (no error page), ticks every
card on the page and sends them to the crowd for crop boxes; at 1366 x 800 and 390 x 844
nothing scrolls sideways. ``KEYSTONE_SHOTS=DIR`` keeps screenshots to look at."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from annotation.models import Batch
from core.db import db


@pytest.fixture
def titled_cards(make_card, card_image):  # type: ignore[no-untyped-def]
    base = card_image()
    ids = []
    for index, title in enumerate(["Niagara Falls from below", "Yosemite valley", "The 100% Niagara view"]):
        image = base.copy()
        image[0, 0, 0] = index
        ids.append(make_card(image, state="pass", metadata={"title": title}, accession=f"1996.{index}"))
    return ids


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_a_curator_searches_ticks_all_and_sends_them_to_the_crowd(
    app, server, screen_page, make_person, look, titled_cards, screen
):
    page = screen_page(screen, make_person("curator"))
    page.goto(f"{server}/cards")
    page.fill("#card-search", "niagara")
    page.press("#card-search", "Enter")
    page.wait_for_load_state()
    assert page.locator(".card-tile").count() == 2
    assert "2 cards matching niagara" in page.locator("#cards-count").inner_text()
    look(page, f"cards-search-{screen}")
    page.fill("#card-search", "100%")
    page.press("#card-search", "Enter")
    page.wait_for_load_state()
    assert page.locator(".tile-title").all_inner_texts() == ["The 100% Niagara view"]
    page.fill("#card-search", "'; drop table cards; --")
    page.press("#card-search", "Enter")
    page.wait_for_load_state()
    assert page.locator(".empty").inner_text() == "No cards match these filters."
    page.fill("#card-search", "niagara")
    page.press("#card-search", "Enter")
    page.wait_for_load_state()
    page.click("#select-page")
    assert page.locator("input[form=bulk-cards]:checked").count() == 2
    page.select_option("#bulk-cards select[name=kind]", "crop")
    page.fill("#bulk-cards input[name=name]", "falls boxes")
    page.click("#bulk-send")
    page.wait_for_load_state()
    assert "/crowd/batches" in page.url
    assert "2 crop cards" in page.locator(".flash-success").inner_text()
    with app.app_context():
        batch = db.session.scalar(select(Batch))
        assert batch is not None and batch.kind == "crop"
        assert sorted(item.card_id for item in batch.items) == [titled_cards[0], titled_cards[2]]
    assert page.locator("section.batch h2").first.inner_text().startswith(f"Batch {batch.id}: falls boxes · crop")

"""Searching the cards list (issue 33.7): by id, accession, file name, title or any catalogue
text, with the filters, on SQLite and PostgreSQL; hostile searches are plain text; the bulk
form is offered to curators only."""

from __future__ import annotations

import re

import pytest

from core.db import db
from core.models import MetadataRecord


def tile_ids(html: str) -> list[int]:
    return [int(n) for n in re.findall(r'<a href="/cards/(\d+)">', html)]


@pytest.fixture
def catalogue(make_card, card_image, app):  # type: ignore[no-untyped-def]
    base = card_image()

    def card(index: int, **fields):  # type: ignore[no-untyped-def]
        image = base.copy()
        image[0, 0, 0] = index
        return make_card(image, **fields)

    ids = {
        "niagara": card(
            1,
            accession="1996.0009.17827",
            metadata={"title": "Niagara Falls from below", "Subjects": "Falls\nRivers"},
            source_name="keystone_17827.tif",
        ),
        "percent": card(2, accession="2001.50%", metadata={"title": "100% pure: a 50_50 mix"}, collection="second"),
        "quote": card(3, metadata={"title": 'The "Maid of the Mist" at Montréal'}, state="review"),
        "plain": card(4, metadata={"title": "Yosemite valley"}, source_name="yosemite.jpg"),
    }
    with app.app_context():
        db.session.add(
            MetadataRecord(
                collection_id=1,
                record_key="accession:x",
                accession="1888.1",
                fields={"Photographer": "Benjamin West Kilburn", "Place": "Littleton, N.H."},
                source_file="museum.csv",
                row_number=2,
                card_id=ids["plain"],
            )
        )
        db.session.commit()
    return ids


def search(client, q: str, **args) -> tuple[int, list[int], str]:  # type: ignore[no-untyped-def]
    response = client.get("/cards", query_string={"q": q, **args})
    html = response.get_data(as_text=True)
    return response.status_code, sorted(tile_ids(html)), html


@pytest.mark.both_databases
@pytest.mark.parametrize(
    ("q", "expected"),
    [
        ("niagara", ["niagara"]),  # title, any case
        ("NIAGARA falls", ["niagara"]),
        ("17827", ["niagara"]),  # accession and file name
        ("keystone_17827", ["niagara"]),
        ("rivers", ["niagara"]),  # any catalogue field
        ("kilburn", ["plain"]),  # a metadata CSV row matched to the card
        ("1888.1", ["plain"]),
        ("%", ["percent"]),  # % and _ are literal, not wildcards
        ("50_50", ["percent"]),
        ("_", ["niagara", "percent"]),  # only the names and titles that hold one
        ('"Maid of the Mist"', ["quote"]),
        ("montréal", ["quote"]),
        ("'; drop table cards; --", []),
        ("\\", []),
        ("nothing like this", []),
    ],
)
def test_search_finds_cards_by_their_catalogue_text(app, client, login, catalogue, q, expected):
    login("curator")
    status, found, html = search(client, q)
    assert status == 200
    assert found == sorted(catalogue[name] for name in expected), q
    if not expected:
        assert "No cards match these filters." in html


@pytest.mark.both_databases
def test_search_by_id_and_with_the_filters(app, client, login, catalogue):
    login("curator")
    plain = catalogue["plain"]
    assert search(client, str(plain))[1] == [plain]
    assert search(client, f"#{plain}")[1] == [plain]
    assert search(client, "mist", state="review")[1] == [catalogue["quote"]]
    assert search(client, "mist", state="pass")[1] == []
    second = search(client, "", collection="2")
    assert second[1] == [catalogue["percent"]]
    assert search(client, "falls", collection="2")[1] == []
    assert search(client, "99999999999999999999999")[0] == 200  # past any id: text only


@pytest.mark.both_databases
def test_hostile_searches_are_answered_not_crashed(app, client, login, catalogue):
    login("curator")
    status, found, html = search(client, "a" * 5000)
    assert status == 200 and found == []
    assert "only its first 200 were searched for" in html
    assert 'value="' + "a" * 200 + '"' in html
    assert search(client, "a\x00b")[0] == 400  # the app refuses NUL in any request, with a page saying so
    for q in ("\x07bell", "%" * 5000, "_" * 300, "<script>alert(1)</script>", "' OR 1=1 --", "\u202e\ufeff"):
        status, _, html = search(client, q)
        assert status == 200 and "<script>alert(1)</script>" not in html


def test_search_keeps_its_words_across_pages_and_tabs(app, client, login, catalogue):
    app.config["CATALOG_PAGE_SIZE"] = 1
    login("curator")
    status, found, html = search(client, "_")
    assert status == 200 and len(found) == 1
    assert 'href="/cards?q=_&amp;page=2"' in html
    assert 'href="/cards?q=_&amp;state=pass"' in html
    assert search(client, "_", page="2")[1] != found


def test_the_bulk_form_is_offered_to_curators_only(app, client, login, catalogue):
    login("exporter")
    html = client.get("/cards").get_data(as_text=True)
    assert 'id="bulk-cards"' not in html and 'form="bulk-cards"' not in html


def test_the_bulk_form_posts_ticked_cards_to_the_crowd(app, client, login, catalogue):
    login("curator")
    html = client.get("/cards").get_data(as_text=True)
    assert '<form method="post" action="/crowd/batches/new" id="bulk-cards"' in html
    boxes = re.findall(r'<input type="checkbox" name="cards" value="(\d+)" form="bulk-cards">', html)
    assert sorted(int(b) for b in boxes) == sorted(catalogue.values())
    assert 'src="/static/cards.js"' in html

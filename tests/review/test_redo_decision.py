"""Redo after an undo on the curator's card page (issue 33.7): the undo bar offers the decision
back once; Redo makes it again (grade, note, crowd task); a stale or repeated redo is refused."""

from __future__ import annotations

import re

import pytest
from sqlalchemy import func, select


@pytest.fixture
def graded_card(app, make_card, add_stage_result, card_image, decide_orientation) -> int:  # type: ignore[no-untyped-def]
    from review.tasks import sync_reviews

    card_id = make_card(card_image(), state="pass")
    add_stage_result(card_id, "grade", outcome="few", reason="few", metrics={"uncertainty": 0.4, "reasons": ["few"]})
    with app.app_context():
        sync_reviews()
    decide_orientation([card_id])
    return card_id


def _review(app, card_id: int) -> tuple[str, str | None, str, int]:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    with app.app_context():
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
        return review.decision, review.grade, review.note, review.version


def _bar(html: str, verb: str) -> tuple[str, str]:
    bar = re.search(rf'<form method="post" action="([^"]+/{verb})">.*?name="version" value="(\d+)"', html, re.DOTALL)
    assert bar, f"no {verb} button on the page"
    return bar.group(1), bar.group(2)


@pytest.mark.parametrize(
    ("choice", "decision", "grade"), [("change:failure", "changed", "failure"), ("reject", "rejected", None)]
)
def test_undo_then_redo_makes_the_decision_again(app, client, login, csrf_token, graded_card, choice, decision, grade):  # type: ignore[no-untyped-def]
    card = graded_card
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    version = str(_review(app, card)[3])
    done = client.post(
        f"/review/cards/{card}/decide",
        data={"choice": choice, "version": version, "note": "scratched plate", "csrf_token": token},
        follow_redirects=True,
    )
    undo_action, after_decision = _bar(done.get_data(as_text=True), "undo")
    undone = client.post(undo_action, data={"version": after_decision, "csrf_token": token}, follow_redirects=True)
    html = undone.get_data(as_text=True)
    assert _review(app, card)[:2] == ("pending", None)
    assert 'id="redo-button">Redo</button>' in html and "Undone: card" in html
    redo_action, after_undo = _bar(html, "redo")
    assert "redo-button" not in client.get(f"/review/cards/{card}").get_data(as_text=True)  # offered once
    redone = client.post(redo_action, data={"version": after_undo, "csrf_token": token}, follow_redirects=True)
    assert redone.status_code == 200
    assert _review(app, card)[:3] == (decision, grade, "scratched plate")
    assert 'id="undo-button">Undo</button>' in redone.get_data(as_text=True)  # and it can be undone again
    again = client.post(redo_action, data={"version": after_undo, "csrf_token": token})
    assert again.status_code == 409  # the version moved on: nothing redone twice


def test_redo_without_an_undo_and_bad_input_are_refused(app, client, login, csrf_token, graded_card):  # type: ignore[no-untyped-def]
    card = graded_card
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    version = str(_review(app, card)[3])
    nothing = client.post(f"/review/cards/{card}/redo", data={"version": version, "csrf_token": token})
    assert nothing.status_code == 409 and "no undone decision to redo" in nothing.get_data(as_text=True)
    for bad in ("", "x", "1" * 5000, "-1", "'; drop table card_reviews; --"):
        assert client.post(f"/review/cards/{card}/redo", data={"version": bad, "csrf_token": token}).status_code == 400
    assert client.post("/review/cards/999999/redo", data={"version": "1", "csrf_token": token}).status_code == 404


def test_redo_of_a_send_back_makes_a_new_batch(app, client, login, csrf_token, graded_card):  # type: ignore[no-untyped-def]
    from annotation.models import Batch
    from core.db import db

    card = graded_card
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    version = str(_review(app, card)[3])
    done = client.post(
        f"/review/cards/{card}/decide",
        data={"choice": "send_back", "kind": "judge", "version": version, "csrf_token": token},
        follow_redirects=True,
    )
    undo_action, after = _bar(done.get_data(as_text=True), "undo")
    redo_action, after_undo = _bar(
        client.post(undo_action, data={"version": after, "csrf_token": token}, follow_redirects=True).get_data(as_text=True),
        "redo",
    )
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Batch)) == 0
    client.post(redo_action, data={"version": after_undo, "csrf_token": token})
    assert _review(app, card)[0] == "sent_back"
    with app.app_context():
        batch = db.session.scalar(select(Batch))
        assert batch is not None and batch.kind == "judge" and [i.card_id for i in batch.items if not i.is_gold] == [card]

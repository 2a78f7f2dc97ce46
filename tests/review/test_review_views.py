"""Review pages over HTTP: roles, CSRF, decisions and conflicts, the anaglyph, history, disputes."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import select


@pytest.fixture
def graded(app, make_card, add_stage_result, card_image, decide_orientation) -> list[int]:  # type: ignore[no-untyped-def]
    """Three graded, synced cards (orientation decided); the queue order is cards[1], cards[0], cards[2]."""
    from review.tasks import sync_reviews

    ids = []
    for index, (grade, uncertainty) in enumerate([("few", 0.3), ("some", 0.8), ("failure", 0.1)]):
        card_id = make_card(card_image()[:, index:], state="pass", collection="keystone")
        add_stage_result(
            card_id,
            "grade",
            outcome=grade,
            reason=f"reason {grade}",
            metrics={"uncertainty": uncertainty, "reasons": [f"reason {grade}"], "coverage": 0.91},
        )
        ids.append(card_id)
    decide_orientation(ids)
    with app.app_context():
        sync_reviews()
    return ids


def review_of(app, card_id: int) -> Any:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    with app.app_context():
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
        db.session.expunge(review)
        return review


@pytest.mark.parametrize(
    ("role", "status"), [(None, 302), ("annotator", 403), ("exporter", 403), ("curator", 200), ("admin", 200)]
)
def test_review_pages_are_for_curators(client, as_role, graded, role, status) -> None:  # type: ignore[no-untyped-def]
    as_role(role)
    for url in ("/review/", f"/review/cards/{graded[0]}", f"/review/cards/{graded[0]}/history"):
        response = client.get(url)
        assert response.status_code == status, url
        if status == 302:
            assert response.headers["Location"].startswith("/auth/login?next=")
    if role == "annotator":
        assert "This page is for curators and admins" in client.get("/review/").get_data(as_text=True)


def test_an_annotator_cannot_post_a_decision(app, client, login, csrf_token, graded) -> None:  # type: ignore[no-untyped-def]
    login("annotator")
    token = csrf_token("/")  # the log-out form on the home page carries the session's token
    response = client.post(
        f"/review/cards/{graded[0]}/decide", json={"action": "accept", "version": 1}, headers={"X-CSRFToken": token}
    )
    assert response.status_code == 403
    assert client.post("/review/sync", data={"csrf_token": token}).status_code == 403
    assert review_of(app, graded[0]).decision == "pending"


def test_the_nav_shows_review_to_curators_only(client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    assert '<a href="/review/"' in client.get(f"/review/cards/{graded[0]}").get_data(as_text=True)


def test_queue_lists_cards_by_uncertainty_and_filters(client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    page = client.get("/review/").get_data(as_text=True)
    positions = [page.index(f'href="/review/cards/{card}"') for card in (graded[1], graded[0], graded[2])]
    assert positions == sorted(positions)
    assert "3 cards waiting" in page and "0.80" in page and "reason some" in page
    filtered = client.get("/review/?grade=failure").get_data(as_text=True)
    assert f'href="/review/cards/{graded[2]}?grade=failure"' in filtered and f"/review/cards/{graded[0]}" not in filtered
    assert "1 card waiting" in client.get("/review/?reason=REASON%20FEW").get_data(as_text=True)
    bad = client.get("/review/?grade=great")
    assert bad.status_code == 400 and "Unknown grade &#39;great&#39;" in bad.get_data(as_text=True)
    assert client.get("/review/?page=9").status_code == 404


def test_a_decision_needs_the_csrf_token(app, client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    response = client.post(f"/review/cards/{graded[0]}/decide", data={"choice": "accept", "version": "1"})
    assert response.status_code == 400 and "CSRF" in response.get_data(as_text=True)
    response = client.post(f"/review/cards/{graded[0]}/decide", json={"action": "accept", "version": 1})
    assert response.status_code == 400
    assert review_of(app, graded[0]).decision == "pending"


def test_a_form_decision_redirects_to_the_next_card(app, client, login, csrf_token, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    token = csrf_token(f"/review/cards/{graded[1]}")
    response = client.post(
        f"/review/cards/{graded[1]}/decide",
        data={"choice": "change:failure", "version": "1", "note": "halves swapped", "csrf_token": token},
    )
    assert response.status_code == 303 and response.headers["Location"] == f"/review/cards/{graded[0]}"
    review = review_of(app, graded[1])
    assert (review.decision, review.grade, review.note, review.version) == ("changed", "failure", "halves swapped", 2)
    # The last card in the queue leads back to the queue.
    response = client.post(
        f"/review/cards/{graded[2]}/decide?grade=failure", data={"choice": "accept", "version": "1", "csrf_token": token}
    )
    assert response.headers["Location"] == "/review/?grade=failure"


def test_a_json_decision_answers_with_the_next_card(app, client, login, csrf_token, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    token = csrf_token(f"/review/cards/{graded[1]}")
    response = client.post(
        f"/review/cards/{graded[1]}/decide", json={"action": "accept", "version": 1}, headers={"X-CSRFToken": token}
    )
    assert response.status_code == 200
    assert response.get_json() == {
        "card": graded[1],
        "decision": "accepted",
        "grade": "some",
        "version": 2,
        "batch": None,
        "next_url": f"/review/cards/{graded[0]}",
    }
    refused = client.post(
        f"/review/cards/{graded[0]}/decide",
        json={"action": "change", "grade": "great", "version": 1},
        headers={"X-CSRFToken": token},
    )
    assert refused.status_code == 400 and "got 'great'" in refused.get_json()["error"]["message"]
    assert (
        client.post(
            f"/review/cards/{graded[0]}/decide", json={"action": "accept", "version": "one"}, headers={"X-CSRFToken": token}
        ).status_code
        == 400
    )


def test_a_stale_version_gets_409_naming_who_changed_the_card(app, client, login, csrf_token, make_person, graded) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person
    from review.tasks import decide

    alice = make_person("curator", username="alice")
    with app.app_context():
        decide(
            review_of(app, graded[0]).id,
            "reject",
            expected_version=1,
            curator=db.session.get(Person, alice.id),
            note="a card back",
        )
    login("curator", username="bob")
    token = csrf_token(f"/review/cards/{graded[0]}")
    response = client.post(
        f"/review/cards/{graded[0]}/decide", json={"action": "accept", "version": 1}, headers={"X-CSRFToken": token}
    )
    assert response.status_code == 409
    message = response.get_json()["error"]["message"]
    assert f"Card {graded[0]} was changed by alice at " in message and "it is now version 2: rejected" in message
    form = client.post(f"/review/cards/{graded[0]}/decide", data={"choice": "accept", "version": "1", "csrf_token": token})
    assert form.status_code == 409 and "was changed by alice" in form.get_data(as_text=True)
    assert review_of(app, graded[0]).decision == "rejected"


def test_bulk_actions_apply_to_the_selection_and_report_conflicts(app, client, login, csrf_token, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    token = csrf_token("/review/")
    reviews = [review_of(app, card) for card in graded]
    client.post(f"/review/cards/{graded[2]}/decide", data={"choice": "reject", "version": "1", "csrf_token": token})
    response = client.post(
        "/review/bulk",
        data={"item": [f"{r.id}:1" for r in reviews], "action": "change", "grade": "some", "csrf_token": token},
        follow_redirects=True,
    )
    page = response.get_data(as_text=True)
    assert "applied to 2 of 3 cards" in page and f"Card {graded[2]} was changed by curator-" in page
    assert [(review_of(app, c).decision, review_of(app, c).grade) for c in graded] == [
        ("changed", "some"),
        ("accepted", "some"),
        ("rejected", None),
    ]
    as_json = client.post(
        "/review/bulk",
        json={"action": "reject", "items": [{"review": reviews[0].id, "version": 1}]},
        headers={"X-CSRFToken": token},
    )
    assert as_json.get_json()["outcomes"][0]["status"] == "conflict"
    assert client.post("/review/bulk", data={"item": ["x:y"], "action": "reject", "csrf_token": token}).status_code == 400


@pytest.fixture
def rectified(graded, add_stage_result, data_dir: Path) -> tuple[int, np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    """Card graded[0] with rectified previews: a left and right view of 160 x 120 px (PNG, exact values)."""
    rng = np.random.default_rng(7)
    left = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    right = np.roll(left, -6, axis=1)  # 6 px of disparity
    folder = data_dir / "derived" / "rect"
    folder.mkdir(parents=True)
    for name, image in (("left_preview", left), ("right_preview", right)):
        Image.fromarray(image).save(folder / f"{name}.png")
    add_stage_result(
        graded[0],
        "rectify",
        outcome=None,
        reason="rectified",
        artifacts={"left_preview": "derived/rect/left_preview.png", "right_preview": "derived/rect/right_preview.png"},
    )
    return graded[0], left, right


def test_the_anaglyph_is_red_left_cyan_right_and_cached_by_etag(client, login, rectified) -> None:  # type: ignore[no-untyped-def]
    card_id, left, right = rectified
    login("curator")
    page = client.get(f"/review/cards/{card_id}").get_data(as_text=True)
    assert f'src="/review/cards/{card_id}/anaglyph.png?v=' in page and 'class="wiggle-right"' in page
    response = client.get(f"/review/cards/{card_id}/anaglyph.png")
    assert response.status_code == 200 and response.mimetype == "image/png"
    picture = np.asarray(Image.open(io.BytesIO(response.data)))
    assert picture.shape == (120, 160, 3)

    def luma(image: np.ndarray) -> np.ndarray:
        return np.asarray(Image.fromarray(image).convert("L")).astype(int)

    assert np.abs(picture[..., 0].astype(int) - luma(left)).max() <= 1
    assert np.abs(picture[..., 1].astype(int) - luma(right)).max() <= 1
    assert np.array_equal(picture[..., 1], picture[..., 2])
    etag = response.headers["ETag"]
    again = client.get(f"/review/cards/{card_id}/anaglyph.png", headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert client.get(f"/review/cards/{rectified[0] + 1}/anaglyph.png").status_code == 404  # no rectified pair


def test_the_history_page_lists_every_change(app, client, login, csrf_token, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator", username="carol")
    token = csrf_token(f"/review/cards/{graded[0]}")
    client.post(
        f"/review/cards/{graded[0]}/decide",
        data={"choice": "change:some", "version": "1", "note": "fringes on the left", "csrf_token": token},
    )
    page = client.get(f"/review/cards/{graded[0]}/history").get_data(as_text=True)
    assert page.index("grade 1: graded") < page.index("review 1: change")
    assert "carol" in page and "pipeline" in page and "fringes on the left" in page
    assert '"decision": "pending"' in page and '"decision": "changed"' in page
    assert client.get("/review/cards/999/history").status_code == 404


@pytest.fixture
def crop_dispute(make_card, card_image, add_crop_dispute) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    card_id = make_card(card_image()[:, 30:], state="review")  # 574 x 200 px
    _, aggregate_id = add_crop_dispute(card_id, right_x0=290, right_x1s=(560, 470), consensus_x1=515)
    return card_id, aggregate_id


def test_disputes_are_listed_shown_with_boxes_and_resolved_as_gold(app, client, login, csrf_token, crop_dispute) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, GoldAnswer
    from core.db import db

    card_id, aggregate_id = crop_dispute
    login("curator")
    queue = client.get("/review/").get_data(as_text=True)
    assert f'href="/review/disputes/{aggregate_id}"' in queue and "right box: mean IoU 0.58" in queue
    page = client.get(f"/review/disputes/{aggregate_id}").get_data(as_text=True)
    assert page.count('class="box box-right crowd-answer') == 2 and page.count("crowd-aggregate") == 2
    assert 'width="270"' in page  # the 290..560 answer box
    token = csrf_token(f"/review/disputes/{aggregate_id}")
    form = {
        "left_x0": "0",
        "left_y0": "0",
        "left_x1": "280",
        "left_y1": "200",
        "right_x0": "290",
        "right_y0": "0",
        "right_x1": "9999",
        "right_y1": "200",
        "make_gold": "on",
        "csrf_token": token,
    }
    refused = client.post(f"/review/disputes/{aggregate_id}", data=form)
    assert refused.status_code == 400 and "The right box is refused" in refused.get_data(as_text=True)
    form["right_x1"] = "560"
    done = client.post(f"/review/disputes/{aggregate_id}", data=form)
    assert done.status_code == 303
    with app.app_context():
        aggregate = db.session.get(Aggregate, aggregate_id)
        assert (aggregate.state, aggregate.label["right"]) == ("approved", [290.0, 0.0, 560.0, 200.0])
        gold = db.session.scalar(select(GoldAnswer).where(GoldAnswer.card_id == card_id))
        assert gold.answer == {"left": [0.0, 0.0, 280.0, 200.0], "right": [290.0, 0.0, 560.0, 200.0]}
    again = client.post(f"/review/disputes/{aggregate_id}", data=form)
    assert again.status_code == 409 and "already resolved by curator-" in again.get_data(as_text=True)
    card_page = client.get(f"/review/cards/{card_id}").get_data(as_text=True)
    # the resolved crop is in; the card the filter sent to review still waits for a judgement
    assert "it is waiting for the crowd" in card_page and "crowd-aggregate" in card_page


def test_card_page_shows_the_parallax_preview_when_views_exist(
    app, client, login, make_card, add_stage_result, card_image
) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    login("curator")
    with_views, without = make_card(card_image()[:, 1:], state="pass"), make_card(card_image()[:, 2:], state="pass")
    add_stage_result(with_views, "views", outcome=None, artifacts={"preview": "derived/x/views/preview.webp"})
    with app.app_context():
        db.session.add_all([CardReview(card_id=with_views, auto_grade="few"), CardReview(card_id=without, auto_grade="few")])
        db.session.commit()
    page = client.get(f"/review/cards/{with_views}").get_data(as_text=True)
    assert f"/viewer/cards/{with_views}/files/preview" in page and f'href="/viewer/cards/{with_views}"' in page
    assert "/files/preview" not in client.get(f"/review/cards/{without}").get_data(as_text=True)


# ------------------------------------------------------------- cards held back: say why, link, come back


@pytest.fixture
def held(app, make_card, add_stage_result, card_image, decide_orientation, add_crop_dispute) -> dict[str, int]:  # type: ignore[no-untyped-def]
    """Three graded cards in the queue: one whose crop the crowd disputes, one whose orientation
    nobody has decided, and one free to accept; with the dispute's batch and aggregate ids."""
    from review.tasks import sync_reviews

    cards = {}
    for n, (name, uncertainty) in enumerate((("disputed", 0.9), ("undecided", 0.6), ("free", 0.3))):
        cards[name] = make_card(card_image()[:, n:], state="pass")  # the disputed card is 604 x 200 px
        add_stage_result(cards[name], "grade", outcome="some", metrics={"uncertainty": uncertainty, "reasons": ["fringes"]})
    decide_orientation([cards["disputed"], cards["free"]])
    with app.app_context():
        sync_reviews()
    batch, aggregate = add_crop_dispute(cards["disputed"])
    return cards | {"batch": batch, "aggregate": aggregate}


def queue_row(page: str, card_id: int) -> str:
    start = page.index(f'<tr data-card="{card_id}"')
    return page[start : page.index("</tr>", start)]


def test_the_queue_says_which_cards_are_held_back_and_links_the_dispute(client, login, held) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    page = client.get("/review/?grade=some").get_data(as_text=True)
    disputed = queue_row(page, held["disputed"])
    assert (
        f"<strong>Disputed:</strong> the crowd disagrees on its crop (batch {held['batch']}, dispute {held['aggregate']})."
        in disputed
    )
    # straight to the dispute, and from there back to the card with the queue's filters
    assert f'href="/review/disputes/{held["aggregate"]}?next=/review/cards/{held["disputed"]}?grade%3Dsome"' in disputed
    undecided = queue_row(page, held["undecided"])
    assert "<strong>Cannot be accepted yet:</strong> its orientation is undecided (waiting for " in undecided
    assert "Disputed" not in undecided and "/review/disputes/" not in undecided
    free = queue_row(page, held["free"])
    assert "held-reasons" not in free and 'class="held-back"' not in free


def test_a_decided_card_in_the_queue_is_marked_only_for_its_dispute(app, client, login, held) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person
    from review.tasks import decide

    carol = login("curator")
    with app.app_context():
        for name in ("disputed", "undecided"):  # rejecting is not held back
            decide(review_of(app, held[name]).id, "reject", expected_version=1, curator=db.session.get(Person, carol.id))
    page = client.get("/review/?decision=all").get_data(as_text=True)
    assert "<strong>Disputed:</strong> the crowd disagrees on its crop" in queue_row(page, held["disputed"])
    assert "held-reasons" not in queue_row(page, held["undecided"])  # not to be accepted, so nothing to say


def test_the_queue_reads_held_back_cards_in_a_fixed_number_of_queries(  # type: ignore[no-untyped-def]
    app, client, login, held, make_card, add_stage_result, card_image, add_crop_dispute
) -> None:
    from sqlalchemy import event

    from core.db import db
    from review.tasks import sync_reviews

    login("curator")

    def queries() -> int:
        seen: list[str] = []

        def count(*args: Any) -> None:
            seen.append(args[2])

        with app.app_context():
            engine = db.engine
        event.listen(engine, "before_cursor_execute", count)
        try:
            assert client.get("/review/").status_code == 200
        finally:
            event.remove(engine, "before_cursor_execute", count)
        return len(seen)

    three = queries()
    for n in range(4):  # four more disputed cards, each its own batch
        card_id = make_card(card_image()[:, n + 3 :], state="pass")
        add_stage_result(card_id, "grade", outcome="few", metrics={"uncertainty": 0.5, "reasons": ["fringes"]})
        with app.app_context():
            sync_reviews()
        add_crop_dispute(card_id)
    page = client.get("/review/").get_data(as_text=True)
    assert page.count("<strong>Disputed:</strong>") == 5
    assert queries() == three


def test_the_card_page_disables_accept_while_the_card_is_held_back(client, login, held) -> None:  # type: ignore[no-untyped-def]
    import re

    login("curator")

    def buttons(card_id: int) -> tuple[dict[str, bool], str]:
        page = client.get(f"/review/cards/{card_id}").get_data(as_text=True)
        found = re.findall(r'<button type="submit" name="choice" value="([^"]+)"([^>]*)>', page)
        return {value: " disabled" in attributes for value, attributes in found}, page

    expected = {"accept": True, "change:few": True, "change:some": True, "change:failure": True, "send_back": False}
    disabled, page = buttons(held["disputed"])
    assert disabled == expected | {"reject": False}
    assert f"Not accepted now: the crowd disagrees on its crop (batch {held['batch']}, dispute {held['aggregate']})." in page
    link = f'href="/review/disputes/{held["aggregate"]}?next=/review/cards/{held["disputed"]}"'
    assert f'<a class="button dispute-link" {link}>Resolve dispute {held["aggregate"]}</a>' in page
    assert 'data-held-back="true"' in page

    disabled, page = buttons(held["undecided"])
    assert disabled == expected | {"reject": False}
    assert "Not accepted now: its orientation is undecided (waiting for " in page and "dispute-link" not in page

    disabled, page = buttons(held["free"])
    assert not any(disabled.values()) and 'id="card-blockers"' not in page and 'data-held-back=""' in page


def test_accepting_a_disputed_card_answers_409_with_the_disputes_link(app, client, login, csrf_token, held) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    card_id = held["disputed"]
    token = csrf_token(f"/review/cards/{card_id}")
    link = f"/review/disputes/{held['aggregate']}?next=/review/cards/{card_id}"
    for action in ({"action": "accept"}, {"action": "change", "grade": "few"}):
        refused = client.post(f"/review/cards/{card_id}/decide", json={**action, "version": 1}, headers={"X-CSRFToken": token})
        assert refused.status_code == 409
        error = refused.get_json()["error"]
        assert error["dispute_url"] == link and "while the crowd disagrees on its crop" in error["message"]
    form = client.post(f"/review/cards/{card_id}/decide", data={"choice": "accept", "version": "1", "csrf_token": token})
    assert form.status_code == 409 and f'<a href="{link}" class="dispute-link">' in form.get_data(as_text=True)
    # held back for another reason: refused, without a dispute to link to
    other = client.post(
        f"/review/cards/{held['undecided']}/decide", json={"action": "accept", "version": 1}, headers={"X-CSRFToken": token}
    )
    assert other.status_code == 409 and "dispute_url" not in other.get_json()["error"]
    assert review_of(app, card_id).decision == "pending"


CROP_FORM = {
    "left_x0": "0",
    "left_y0": "0",
    "left_x1": "280",
    "left_y1": "200",
    "right_x0": "310",
    "right_y0": "0",
    "right_x1": "600",
    "right_y1": "200",
}


def test_settling_a_dispute_from_the_card_returns_to_the_card(client, login, csrf_token, held) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    card_id, aggregate_id = held["disputed"], held["aggregate"]
    back = f"/review/cards/{card_id}?grade=some"
    page = client.get(f"/review/disputes/{aggregate_id}", query_string={"next": back}).get_data(as_text=True)
    assert f'action="/review/disputes/{aggregate_id}?next=/review/cards/{card_id}?grade%3Dsome"' in page
    token = csrf_token(f"/review/disputes/{aggregate_id}")
    # a mistake keeps the way back
    wrong = client.post(
        f"/review/disputes/{aggregate_id}", query_string={"next": back}, data={**CROP_FORM, "left_x1": "", "csrf_token": token}
    )
    assert wrong.status_code == 400 and f"?next=/review/cards/{card_id}?grade%3Dsome" in wrong.get_data(as_text=True)
    done = client.post(f"/review/disputes/{aggregate_id}", query_string={"next": back}, data={**CROP_FORM, "csrf_token": token})
    assert done.status_code == 303 and done.headers["Location"] == back
    card_page = client.get(back).get_data(as_text=True)
    assert f"Card {card_id}: your crop answer is now the card&#39;s truth." in card_page
    assert 'id="card-blockers"' not in card_page
    assert '<button type="submit" name="choice" value="accept" class="button">' in card_page


HOSTILE_NEXT = [
    "//evil.com",
    "https://evil.com",
    "http://evil.com/review/cards/1",
    "/\\evil.com",
    "///evil.com",
    "javascript:alert(1)",
    "/auth/people",
    "/review/../auth/people",
    "/review/%2e%2e/auth/people",
    "/review/cards/1\r\nLocation: //evil.com",
    "review/cards/1",
]


@pytest.mark.parametrize("target", ["//evil.com", "https://evil.com", "/review/../auth/people"])
def test_a_hostile_next_falls_back_to_the_queue(client, login, csrf_token, held, target: str) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    aggregate_id = held["aggregate"]
    page = client.get(f"/review/disputes/{aggregate_id}", query_string={"next": target}).get_data(as_text=True)
    assert f'action="/review/disputes/{aggregate_id}"' in page and "evil" not in page
    token = csrf_token(f"/review/disputes/{aggregate_id}")
    done = client.post(f"/review/disputes/{aggregate_id}", query_string={"next": target}, data={**CROP_FORM, "csrf_token": token})
    assert done.status_code == 303 and done.headers["Location"] == "/review/#disputes"


@pytest.mark.parametrize("target", HOSTILE_NEXT)
def test_only_a_review_page_is_a_place_to_return_to(target: str) -> None:
    from review.views import review_return_path

    assert review_return_path(target) is None
    assert review_return_path("/review/cards/12?grade=some") == "/review/cards/12?grade=some"
    assert review_return_path("/review/") == "/review/"

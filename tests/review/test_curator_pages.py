"""Curator pages without a browser: undo after each decision (and its bad input), the
nearest-threshold table (from the grade record, or computed from levels and thresholds), the
judge dispute form that pre-selects nothing the crowd was unsure of, and the card-state sentence."""

from __future__ import annotations

import math
import re

import pytest
from sqlalchemy import func, select


@pytest.fixture
def two_graded(app, make_card, add_stage_result, card_image, decide_orientation) -> list[int]:  # type: ignore[no-untyped-def]
    from review.tasks import sync_reviews

    ids = []
    for index, grade in enumerate(("few", "some")):
        card_id = make_card(card_image()[:, index:], state="pass")
        add_stage_result(
            card_id,
            "grade",
            outcome=grade,
            reason=f"reason {grade}",
            metrics={"uncertainty": 0.5 - index / 10, "reasons": [f"reason {grade}"]},
        )
        ids.append(card_id)
    with app.app_context():
        sync_reviews()
    decide_orientation(ids)  # the flow rule: only a card with a decided orientation can be accepted
    return ids


def _review(app, card_id: int) -> tuple[str, str | None, int]:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    with app.app_context():
        review = db.session.scalar(select(CardReview).where(CardReview.card_id == card_id))
        return review.decision, review.grade, review.version


def _undo_form(html: str) -> tuple[str, str]:
    bar = re.search(r'<form method="post" action="([^"]+/undo)">.*?name="version" value="(\d+)"', html, re.DOTALL)
    assert bar, "no undo button on the page"
    return bar.group(1), bar.group(2)


def test_each_decision_is_confirmed_and_undone(app, client, login, csrf_token, two_graded) -> None:  # type: ignore[no-untyped-def]
    card = two_graded[0]
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    for choice, decision, grade in [
        ("accept", "accepted", "few"),
        ("change:failure", "changed", "failure"),
        ("reject", "rejected", None),
    ]:
        version = str(_review(app, card)[2])
        done = client.post(
            f"/review/cards/{card}/decide",
            data={"choice": choice, "version": version, "csrf_token": token},
            follow_redirects=True,
        )
        html = done.get_data(as_text=True)
        assert f"Card {card}: " in html and 'id="undo-bar"' in html
        assert _review(app, card)[:2] == (decision, grade)
        action, after = _undo_form(html)
        assert "undo-bar" not in client.get("/review/").get_data(as_text=True)  # shown once
        undone = client.post(action, data={"version": after, "csrf_token": token}, follow_redirects=True)
        assert undone.status_code == 200 and "Undone: card" in undone.get_data(as_text=True)
        assert _review(app, card)[:2] == ("pending", None)
        again = client.post(action, data={"version": after, "csrf_token": token})
        assert again.status_code == 409  # the version moved on: nothing undone twice


def test_a_send_back_names_its_batch_and_undo_removes_it(app, client, login, csrf_token, two_graded) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Batch
    from core.db import db

    card = two_graded[0]
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    done = client.post(
        f"/review/cards/{card}/decide",
        json={"action": "send_back", "kind": "judge", "version": 1},
        headers={"X-CSRFToken": token},
    )
    batch_id = done.get_json()["batch"]
    html = client.get(done.get_json()["next_url"]).get_data(as_text=True)
    assert f"new crowd batch {batch_id}" in html and f'href="/crowd/batches#batch-{batch_id}"' in html
    action, version = _undo_form(html)
    assert client.post(action, data={"version": version, "csrf_token": token}).status_code == 303
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Batch).where(Batch.id == batch_id)) == 0
    assert _review(app, card)[0] == "pending"


def test_undo_refuses_once_the_crowd_answered(app, client, login, csrf_token, two_graded) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Answer, BatchItem
    from annotation.workers import get_or_create_worker
    from core.db import db

    card = two_graded[0]
    login("curator")
    token = csrf_token(f"/review/cards/{card}")
    batch_id = client.post(
        f"/review/cards/{card}/decide",
        json={"action": "send_back", "kind": "judge", "version": 1},
        headers={"X-CSRFToken": token},
    ).get_json()["batch"]
    with app.app_context():
        item = db.session.scalar(select(BatchItem).where(BatchItem.batch_id == batch_id, BatchItem.card_id == card))
        db.session.add(
            Answer(
                item_id=item.id,
                worker_id=get_or_create_worker("invite", "w").id,
                idempotency_key="key-undo-abcdef",
                payload={"is_stereo": True, "upside_down": False, "inverted": False},
            )
        )
        db.session.commit()
    refused = client.post(f"/review/cards/{card}/undo", data={"version": str(_review(app, card)[2]), "csrf_token": token})
    assert refused.status_code == 409 and "already answered" in refused.get_data(as_text=True)
    assert _review(app, card)[0] == "sent_back"


def test_undo_bad_input(client, login, csrf_token, two_graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    token = csrf_token("/review/")
    for data, status in [({}, 400), ({"version": "x"}, 400), ({"version": "-1"}, 400), ({"version": "1"}, 409)]:
        response = client.post(f"/review/cards/{two_graded[0]}/undo", data={**data, "csrf_token": token})
        assert response.status_code == status, data
    assert client.post("/review/cards/99999/undo", data={"version": "1", "csrf_token": token}).status_code == 404
    assert client.post(f"/review/cards/{two_graded[0]}/undo", data={"version": "1"}).status_code == 400  # no CSRF


def test_the_threshold_table_from_levels_and_from_a_recorded_nearest(app) -> None:  # type: ignore[no-untyped-def]
    from pipeline.grading import GradeThresholds
    from pipeline.records import param_hash
    from review.threshold_table import threshold_table

    metrics = {
        "good_match_fraction": 0.25,
        "dy_p95_px": 1.2,
        "coverage": 0.7,
        "swapped": False,
        "levels": {"good_match_fraction": 0, "dy_p95_px": 0, "coverage": 1, "swapped": 0},
        "thresholds_hash": param_hash(GradeThresholds()),
    }
    defaults = GradeThresholds()
    with app.app_context():
        table = threshold_table(metrics)
        assert table is not None and table.thresholds_known and not table.from_record
        rows = {row.measurement: row for row in table.rows}
        coverage_some = defaults.coverage.some
        assert rows["coverage"].threshold == f"< {100 * coverage_some:g} %" and rows["coverage"].side == "beyond"
        assert rows["coverage"].margin == f"{100 * (0.7 - coverage_some):+.2f} points"
        dy_some = defaults.dy_p95_px.some
        assert rows["dy_p95_px"].margin == f"{1.2 - dy_some:+.1f} px" and rows["dy_p95_px"].side == "within"
        assert rows["swapped"].value == "no" and math.isinf(rows["swapped"].distance)
        assert table.rows[-1].measurement == "swapped"  # flags are never near
        assert [row.distance for row in table.rows] == sorted(row.distance for row in table.rows)
        assert table.nearest is not None and table.nearest.measurement in rows

        recorded = threshold_table(
            {**metrics, "nearest": {"measurement": "coverage", "value": 0.7, "threshold": 0.8, "margin": -0.1, "level": "some"}}
        )
        assert recorded.from_record and recorded.nearest.measurement == "coverage"
        unknown = threshold_table({**metrics, "thresholds_hash": "not-a-hash"})
        assert not unknown.thresholds_known and unknown.nearest is not None
        assert threshold_table({"uncertainty": 0.5}) is None and threshold_table(None) is None

        from pipeline.grading import (
            grade,  # a record from the current grader: its own rows and nearest
        )

        result = grade({k: metrics[k] for k in metrics["levels"]}, defaults)
        current = threshold_table({**metrics, "checks": result.checks, "nearest": result.nearest})
        assert current.from_record and current.nearest.measurement == result.nearest["measurement"]
        assert [row.measurement for row in current.rows] == [row.measurement for row in table.rows]


@pytest.fixture
def make_judge_dispute(app, make_card, card_image):  # type: ignore[no-untyped-def]
    """``make_judge_dispute(swapped=None)``: a judge aggregate waiting for a curator, four answers
    (one by a person with an account, who says upside down); with ``swapped`` (one vote per answer),
    the answers were asked the eye order too, and the label and posterior have it."""
    from annotation.batches import create_batch
    from annotation.models import Aggregate, Answer, BatchItem
    from annotation.workers import get_or_create_worker
    from core.db import db
    from core.models import Person

    def make(swapped: list[bool] | None = None) -> int:
        card_id = make_card(card_image(), state="review")
        with app.app_context():
            batch = create_batch([card_id], "judge", 4, 0.0)
            item = db.session.scalar(select(BatchItem).where(BatchItem.batch_id == batch.id))
            person = db.session.scalar(select(Person).where(Person.username == "maria"))
            if person is None:
                person = Person(username="maria", display_name="María Ortega")
                db.session.add(person)
                db.session.flush()
            for n in range(4):
                worker = get_or_create_worker("invite", f"friend{n}")
                if n == 0:
                    worker.person_id = person.id
                payload = {"is_stereo": True, "upside_down": n == 0, "inverted": False}
                if swapped is not None:
                    payload["swapped"] = swapped[n]
                db.session.add(
                    Answer(item_id=item.id, worker_id=worker.id, idempotency_key=f"key-{n}-judge-{batch.id}", payload=payload)
                )
            label = {"is_stereo": True, "upside_down": False, "inverted": False}
            posterior = {"is_stereo": [0.02, 0.98], "upside_down": [0.75, 0.25], "inverted": [0.97, 0.03]}
            if swapped is not None:
                label["swapped"], posterior["swapped"] = True, [0.4, 0.6]
            aggregate = Aggregate(
                batch_id=batch.id,
                card_id=card_id,
                kind="judge",
                state="needs_curator",
                answers=4,
                label=label,
                posterior=posterior,
                reasons="upside_down: posterior 0.75 < 0.9",
            )
            db.session.add(aggregate)
            db.session.commit()
            return aggregate.id

    return make


@pytest.fixture
def judge_dispute(make_judge_dispute) -> int:  # type: ignore[no-untyped-def]
    return make_judge_dispute()


def test_the_judge_dispute_shows_votes_and_preselects_only_confident_answers(client, login, csrf_token, judge_dispute) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    url = f"/review/disputes/{judge_dispute}"
    html = client.get(url).get_data(as_text=True)
    assert "María Ortega" in html and "friend1 (invite link)" in html
    assert "upside down: 25 % likely" in html and "a stereo pair: 98 % likely" in html
    assert "[0.75, 0.25]" not in html  # no raw JSON posterior
    checked = dict(re.findall(r'name="(\w+)" value="(yes|no)"[^>]*checked', html))
    assert checked == {"is_stereo": "yes", "inverted": "no"}  # upside_down (75 % sure) is left to the curator
    token = csrf_token(url)
    unchosen = client.post(url, data={"csrf_token": token, "is_stereo": "yes", "inverted": "no"})
    assert unchosen.status_code == 400 and "Choose yes or no for whether the card is upside down" in unchosen.get_data(
        as_text=True
    )
    bad = client.post(url, data={"csrf_token": token, "is_stereo": "yes", "inverted": "no", "upside_down": "maybe"})
    assert bad.status_code == 400
    done = client.post(url, data={"csrf_token": token, "is_stereo": "yes", "inverted": "no", "upside_down": "yes"})
    assert done.status_code == 303
    # Answers from before the eye-order question: it is neither shown nor asked of the curator.
    assert 'name="swapped"' not in html and "eye order" not in html


def test_the_judge_dispute_shows_and_asks_the_eye_order_where_the_crowd_was_asked_it(  # type: ignore[no-untyped-def]
    app, client, login, csrf_token, make_judge_dispute
) -> None:
    from annotation.models import Aggregate
    from core.db import db

    aggregate_id = make_judge_dispute(swapped=[True, True, False, True])
    login("curator")
    url = f"/review/disputes/{aggregate_id}"
    html = client.get(url).get_data(as_text=True)
    assert "in the wrong eye order (photos exchanged): 60 % likely" in html
    votes = html[html.index('id="votes"') : html.index("</table>", html.index('id="votes"'))]
    assert "<th>in the wrong eye order (photos exchanged)?</th>" in votes
    assert votes.count('data-label="in the wrong eye order (photos exchanged)">yes</td>') == 3
    assert re.search(r'data-label="in the wrong eye order \(photos exchanged\)">3 of 4</td>', votes)
    assert "Is it in the wrong eye order (photos exchanged)?" in html
    assert 'name="swapped" value="yes"' in html and not re.search(r'name="swapped" value="\w+"[^>]*checked', html)  # 60 %: unsure
    token = csrf_token(url)
    answers = {"csrf_token": token, "is_stereo": "yes", "inverted": "no", "upside_down": "no"}
    unchosen = client.post(url, data=answers)
    assert unchosen.status_code == 400
    assert "Choose yes or no for whether the card is in the wrong eye order (photos exchanged)" in unchosen.get_data(as_text=True)
    assert client.post(url, data={**answers, "swapped": "yes"}).status_code == 303
    with app.app_context():
        stored = db.session.get(Aggregate, aggregate_id)
        assert stored.state == "approved"
        assert stored.label == {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": True}
    card_page = client.get(f"/review/cards/{stored.card_id}").get_data(as_text=True)
    crowd = card_page[card_page.index("<h2>The crowd</h2>") :]
    assert re.search(r"<td>swapped</td><td>[^<]*</td><td>3 of 4</td>", crowd), crowd[:1500]


def test_a_card_without_a_review_says_where_it_stands(client, login, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    culled = make_card(card_image(), state="culled")
    add_stage_result(culled, "filter", outcome="culled", reason="0.3 % good matches")
    waiting = make_card(card_image()[:, 2:], state="pass")
    add_stage_result(waiting, "filter")
    failed = make_card(card_image()[:, 4:], state="pass")
    add_stage_result(failed, "filter")
    add_stage_result(failed, "rectify", status="failed", outcome=None, reason="epipole inside the image")
    login("curator")
    pages = {card: client.get(f"/review/cards/{card}").get_data(as_text=True) for card in (culled, waiting, failed)}
    assert "The filter culled this card (0.3 % good matches)" in pages[culled]
    assert "waiting for its orientation stage" in pages[waiting]  # the filter passed it; the orientation step is next
    assert "The rectify stage failed on this card (epipole inside the image)" in pages[failed]
    assert not any("Run the grade stage" in page or "Why the grader said so" in page for page in pages.values())

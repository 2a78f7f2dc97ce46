"""The curators' crowd management (issue 33.6): named, paused and closed batches; the new-batch
form's defaults, its count of waiting cards and its errors next to their fields; invite links
with an expiry, a QR code and a revoke; every worker's agreement with the crowd (the spammer)."""

from __future__ import annotations

import re
from datetime import timedelta

import pytest
from sqlalchemy import select

from annotation.models import Batch, Worker
from core.audit import AuditEvent
from core.db import db, utcnow

TOKEN = re.compile(r'data-worker-token="([^"]*)"')
JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False}
REQUEST_KEY = "k" * 20


@pytest.fixture
def cards(make_card, card_image):  # type: ignore[no-untyped-def]
    base = card_image()
    made: list[int] = []

    def make(k: int, state: str = "review") -> list[int]:
        ids = []
        for _ in range(k):
            image = base.copy()
            image[0, 0, 0] = len(made) % 256
            image[0, 1, 0] = len(made) // 256
            made.append(1)
            ids.append(make_card(image, state=state))
        return ids

    return make


def batch_of(app, card_ids, kind="judge", n=2) -> int:  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    with app.app_context():
        return create_batch(card_ids, kind, n, 0.0).id


class Invited:
    def __init__(self, worker_id: int, token: str) -> None:
        self.id, self.token = worker_id, token


def invited(app, name: str) -> Invited:  # type: ignore[no-untyped-def]
    from annotation.providers import InviteProvider

    with app.app_context():
        worker = InviteProvider.invite(name)
        return Invited(worker.id, worker.token)


def signed_token(client, link_token: str) -> str:  # type: ignore[no-untyped-def]
    page = client.get(f"/crowd/invite/{link_token}")
    assert page.status_code == 200, page.get_data(as_text=True)
    return TOKEN.search(page.get_data(as_text=True)).group(1)


def fetch(client, token: str) -> dict:  # type: ignore[no-untyped-def]
    response = client.post("/crowd/api/next?kind=judge", headers={"X-Crowd-Token": token}, json={})
    assert response.status_code == 200, response.get_data(as_text=True)
    return response.get_json()


def post_form(client, csrf_token, url: str, **fields):  # type: ignore[no-untyped-def]
    return client.post(url, data={"csrf_token": csrf_token("/crowd/batches"), **fields})


# --------------------------------------------------------------------------- batch states


@pytest.mark.both_databases
def test_a_paused_batch_gives_no_new_task_and_a_resumed_one_does(app, client, cards):
    from annotation.labels import batch_labels, set_batch_state

    batch = batch_of(app, cards(2))
    worker = invited(app, "paula")
    token = signed_token(client, worker.token)
    with app.app_context():
        set_batch_state(batch, "paused", None)
        assert batch_labels([batch])[batch].state == "paused"
    assert fetch(client, token)["tasks"] == []
    with app.app_context():
        set_batch_state(batch, "open", None)
    assert len(fetch(client, token)["tasks"]) == 2


def test_a_closed_batch_stays_closed_and_its_cards_wait_again(app, client, cards):
    from annotation.batches import waiting_card_ids
    from annotation.labels import batch_labels, set_batch_state
    from annotation.task_errors import TaskError

    ids = cards(3)
    batch = batch_of(app, ids[:2])
    with app.app_context():
        # two of the three review cards are in an open judge batch: one waits for a new one
        assert waiting_card_ids("judge") == [ids[2]] and waiting_card_ids("crop") == ids
        set_batch_state(batch, "paused", None)
        assert waiting_card_ids("judge") == [ids[2]]  # a paused batch still holds its cards
        set_batch_state(batch, "closed", None)
        assert waiting_card_ids("judge") == ids
        with pytest.raises(TaskError) as refused:
            set_batch_state(batch, "open", None)
        assert refused.value.status == 409 and "closed" in refused.value.message
        assert batch_labels([batch])[batch].state == "closed"
    token = signed_token(client, invited(app, "carl").token)
    assert fetch(client, token)["tasks"] == []


def test_batches_page_names_pauses_and_closes_a_batch(app, client, cards, login, csrf_token):
    batch = batch_of(app, cards(2))
    login("curator")
    response = post_form(client, csrf_token, f"/crowd/batches/{batch}/name", name="  November\tband  ")
    assert response.status_code == 303
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert f"Batch {batch}: November band · judge" in html
    assert post_form(client, csrf_token, f"/crowd/batches/{batch}/state", state="paused").status_code == 303
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert 'class="tag tag-paused">paused</span>' in html and 'value="open" class="button-quiet">Resume' in html
    assert post_form(client, csrf_token, f"/crowd/batches/{batch}/state", state="closed").status_code == 303
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert 'class="tag tag-closed">closed</span>' in html and "Resume</button>" not in html
    again = post_form(client, csrf_token, f"/crowd/batches/{batch}/state", state="open")
    assert again.status_code == 409 and "cannot be changed again" in again.get_data(as_text=True)
    for bad in ("running", "x" * 5000, "'; drop table crowd_batches; --"):
        assert post_form(client, csrf_token, f"/crowd/batches/{batch}/state", state=bad).status_code == 400
    assert post_form(client, csrf_token, "/crowd/batches/999999/state", state="paused").status_code == 404
    too_long = post_form(client, csrf_token, f"/crowd/batches/{batch}/name", name="n" * 5000)
    assert too_long.status_code == 400 and "at most 120 characters" in too_long.get_data(as_text=True)
    with app.app_context():
        actions = list(db.session.scalars(select(AuditEvent.action).where(AuditEvent.entity_id == batch).order_by(AuditEvent.id)))
    assert actions == ["name", "pause", "close"]


# --------------------------------------------------------------------------- the new-batch form


def test_new_batch_form_ticks_the_queue_only_while_cards_wait(app, client, cards, login, csrf_token):
    ids = cards(3)
    login("curator")
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert re.search(r'name="from_review" value="1" checked', html)
    assert "(judge: 3, crop: 3, confirm: 0 cards)" in html
    response = post_form(
        client, csrf_token, "/crowd/batches/new", kind="judge", from_review="1", name="first", request_key=REQUEST_KEY
    )
    assert response.status_code == 303
    with app.app_context():
        batch = db.session.scalar(select(Batch))
        assert sorted(item.card_id for item in batch.items) == ids
    html = client.get("/crowd/batches").get_data(as_text=True)
    # the three cards are in an open judge batch now: the box is no longer ticked
    assert "(judge: 0, crop: 3, confirm: 0 cards)" in html
    assert not re.search(r'name="from_review" value="1" checked', html)
    assert f"Batch {batch.id}: first · judge" in html


@pytest.mark.parametrize(
    ("typed", "error"),
    [
        ("12abc", "Card ids are whole numbers"),
        ("999999", "No card with id 999999"),  # a 404, with the form
        ("%", "Card ids are whole numbers"),
        ("'; drop table cards; --", "Card ids are whole numbers"),
        ("1 " * 10_001, "Expected at most 10000 card ids"),
    ],
)
def test_a_bad_card_id_shows_the_form_again_with_the_error_beside_it(app, client, cards, login, csrf_token, typed, error):
    cards(1)
    login("curator")
    response = post_form(
        client, csrf_token, "/crowd/batches/new", kind="crop", cards=typed, name="my batch", answers_per_item="4"
    )
    html = response.get_data(as_text=True)
    assert response.status_code == (404 if typed == "999999" else 400)
    field = re.search(r'<input type="text" id="new-batch-cards" name="cards" value="([^"]*)"[^>]*aria-invalid="true"', html)
    assert field is not None
    assert field.group(1).replace("&#39;", "'") == typed[:200_000]
    assert re.search(r'<p class="field-error" id="error-cards" role="alert">[^<]*' + re.escape(error), html)
    # what else was typed stays as it was
    assert 'name="name" value="my batch"' in html and 'name="answers_per_item" value="4"' in html
    assert '<option value="crop" selected>' in html
    with app.app_context():
        assert db.session.scalar(select(Batch.id)) is None


def test_the_new_batch_form_marks_each_bad_number(app, client, cards, login, csrf_token):
    ids = cards(1)
    login("curator")
    response = post_form(
        client, csrf_token, "/crowd/batches/new", kind="judge", cards=str(ids[0]), answers_per_item="0", gold_rate="nan"
    )
    html = response.get_data(as_text=True)
    assert response.status_code == 400
    assert 'id="error-answers_per_item"' in html and 'id="error-gold_rate"' in html and 'id="error-cards"' not in html
    empty = post_form(client, csrf_token, "/crowd/batches/new", kind="judge")
    assert empty.status_code == 400 and "No cards: list card ids" in empty.get_data(as_text=True)


def test_cards_ticked_on_the_cards_list_make_a_batch(app, client, cards, login, csrf_token):
    ids = cards(3, state="pass")
    login("curator")
    token = csrf_token("/cards")
    response = client.post(
        "/crowd/batches/new",
        data={
            "csrf_token": token,
            "kind": "crop",
            "cards": [str(ids[0]), str(ids[2])],
            "name": "boxes",
            "request_key": REQUEST_KEY,
        },
    )
    assert response.status_code == 303
    with app.app_context():
        batch = db.session.scalar(select(Batch))
        assert batch.kind == "crop" and sorted(item.card_id for item in batch.items) == [ids[0], ids[2]]


# --------------------------------------------------------------------------- invite links


def test_invite_links_are_listed_with_a_qr_code_and_an_expiry(app, client, login, csrf_token):
    login("curator")
    response = post_form(client, csrf_token, "/crowd/invites", name="Ada", days="14")
    assert response.status_code == 303
    with app.app_context():
        worker = db.session.scalar(select(Worker).where(Worker.external_id == "Ada"))
        from annotation.labels import invite_statuses

        status = invite_statuses([worker.id])[worker.id]
    assert timedelta(days=13, hours=23) < status.expires_at - utcnow() <= timedelta(days=14)
    html = client.get("/crowd/batches").get_data(as_text=True)
    link = f"http://localhost/crowd/invite/{worker.token}"
    assert f'<code class="invite-url" id="invite-url-{worker.id}">{link}</code>' in html
    assert f'data-copy-target="invite-url-{worker.id}" hidden>Copy link</button>' in html
    qr = re.search(r'<svg xmlns="http://www.w3.org/2000/svg" width="(\d+)" height="\1" class="invite-qr">', html)
    assert qr is not None and int(qr.group(1)) > 60
    assert "annotation/staff.js" in html
    for bad in ("0", "366", "x", "1e3"):
        assert post_form(client, csrf_token, "/crowd/invites", name=f"n{bad}", days=bad).status_code == 400


def test_the_qr_code_reads_back_as_the_link() -> None:
    segno = pytest.importorskip("segno")
    from annotation.staff_views import invite_qr_svg

    link = "http://keystone.example/crowd/invite/abcDEF123_-"
    svg = str(invite_qr_svg(link))
    assert svg.startswith("<svg") and "<?xml" not in svg and "<script" not in svg
    # the symbol for this link (version 4, error level M: 33 modules) with the 4-module quiet zone the standard asks for, at 4 px
    symbol = segno.make(link, error="m")
    assert symbol.designator == "4-M" and symbol.symbol_size(scale=4, border=4) == (164, 164)
    assert 'width="164" height="164"' in svg
    # no line is longer than the symbol: the path draws the 33 x 33 matrix and nothing else
    runs = [int(n) for n in re.findall(r"h(\d+)", svg)]
    assert runs and max(runs) <= 33


def test_a_revoked_invite_refuses_with_a_page_and_ends_its_open_session(app, client, cards, login, csrf_token):
    batch_of(app, cards(3))
    worker = invited(app, "revoked-one")
    token = signed_token(client, worker.token)
    assert len(fetch(client, token)["tasks"]) == 2
    login("curator")
    response = post_form(client, csrf_token, f"/crowd/invites/{worker.id}/revoke")
    assert response.status_code == 303
    refused = client.get(f"/crowd/invite/{worker.token}")
    assert refused.status_code == 410 and "withdrawn" in refused.get_data(as_text=True)
    api = client.post("/crowd/api/next?kind=judge", headers={"X-Crowd-Token": token}, json={})
    assert api.status_code == 410
    again = post_form(client, csrf_token, f"/crowd/invites/{worker.id}/revoke")
    assert again.status_code == 409
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert "revoked " in html and f"/crowd/invite/{worker.token}</code>" not in html
    assert post_form(client, csrf_token, "/crowd/invites/999999/revoke").status_code == 404


def test_an_expired_invite_refuses_with_a_page(app, client, cards):
    from annotation.labels import record_invite

    worker = invited(app, "late")
    with app.app_context():
        record_invite(db.session.get(Worker, worker.id), 1, None)
        event = db.session.scalar(select(AuditEvent).where(AuditEvent.entity == "crowd_invite"))
        expired = (utcnow() - timedelta(days=2)).isoformat()
        # the trail refuses edits; a new create event is how an expiry is recorded
        db.session.add(
            AuditEvent(entity="crowd_invite", entity_id=worker.id, action="create", actor="test", after={"expires_at": expired})
        )
        db.session.commit()
        assert event is not None
    response = client.get(f"/crowd/invite/{worker.token}")
    assert response.status_code == 410 and "expired on" in response.get_data(as_text=True)


def test_an_invite_without_a_recorded_expiry_keeps_working(app, client, cards):
    batch_of(app, cards(1))
    worker = invited(app, "cli-made")  # keystone crowd invite records no expiry
    assert client.get(f"/crowd/invite/{worker.token}").status_code == 200


# --------------------------------------------------------------------------- the workers list


def test_the_demo_spammer_shows_by_its_agreement_with_the_crowd(app, make_card, card_image):
    """The demo's crowd, small: the spammer meets too little gold to be flagged (fewer than
    KEYSTONE_CROWD_MIN_GOLD gold answers), so gold alone never shows it; its agreement does."""
    from annotation.progress import LOW_AGREEMENT, worker_progress
    from annotation.simulate import seed_simulated_crowd

    base = card_image()
    ids = []
    for index in range(8):
        image = base.copy()
        image[0, 0, 0] = index
        ids.append(make_card(image, state="review"))
    with app.app_context():
        summary = seed_simulated_crowd(ids[:6], kind="judge", workers=6, n=4, seed=1, gold={ids[6]: JUDGE_OK, ids[7]: JUDGE_OK})
        rows = {row["name"]: row for row in worker_progress()}
    spammer = next(w["name"] for w in summary["workers"] if w["spammer"])
    honest = [w["name"] for w in summary["workers"] if not w["spammer"]]
    assert rows[spammer]["compared"] >= 3
    assert rows[spammer]["agreement"] < LOW_AGREEMENT
    assert min(rows[name]["agreement"] for name in honest) > rows[spammer]["agreement"]
    assert all(rows[name]["agreement"] >= 0.6 for name in honest)

"""Crowd annotation over HTTP and the CLI: entry points, assignment, submits, bad input, roles, aggregation."""

from __future__ import annotations

import json
import math
import re
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import func, select

from annotation.models import Aggregate, Answer, Batch, BatchItem, CrowdSession, Reservation, Worker
from core.db import db, utcnow

TOKEN = re.compile(r'data-worker-token="([^"]*)"')
JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False}


@pytest.fixture
def cards(make_card, card_image):  # type: ignore[no-untyped-def]
    """``cards(k, state=...)``: k distinct real stereo cards (604 x 200 px), their ids."""
    base = card_image()

    def make(k: int, state: str = "review") -> list[int]:
        ids = []
        for _ in range(k):
            image = base.copy()
            image[0, 0, 0] = len(make.made) % 256  # distinct bytes, distinct content hash
            image[0, 1, 0] = len(make.made) // 256
            make.made.append(1)
            ids.append(make_card(image, state=state))
        return ids

    make.made = []  # type: ignore[attr-defined]
    return make


def new_batch(app, card_ids, kind="judge", n=3, gold_rate=0.0, gold=None) -> int:  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch

    with app.app_context():
        return create_batch(card_ids, kind, n, gold_rate, gold=gold).id


def invite(app, client, name: str) -> str:  # type: ignore[no-untyped-def]
    """Invite NAME, open their link, return the signed worker token the page carries."""
    from annotation.providers import InviteProvider

    with app.app_context():
        link_token = InviteProvider.invite(name).token
    page = client.get(f"/crowd/invite/{link_token}")
    assert page.status_code == 200
    return TOKEN.search(page.get_data(as_text=True)).group(1)


def api(client, path: str, token: str | None, body=None, **kwargs):  # type: ignore[no-untyped-def]
    headers = {"X-Crowd-Token": token} if token is not None else {}
    if "data" in kwargs:
        return client.post(f"/crowd/api/{path}", headers=headers, **kwargs)
    return client.post(f"/crowd/api/{path}", headers=headers, json=body if body is not None else {})


def fetch(client, token: str, kind: str = "judge") -> dict:  # type: ignore[no-untyped-def]
    response = api(client, "next", token, {"kind": kind})
    assert response.status_code == 200, response.get_data(as_text=True)
    return response.get_json()


def answer(client, token: str, task_token: str, payload, key: str):  # type: ignore[no-untyped-def]
    return api(client, "submit", token, {"token": task_token, "answer": payload, "key": key})


def count(app, model) -> int:  # type: ignore[no-untyped-def]
    with app.app_context():
        return db.session.scalar(select(func.count()).select_from(model))


def item_of(app, task_token: str) -> int:  # type: ignore[no-untyped-def]
    with app.app_context():
        return db.session.scalar(select(Reservation.item_id).where(Reservation.token == task_token))


# ---------------------------------------------------------------------------------------------
# Assignment through the routes


@pytest.mark.both_databases
def test_workers_never_get_an_item_twice_and_items_get_exactly_n(app, client, cards):
    batch = new_batch(app, cards(4), n=2)
    tokens = [invite(app, client, f"ann-{i}") for i in range(3)]
    seen: dict[str, list[int]] = {t: [] for t in tokens}
    reasons = {}
    for round_ in range(10):
        for w, t in enumerate(tokens):
            data = fetch(client, t)
            if not data["tasks"]:
                reasons[t] = data["reason"]
                continue
            assert len(data["tasks"]) <= 2  # current + one preloaded
            task = data["tasks"][0]
            seen[t].append(item_of(app, task["token"]))
            assert answer(client, t, task["token"], JUDGE_OK, f"key-{w}-{round_:04d}").status_code == 201
    for items in seen.values():
        assert len(items) == len(set(items)), f"worker got an item twice: {items}"
    with app.app_context():
        per_item = dict(db.session.execute(select(Answer.item_id, func.count()).group_by(Answer.item_id)).all())
        assert sorted(per_item.values()) == [2, 2, 2, 2]
        assert db.session.get(Batch, batch) is not None
    assert sum(len(v) for v in seen.values()) == 8
    assert set(reasons.values()) <= {"batch_complete", "nothing_left_for_worker"}


def test_reservations_hold_slots_and_lapse_back_to_the_pool(app, client, cards):
    new_batch(app, cards(1), n=1)
    first, second = invite(app, client, "a"), invite(app, client, "b")
    held = fetch(client, first)["tasks"]
    assert len(held) == 1
    blocked = fetch(client, second)
    assert blocked["tasks"] == [] and blocked["reason"] == "all_reserved" and blocked["retry_after"]
    with app.app_context():
        row = db.session.scalar(select(Reservation))
        row.expires_at = utcnow() - timedelta(seconds=1)
        db.session.commit()
    assert len(fetch(client, second)["tasks"]) == 1


# ---------------------------------------------------------------------------------------------
# Idempotent submits and refusals


@pytest.mark.both_databases
def test_double_submit_and_replay_store_one_answer(app, client, cards):
    new_batch(app, cards(2), n=3)
    t = invite(app, client, "clicker")
    task = fetch(client, t)["tasks"][0]
    first = answer(client, t, task["token"], JUDGE_OK, "same-key-123")
    replay = answer(client, t, task["token"], JUDGE_OK, "same-key-123")
    other_key = answer(client, t, task["token"], {**JUDGE_OK, "inverted": True}, "other-key-456")
    assert first.status_code == 201 and first.get_json()["duplicate"] is False
    assert replay.status_code == 200 and replay.get_json() == {**first.get_json(), "duplicate": True}
    assert other_key.status_code == 409
    assert other_key.get_json()["error"]["message"] == "You already answered this task"
    assert count(app, Answer) == 1
    with app.app_context():
        assert db.session.scalar(select(Answer.payload)) == JUDGE_OK


def _state(app):  # type: ignore[no-untyped-def]
    with app.app_context():
        return (
            db.session.scalar(select(func.count()).select_from(Answer)),
            [(r.token, r.answered_at) for r in db.session.scalars(select(Reservation).order_by(Reservation.id))],
        )


@pytest.mark.parametrize(
    ("body", "status", "message"),
    [
        ('{"token": "x", "answer": ', 400, "malformed"),
        ("[1, 2]", 400, "JSON object body"),
        ('{"left": [NaN, 0, 100, 100], "right": [400, 0, 500, 100]}', 400, "finite numbers in the JSON body, got NaN"),
        ('{"left": [-5, 0, 100, 100], "right": [400, 0, 500, 100]}', 400, "inside the 604x200 image"),
        ('{"left": [0, 0, 1e300, 100], "right": [400, 0, 500, 100]}', 400, "inside the 604x200 image"),
        ('{"left": [0, 0, Infinity, 100], "right": [400, 0, 500, 100]}', 400, "finite numbers in the JSON body, got Infinity"),
        ('{"left": [100, 0, 10, 100], "right": [400, 0, 500, 100]}', 400, "x0 < x1"),
        ('{"left": [0, 0, 10, 10], "right": [400, 0, 500, 100]}', 400, "at least 16 x 16 pixels"),
        ('{"left": [0, 0, "a", 100], "right": [400, 0, 500, 100]}', 400, "four numbers"),
        ('{"left": [0, 0, 100, 100]}', 400, "right box"),
        ('{"left": [0, 0, 100, 100], "right": [400, 0, 500, 100], "extra": 1}', 400, "Unexpected fields"),
    ],
)
def test_bad_crop_answers_are_refused_and_change_nothing(app, client, cards, body, status, message):
    new_batch(app, cards(1), kind="crop", n=1)
    t = invite(app, client, "cropper")
    task = fetch(client, t, "crop")["tasks"][0]
    before = _state(app)
    raw = (
        body
        if body.startswith(('{"token', "["))
        else (f'{{"token": "{task["token"]}", "key": "bad-input-key", "answer": {body}}}')
    )
    response = api(client, "submit", t, data=raw, content_type="application/json")
    assert response.status_code == status, response.get_data(as_text=True)
    assert message in response.get_json()["error"]["message"]
    assert _state(app) == before
    good = answer(client, t, task["token"], {"left": [10, 5, 290, 195], "right": [310, 5, 598, 195.5]}, "good-key-1")
    assert good.status_code == 201


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        ({"is_stereo": "yes", "upside_down": False, "inverted": False}, "is_stereo to be true or false"),
        ({"is_stereo": True, "upside_down": False}, "inverted to be true or false"),
        ([True, False, False], "Expected a JSON object as the answer"),
    ],
)
def test_bad_judgements_are_refused(app, client, cards, payload, message):
    new_batch(app, cards(1), n=1)
    t = invite(app, client, "judge")
    task = fetch(client, t)["tasks"][0]
    response = answer(client, t, task["token"], payload, "judge-key-1")
    assert response.status_code == 400 and message in response.get_json()["error"]["message"]
    assert count(app, Answer) == 0


@pytest.mark.both_databases
def test_expired_and_foreign_reservations_are_refused(app, client, cards):
    new_batch(app, cards(2), n=2)
    alice, bob = invite(app, client, "alice"), invite(app, client, "bob")
    mine = fetch(client, alice)["tasks"][0]
    theirs = answer(client, bob, mine["token"], JUDGE_OK, "bob-steals-1")
    assert theirs.status_code == 403
    assert theirs.get_json()["error"]["message"] == "This task is reserved for another worker"
    with app.app_context():
        row = db.session.scalar(select(Reservation).where(Reservation.token == mine["token"]))
        row.expires_at = utcnow() - timedelta(minutes=1)
        db.session.commit()
    late = answer(client, alice, mine["token"], JUDGE_OK, "alice-late-1")
    assert late.status_code == 409 and "expired" in late.get_json()["error"]["message"]
    unknown = answer(client, alice, "no-such-task", JUDGE_OK, "alice-none-1")
    assert unknown.status_code == 404
    assert count(app, Answer) == 0


def test_api_needs_the_signed_token_and_json(app, client, cards):
    new_batch(app, cards(1), n=1)
    t = invite(app, client, "someone")
    assert api(client, "next", None, {}).status_code == 403  # the anti-forgery token is missing
    forged = api(client, "next", t[:-2] + "xx", {})
    assert forged.status_code == 403 and "Invalid worker token" in forged.get_json()["error"]["message"]
    form_post = client.post("/crowd/api/next", headers={"X-Crowd-Token": t}, data={"kind": "judge"})
    assert form_post.status_code == 415
    assert count(app, Reservation) == 0


def test_undo_withdraws_the_last_answer_and_reserves_it_again(app, client, cards):
    new_batch(app, cards(2), n=1)
    t = invite(app, client, "undoer")
    task = fetch(client, t)["tasks"][0]
    assert answer(client, t, task["token"], JUDGE_OK, "undo-key-1").status_code == 201
    undone = api(client, "undo", t, {})
    assert undone.status_code == 200 and undone.get_json()["task"]["token"] == task["token"]
    assert count(app, Answer) == 0
    again = answer(client, t, task["token"], {**JUDGE_OK, "upside_down": True}, "undo-key-2")
    assert again.status_code == 201
    with app.app_context():
        assert db.session.scalar(select(Answer.payload))["upside_down"] is True
    assert api(client, "undo", t, {}).status_code == 200
    assert api(client, "undo", t, {}).status_code == 409  # nothing left to undo


def test_task_image_is_served_by_reservation_token_only(app, client, cards):
    new_batch(app, cards(1), n=1)
    t = invite(app, client, "viewer")
    task = fetch(client, t)["tasks"][0]
    image = client.get(task["image_url"])
    assert image.status_code == 200 and image.mimetype == "image/jpeg" and image.data[:2] == b"\xff\xd8"
    assert client.get("/crowd/task/guessed/image").status_code == 404


# ---------------------------------------------------------------------------------------------
# Providers


def test_mturk_preview_disables_submit_and_may_be_framed_by_mturk(app, client, cards):
    new_batch(app, cards(1), n=1)
    page = client.get("/crowd/mturk?assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE&hitId=H1")
    html = page.get_data(as_text=True)
    assert page.status_code == 200
    assert re.search(r'<button type="submit" id="submit-answer" disabled', html)
    assert 'data-preview="true"' in html and 'data-worker-token=""' in html
    csp = page.headers["Content-Security-Policy"]
    assert "frame-ancestors 'self' https://www.mturk.com https://workersandbox.mturk.com" in csp
    assert "X-Frame-Options" not in page.headers
    assert count(app, Worker) == 0 and count(app, Reservation) == 0
    # Every other page stays unframeable.
    assert client.get("/auth/login").headers["X-Frame-Options"] == "SAMEORIGIN"


def test_mturk_assignment_posts_back_to_turk_submit_to(app, client, cards):
    new_batch(app, cards(1), n=1)
    url = "/crowd/mturk?assignmentId=A123&hitId=H1&workerId=W9&turkSubmitTo=https%3A%2F%2Fworkersandbox.mturk.com"
    page = client.get(url)
    html = page.get_data(as_text=True)
    assert page.status_code == 200 and "Set-Cookie" not in page.headers  # no reliance on cookies
    assert not re.search(r'id="submit-answer" disabled', html)
    t = TOKEN.search(html).group(1)
    task = fetch(client, t)["tasks"][0]
    stored = answer(client, t, task["token"], JUDGE_OK, "mturk-key-1")
    assert stored.status_code == 201
    assert stored.get_json()["finish"] == {
        "post": {"url": "https://workersandbox.mturk.com/mturk/externalSubmit", "fields": {"assignmentId": "A123"}}
    }
    evil = client.get("/crowd/mturk?assignmentId=A1&hitId=H&workerId=W&turkSubmitTo=https%3A%2F%2Fevil.example")
    assert evil.status_code == 400 and "turkSubmitTo" in evil.get_data(as_text=True)


def test_prolific_entry_and_completion_redirect(app, client, cards):
    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "C1A2B3"
    new_batch(app, cards(1), n=1)
    url = "/crowd/prolific?PROLIFIC_PID=pid-1&STUDY_ID=study-1&SESSION_ID=sess-1"
    t = TOKEN.search(client.get(url).get_data(as_text=True)).group(1)
    client.get(url)  # the same participant coming back is the same worker
    assert count(app, Worker) == 1
    done = client.get(f"/crowd/finish?t={t}")
    assert done.status_code == 303
    assert done.headers["Location"] == "https://app.prolific.com/submissions/complete?cc=C1A2B3"
    missing = client.get("/crowd/prolific?PROLIFIC_PID=pid-1")
    assert missing.status_code == 400 and "STUDY_ID, SESSION_ID" in missing.get_data(as_text=True)
    assert client.get("/crowd/finish?t=forged").status_code == 403


def test_invite_link_shows_progress_and_bad_links_404(app, client, cards):
    new_batch(app, cards(2), n=1)
    t = invite(app, client, "grace")
    task = fetch(client, t)["tasks"][0]
    answer(client, t, task["token"], JUDGE_OK, "grace-key-1")
    with app.app_context():
        link = db.session.scalar(select(Worker.token).where(Worker.external_id == "grace"))
    html = client.get(f"/crowd/invite/{link}").get_data(as_text=True)
    assert re.search(r'<strong id="answered">1</strong>', html)
    assert client.get("/crowd/invite/not-a-token").status_code == 404


# ---------------------------------------------------------------------------------------------
# Roles


@pytest.mark.parametrize(
    ("role", "cards_status", "batches_status"),
    [("annotator", 403, 403), ("curator", 200, 200), ("exporter", 200, 403), ("admin", 200, 200)],
)
def test_roles_on_staff_pages(client, as_role, role, cards_status, batches_status):
    as_role(role)
    assert client.get("/cards").status_code == cards_status
    assert client.get("/crowd/batches").status_code == batches_status


def test_anonymous_staff_page_redirects_to_login(client):
    response = client.get("/crowd/batches")
    assert response.status_code == 302 and "/auth/login" in response.headers["Location"]


def test_batches_page_shows_progress(app, client, cards, login):
    new_batch(app, cards(3), n=2)
    t = invite(app, client, "worker-one")
    task = fetch(client, t)["tasks"][0]
    answer(client, t, task["token"], JUDGE_OK, "progress-key")
    login("curator")
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert "<strong>1 of 6</strong> answers needed" in html and "1 cards reserved now" in html
    assert "invite:worker-one" in html
    assert "3 cards × 2 answers" in html and "0 gold cards" in html and "built-in method" not in html


# ---------------------------------------------------------------------------------------------
# Quality and aggregation


def _answer_all(app, client, tokens, kind, choose):  # type: ignore[no-untyped-def]
    """Each worker answers every task they get; ``choose(worker_index, card_id)`` is the answer."""
    for w, t in enumerate(tokens):
        for step in range(50):
            data = fetch(client, t, kind)
            if not data["tasks"]:
                break
            task = data["tasks"][0]
            with app.app_context():
                card = db.session.scalar(
                    select(BatchItem.card_id)
                    .join(Reservation, Reservation.item_id == BatchItem.id)
                    .where(Reservation.token == task["token"])
                )
            assert answer(client, t, task["token"], choose(w, card), f"sim-{w}-{step}-{kind}").status_code == 201


@pytest.mark.both_databases
def test_judge_aggregation_stores_approved_and_needs_curator(app, client, cards):
    *clear, split = cards(9)
    gold = {g: JUDGE_OK for g in cards(3)}
    batch = new_batch(app, [*clear, split], n=3, gold_rate=0.3, gold=gold)
    tokens = [invite(app, client, f"sim-{i}") for i in range(3)]

    # Everyone agrees on the 8 clear cards; on `split` two of three say upside-down.
    def choose(w, card):  # type: ignore[no-untyped-def]
        return {**JUDGE_OK, "upside_down": w != 0} if card == split else JUDGE_OK

    _answer_all(app, client, tokens, "judge", choose)
    from annotation.results import aggregate_batch

    with app.app_context():
        report = aggregate_batch(batch)
        rows = {a.card_id: a for a in db.session.scalars(select(Aggregate))}
    assert set(rows) == {*clear, split}
    assert (report.approved, report.needs_curator, report.pending, report.flagged_workers) == (8, 1, 0, 0)
    for card in clear:
        assert rows[card].state == "approved" and rows[card].confident is True and rows[card].label == JUDGE_OK
        assert rows[card].posterior["upside_down"][0] > 0.95 and rows[card].answers == 3
    assert rows[split].state == "needs_curator" and rows[split].label["upside_down"] is True
    assert 0.5 < rows[split].posterior["upside_down"][1] < 0.95
    assert rows[split].reasons.startswith("upside_down: posterior 0.")
    assert math.isclose(sum(rows[split].posterior["upside_down"]), 1.0)
    # Agreement over the 9 regular items: 8 unanimous, one split 2-1 (1 agreeing pair of 3).
    upside = report.agreement["upside_down"]
    assert math.isclose(upside["percent_agreement"], (8 + 1 / 3) / 9, rel_tol=1e-5)
    pi_yes = (2 / 3) / 9
    p_e = 2 * pi_yes * (1 - pi_yes)
    assert math.isclose(upside["gwet_ac1"], ((8 + 1 / 3) / 9 - p_e) / (1 - p_e), rel_tol=1e-5)
    assert report.agreement["is_stereo"]["percent_agreement"] == 1.0


def test_crop_aggregation_consensus_within_pixels_and_disputes(app, client, cards):
    agreed, disputed = cards(2)
    batch = new_batch(app, [agreed, disputed], kind="crop", n=3)
    tokens = [invite(app, client, f"box-{i}") for i in range(3)]
    truth = {"left": [10.0, 8.0, 290.0, 192.0], "right": [316.0, 8.0, 596.0, 192.0]}

    def choose(w, card):  # type: ignore[no-untyped-def]
        jitter = [0.0, 1.5, -1.0][w]
        if card == disputed and w > 0:
            return {"left": [100.0 * w, 20.0, 100.0 * w + 60.0, 80.0], "right": truth["right"]}
        return {h: [v + jitter for v in box] for h, box in truth.items()}

    _answer_all(app, client, tokens, "crop", choose)
    from annotation.results import aggregate_batch

    with app.app_context():
        report = aggregate_batch(batch)
        rows = {a.card_id: a for a in db.session.scalars(select(Aggregate))}
    assert (report.approved, report.needs_curator) == (1, 1)
    assert rows[agreed].state == "approved"
    for half in ("left", "right"):
        assert max(abs(a - b) for a, b in zip(rows[agreed].label[half], truth[half])) <= 1.5
    assert rows[disputed].state == "needs_curator" and "left box" in rows[disputed].reasons
    # Alpha compares within-card to between-card disagreement: with one wild box in three it
    # stays far from 1 on the left half.
    assert report.agreement["left"]["krippendorff_alpha"] < 0.5
    assert isinstance(report.agreement["right"]["krippendorff_alpha"], float)


def test_workers_failing_gold_are_flagged_and_no_longer_served(app, client, cards):
    app.config.update(KEYSTONE_CROWD_MIN_GOLD=3, KEYSTONE_CROWD_GOLD_THRESHOLD=0.7)
    regular = cards(6)
    gold_ids = cards(3)
    new_batch(app, regular, n=3, gold_rate=1.0, gold={g: JUDGE_OK for g in gold_ids})
    spammer = invite(app, client, "spammer")
    served = 0
    for step in range(20):
        data = fetch(client, spammer)
        if not data["tasks"]:
            assert data["reason"] == "worker_flagged"
            break
        task = data["tasks"][0]
        # Always "inverted": wrong on every gold card.
        r = answer(client, spammer, task["token"], {**JUDGE_OK, "inverted": True}, f"spam-key-{step:03d}")
        assert r.status_code == 201, r.get_data(as_text=True)
        served += 1
    with app.app_context():
        worker = db.session.scalar(select(Worker).where(Worker.external_id == "spammer"))
        assert worker.flagged is True
        flags = list(db.session.scalars(select(Answer.flagged).where(Answer.worker_id == worker.id)))
    assert served < 9 and all(flags) and len(flags) == served


# ---------------------------------------------------------------------------------------------
# CLI


@pytest.mark.parametrize("command", ["export", "aggregate"])
def test_cli_batch_ids_are_read_strictly(app, runner, cards, tmp_path: Path, command):
    from annotation.cli import crowd_group

    app.cli.add_command(crowd_group)
    ids = cards(1)
    for _ in range(10):  # batch 10 exists: `1_0` and a fullwidth digit would otherwise reach it
        new_batch(app, ids, n=1)
    out = ["--out", str(tmp_path / "out")] if command == "export" else []
    for hostile in ("1_0", "\uff11\uff10", "9223372036854775808", "0"):
        refused = runner.invoke(args=["crowd", command, hostile, *out])
        assert refused.exit_code == 2, (hostile, refused.output)
        assert "Expected a record id (ASCII digits, 1 to 2147483647), got" in refused.output
    assert not (tmp_path / "out").exists()
    done = runner.invoke(args=["crowd", command, "10", *out, "--json"])
    assert done.exit_code == 0, done.output
    assert json.loads(done.output)["batch"] == 10


def test_cli_card_ids_are_read_strictly(app, runner, cards):
    from annotation.cli import crowd_group

    app.cli.add_command(crowd_group)
    ids = cards(2)
    for hostile in (f"{ids[0]},1_0", "\uff11", f"{ids[0]} 9223372036854775808"):
        refused = runner.invoke(args=["crowd", "create-batch", "--cards", hostile])
        assert refused.exit_code == 2, (hostile, refused.output)
        assert "Invalid value for '--cards': Expected a record id" in refused.output
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Batch)) == 0
    created = runner.invoke(args=["crowd", "create-batch", "--cards", f"{ids[0]},{ids[1]}", "--gold-rate", "0", "--json"])
    assert created.exit_code == 0, created.output
    assert json.loads(created.output)["items"] == 2


def test_cli_create_invite_aggregate_export(app, runner, client, cards, tmp_path: Path):
    from annotation.cli import crowd_group

    app.cli.add_command(crowd_group)  # app/cli.py registers it on `keystone`
    review = cards(2, state="review")
    other = cards(1, state="pass")
    created = runner.invoke(
        args=["crowd", "create-batch", "--from-review", "--cards", str(other[0]), "--n", "1", "--gold-rate", "0", "--json"]
    )
    assert created.exit_code == 0, created.output
    doc = json.loads(created.output)
    assert doc["items"] == 3 and doc["answers_per_item"] == 1 and doc["gold_items"] == 0
    invited = runner.invoke(args=["crowd", "invite", "ada", "--json"])
    link = json.loads(invited.output)["link"]
    assert link.startswith("http://127.0.0.1:5000/crowd/invite/")
    assert runner.invoke(args=["crowd", "invite", "ada"]).exit_code == 1
    page = client.get(link.removeprefix("http://127.0.0.1:5000"))
    t = TOKEN.search(page.get_data(as_text=True)).group(1)
    _answer_all(app, client, [t], "judge", lambda w, card: JUDGE_OK)
    aggregated = runner.invoke(args=["crowd", "aggregate", str(doc["batch"]), "--json"])
    assert aggregated.exit_code == 0, aggregated.output
    assert json.loads(aggregated.output)["pending"] == 0
    out = tmp_path / "export"
    exported = runner.invoke(args=["crowd", "export", str(doc["batch"]), "--out", str(out), "--json"])
    assert exported.exit_code == 0, exported.output
    import pyarrow.parquet as pq

    assert pq.read_table(out / "answers.parquet").num_rows == 3
    assert (out / "aggregates.csv").read_text().count("\n") == 4  # header + 3 cards
    exported_rows = pq.read_table(out / "answers.parquet").to_pylist()
    assert set(review) <= {int(r["card_id"]) for r in exported_rows}
    with app.app_context():
        ada = db.session.scalar(select(Worker.id).where(Worker.external_id == "ada"))
    assert {r["session"] for r in exported_rows} == {f"invite-worker-{ada}"}  # the session each answer came from
    bad = runner.invoke(args=["crowd", "create-batch", "--cards", "99999"])
    assert bad.exit_code == 1 and "No card with id 99999" in bad.output


# ---------------------------------------------------------------------------------------------
# Pages and concurrency


def test_judge_and_crop_pages_are_keyboard_first_and_script_only_from_self(app, client, cards):
    new_batch(app, cards(1), n=1)
    t_page = client.get("/crowd/prolific?PROLIFIC_PID=p&STUDY_ID=s&SESSION_ID=x")
    html = t_page.get_data(as_text=True)
    assert 'data-key="n"' in html and 'data-key="f"' in html and 'data-key="i"' in html
    assert "<kbd>U</kbd>" in html and 'id="help"' in html and "<script>" not in html
    assert "script-src 'self'" in t_page.headers["Content-Security-Policy"]
    crop = client.get("/crowd/prolific?PROLIFIC_PID=p&STUDY_ID=s&SESSION_ID=x&kind=crop")
    crop_html = crop.get_data(as_text=True)
    assert crop.status_code == 200 and "annotation/crop.js" in crop_html and 'data-min-box="16"' in crop_html
    assert client.get("/crowd/prolific?PROLIFIC_PID=p&STUDY_ID=s&SESSION_ID=x&kind=paint").status_code == 400
    for name in ("judge.js", "crop.js", "crowd.css"):
        with client.get(f"/crowd/static/annotation/{name}") as static:
            assert static.status_code == 200


@pytest.mark.both_databases
def test_concurrent_workers_lose_and_duplicate_nothing(app, cards):
    import threading

    n, k_items, k_workers = 3, 8, 8
    new_batch(app, cards(k_items), n=n)
    tokens = [invite(app, app.test_client(), f"load-{i}") for i in range(k_workers)]
    statuses: list[int] = []
    lock = threading.Lock()

    def work(w: int) -> None:
        client = app.test_client()
        for step in range(k_items + 2):
            response = api(client, "next", tokens[w], {"kind": "judge"})
            got = response.get_json()
            with lock:
                statuses.append(response.status_code)
            if not got or not got.get("tasks"):
                return
            response = answer(client, tokens[w], got["tasks"][0]["token"], JUDGE_OK, f"load-{w}-{step:03d}")
            with lock:
                statuses.append(response.status_code)

    threads = [threading.Thread(target=work, args=(w,)) for w in range(k_workers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not any(s >= 500 for s in statuses), statuses
    with app.app_context():
        per_item = dict(db.session.execute(select(Answer.item_id, func.count()).group_by(Answer.item_id)).all())
        pairs = db.session.execute(select(Answer.item_id, Answer.worker_id)).all()
    assert sorted(per_item.values()) == [n] * k_items  # none lost, none beyond N
    assert len(pairs) == len(set(pairs)) == n * k_items


# ---------------------------------------------------------------------------------------------
# Sessions: a participant id is not a credential


def prolific(client, pid: str, session: str, study: str = "study-1", address: str = "192.0.2.1"):  # type: ignore[no-untyped-def]
    return client.get(
        f"/crowd/prolific?PROLIFIC_PID={pid}&STUDY_ID={study}&SESSION_ID={session}", environ_overrides={"REMOTE_ADDR": address}
    )


def prolific_token(client, pid: str, session: str, **kwargs) -> str:  # type: ignore[no-untyped-def]
    page = prolific(client, pid, session, **kwargs)
    assert page.status_code == 200, page.get_data(as_text=True)
    return TOKEN.search(page.get_data(as_text=True)).group(1)


@pytest.mark.both_databases
def test_a_borrowed_participant_id_cannot_see_undo_or_complete_the_first_sessions_work(app, client, cards):
    from annotation.models import CrowdSession

    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "C0DE"
    new_batch(app, cards(4), n=2)
    first = prolific_token(client, "pid-victim", "session-a")
    (task, preloaded) = fetch(client, first)["tasks"]
    assert answer(client, first, task["token"], JUDGE_OK, "victim-key-1").status_code == 201
    answered_item = item_of(app, task["token"])

    # Someone who read the participant id opens their own session under it.
    page = prolific(client, "pid-victim", "session-b", address="198.51.100.7")
    assert page.status_code == 200 and re.search(r'<strong id="answered">0</strong>', page.get_data(as_text=True))
    borrowed = TOKEN.search(page.get_data(as_text=True)).group(1)
    refused = api(client, "undo", borrowed, {})
    assert refused.status_code == 409 and refused.get_json()["error"]["message"] == "There is no answer to undo"
    stolen = answer(client, borrowed, preloaded["token"], JUDGE_OK, "thief-key-01")
    assert stolen.status_code == 403 and "another session" in stolen.get_json()["error"]["message"]
    replayed = answer(client, borrowed, task["token"], JUDGE_OK, "victim-key-1")
    assert replayed.status_code in (403, 409)
    theirs = fetch(client, borrowed)
    # Still one worker for the N-answers rule: never the item this participant answered or holds.
    assert theirs["answered"] == 0 and len(theirs["tasks"]) == 2
    assert {item_of(app, t["token"]) for t in theirs["tasks"]}.isdisjoint({answered_item, item_of(app, preloaded["token"])})
    assert {t["token"] for t in theirs["tasks"]}.isdisjoint({task["token"], preloaded["token"]})
    assert client.get(f"/crowd/finish?t={borrowed}").status_code == 303
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Worker)) == 1
        completed = dict(db.session.execute(select(CrowdSession.external_id, CrowdSession.completed_at)).all())
        answers = db.session.execute(select(Answer.item_id, Answer.idempotency_key)).all()
    assert completed["session-a"] is None and completed["session-b"] is not None
    assert answers == [(answered_item, "victim-key-1")]  # the first session's answer survived

    # The first session works as before: its progress, its preloaded task, its own undo.
    again = prolific(client, "pid-victim", "session-a")
    assert re.search(r'<strong id="answered">1</strong>', again.get_data(as_text=True))
    mine = fetch(client, first)
    assert mine["answered"] == 1 and mine["tasks"][0]["token"] == preloaded["token"]
    undone = api(client, "undo", first, {})
    assert undone.status_code == 200 and undone.get_json()["task"]["token"] == task["token"]
    assert answer(client, first, task["token"], {**JUDGE_OK, "inverted": True}, "victim-key-2").status_code == 201

    # A session key stays with the participant that opened it.
    hijack = prolific(client, "pid-other", "session-a")
    assert hijack.status_code == 409 and "another participant" in hijack.get_data(as_text=True)
    other_study = prolific(client, "pid-victim", "session-a", study="study-2")
    assert other_study.status_code == 409 and "another study" in other_study.get_data(as_text=True)


@pytest.mark.both_databases
def test_a_second_mturk_assignment_of_one_worker_cannot_undo_the_first(app, client, cards):
    new_batch(app, cards(3), n=2)
    url = "/crowd/mturk?assignmentId={}&hitId=H1&workerId=W7&turkSubmitTo=https%3A%2F%2Fwww.mturk.com"
    first = TOKEN.search(client.get(url.format("A-1")).get_data(as_text=True)).group(1)
    task = fetch(client, first)["tasks"][0]
    assert answer(client, first, task["token"], JUDGE_OK, "turk-key-01").status_code == 201
    second = TOKEN.search(client.get(url.format("A-2")).get_data(as_text=True)).group(1)
    assert api(client, "undo", second, {}).status_code == 409
    assert count(app, Answer) == 1
    assert api(client, "undo", first, {}).status_code == 200
    assert count(app, Answer) == 0


@pytest.mark.both_databases
def test_new_sessions_are_limited_per_address_and_per_study(app, client, cards):
    from annotation.models import CrowdSession

    new_batch(app, cards(1), n=1)
    # The default limit: the probe's 100 anonymous visits from one address make 20 workers, not 100.
    statuses = [prolific(client, f"probe-{i}", f"probe-session-{i}").status_code for i in range(100)]
    assert statuses == [200] * 20 + [429] * 80
    assert count(app, Worker) == 20
    refused = prolific(client, "probe-x", "probe-session-x")
    assert refused.status_code == 429
    retry = int(refused.headers["Retry-After"])
    assert 3590 <= retry <= 3600
    assert "Too many new sessions from your network address" in refused.get_data(as_text=True)
    as_json = client.get(
        "/crowd/prolific?PROLIFIC_PID=j&STUDY_ID=study-1&SESSION_ID=j",
        headers={"Accept": "application/json"},
        environ_overrides={"REMOTE_ADDR": "192.0.2.1"},
    )
    assert as_json.status_code == 429 and as_json.get_json()["error"]["code"] == 429
    # Reopening a session already made is never limited; another address is not limited by this one.
    assert prolific(client, "probe-3", "probe-session-3").status_code == 200
    assert prolific(client, "elsewhere", "elsewhere-1", address="203.0.113.9").status_code == 200

    # Per study, across addresses.
    app.config["KEYSTONE_CROWD_SESSIONS_PER_STUDY"] = 3
    opened = [
        prolific(client, f"s-{i}", f"s-session-{i}", study="small", address=f"198.51.100.{i}").status_code for i in range(4)
    ]
    assert opened == [200, 200, 200, 429]
    assert "in this study" in prolific(client, "s-9", "s-9", study="small", address="198.51.100.99").get_data(as_text=True)
    assert prolific(client, "s-9", "s-9", study="other", address="198.51.100.99").status_code == 200

    # The window slides: once the address's sessions are older than it, new ones open again.
    with app.app_context():
        for row in db.session.scalars(select(CrowdSession)):
            row.created_at = row.created_at - timedelta(hours=2)
        db.session.commit()
    assert prolific(client, "probe-y", "probe-session-y").status_code == 200


@pytest.mark.both_databases
def test_a_flagged_participant_stays_flagged_in_new_sessions_and_new_ids_from_its_address(app, client, cards, login):
    app.config.update(KEYSTONE_CROWD_MIN_GOLD=3, KEYSTONE_CROWD_GOLD_THRESHOLD=0.7)
    new_batch(app, cards(6), n=3, gold_rate=1.0, gold={g: JUDGE_OK for g in cards(3)})
    spam_address = "192.0.2.66"
    spammer = prolific_token(client, "spammer", "spam-1", address=spam_address)
    for step in range(20):
        data = fetch(client, spammer)
        if not data["tasks"]:
            break
        assert (
            answer(client, spammer, data["tasks"][0]["token"], {**JUDGE_OK, "inverted": True}, f"spam-key-{step:03d}").status_code
            == 201
        )
    assert data["reason"] == "worker_flagged"

    # The same participant id in a new session, from anywhere: still flagged.
    again = prolific_token(client, "spammer", "spam-2", address="203.0.113.50")
    assert fetch(client, again) == {"tasks": [], "answered": 0, "reason": "worker_flagged", "retry_after": None, "positions": {}}
    # A new participant id in the same study from the spammer's address gets no work either.
    renamed = prolific_token(client, "spammer-renamed", "spam-3", address=spam_address)
    assert fetch(client, renamed)["reason"] == "worker_flagged"
    # Not prevented elsewhere: another study from that address, or the same study from another address.
    assert fetch(client, prolific_token(client, "next-door", "nd-1", study="study-2", address=spam_address))["tasks"]
    assert fetch(client, prolific_token(client, "honest", "h-1", address="203.0.113.51"))["tasks"]
    with app.app_context():
        flags = dict(db.session.execute(select(Worker.external_id, Worker.flagged)).all())
    assert flags == {"spammer": True, "spammer-renamed": False, "next-door": False, "honest": False}
    from annotation.progress import worker_progress

    with app.app_context():
        staff = {row["name"]: row for row in worker_progress()}
    assert (staff["spammer"]["sessions"], staff["spammer"]["served"]) == (2, False)
    assert (staff["spammer-renamed"]["refused_sessions"], staff["honest"]["refused_sessions"]) == (1, 0)
    login("curator")
    assert "1 refused (address of a flagged worker)" in client.get("/crowd/batches").get_data(as_text=True)


def test_one_ipv6_subscriber_counts_as_one_client_and_studies_can_be_closed(app, client, cards):
    from annotation.sessions import client_network

    assert client_network("2001:db8:1:2:3:4:5:6") == client_network("2001:db8:1:2:ffff::1") == "2001:db8:1:2::/64"
    assert client_network("::ffff:192.0.2.9") == "192.0.2.9" and client_network("192.0.2.9") == "192.0.2.9"
    new_batch(app, cards(1), n=1)
    app.config["KEYSTONE_CROWD_SESSIONS_PER_ADDRESS"] = 2
    opened = [prolific(client, f"v6-{i}", f"v6-session-{i}", address=f"2001:db8:1:2::{i + 1:x}").status_code for i in range(3)]
    assert opened == [200, 200, 429]
    assert prolific(client, "v6-x", "v6-session-x", address="2001:db8:1:3::1").status_code == 200  # another /64
    app.config["KEYSTONE_CROWD_STUDIES"] = "study-open, study-2"
    closed = prolific(client, "p", "closed-1", study="made-up", address="198.51.100.1")
    assert closed.status_code == 404 and "not open here" in closed.get_data(as_text=True)
    assert prolific(client, "p", "open-1", study="study-open", address="198.51.100.1").status_code == 200
    assert count(app, Worker) == 4


@pytest.mark.both_databases
def test_the_address_limit_holds_when_visitors_arrive_at_once(app, cards):
    import threading

    new_batch(app, cards(1), n=1)
    app.config["KEYSTONE_CROWD_SESSIONS_PER_ADDRESS"] = 3
    statuses: list[int] = []
    lock = threading.Lock()
    start = threading.Barrier(8)

    def visit(i: int) -> None:
        client = app.test_client()
        start.wait()
        status = prolific(client, f"rush-{i}", f"rush-session-{i}").status_code
        with lock:
            statuses.append(status)

    threads = [threading.Thread(target=visit, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert sorted(statuses) == [200] * 3 + [429] * 5
    assert count(app, Worker) == 3


@pytest.mark.both_databases
def test_invited_annotators_keep_their_work_across_the_sessions_migration(app, client, cards):
    from alembic import command

    from app.schema import alembic_config, upgrade

    new_batch(app, cards(3), n=1)
    before = invite(app, client, "mid-way")
    task = fetch(client, before)["tasks"][0]
    assert answer(client, before, task["token"], JUDGE_OK, "mid-way-key-1").status_code == 201
    with app.app_context():
        link = db.session.scalar(select(Worker.token).where(Worker.external_id == "mid-way"))
        db.session.remove()
        config = alembic_config(db.engine)
        with db.engine.begin() as connection:
            config.attributes["connection"] = connection
            command.downgrade(config, "0004")
        upgrade(db.engine)
        assert db.session.scalar(select(func.count()).select_from(Answer).where(Answer.session_id.is_(None))) == 0
    page = client.get(f"/crowd/invite/{link}").get_data(as_text=True)
    assert re.search(r'<strong id="answered">1</strong>', page)
    after = TOKEN.search(page).group(1)
    undone = api(client, "undo", after, {})
    assert undone.status_code == 200 and undone.get_json()["task"]["token"] == task["token"]


# ---------------------------------------------------------------------------------------------
# A token ends with its session (/crowd/finish) and after KEYSTONE_CROWD_TOKEN_HOURS; the worker's
# link then leads back in (invite: a new session) or says the session is finished.


def _refused(response, status: int, words: str) -> None:  # type: ignore[no-untyped-def]
    assert response.status_code == status, response.get_data(as_text=True)
    error = response.get_json()["error"]
    assert error["code"] == status and words in error["message"]


def _reopen(app, client, name: str) -> str:  # type: ignore[no-untyped-def]
    """Open the invited annotator NAME's link again; the fresh token its page carries."""
    with app.app_context():
        link = db.session.query(Worker).filter_by(external_id=name).one().token
    page = client.get(f"/crowd/invite/{link}")
    assert page.status_code == 200
    return TOKEN.search(page.get_data(as_text=True)).group(1)


@pytest.mark.both_databases
def test_a_finished_session_takes_no_more_calls_and_the_invite_link_starts_a_new_one(app, client, cards):
    new_batch(app, cards(4), n=1)
    t = invite(app, client, "finisher")
    first, second = fetch(client, t)["tasks"][:2]
    assert answer(client, t, first["token"], JUDGE_OK, "finish-key-1").status_code == 201
    assert client.get(f"/crowd/finish?t={t}").status_code == 200
    assert client.get(f"/crowd/finish?t={t}").status_code == 200  # a reload of the finish page

    _refused(api(client, "next", t, {"kind": "judge"}), 410, "session is finished")
    _refused(answer(client, t, second["token"], JUDGE_OK, "finish-key-2"), 410, "session is finished")
    _refused(api(client, "undo", t, {}), 410, "session is finished")
    _refused(api(client, "renew", t, {"token": second["token"]}), 410, "session is finished")

    fresh = _reopen(app, client, "finisher")
    assert fetch(client, fresh)["tasks"]
    with app.app_context():
        sessions = db.session.query(CrowdSession).filter_by(provider="invite").order_by(CrowdSession.id).all()
        mine = [s for s in sessions if s.worker.external_id == "finisher"]
        assert [s.completed_at is not None for s in mine] == [True, False]
        assert mine[1].external_id == f"{mine[0].external_id}-2"
    _refused(api(client, "undo", t, {}), 410, "session is finished")  # the old page stays refused


@pytest.mark.both_databases
def test_finishing_a_session_gives_its_held_cards_back_at_once(app, client, cards):
    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "C1A2B3"
    new_batch(app, cards(2), n=1)
    url = "/crowd/prolific?PROLIFIC_PID=pid-7&STUDY_ID=study-7&SESSION_ID=sess-7"
    t = TOKEN.search(client.get(url).get_data(as_text=True)).group(1)
    held = fetch(client, t)["tasks"]
    assert len(held) == 2
    other = invite(app, client, "next-in-line")
    assert fetch(client, other)["tasks"] == []  # both cards are held
    assert client.get(f"/crowd/finish?t={t}").status_code == 303
    assert len(fetch(client, other)["tasks"]) == 2  # given back by the finish


def test_a_finished_prolific_session_says_so_when_its_link_is_opened_again(app, client, cards):
    app.config["KEYSTONE_PROLIFIC_COMPLETION_CODE"] = "C1A2B3"
    new_batch(app, cards(2), n=1)
    url = "/crowd/prolific?PROLIFIC_PID=pid-9&STUDY_ID=study-9&SESSION_ID=sess-9"
    t = TOKEN.search(client.get(url).get_data(as_text=True)).group(1)
    assert client.get(f"/crowd/finish?t={t}").status_code == 303
    _refused(api(client, "next", t, {"kind": "judge"}), 410, "session is finished")
    back = client.get(url)
    assert back.status_code == 410 and "start a new session from the study page" in back.get_data(as_text=True)
    other = client.get("/crowd/prolific?PROLIFIC_PID=pid-9&STUDY_ID=study-9&SESSION_ID=sess-10")
    assert other.status_code == 200 and TOKEN.search(other.get_data(as_text=True)).group(1)


def test_tokens_expire_after_the_configured_lifetime_and_the_link_signs_a_fresh_one(app, client, cards, monkeypatch):
    import annotation.providers as providers

    app.config["KEYSTONE_CROWD_TOKEN_HOURS"] = 2
    new_batch(app, cards(2), n=1)
    clock = [1_000_000.0]
    monkeypatch.setattr(providers, "_now", lambda: clock[0])
    t = invite(app, client, "sleeper")
    task = fetch(client, t)["tasks"][0]
    clock[0] += 2 * 3600 - 5
    assert fetch(client, t)["tasks"]  # still within its lifetime
    clock[0] += 10
    _refused(api(client, "next", t, {"kind": "judge"}), 401, "has expired")
    _refused(answer(client, t, task["token"], JUDGE_OK, "late-key-1"), 401, "open your link again")
    _refused(api(client, "undo", t, {}), 401, "has expired")
    _refused(api(client, "renew", t, {"token": task["token"]}), 401, "has expired")
    assert fetch(client, _reopen(app, client, "sleeper"))["tasks"]


def test_the_token_lifetime_has_a_default_of_hours(app):
    from annotation.crowd_settings import DEFAULT_TOKEN_HOURS, token_lifetime_s

    with app.app_context():
        assert 1 <= DEFAULT_TOKEN_HOURS <= 24 and token_lifetime_s() == DEFAULT_TOKEN_HOURS * 3600


# ---------------------------------------------------------------------------------------------
# Creating a batch from the staff form is idempotent: the form's one-time key makes one batch


def _new_batch_form(client) -> dict[str, str]:  # type: ignore[no-untyped-def]
    html = client.get("/crowd/batches").get_data(as_text=True)
    form = html[html.index('id="new-batch"') :]
    fields = dict(re.findall(r'name="(csrf_token|request_key)" value="([^"]*)"', form))
    return {"csrf_token": fields["csrf_token"], "request_key": fields.get("request_key", "")}


@pytest.mark.both_databases
def test_four_identical_create_batch_submits_make_one_batch(app, client, cards, login, post_at_once):

    ids = cards(3)
    login("curator")
    form = {**_new_batch_form(client), "cards": ",".join(map(str, ids)), "kind": "judge", "answers_per_item": "2"}
    answers = post_at_once("/crowd/batches/new", form, 4)
    assert sorted(r.status_code for r in answers) == [303] * 4
    assert count(app, Batch) == 1
    with app.app_context():
        batch = db.session.scalar(select(Batch.id))
    again = client.post("/crowd/batches/new", data=form, follow_redirects=True)  # a resubmit later on
    assert again.status_code == 200 and count(app, Batch) == 1
    assert f"This form was already submitted: it made batch {batch}, so no new batch was created" in again.get_data(as_text=True)
    assert any(r.headers["Location"].endswith(f"#batch-{batch}") for r in answers)

    fresh = {**form, **_new_batch_form(client)}  # the form filled in again: a new key, a new batch
    assert client.post("/crowd/batches/new", data=fresh).status_code == 303 and count(app, Batch) == 2


def test_create_batch_from_the_cli_is_not_deduplicated(app, runner, cards):
    ids = ",".join(map(str, cards(2)))
    for _ in range(2):
        result = runner.invoke(args=["crowd", "create-batch", "--cards", ids, "--n", "1", "--gold-rate", "0"])
        assert result.exit_code == 0, result.output
    assert count(app, Batch) == 2

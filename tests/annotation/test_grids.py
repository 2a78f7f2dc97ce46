"""Confirm grids end to end over the test client: cards the orientation step proposed with a
narrow margin are queued for grids (not judge tasks), a grid hides gold, taps are stored once
however often a grid is posted, aggregated per flag, and become the orientation the pipeline
uses (a curator's override still wins flag by flag); workers who miss gold are flagged; bad
posts are 4xx with a sentence."""

from __future__ import annotations

import json
import re

import pytest
from sqlalchemy import select

from annotation.models import Answer, Batch, BatchItem, Reservation, Worker
from app.cli import cli
from core.db import db

pytestmark = pytest.mark.both_databases

TOKEN = re.compile(r'data-worker-token="([^"]*)"')
FLAGS = ("upside_down", "inverted", "swapped")
NONE = dict.fromkeys(FLAGS, False)


def _orientation(outcome: str, proposed: dict, confidence: float) -> dict:
    return {
        "decision": outcome,
        "confidence": confidence,
        "proposed": proposed,
        "flags": {f: {"p": float(proposed[f]), "decided": outcome == "auto", "value": proposed[f]} for f in FLAGS},
    }


@pytest.fixture
def grid_world(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    """Six cards the step wants confirmed (card 1 proposed upside down) and four it decided
    with a wide margin (gold material); returns ``{"confirm": [ids], "known": [ids]}``."""
    base = card_image()
    ids: dict[str, list[int]] = {"confirm": [], "known": []}
    for i in range(10):
        image = base.copy()
        image[0, 0, 0] = i  # distinct content hashes
        card_id = make_card(image, state="pass")
        add_stage_result(card_id, "filter", outcome="pass")
        group = "confirm" if i < 6 else "known"
        proposed = {**NONE, "upside_down": i == 1}
        metrics = _orientation("confirm" if group == "confirm" else "auto", proposed, 0.7 if group == "confirm" else 0.999)
        add_stage_result(card_id, "orientation", outcome=metrics["decision"], metrics=metrics, param_hash="orient0123456789")
        ids[group].append(card_id)
    app.config.update(KEYSTONE_CROWD_GRID_SIZE=8, KEYSTONE_CROWD_GRID_GOLD=2)
    return ids


def _cards(runner) -> dict[int, dict]:  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, ["cards", "--json"])
    assert result.exit_code == 0, result.output
    return {card["id"]: card for card in json.loads(result.stdout)["cards"]}


def _worker(app, client, name: str) -> str:  # type: ignore[no-untyped-def]
    from annotation.providers import InviteProvider

    with app.app_context():
        link = f"/crowd/invite/{InviteProvider.invite(name).token}"
    html = client.get(link + "?kind=confirm").get_data(as_text=True)
    assert "annotation/grid.js" in html
    return TOKEN.search(html).group(1)  # type: ignore[union-attr]


def _api(client, path: str, token: str, body):  # type: ignore[no-untyped-def]
    return client.post(f"/crowd/api/{path}", headers={"X-Crowd-Token": token}, json=body)


def _items(app, tokens: list[str]) -> dict[str, BatchItem]:  # type: ignore[no-untyped-def]
    with app.app_context():
        rows = db.session.execute(
            select(Reservation.token, BatchItem)
            .join(BatchItem, Reservation.item_id == BatchItem.id)
            .where(Reservation.token.in_(tokens))
        ).all()
        for _, item in rows:
            db.session.expunge(item)
        return {token: item for token, item in rows}


def _create_batch(runner, n: int = 2) -> dict:  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, ["crowd", "create-batch", "--from-orientation", "--kind", "confirm", "--n", str(n), "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def _taps(items: dict[str, BatchItem], wrong_on: dict[int, str], gold_right: bool = True) -> list[dict]:
    """Answers for a grid: gold answered right (or each gold inverted), ``wrong_on`` cards tapped on one flag."""
    answers = []
    for token, item in items.items():
        if item.is_gold:
            taps = dict(item.gold_answer) if gold_right else {f: not v for f, v in item.gold_answer.items()}
        else:
            taps = {**NONE, **({wrong_on[item.card_id]: True} if item.card_id in wrong_on else {})}
        answers.append({"token": token, "taps": taps})
    return answers


def test_confirm_cards_go_to_grids_and_the_crowds_taps_decide_them(app, client, runner, grid_world, make_person, tmp_path):  # type: ignore[no-untyped-def]
    from annotation.batches import confirm_gold_needed, orientation_queue_card_ids

    confirm, known = grid_world["confirm"], grid_world["known"]
    before = _cards(runner)
    for card_id in confirm:
        assert before[card_id]["orientation"]["decided_by"] is None
        assert before[card_id]["stages"]["judge"] == {
            "status": "pending",
            "outcome": None,
            "reason": "waiting for people (a grid confirmation)",
            "metrics": {},
        }
    assert all(before[k]["orientation"]["decided_by"] == "auto" for k in known)
    with app.app_context():
        assert orientation_queue_card_ids() == []  # confirm cards never go to one-card judge tasks
        # Enough gold for every grid a worker could be given (grids of 8 with 2 gold), at least 4.
        assert (confirm_gold_needed(6), confirm_gold_needed(100)) == (4, 34)

    # Three answers a card: with six cards a batch gives Dawid-Skene little to learn each worker
    # from (two answers reach posterior 0.89-0.97 here, but 0.99 over grids of 30 cards).
    doc = _create_batch(runner, n=3)
    assert doc["items"] == 6 and doc["gold_items"] == 4
    again = runner.invoke(cli, ["crowd", "create-batch", "--from-orientation", "--kind", "confirm", "--json"])
    assert again.exit_code == 2 and "no cards" in again.output  # on their way already
    with app.app_context():
        gold = db.session.scalars(select(BatchItem).where(BatchItem.batch_id == doc["batch"], BatchItem.is_gold)).all()
        # Gold shows each known card wrong on one flag in turn, or right; the known truth is no flag.
        assert sorted(tuple(f for f in FLAGS if g.shown[f]) for g in gold) == [(), ("inverted",), ("swapped",), ("upside_down",)]
        assert all(g.gold_answer == g.shown for g in gold)

    # Card 1 is shown upside down as proposed and the crowd taps "upside down"; card 2's depth
    # is inside out; the rest are confirmed with no tap at all.
    wrong = {confirm[1]: "upside_down", confirm[2]: "swapped"}
    for name in ("ada", "bob", "cy"):
        token = _worker(app, client, name)
        grid = _api(client, "grid", token, {}).get_json()
        tokens = [c["token"] for c in grid["cards"]]
        assert len(tokens) == 8
        again = _api(client, "grid", token, {}).get_json()  # a reload shows the same grid
        assert sorted(c["token"] for c in again["cards"]) == sorted(tokens)
        items = _items(app, tokens)
        assert sum(i.is_gold for i in items.values()) == 2 and {i.card_id for i in items.values() if not i.is_gold} == set(
            confirm
        )
        picture = client.get(grid["cards"][0]["picture_url"])
        assert picture.status_code == 200 and picture.mimetype == "image/jpeg" and picture.data[:2] == b"\xff\xd8"
        assert client.get(grid["cards"][0]["picture_url"], headers={"If-None-Match": picture.headers["ETag"]}).status_code == 304
        answers = _taps(items, wrong)
        first = _api(client, "grid/submit", token, {"key": f"grid-{name}-1", "answers": answers})
        assert first.status_code == 201, first.get_json()
        assert first.get_json() | {"answered": 0} == {"stored": 8, "duplicates": 0, "refused": [], "answered": 0}
        repeat = _api(client, "grid/submit", token, {"key": f"grid-{name}-1", "answers": answers})
        assert repeat.status_code == 200 and repeat.get_json()["duplicates"] == 8 and repeat.get_json()["stored"] == 0
    with app.app_context():
        assert db.session.scalar(select(db.func.count()).select_from(Answer)) == 24
        assert not any(w.flagged for w in db.session.scalars(select(Worker)))

    aggregated = runner.invoke(cli, ["crowd", "aggregate", str(doc["batch"]), "--json"])
    assert aggregated.exit_code == 0, aggregated.output
    assert json.loads(aggregated.stdout)["approved"] == 6, aggregated.stdout

    exported = runner.invoke(cli, ["crowd", "export", str(doc["batch"]), "--out", str(tmp_path / "export"), "--json"])
    assert exported.exit_code == 0, exported.output
    assert "upside_down" in (tmp_path / "export" / "aggregates.csv").read_text()

    after = _cards(runner)
    # Card 1 was proposed upside down; the crowd tapped it: it is not. Card 2: exchanged.
    assert {f: after[confirm[1]]["orientation"][f] for f in FLAGS} == NONE
    assert {f: after[confirm[2]]["orientation"][f] for f in FLAGS} == {**NONE, "swapped": True}
    for card_id in confirm:
        assert after[card_id]["orientation"]["decided_by"] == "crowd"
        assert after[card_id]["stages"]["judge"]["status"] == "skipped"
        assert "crowd confirmation" in after[card_id]["stages"]["judge"]["reason"]
        assert (
            after[card_id]["stages"]["rectify"]["reason"] is None
            or "undecided" not in after[card_id]["stages"]["rectify"]["reason"]
        )
    assert {f: after[confirm[0]]["orientation"][f] for f in FLAGS} == NONE

    # A curator's override still wins, flag by flag.
    from core.models import Person
    from review.orientation import override_orientation

    curator = make_person("curator")
    with app.app_context():
        override_orientation(confirm[2], {"swapped": False}, curator=db.session.get(Person, curator.id), note="looked at it")
    card = _cards(runner)[confirm[2]]["orientation"]
    assert card["swapped"] is False and card["decided_by"] == "curator"


def test_a_worker_who_misses_gold_is_flagged_like_a_spammer(app, client, runner, grid_world):  # type: ignore[no-untyped-def]
    app.config.update(KEYSTONE_CROWD_GRID_GOLD=3, KEYSTONE_CROWD_GRID_SIZE=9)
    doc = _create_batch(runner, n=3)
    token = _worker(app, client, "careless")
    grid = _api(client, "grid", token, {}).get_json()
    items = _items(app, [c["token"] for c in grid["cards"]])
    assert sum(i.is_gold for i in items.values()) == 3
    response = _api(client, "grid/submit", token, {"key": "careless-1", "answers": _taps(items, {}, gold_right=False)})
    assert response.status_code in (200, 201), response.get_json()
    with app.app_context():
        worker = db.session.scalar(select(Worker).where(Worker.external_id == "careless"))
        assert worker.flagged
        answers = db.session.scalars(select(Answer).where(Answer.worker_id == worker.id)).all()
        assert answers and all(a.flagged for a in answers)  # they fill no slot and leave aggregation
        batch = db.session.get(Batch, doc["batch"])
        assert all(it.answers == 0 for it in batch.items if not it.is_gold)
    refused = _api(client, "grid", token, {}).get_json()
    assert refused["cards"] == [] and refused["reason"] == "worker_flagged"


def test_bad_grid_posts_are_refused_with_a_reason(app, client, runner, grid_world):  # type: ignore[no-untyped-def]
    _create_batch(runner)
    token = _worker(app, client, "ada")
    other = _worker(app, client, "bob")
    grid = _api(client, "grid", token, {}).get_json()
    first = grid["cards"][0]["token"]
    good = {"token": first, "taps": NONE}
    cases = [
        ({"answers": [good]}, 400, "idempotency key"),
        ({"key": "k" * 41, "answers": [good]}, 400, "idempotency key"),
        ({"key": "grid-key-1", "answers": "all fine"}, 400, "list"),
        ({"key": "grid-key-1", "answers": []}, 400, "list"),
        ({"key": "grid-key-1", "answers": [good] * 49}, 400, "list"),
        ({"key": "grid-key-1", "answers": [{"taps": NONE}]}, 400, "token"),
        ({"key": "grid-key-1", "answers": [{"token": first, "taps": {**NONE, "sideways": True}}]}, 400, "sideways"),
        ({"key": "grid-key-1", "answers": [{"token": first, "taps": {**NONE, "inverted": "yes"}}]}, 400, "inverted"),
        ({"key": "grid-key-1", "answers": [{"token": first, "taps": {"inverted": True}}]}, 400, "upside_down"),
        ({"key": "grid-key-1", "answers": [good, good]}, 400, "once"),
        ({"key": "grid-key-1", "answers": [{"token": "no-such-token", "taps": NONE}]}, 404, "No such task"),
    ]
    for body, status, words in cases:
        response = _api(client, "grid/submit", token, body)
        assert response.status_code == status, (body, response.get_json())
        assert words in response.get_json()["error"]["message"], (body, response.get_json())
    # Another worker cannot answer this grid; no token, no JSON: refused too.
    assert _api(client, "grid/submit", other, {"key": "grid-key-2", "answers": [good]}).status_code == 403
    assert client.post("/crowd/api/grid/submit", json={"key": "grid-key-3", "answers": [good]}).status_code == 403
    plain = client.post("/crowd/api/grid/submit", headers={"X-Crowd-Token": token}, data="key=1")
    assert plain.status_code in (400, 415)
    assert _api(client, "next", token, {"kind": "confirm"}).status_code == 400  # grids only
    assert client.get("/crowd/task/no-such-token/grid.jpg").status_code == 404
    with app.app_context():
        assert db.session.scalar(select(db.func.count()).select_from(Answer)) == 0  # nothing stored by a bad post


def test_curators_make_a_confirm_batch_and_reach_the_grid_from_the_crowd_pages(  # type: ignore[no-untyped-def]
    app, client, runner, grid_world, login, csrf_token, make_card, card_image
):
    login("curator")
    assert 'id="confirm-grid-link"' in client.get("/crowd/batches").get_data(as_text=True)
    form = {"kind": "confirm", "from_review": "1", "answers_per_item": "2", "csrf_token": csrf_token("/crowd/batches")}
    assert client.post("/crowd/batches/new", data=form).status_code == 303
    with app.app_context():
        batch = db.session.scalar(select(Batch))
        assert batch.kind == "confirm" and sorted(it.card_id for it in batch.items if not it.is_gold) == grid_world["confirm"]
        assert sum(it.is_gold for it in batch.items) == 4  # gold made from the decided cards
    page = client.get("/crowd/batches")
    assert page.status_code == 200 and "confirm" in page.get_data(as_text=True)
    # A card nobody proposed an orientation for cannot be shown in a grid: a sentence, no batch.
    refused = client.post("/crowd/batches/new", data={**form, "from_review": "", "cards": str(grid_world["known"][0] + 100)})
    assert refused.status_code == 404
    bare = make_card(card_image()[:, ::-1].copy(), state="pass")  # no orientation result
    no_proposal = runner.invoke(cli, ["crowd", "create-batch", "--kind", "confirm", "--cards", str(bare), "--json"])
    assert no_proposal.exit_code == 1 and "no proposed orientation to confirm" in no_proposal.output
    response = client.get("/crowd/grid")
    assert response.status_code == 303 and "kind=confirm" in response.headers["Location"]
    page = client.get(response.headers["Location"]).get_data(as_text=True)
    assert "annotation/grid.js" in page and 'data-grid-url="/crowd/api/grid"' in page


def test_a_card_the_grid_cannot_agree_on_goes_to_a_judge_task(app, client, runner, grid_world):  # type: ignore[no-untyped-def]
    from annotation.batches import confirm_queue_card_ids, orientation_queue_card_ids
    from annotation.models import Aggregate
    from review.tasks import disputed_aggregates

    confirm = grid_world["confirm"]
    doc = _create_batch(runner, n=2)
    for name, wrong in (("ada", {confirm[0]: "inverted"}), ("bob", {})):  # one says negative, one does not
        token = _worker(app, client, name)
        grid = _api(client, "grid", token, {}).get_json()
        items = _items(app, [c["token"] for c in grid["cards"]])
        assert _api(client, "grid/submit", token, {"key": f"split-{name}", "answers": _taps(items, wrong)}).status_code == 201
    report = runner.invoke(cli, ["crowd", "aggregate", str(doc["batch"]), "--json"])
    assert report.exit_code == 0, report.output
    counts = json.loads(report.stdout)
    with app.app_context():
        states = {row.card_id: row.state for row in db.session.scalars(select(Aggregate))}
        assert states[confirm[0]] == "escalated"
        assert counts["escalated"] == sum(s == "escalated" for s in states.values()) and counts["needs_curator"] == 0
        escalated = {card_id for card_id, state in states.items() if state == "escalated"}
        # People judge those from scratch; the grid does not ask again; no curator dispute.
        assert set(orientation_queue_card_ids()) == escalated
        assert confirm_queue_card_ids() == []
        assert disputed_aggregates() == ([], 0)
    assert _cards(runner)[confirm[0]]["orientation"]["decided_by"] is None


def test_a_grid_whose_holds_lapsed_is_renewed_and_sent_again_under_the_same_key(app, client, runner, grid_world):  # type: ignore[no-untyped-def]
    from datetime import timedelta

    from core.db import utcnow

    _create_batch(runner)
    token = _worker(app, client, "slow")
    grid = _api(client, "grid", token, {}).get_json()
    tokens = [c["token"] for c in grid["cards"]]
    with app.app_context():
        for row in db.session.scalars(select(Reservation).where(Reservation.token.in_(tokens))):
            row.expires_at = utcnow() - timedelta(seconds=1)
        db.session.commit()
    answers = [{"token": t, "taps": NONE} for t in tokens]
    late = _api(client, "grid/submit", token, {"key": "slow-grid-1", "answers": answers})
    assert late.status_code == 409 and "expired" in late.get_json()["error"]["message"]
    for t in tokens:  # what the page does: renew every card, send the same answers again
        assert _api(client, "renew", token, {"token": t}).status_code == 200
    again = _api(client, "grid/submit", token, {"key": "slow-grid-1", "answers": answers})
    assert again.status_code == 201 and again.get_json()["stored"] == len(tokens)

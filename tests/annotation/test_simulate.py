"""The demo's simulated crowd: real use cases, realistic noise, approved and disputed aggregates."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from annotation.models import Aggregate, Answer, Batch, BatchItem, Reservation, Worker
from core.db import db


@pytest.fixture
def split_cards(make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    """``split_cards(k)``: k real stereo cards (604 x 200 px) with a filter result holding the split boxes."""
    base = card_image()

    def make(k: int) -> list[int]:
        ids = []
        for index in range(k):
            image = base.copy()
            image[0, 0, 0] = index  # distinct content, distinct cards
            card = make_card(image, state="review")
            add_stage_result(card, "filter", outcome="review")
            ids.append(card)
        return ids

    return make


JUDGE_OK = {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": False}


def _aggregates(batch_id: int) -> dict[int, Aggregate]:
    return {a.card_id: a for a in db.session.scalars(select(Aggregate).where(Aggregate.batch_id == batch_id))}


def test_crop_crowd_approves_boxes_near_the_truth_and_disputes_the_hard_card(app, split_cards):  # type: ignore[no-untyped-def]
    from annotation.simulate import crop_truth_from_filter, seed_simulated_crowd

    cards = split_cards(5)
    with app.app_context():
        summary = seed_simulated_crowd(cards, kind="crop", seed=0)
        assert summary["batch"] is not None and summary["cards"] == sorted(cards) and summary["skipped"] == []
        assert summary["answers"] == 15 and summary["pending"] == 0
        assert summary["approved"] + summary["needs_curator"] == 5
        assert summary["approved"] >= 3 and summary["needs_curator"] >= 1
        aggregates = _aggregates(summary["batch"])
        assert aggregates[summary["hard_card"]].state == "needs_curator"
        assert "spread" in aggregates[summary["hard_card"]].reasons
        for card_id, aggregate in aggregates.items():
            if aggregate.state != "approved":
                continue
            truth = crop_truth_from_filter(card_id)
            for half in ("left", "right"):
                error = [abs(a - b) for a, b in zip(aggregate.label[half], truth[half], strict=True)]
                assert max(error) < 4.0, (card_id, half, aggregate.label[half], truth[half])
        # Through the real use cases: N answers per item from N distinct invited workers, nothing left held.
        pairs = db.session.execute(
            select(Answer.item_id, Answer.worker_id).join(BatchItem).where(BatchItem.batch_id == summary["batch"])
        ).all()
        assert len(pairs) == len(set(pairs)) == 15
        per_item = db.session.execute(
            select(Answer.item_id, func.count(func.distinct(Answer.worker_id)))
            .join(BatchItem)
            .where(BatchItem.batch_id == summary["batch"])
            .group_by(Answer.item_id)
        ).all()
        assert sorted(count for _, count in per_item) == [3] * 5
        assert db.session.scalar(select(func.count()).select_from(Reservation).where(Reservation.answered_at.is_(None))) == 0
        names = [w["name"] for w in summary["workers"]]
        assert names == [f"sim-0-{i}" for i in range(6)] and [w["spammer"] for w in summary["workers"]][-1]
        assert {w.provider for w in db.session.scalars(select(Worker))} == {"invite"}


def test_judge_crowd_with_gold_approves_the_truth_and_refills_flagged_slots(app, split_cards):  # type: ignore[no-untyped-def]
    from annotation.simulate import seed_simulated_crowd

    cards = split_cards(10)
    regular = cards[:6]
    # Gold over-represents the rare answers, as curators are told to pick it.
    gold = {
        cards[6]: JUDGE_OK,
        cards[7]: {**JUDGE_OK, "upside_down": True},
        cards[8]: {**JUDGE_OK, "inverted": True},
        cards[9]: {**JUDGE_OK, "is_stereo": False, "swapped": True},
    }
    truth = {regular[0]: {"upside_down": True}, regular[1]: {"swapped": True}}
    with app.app_context():
        summary = seed_simulated_crowd(regular, kind="judge", seed=8, gold=gold, truth=truth)
        assert summary["gold_cards"] == sorted(gold)
        assert summary["approved"] >= 4 and summary["approved"] + summary["needs_curator"] == 6
        batch = db.session.get(Batch, summary["batch"])
        assert batch.answers_per_item == 4 and batch.gold_rate == 0.3
        aggregates = _aggregates(summary["batch"])
        # Simulated workers answer the eye-order question too: every label carries it, and the
        # card with swapped photos is labelled swapped wherever it was approved.
        assert all("swapped" in a.label and len(a.posterior["swapped"]) == 2 for a in aggregates.values())
        for card_id, aggregate in aggregates.items():
            if aggregate.state == "approved":
                assert aggregate.label == {**JUDGE_OK, **truth.get(card_id, {})}
        assert aggregates[summary["hard_card"]].state == "needs_curator"
        assert "inverted: posterior" in aggregates[summary["hard_card"]].reasons
        # Workers who failed gold (one slip in their first three gold answers is enough) are
        # flagged with all their answers, and their slots were served again: no card waits for
        # answers (pending 0) although every item needs 4 usable ones.
        flagged = list(db.session.scalars(select(Worker.id).where(Worker.flagged.is_(True))))
        assert summary["flagged_workers"] == len(flagged) >= 1 and summary["pending"] == 0
        assert (
            db.session.scalar(
                select(func.count()).select_from(Answer).where(Answer.worker_id.in_(flagged), Answer.flagged.is_(False))
            )
            == 0
        )
        usable = dict(
            db.session.execute(
                select(Answer.item_id, func.count())
                .join(BatchItem)
                .where(BatchItem.batch_id == batch.id, BatchItem.is_gold.is_(False), Answer.flagged.is_(False))
                .group_by(Answer.item_id)
            ).all()
        )
        assert sorted(usable.values()) == [4] * 6
        gold_answers = db.session.scalar(
            select(func.count()).select_from(Answer).join(BatchItem).where(BatchItem.is_gold.is_(True))
        )
        regular_answers = db.session.scalar(
            select(func.count()).select_from(Answer).join(BatchItem).where(BatchItem.is_gold.is_(False))
        )
        assert gold_answers > 0 and summary["answers"] == gold_answers + regular_answers > 6 * 4


def test_cards_without_a_split_are_skipped_and_unknown_cards_refused(app, split_cards, make_card):  # type: ignore[no-untyped-def]
    from annotation.simulate import seed_simulated_crowd
    from annotation.task_errors import TaskError

    with app.app_context():
        unsplit = make_card(state="review")
        summary = seed_simulated_crowd([unsplit], kind="crop")
        assert summary["batch"] is None and summary["answers"] == 0
        assert summary["skipped"] == [
            {"card": unsplit, "reason": "no filter split boxes (left_box/right_box) and no truth given"}
        ]
        with pytest.raises(TaskError, match="No card with id 999") as refused:
            seed_simulated_crowd([unsplit, 999], kind="judge")
        assert refused.value.status == 404
        with pytest.raises(TaskError, match="at least n \\+ 1"):
            seed_simulated_crowd([unsplit], kind="judge", workers=3)
        assert db.session.scalar(select(func.count()).select_from(Batch)) == 0
        assert db.session.scalar(select(func.count()).select_from(Worker)) == 0


def test_simulated_boxes_obey_the_submit_rules_and_sit_near_the_truth() -> None:
    import numpy as np

    from annotation.simulate import SimulatedWorker, simulated_answer

    truth = {"left": [10.0, 8.0, 280.0, 190.0], "right": [320.0, 8.0, 590.0, 190.0]}
    careful, spammer = SimulatedWorker(1, "a", 1.0, False), SimulatedWorker(2, "s", 0.5, True)
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(200):
        for worker in (careful, spammer):
            answer = simulated_answer("crop", truth, worker, (604, 200), rng, min_box=16)
            for half in ("left", "right"):
                x0, y0, x1, y1 = answer[half]
                assert 0 <= x0 and 0 <= y0 and x1 <= 604 and y1 <= 200 and x1 - x0 >= 16 and y1 - y0 >= 16
                if worker is careful:
                    errors += [abs(a - b) for a, b in zip(answer[half], truth[half], strict=True)]
    assert 0.5 < float(np.median(errors)) < 1.5  # sigma 1.5 px: median |error| = 0.67 sigma = 1.0 px


def test_batches_page_shows_each_workers_answers_gold_and_flags(app, client, split_cards, login):  # type: ignore[no-untyped-def]
    from annotation.simulate import seed_simulated_crowd

    cards = split_cards(7)
    with app.app_context():
        summary = seed_simulated_crowd(cards[:4], kind="judge", seed=1, gold={g: JUDGE_OK for g in cards[4:]})
    login("curator")
    html = client.get("/crowd/batches").get_data(as_text=True)
    assert "<h2>Workers</h2>" in html
    with app.app_context():
        from annotation.progress import worker_progress

        rows = {row["name"]: row for row in worker_progress()}
    assert sum(row["answers"] for row in rows.values()) == summary["answers"]
    for name, row in rows.items():
        gold = f"{row['gold_correct']}/{row['gold_total']}" if row["gold_total"] else "–"
        status = "served" if row["served"] else "flagged: not served"
        assert f"<td>invite:{name}</td><td>{row['answers']}</td><td>{gold}" in html
        assert status in html
    assert sum(row["gold_total"] for row in rows.values()) > 0

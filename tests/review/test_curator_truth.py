"""A curator's decision on a disputed crowd answer is the card's truth: re-aggregating the
batch (say after late answers) never overwrites it."""

from __future__ import annotations

import pytest


@pytest.mark.both_databases
def test_reaggregating_keeps_the_curators_label(app, make_card, make_person, card_image) -> None:  # type: ignore[no-untyped-def]
    from annotation.answers import submit
    from annotation.batches import create_batch
    from annotation.models import Aggregate
    from annotation.reservations import next_tasks
    from annotation.results import aggregate_batch
    from annotation.workers import get_or_create_worker
    from core.db import db
    from core.models import Person
    from review.tasks import resolve_aggregate

    card_id = make_card(card_image(), state="review")
    carol = make_person("curator", username="carol")
    crowd_says = {"is_stereo": True, "upside_down": False, "inverted": False}
    with app.app_context():
        batch_id = create_batch([card_id], "judge", 2, 0.0).id
        for name in ("w1", "w2"):
            worker = get_or_create_worker("invite", name)
            tasks, _ = next_tasks(worker, "judge", hold=1)
            submit(worker, tasks[0].reservation_token, crowd_says, idempotency_key=f"{name}-answer-1")
        aggregate_batch(batch_id)
        aggregate = db.session.scalar(db.select(Aggregate).where(Aggregate.card_id == card_id))
        truth = {"is_stereo": True, "upside_down": True, "inverted": False}
        if aggregate.state == "needs_curator":
            resolve_aggregate(aggregate.id, truth, curator=db.session.get(Person, carol.id))
        else:  # two agreeing answers may be approved already; a curator can still set the truth
            aggregate.state, aggregate.reasons = "needs_curator", "test: disputed"
            db.session.commit()
            resolve_aggregate(aggregate.id, truth, curator=db.session.get(Person, carol.id))

        report = aggregate_batch(batch_id)
        db.session.expire_all()
        aggregate = db.session.get(Aggregate, aggregate.id)
        assert (aggregate.state, aggregate.label, aggregate.resolved_by) == ("approved", truth, carol.id)
        assert report.approved == 1 and report.needs_curator == 0

"""Assignment rules: one answer per worker per item, N answers, expiry, gold rate, flagged workers."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from annotation.assignment import (
    Assignment,
    AssignmentPolicy,
    BatchItem,
    NoTask,
    NoTaskReason,
    Reservation,
    next_assignment,
)

NOW = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
NO_GOLD = AssignmentPolicy(answers_per_item=3, gold_rate=0.0)


def item(item_id: str, *workers: str) -> BatchItem:
    return BatchItem(item_id, frozenset(workers))


def test_returns_a_reservation_that_expires_after_the_ttl() -> None:
    policy = AssignmentPolicy(gold_rate=0.0, reservation_ttl=timedelta(minutes=5))
    got = next_assignment([item("a")], [], set(), "w1", NOW, policy=policy)
    assert got == Assignment("a", False, NOW + timedelta(minutes=5))


def test_never_an_item_the_worker_answered_or_holds() -> None:
    items = [item("a", "w1"), item("b"), item("c")]
    held = [Reservation("b", "w1", NOW + timedelta(minutes=1))]
    got = next_assignment(items, held, set(), "w1", NOW, policy=NO_GOLD)
    assert isinstance(got, Assignment) and got.item_id == "c"


def test_prefers_the_item_closest_to_completion() -> None:
    items = [item("empty"), item("two", "x", "y"), item("one", "x")]
    got = next_assignment(items, [], set(), "w1", NOW, policy=NO_GOLD)
    assert isinstance(got, Assignment) and got.item_id == "two"
    # An open hold counts toward completion too.
    holds = [
        Reservation("one", "z", NOW + timedelta(minutes=1)),
        Reservation("one", "q", NOW + timedelta(minutes=1)),
    ]
    items = [item("empty"), item("one", "x")]
    got = next_assignment(items, holds, set(), "w1", NOW, policy=NO_GOLD)
    assert isinstance(got, Assignment) and got.item_id == "empty"  # "one" is full: 1 answer + 2 holds


def test_each_item_gets_exactly_n_answers_from_n_different_workers() -> None:
    answered: dict[str, set[str]] = {f"card{i}": set() for i in range(10)}
    workers = [f"w{j}" for j in range(7)]
    served = 0
    while True:
        progress = False
        for w in workers:
            items = [BatchItem(k, frozenset(v)) for k, v in answered.items()]
            got = next_assignment(items, [], set(), w, NOW, policy=NO_GOLD)
            if isinstance(got, Assignment):
                assert w not in answered[str(got.item_id)]
                answered[str(got.item_id)].add(w)
                served += 1
                progress = True
        if not progress:
            break
    assert served == 30
    assert all(len(v) == 3 for v in answered.values())
    items = [BatchItem(k, frozenset(v)) for k, v in answered.items()]
    assert next_assignment(items, [], set(), "newcomer", NOW, policy=NO_GOLD) == NoTask(NoTaskReason.BATCH_COMPLETE)


def test_open_reservations_block_and_expired_ones_return_to_the_pool() -> None:
    items = [item("a", "x")]
    holds = [
        Reservation("a", "y", NOW + timedelta(minutes=2)),
        Reservation("a", "z", NOW + timedelta(minutes=4)),
    ]
    got = next_assignment(items, holds, set(), "w1", NOW, policy=NO_GOLD)
    assert got == NoTask(NoTaskReason.ALL_RESERVED, retry_after=NOW + timedelta(minutes=2))
    # Three minutes later y's hold has lapsed: its slot is free again.
    later = NOW + timedelta(minutes=3)
    got = next_assignment(items, holds, set(), "w1", later, policy=NO_GOLD)
    assert isinstance(got, Assignment) and got.item_id == "a"
    # A reservation expiring exactly now is already lapsed.
    got = next_assignment(items, holds, set(), "w1", NOW + timedelta(minutes=2), policy=NO_GOLD)
    assert isinstance(got, Assignment)


def test_nothing_left_for_a_worker_who_answered_the_rest() -> None:
    items = [item("a", "w1"), item("b", "w1", "x", "y")]
    got = next_assignment(items, [], set(), "w1", NOW, policy=NO_GOLD)
    assert got == NoTask(NoTaskReason.NOTHING_LEFT_FOR_WORKER)


def test_flagged_worker_gets_nothing() -> None:
    got = next_assignment([item("a")], [], set(), "w1", NOW, policy=NO_GOLD, flagged_workers={"w1"})
    assert got == NoTask(NoTaskReason.WORKER_FLAGGED)


def test_gold_rate_within_tolerance_over_many_draws() -> None:
    # 2,000 workers x 5 successive tasks = 10,000 draws at 20 %; binomial sd = 0.4 %.
    policy = AssignmentPolicy(answers_per_item=10**6, gold_rate=0.2, seed=3)
    gold_ids = {f"g{i}" for i in range(5)}
    gold_draws = 0
    draws = 0
    for w in range(2000):
        worker = f"w{w}"
        answered: set[str] = set()
        for _ in range(5):
            items = [item(f"c{i}", *([worker] if f"c{i}" in answered else [])) for i in range(10)]
            items += [item(g, *([worker] if g in answered else [])) for g in sorted(gold_ids)]
            got = next_assignment(items, [], gold_ids, worker, NOW, policy=policy)
            assert isinstance(got, Assignment)
            assert got.is_gold == (got.item_id in gold_ids)
            answered.add(str(got.item_id))
            gold_draws += got.is_gold
            draws += 1
    assert gold_draws / draws == pytest.approx(0.2, abs=0.015)


def test_gold_draw_is_deterministic_and_gold_is_not_capped_at_n() -> None:
    policy = AssignmentPolicy(answers_per_item=1, gold_rate=1.0)
    items = [item("c1"), item("g1", "x", "y", "z")]  # gold already answered by 3 > N workers
    first = next_assignment(items, [], {"g1"}, "w1", NOW, policy=policy)
    again = next_assignment(items, [], {"g1"}, "w1", NOW, policy=policy)
    assert first == again == Assignment("g1", True, NOW + policy.reservation_ttl)


def test_no_gold_only_work_once_the_regular_items_are_done() -> None:
    policy = AssignmentPolicy(answers_per_item=1, gold_rate=1.0)
    items = [item("c1", "x"), item("g1")]
    assert next_assignment(items, [], {"g1"}, "w1", NOW, policy=policy) == NoTask(NoTaskReason.BATCH_COMPLETE)


def test_gold_falls_back_to_regular_work_when_the_worker_saw_all_gold() -> None:
    policy = AssignmentPolicy(gold_rate=1.0)
    items = [item("c1"), item("g1", "w1")]
    got = next_assignment(items, [], {"g1"}, "w1", NOW, policy=policy)
    assert got == Assignment("c1", False, NOW + policy.reservation_ttl)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"answers_per_item": 0}, "answers_per_item >= 1"),
        ({"gold_rate": 1.2}, "gold_rate"),
        ({"reservation_ttl": timedelta(0)}, "positive reservation_ttl"),
    ],
)
def test_bad_policy_is_refused(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        AssignmentPolicy(**kwargs)  # type: ignore[arg-type]


def test_equally_complete_items_go_by_the_batchs_shuffle_the_same_for_every_worker() -> None:
    items = [BatchItem("low", rank=5), BatchItem("high", rank=9), BatchItem("mid", rank=7)]
    for worker in ("w1", "w2", "w3"):
        got = next_assignment(items, [], set(), worker, NOW, policy=NO_GOLD)
        assert isinstance(got, Assignment) and got.item_id == "high"
    # Completion still comes first: one answer beats the highest rank.
    items.append(BatchItem("started", frozenset({"x"}), rank=0))
    got = next_assignment(items, [], set(), "w1", NOW, policy=NO_GOLD)
    assert isinstance(got, Assignment) and got.item_id == "started"


def test_item_rank_is_stable_and_spread() -> None:
    from annotation.assignment import item_rank

    ranks = [item_rank(12, i) for i in range(2000)]
    assert ranks == [item_rank(12, i) for i in range(2000)]  # no process-salted hash()
    assert all(0 <= r < 2**63 for r in ranks) and len(set(ranks)) == 2000
    assert item_rank(12, 1) != item_rank(13, 1)  # each batch has its own shuffle
    # Roughly uniform: each quarter of the range holds about a quarter of the items.
    quarters = [sum(1 for r in ranks if q * 2**61 <= r < (q + 1) * 2**61) for q in range(4)]
    assert all(430 <= q <= 570 for q in quarters), quarters

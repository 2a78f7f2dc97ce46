"""`keystone orientation fit`: a collection's decided cards refit the learned heads, versioned,
reported held out, and the refit reaches the orientation step's inputs (so only the next run
changes decisions)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.upright import FEATURE_SIZE, shipped_head, write_learned_differences


def _readings(rng: np.random.Generator, direction: np.ndarray, upside_down: bool) -> dict[str, np.ndarray]:
    """Two photos' turn and tone differences that a head along ``direction`` reads right, with
    noise, as scanned (a card turned 180 deg reads negated)."""
    sign = -1.0 if upside_down else 1.0
    turn = sign * (direction * 0.02 + rng.normal(scale=0.05, size=(2, FEATURE_SIZE)))
    tone = direction * 0.01 + rng.normal(scale=0.05, size=(2, FEATURE_SIZE))
    return {"turn": turn.astype(np.float32), "tone": tone.astype(np.float32)}


@pytest.fixture
def decided_collection(app, data_dir, make_card, add_stage_result, card_image, make_person):  # type: ignore[no-untyped-def]
    """14 cards of collection "prints": 10 decided automatically with P 0.995, 2 turned ones a
    curator decided, 2 the step was unsure of (not labels)."""
    from core.db import db
    from core.models import Person
    from review.orientation import override_orientation

    rng = np.random.default_rng(3)
    direction = rng.normal(size=FEATURE_SIZE)
    ids = []
    for k in range(14):
        image = card_image()
        image[0, 0] = k  # a card of its own (content hash)
        card_id = make_card(image, collection="prints", state="pass")
        add_stage_result(card_id, "filter")
        upside_down = k in (10, 11)
        work = data_dir / "derived" / f"card{k}" / "orientation"
        path = write_learned_differences(work / "upright_differences.npz", _readings(rng, direction, upside_down))
        sure = k < 10
        add_stage_result(
            card_id,
            "orientation",
            outcome="auto" if sure else "ask",
            metrics={
                "combination_probability": 0.995 if sure else 0.6,
                "proposed": {"upside_down": False, "inverted": False, "swapped": False},
                "flags": {
                    f: {"p": 0.01, "decided": sure, "value": False if sure else None}
                    for f in ("upside_down", "inverted", "swapped")
                },
                "cue_values": {"ground_plane": 0.4, "warm_tone": 0.9},
            },
            artifacts={"upright_differences": str(path.relative_to(data_dir))},
        )
        ids.append(card_id)
    with app.app_context():
        curator = db.session.get(Person, make_person("curator").id)
        for card_id in ids[10:12]:
            override_orientation(card_id, {"upside_down": True, "inverted": False, "swapped": True}, curator=curator)
    return ids, direction


def test_fit_reports_held_out_accuracy_saves_a_version_and_feeds_the_next_run(app, runner, decided_collection, data_dir):  # type: ignore[no-untyped-def]
    ids, direction = decided_collection
    result = runner.invoke(args=["orientation", "fit", "--collection", "prints", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    assert document["cards"] == 12  # 10 sure automatic decisions + 2 curator decisions
    assert document["head_before"] == shipped_head().version
    turn = document["heads"]["turn"]
    # The shipped head knows nothing of this synthetic direction; the refit learns it from the
    # other folds' cards (grouped by card), so its held-out accuracy rises.
    assert turn["after"]["n"] == 24
    assert turn["after"]["accuracy"] >= 0.9 > turn["before"]["accuracy"]
    assert document["saved"] is True and document["head_after"].startswith("prints-")

    from core.audit import AuditEvent
    from core.db import db
    from review.models import UprightHeadFit
    from review.upright_fit import upright_head_inputs

    with app.app_context():
        fit = db.session.query(UprightHeadFit).one()
        assert fit.version == document["head_after"] and fit.fitted_on == 12
        assert db.session.query(AuditEvent).filter_by(entity="upright_head", action="fit").count() == 1
        inputs = upright_head_inputs(ids)
        assert set(inputs) == set(ids)
        entry = inputs[ids[0]]["upright_head"]
        assert entry["version"] == fit.version
        head = json.loads((Path(data_dir) / entry["path"]).read_text())
        assert head["version"] == fit.version and len(head["turn"]) == FEATURE_SIZE

        # the orientation step's inputs now carry the head, so its inputs digest changes and
        # the next run recomputes it
        from core.hooks import approved_decisions
        from core.models import Card
        from pipeline.stages.orientation import orientation_inputs

        card = db.session.get(Card, ids[0])
        step_inputs = orientation_inputs(card, approved_decisions([ids[0]])[ids[0]])
        assert step_inputs["upright_head"]["version"] == fit.version


def test_dry_run_saves_nothing_and_a_second_collection_keeps_the_shipped_head(app, runner, decided_collection, make_card):  # type: ignore[no-untyped-def]
    other = make_card(collection="elsewhere", state="pass")
    result = runner.invoke(args=["orientation", "fit", "--collection", "prints", "--dry-run", "--json"])
    assert result.exit_code == 0 and json.loads(result.output)["saved"] is False
    runner.invoke(args=["orientation", "fit", "--collection", "prints"])
    from review.upright_fit import upright_head_inputs

    with app.app_context():
        assert other not in upright_head_inputs([other])


def test_fit_refuses_unknown_collections_and_too_few_cards(app, runner, make_card):  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["orientation", "fit", "--collection", "nowhere", "--json"])
    assert result.exit_code == 1 and "no collection 'nowhere'" in json.loads(result.output)["error"]
    make_card(collection="small", state="pass")
    result = runner.invoke(args=["orientation", "fit", "--collection", "small"])
    assert result.exit_code == 1 and "at least 10 cards" in result.output
    assert "Traceback" not in result.output


def test_a_changed_decision_is_listed_when_written(app, make_card, add_stage_result):  # type: ignore[no-untyped-def]
    """The run's report lists the cards whose orientation decision a rerun changed (a refitted
    head reaches the step through its inputs, so only the next run changes decisions)."""
    from pipeline.records import StageRecord
    from runs.writes import write_records

    card_id = make_card(state="pass")
    add_stage_result(card_id, "orientation", outcome="confirm", metrics={"proposed": {"upside_down": False}})
    unchanged = make_card(np.random.default_rng(7).integers(0, 255, size=(120, 330, 3), dtype=np.uint8), state="pass")
    add_stage_result(unchanged, "orientation", outcome="auto", metrics={"proposed": {"upside_down": True}})

    def record(card: int, outcome: str, upside_down: bool) -> StageRecord:
        return StageRecord(
            card, "orientation", "0123456789abcdef", "done", outcome, metrics={"proposed": {"upside_down": upside_down}}
        )

    with app.app_context():
        changes = write_records([record(card_id, "auto", False), record(unchanged, "auto", True)])
    assert changes == [
        {
            "card_id": card_id,
            "before": {"decision": "confirm", "proposed": {"upside_down": False}},
            "after": {"decision": "auto", "proposed": {"upside_down": False}},
        }
    ]

"""``keystone cards`` reports people's stages too: the crowd's judge and crop aggregates and
the curator's review, with skips that say what a card did not need."""

from __future__ import annotations

import json

import pytest


def _cards(runner) -> dict[int, dict]:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["cards", "--json"])
    assert result.exit_code == 0, result.output
    return {row["id"]: row["stages"] for row in json.loads(result.output)["cards"]}


@pytest.mark.both_databases
def test_judge_crop_and_review_statuses(app, runner, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    from annotation.models import Aggregate, Batch
    from core.db import db
    from review.models import CardReview

    passed = make_card(card_image()[:, 1:])
    add_stage_result(passed, "filter", outcome="pass")
    flags = {
        flag: {"p": 0.02, "decided": True, "value": False, "evidence": []} for flag in ("upside_down", "inverted", "swapped")
    }
    add_stage_result(passed, "orientation", outcome="auto", metrics={"flags": flags, "confidence": 0.98})
    asked = make_card(card_image()[:, 5:])
    add_stage_result(asked, "filter", outcome="pass")
    add_stage_result(
        asked,
        "orientation",
        outcome="ask",
        metrics={"flags": {**flags, "swapped": {"p": 0.6, "decided": False, "value": None, "evidence": []}}, "confidence": 0.6},
    )
    add_stage_result(passed, "rectify", outcome=None, metrics={"box_source": "filter split (abc)"})
    disputed = make_card(card_image()[:, 2:])
    add_stage_result(disputed, "filter", outcome="review")
    judged = make_card(card_image()[:, 3:])
    add_stage_result(judged, "filter", outcome="review")
    culled = make_card(card_image()[:, 4:])
    add_stage_result(culled, "filter", outcome="culled", reason="culled: 0.4 % good matches")
    with app.app_context():
        batch = Batch(kind="judge")
        db.session.add(batch)
        db.session.flush()
        label = {"is_stereo": True, "upside_down": False, "inverted": False}
        db.session.add_all(
            [
                Aggregate(
                    batch_id=batch.id,
                    card_id=disputed,
                    kind="judge",
                    label=label,
                    state="needs_curator",
                    reasons="upside_down posterior 0.55 < 0.9",
                    answers=3,
                ),
                Aggregate(batch_id=batch.id, card_id=judged, kind="judge", label=label, state="approved", answers=3),
                CardReview(card_id=passed, auto_grade="some", grade="few", decision="changed", note="sharp enough"),
            ]
        )
        db.session.commit()

    stages = _cards(runner)
    assert stages[passed]["judge"]["status"] == "skipped"
    assert stages[passed]["judge"]["reason"] == (
        "not needed: the filter passed the card as a stereo pair and the orientation step decided it (confidence 0.98)"
    )
    # Passed by the filter, but the orientation step asked: it waits for the crowd's judgement.
    assert stages[asked]["judge"] == {
        "status": "pending",
        "outcome": None,
        "metrics": {},
        "reason": "waiting for people (the orientation step is not sure of swapped)",
    }
    assert stages[asked]["rectify"]["status"] == "pending" and "undecided" in stages[asked]["rectify"]["reason"]
    assert stages[passed]["crop"] == {
        "status": "skipped",
        "outcome": None,
        "metrics": {},
        "reason": "not needed: rectified from filter split (abc)",
    }
    assert stages[passed]["review"]["status"] == "done" and stages[passed]["review"]["outcome"] == "changed"
    assert stages[passed]["review"]["metrics"]["grade"] == "few"
    assert stages[disputed]["judge"]["status"] == "pending"
    assert stages[disputed]["judge"]["reason"] == "waiting for a curator: upside_down posterior 0.55 < 0.9"
    assert stages[judged]["judge"]["status"] == "done" and stages[judged]["judge"]["outcome"] == "stereo"
    assert stages[judged]["crop"]["status"] == "pending" and stages[judged]["review"]["status"] == "pending"
    for stage in ("judge", "crop", "grade", "review", "views"):
        assert stages[culled][stage]["status"] == "skipped", stage
        assert "culled by the filter (culled: 0.4 % good matches)" in stages[culled][stage]["reason"]


def test_views_skipped_for_a_card_graded_failure_matches_the_catalogue_filter(
    app, runner, client, login, make_card, add_stage_result, card_image
) -> None:  # type: ignore[no-untyped-def]
    failed = make_card(card_image()[:, 1:])
    add_stage_result(failed, "filter", outcome="pass")
    add_stage_result(failed, "grade", outcome="failure", reason="failure: rectification sheared 14.0 deg (> 10 deg)")
    clean = make_card(card_image()[:, 2:])
    add_stage_result(clean, "filter", outcome="pass")
    add_stage_result(clean, "grade", outcome="few")
    broken = make_card(card_image()[:, 3:])
    add_stage_result(broken, "filter", outcome="pass")
    add_stage_result(broken, "rectify", status="failed", outcome=None, reason="degenerate_geometry: planar scene")

    stages = _cards(runner)
    assert stages[failed]["views"] == {
        "status": "skipped",
        "outcome": None,
        "metrics": {},
        "reason": "not needed: graded failure",
    }
    assert stages[clean]["views"]["status"] == "pending"
    assert stages[broken]["grade"]["status"] == "skipped"
    assert stages[broken]["grade"]["reason"] == "not run: rectification failed (degenerate_geometry: planar scene)"

    # The catalogue's SQL filter agrees with the derived statuses.
    login("curator")
    page = client.get("/cards?stage=views&status=skipped").get_data(as_text=True)
    assert f'/cards/{failed}"' in page and f'/cards/{broken}"' in page and f'/cards/{clean}"' not in page
    page = client.get("/cards?stage=views&status=pending").get_data(as_text=True)
    assert f'/cards/{clean}"' in page and f'/cards/{failed}"' not in page
    assert client.get("/cards?stage=review&status=done").status_code == 400

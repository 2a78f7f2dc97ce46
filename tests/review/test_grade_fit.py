"""``keystone grade fit`` refits the grader's thresholds to curator labels, reports agreement on
held-out labels, stores a grade model the grade stage then uses; ``grade show`` prints it."""

from __future__ import annotations

import json

import numpy as np
import pytest


def _measurements(rng: np.random.Generator) -> dict:
    return {
        "good_match_fraction": float(rng.uniform(0.05, 0.4)),
        "dy_p95_px": float(rng.uniform(0.2, 1.2)),
        "shear_deg": float(rng.uniform(0, 3)),
        "aspect_change": 1.01,
        "rotation_deg": float(rng.uniform(0, 2)),
        "kept_fraction": 0.95,
        "swapped": False,
        "row_misalignment_px": float(rng.uniform(0.05, 6.0)),
        "coverage": float(rng.uniform(0.85, 1.0)),
        "lr_consistency": float(rng.uniform(0.7, 0.98)),
        "confident_fraction": float(rng.uniform(0.7, 0.98)),
        "disparity_range_px": 30.0,
        "disparity_range_rel": 0.06,
        "texture_gradient": 12.0,
        "textured_fraction": 0.6,
        "photometric_error": 10.0,
        "photometric_error_rel": 0.2,
        "reasons": ["few: every measurement within thresholds"],
        "uncertainty": 0.3,
    }


@pytest.fixture
def labelled(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    """60 graded cards whose curators judged by row misalignment alone: < 1 px few, < 2.5 px some."""
    from core.db import db
    from review.models import CardReview

    rng = np.random.default_rng(7)
    for index in range(60):
        metrics = _measurements(rng)
        rows = metrics["row_misalignment_px"]
        label = "few" if rows < 1.0 else "some" if rows < 2.5 else "failure"
        card_id = make_card(card_image()[:, index:], state="pass")
        add_stage_result(card_id, "grade", outcome="few", metrics=metrics)
        with app.app_context():
            db.session.add(
                CardReview(card_id=card_id, auto_grade="few", grade=label, decision="accepted" if label == "few" else "changed")
            )
            db.session.commit()


def test_fit_stores_a_model_with_held_out_agreement_and_the_stage_uses_it(app, runner, labelled) -> None:  # type: ignore[no-untyped-def]
    from core.audit import AuditEvent
    from core.db import db
    from pipeline.records import param_hash
    from review.models import GradeModel
    from runs.specs import available_stages

    with app.app_context():
        default_hash = param_hash(available_stages()["grade"].params)
    shown = json.loads(runner.invoke(args=["grade", "show", "--json"]).output)
    assert shown["model"] is None

    result = runner.invoke(args=["grade", "fit", "--json"])
    assert result.exit_code == 0, result.output
    fit = json.loads(result.output)
    assert fit["labels"] == 60 and fit["model"] is not None
    held = fit["held_out"]
    assert sum(map(sum, held["confusion"])) == 60  # every label scored once, on a fold it was not fitted on
    # The labels follow one measurement; refitted thresholds find it, the defaults do not.
    assert held["accuracy"] >= 0.8
    assert held["accuracy"] > fit["baseline"]["accuracy"]
    fitted_rows = fit["thresholds"]["row_misalignment_px"]
    assert 0.6 <= fitted_rows["some"] <= 1.4 and 1.8 <= fitted_rows["failure"] <= 3.2

    with app.app_context():
        model = db.session.get(GradeModel, fit["model"])
        assert model.fitted_on == 60 and model.evaluation["accuracy"] == held["accuracy"]
        event = db.session.query(AuditEvent).filter_by(entity="grade_model").one()
        assert event.after == {"thresholds": model.thresholds} and "60 curator labels" in event.why
        # The grade stage now runs with the fitted thresholds: a new parameter hash regrades.
        assert param_hash(available_stages()["grade"].params) != default_hash
    shown = json.loads(runner.invoke(args=["grade", "show", "--json"]).output)
    assert shown["model"] == fit["model"] and shown["thresholds"] == fit["thresholds"]

    report = json.loads(runner.invoke(args=["report", "--json"]).output)
    assert report["grade_model"]["fitted_on"] == 60 and report["grade_model"]["held_out"]["accuracy"] == held["accuracy"]


def test_dry_run_saves_nothing(app, runner, labelled) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import GradeModel

    result = runner.invoke(args=["grade", "fit", "--dry-run", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["model"] is None
    with app.app_context():
        assert db.session.query(GradeModel).count() == 0


def test_too_few_labels_is_a_clear_error(runner) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["grade", "fit", "--json"])
    assert result.exit_code == 1
    assert "label" in json.loads(result.output)["error"]


def _bench_document(n: int = 60) -> dict:
    """A `keystone bench grade --json` document whose true error follows the confident fraction:
    bad-2 = 80 - 100 x confident (so few under 25 % is confident > 0.55, failure over 50 % < 0.3)."""
    rng = np.random.default_rng(3)
    results = []
    for index in range(n):
        measurements = _measurements(rng)
        del measurements["reasons"], measurements["uncertainty"]
        measurements["confident_fraction"] = confident = float(rng.uniform(0.15, 0.75))
        results.append(
            {
                "scene": "s",
                "case": f"c{index}",
                "grade": "some",
                "uncertainty": 0.5,
                "true_bad2": round(80.0 - 100.0 * confident, 3),
                "measurements": measurements,
            }
        )
    results.append(
        {"scene": "s", "case": "culled", "grade": "culled", "uncertainty": None, "true_bad2": 100.0, "measurements": None}
    )
    return {"results": results, "summary": {}}


def test_fit_from_bench_learns_the_true_error_and_the_stage_uses_it(app, runner, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from core.audit import AuditEvent
    from core.db import db
    from review.grading import active_grade_params
    from review.models import GradeModel

    path = tmp_path / "bench.json"
    path.write_text(json.dumps(_bench_document()))
    result = runner.invoke(args=["grade", "fit", "--from-bench", str(path), "--json"])
    assert result.exit_code == 0, result.output
    fit = json.loads(result.output)
    assert fit["labels"] == 60 and fit["source"] == "bench grade (true bad-2)"  # the culled card has no measurements
    assert fit["bands"] == {"few_below": 25.0, "failure_above": 50.0}
    assert fit["held_out"]["accuracy"] >= 0.85 and fit["held_out"]["accuracy"] > fit["baseline"]["accuracy"]
    confident = fit["thresholds"]["confident_fraction"]
    assert 0.5 <= confident["some"] <= 0.6 and 0.25 <= confident["failure"] <= 0.35
    with app.app_context():
        model = db.session.get(GradeModel, fit["model"])
        assert model.evaluation["source"] == "bench grade (true bad-2)" and model.fitted_on == 60
        event = db.session.query(AuditEvent).filter_by(entity="grade_model").one()
        assert "60 bench cards by true bad-2" in event.why
        params, active = active_grade_params()
        assert active.id == model.id and params.thresholds.confident_fraction.some == confident["some"]


def test_fit_from_bench_rejects_what_is_not_a_bench_document(runner, tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "other.json"
    path.write_text(json.dumps({"cards": []}))
    result = runner.invoke(args=["grade", "fit", "--from-bench", str(path), "--json"])
    assert result.exit_code == 1 and "results list" in json.loads(result.output)["error"]
    path.write_text("{not json")
    result = runner.invoke(args=["grade", "fit", "--from-bench", str(path), "--json"])
    assert result.exit_code == 1 and "not readable JSON" in json.loads(result.output)["error"]
    path.write_text(json.dumps(_bench_document()))
    result = runner.invoke(
        args=["grade", "fit", "--from-bench", str(path), "--few-below", "60", "--failure-above", "40", "--json"]
    )
    assert result.exit_code == 1 and "few_below <= failure_above" in json.loads(result.output)["error"]

"""``keystone report`` and the report page: grade fractions beside the paper's, agreement of
the automatic grade with curators (confusion, kappa, precision/recall), crowd agreement."""

from __future__ import annotations

import json

import pytest

# (automatic grade, curator decision, curator grade) for eight cards of one collection.
CARDS = [
    ("few", "accepted", "few"),
    ("few", "changed", "some"),
    ("some", "accepted", "some"),
    ("some", "accepted", "some"),
    ("some", "changed", "failure"),
    ("failure", "accepted", "failure"),
    ("failure", "pending", None),
    ("some", "rejected", None),
]


@pytest.fixture
def graded(app, make_card, add_stage_result, card_image):  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    ids = []
    for index, (auto, decision, grade) in enumerate(CARDS):
        card_id = make_card(card_image()[:, index:], state="pass", collection="stereo views")
        add_stage_result(card_id, "grade", outcome=auto, metrics={"uncertainty": 0.1 * index})
        with app.app_context():
            db.session.add(CardReview(card_id=card_id, auto_grade=auto, grade=grade, decision=decision))
            db.session.commit()
        ids.append(card_id)
    return ids


@pytest.mark.both_databases
def test_report_json_counts_fractions_and_agreement(runner, graded) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["report", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["paper"] == {"fractions": {"few": 0.23, "some": 0.49, "failure": 0.28}, "sample": 711}
    (collection,) = report["collections"]
    assert collection["collection"] == "stereo views" and collection["cards"] == 8
    assert collection["automatic"]["counts"] == {"few": 2, "some": 4, "failure": 2}
    assert collection["automatic"]["fractions"] == {"few": 0.25, "some": 0.5, "failure": 0.25}
    # Curated grades count accepted and changed decisions only (6 cards).
    assert collection["curated"]["counts"] == {"few": 1, "some": 3, "failure": 2}
    assert collection["decisions"] == {"accepted": 4, "changed": 2, "pending": 1, "rejected": 1}

    block = report["automatic_vs_curator"]
    assert block["labels"] == 6
    assert block["confusion"] == [[1, 0, 0], [1, 2, 0], [0, 1, 1]]
    assert block["accuracy"] == pytest.approx(4 / 6, abs=1e-4)
    # kappa = (po - pe) / (1 - pe) with po = 4/6, pe = (1*2 + 3*3 + 2*1) / 36 = 13/36.
    assert block["cohen_kappa"] == pytest.approx((4 / 6 - 13 / 36) / (1 - 13 / 36), abs=1e-4)
    assert block["per_class"]["some"] == {
        "precision": pytest.approx(2 / 3, abs=1e-4),
        "recall": pytest.approx(2 / 3, abs=1e-4),
        "support": 3,
    }
    assert block["per_class"]["few"]["precision"] == 0.5 and block["per_class"]["failure"]["recall"] == 0.5
    assert report["grade_model"] is None and report["crowd"] == []


def test_report_text_names_the_paper_and_the_confusion(runner, graded) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["report"])
    assert result.exit_code == 0, result.output
    assert "paper, 711 cards: 23 % / 49 % / 28 %" in result.output
    assert "stereo views: 8 cards" in result.output
    assert "6 labels, accuracy 67 %" in result.output


def test_report_on_an_empty_catalogue(runner) -> None:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["report", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["collections"] == [] and report["automatic_vs_curator"]["accuracy"] is None


@pytest.mark.parametrize(("role", "status"), [(None, 302), ("annotator", 403), ("curator", 200), ("exporter", 200)])
def test_report_page_roles(client, as_role, graded, role, status) -> None:  # type: ignore[no-untyped-def]
    as_role(role)
    response = client.get("/reports/")
    assert response.status_code == status
    if status == 200:
        page = response.get_data(as_text=True)
        assert "few artifacts 23 %" in page and "Cohen's kappa" in page


def test_report_plots_are_pngs_with_etags(client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    for name in ("grades", "agreement"):
        response = client.get(f"/reports/{name}.png")
        assert response.status_code == 200 and response.mimetype == "image/png"
        assert response.data[:8] == b"\x89PNG\r\n\x1a\n" and len(response.data) > 5_000
        again = client.get(f"/reports/{name}.png", headers={"If-None-Match": response.headers["ETag"]})
        assert again.status_code == 304
    assert client.get("/reports/nothing.png").status_code == 404

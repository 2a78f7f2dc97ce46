"""``keystone report`` and the report page: grade fractions beside the paper's, agreement of
the automatic grade with curators (confusion, kappa, precision/recall), crowd agreement."""

from __future__ import annotations

import json
import re

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
    assert block["labels"] == 6 and block["labels_from"] == {"accepted": 4, "changed": 2}
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
    assert "from 4 accepted automatic grade(s) (agreeing by construction) and 2 changed by a curator" in result.output


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


def test_the_page_says_what_the_agreement_is_computed_from(client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    page = client.get("/reports/").get_data(as_text=True)
    assert re.search(
        r"Computed from 6 cards a curator graded:\s+4 accepted with the automatic grade and 2 given another grade\.", page
    )
    assert "Rejected, sent-back and undecided cards carry no grade and are not counted." in page
    assert "agreement is complete by construction" not in page  # two grades were changed


def test_a_kappa_of_accepted_grades_alone_is_called_what_it_is(
    app, client, login, make_card, add_stage_result, card_image
) -> None:  # type: ignore[no-untyped-def]
    from core.db import db
    from review.models import CardReview

    for index, grade in enumerate(("few", "some", "failure")):
        card_id = make_card(card_image()[:, index:], state="pass")
        add_stage_result(card_id, "grade", outcome=grade)
        with app.app_context():
            db.session.add(CardReview(card_id=card_id, auto_grade=grade, grade=grade, decision="accepted"))
            db.session.commit()
    login("curator")
    page = client.get("/reports/").get_data(as_text=True)
    assert "Cohen&#39;s kappa 1.0" in page or "Cohen's kappa 1.0" in page
    assert re.search(
        r"Computed from 3 cards a curator graded:\s+3 accepted with the automatic grade and 0 given another grade", page
    )
    assert re.search(r"the agreement is complete by construction\s+and says nothing about the grader", page)


def test_the_charts_are_drawn_in_the_page(client, login, graded) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    page = client.get("/reports/").get_data(as_text=True)
    assert "<img" not in page.split("<main", 1)[1]  # no picture for the server to draw
    # paper 23/49/28 %, automatic 25/50/25 %, curated 1/3/2 of 6: nine segments, each with its share
    assert len(re.findall(r'<rect class="grade-(?:few|some|failure)" x=', page)) == 9 + 3  # and the legend's three
    assert re.search(r"<title>stereo views: curated: some 50%</title>", page)
    # the confusion table: counts shaded by their share of the largest (2)
    assert re.search(r'<th scope="row">some</th><td class="num shade-2">1</td><td class="num shade-4">2</td>', page)


def test_the_report_does_not_load_scipy_or_matplotlib() -> None:
    """The page's agreement figures come from pipeline.grade_agreement (numpy alone): importing
    the grading package loaded SciPy, 1.5-3 s the first time a server process drew the report."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from review.report import agreement\n"
        "from review.report_charts import grade_bars\n"
        "assert agreement([('few', 'some')])['labels'] == 1\n"
        "print(sorted(m for m in ('scipy', 'matplotlib', 'pipeline.grading') if m in sys.modules))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"

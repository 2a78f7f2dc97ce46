"""The crowd's question table (annotation/questions.py): what it holds today, the tables it
refuses, and a question added to it (as the how-to in docs/ARCHITECTURE.md says) that the judge
page draws, its script sends, validation accepts, the simulated crowd answers and aggregation
decides, with no other file touched."""

from __future__ import annotations

import dataclasses
import json
import re

import pytest
from sqlalchemy import select

from annotation import questions
from annotation.questions import GRID, JUDGE, Question, asked, check_table, keys, page_table, required_keys

# The question a newcomer adds in the how-to: a yes/no box with its own key.
FADED = Question(
    key="faded",
    name="Faded",
    label="Faded (washed out)",
    hotkey="w",
    help="the photos are pale: their darks are grey, their skies white.",
    review="faded",
)
PROLIFIC_JUDGE_PAGE = "/crowd/prolific?PROLIFIC_PID=p&STUDY_ID=s&SESSION_ID=x&kind=judge"


def test_the_table_holds_the_questions_stored_answers_and_keys_have_always_had() -> None:
    from pipeline.decided_orientation import FLAGS

    assert keys(JUDGE) == ("is_stereo", "upside_down", "inverted", "swapped")
    assert required_keys(JUDGE) == ("is_stereo", "upside_down", "inverted")  # older pages did not ask swapped
    assert [q.hotkey for q in JUDGE] == ["n", "f", "i", "s"]
    assert [q.default for q in JUDGE] == [True, False, False, False]  # ticking "Not a stereo pair" says is_stereo false
    assert [q.key for q in JUDGE if q.gate] == ["is_stereo"]
    assert keys(GRID) == FLAGS  # the grid taps the orientation flags its pictures apply
    assert [q.hotkey for q in GRID] == ["u", "n", "d"]
    assert page_table("judge")[0] == {"key": "is_stereo", "hotkey": "n", "default": True, "widget": "checkbox"}
    assert [row["widget"] for row in page_table("judge")] == ["checkbox", "checkbox", "checkbox", "eye_order"]
    assert [row["key"] for row in page_table("grid")] == ["upside_down", "inverted", "swapped"]


@pytest.mark.parametrize(
    ("table", "page", "message"),
    [
        ((*JUDGE, Question("swapped", "Again", "Again", "w", "", "")), "judge", "new Python-identifier key"),
        ((*JUDGE, Question("faded", "Faded", "Faded", "u", "", "")), "judge", "free lower-case hotkey for faded"),
        ((*JUDGE, Question("faded", "Faded", "Faded", "n", "", "")), "judge", "free lower-case hotkey for faded"),
        ((*JUDGE, Question("faded", "Faded", "Faded", "W", "", "")), "judge", "free lower-case hotkey"),
        ((*JUDGE, Question("faded", "Faded", "Faded", "w", "", "", widget="tap")), "judge", "widget in checkbox, eye_order"),
        ((*GRID, Question("faded", "Faded", "Faded", "h", "", "", widget="tap")), "grid", "free lower-case hotkey"),
        ((*JUDGE, Question("faded", "Faded", "Faded", "w", "", "", answer="number")), "judge", "answer"),  # type: ignore[arg-type]
    ],
)
def test_a_table_that_cannot_share_a_page_is_refused(table: tuple[Question, ...], page: str, message: str) -> None:
    reserved = questions.JUDGE_RESERVED_KEYS if page == "judge" else questions.GRID_RESERVED_KEYS
    with pytest.raises(ValueError, match=re.escape(message)):
        check_table(table, page, reserved)


def test_an_optional_question_is_asked_only_where_an_answer_has_it() -> None:
    old = {"is_stereo": True, "upside_down": False, "inverted": False}
    assert keys(asked(JUDGE, [old, None])) == ("is_stereo", "upside_down", "inverted")
    assert keys(asked(JUDGE, [old, {**old, "swapped": False}])) == ("is_stereo", "upside_down", "inverted", "swapped")


@pytest.fixture(params=[False, True], ids=["required", "optional"])
def with_faded(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Question:
    """The judge table with FADED added, as the how-to does it (and only there): required, or
    optional as a question added where answers exist already must be."""
    faded = dataclasses.replace(FADED, optional=request.param)
    table = (*JUDGE, faded)
    check_table(table, "judge", questions.JUDGE_RESERVED_KEYS)
    monkeypatch.setattr(questions, "JUDGE", table)
    return faded


def test_a_question_added_to_the_table_is_drawn_validated_simulated_and_aggregated(app, client, bare_cards, with_faded) -> None:  # type: ignore[no-untyped-def]
    from annotation.answers import CardSize, validate_payload
    from annotation.models import Aggregate, Answer
    from annotation.simulate import seed_simulated_crowd
    from annotation.task_errors import TaskError
    from core.db import db

    # The judge page draws it (box, key, help line, key hint) and hands it to its script.
    html = client.get(PROLIFIC_JUDGE_PAGE).get_data(as_text=True)
    assert '<label><input type="checkbox" name="faded" data-key="w"> <kbd>W</kbd> Faded (washed out)</label>' in html
    assert "<li><strong>Faded (W)</strong>: the photos are pale: their darks are grey, their skies white.</li>" in html
    assert "Keys: <kbd>N</kbd> <kbd>F</kbd> <kbd>I</kbd> <kbd>S</kbd> <kbd>W</kbd> toggle an answer" in html
    block = re.search(r'<script type="application/json" id="questions">(.*?)</script>', html)
    assert block is not None
    table = json.loads(block.group(1))
    assert [row["key"] for row in table] == ["is_stereo", "upside_down", "inverted", "swapped", "faded"]
    assert table[-1] == {"key": "faded", "hotkey": "w", "default": False, "widget": "checkbox"}

    # Validation asks for it (an optional one only where given) and stores it under its key.
    old_answer = {"is_stereo": True, "upside_down": False, "inverted": False, "swapped": False}
    if with_faded.optional:
        assert validate_payload("judge", old_answer, CardSize(600, 200)) == old_answer
    else:
        with pytest.raises(TaskError, match="Expected faded to be true or false, got None"):
            validate_payload("judge", old_answer, CardSize(600, 200))
    assert validate_payload("judge", {**old_answer, "faded": True}, CardSize(600, 200)) == {**old_answer, "faded": True}
    with pytest.raises(TaskError, match="Expected faded to be true or false, got 'yes'"):
        validate_payload("judge", {**old_answer, "faded": "yes"}, CardSize(600, 200))

    # The simulated crowd answers it through the real submit, and aggregation decides it.
    card_ids = bare_cards(4)
    faded_card = card_ids[0]
    with app.app_context():
        summary = seed_simulated_crowd(card_ids, kind="judge", seed=3, truth={faded_card: {"faded": True}})
        assert "faded" in summary["agreement"]
        stored = list(db.session.scalars(select(Answer)))
        assert len(stored) == 16 and all(isinstance(a.payload.get("faded"), bool) for a in stored)
        labels = {row.card_id: row for row in db.session.scalars(select(Aggregate))}
    assert set(labels) == set(card_ids)
    assert labels[faded_card].label["faded"] is True
    assert all(labels[c].label["faded"] is False for c in card_ids[1:])
    assert labels[faded_card].posterior["faded"][1] > 0.5 > labels[card_ids[1]].posterior["faded"][1]


def test_a_question_added_to_the_table_is_answered_with_its_key_in_the_browser(  # type: ignore[no-untyped-def]
    app, server, browser, bare_cards, with_faded
) -> None:
    from annotation.batches import create_batch
    from annotation.models import Answer
    from annotation.providers import InviteProvider
    from core.db import db

    card_ids = bare_cards(2)
    with app.app_context():
        create_batch(card_ids, "judge", 1, 0.0)
        link = f"{server}/crowd/invite/{InviteProvider.invite('wanda').token}"
    page = browser.new_page()
    page.goto(link)
    page.wait_for_selector("#status:has-text('Card 1')", timeout=15_000)
    page.keyboard.press("Escape")  # the first-time instructions
    page.keyboard.press("w")  # the new question's key
    assert page.is_checked("input[name=faded]")
    page.keyboard.press("n")  # and an old one: not a stereo pair
    page.keyboard.press("Enter")
    for _ in range(100):
        with app.app_context():
            stored = [a.payload for a in db.session.scalars(select(Answer))]
        if stored:
            break
        page.wait_for_timeout(100)
    page.close()
    assert stored == [{"is_stereo": False, "upside_down": False, "inverted": False, "swapped": False, "faded": True}]

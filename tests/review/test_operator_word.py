"""An operator's word for a whole collection (``keystone orientation set|show``): the command,
its audit trail, precedence against the step, the crowd and a curator, flag by flag, and the
orientation step's inputs (a new word reruns the step)."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from PIL import Image
from sqlalchemy import select

from core.db import db
from pipeline.decided_orientation import resolve_orientation

SAID_AT = datetime(2026, 11, 27, 9, 30, tzinfo=UTC)


# ---- precedence: curator > operator > crowd > auto, flag by flag (pure) ----


def _step(outcome: str, upside_down: bool, inverted: bool, swapped: bool, *, decided: bool = True) -> SimpleNamespace:
    values = {"upside_down": upside_down, "inverted": inverted, "swapped": swapped}
    flags = {flag: {"value": value, "decided": decided} for flag, value in values.items()}
    return SimpleNamespace(
        status="done", outcome=outcome, param_hash="abc123", reason=None, metrics={"flags": flags, "confidence": 0.93}
    )


def _crowd(**label: bool) -> SimpleNamespace:
    return SimpleNamespace(label={"is_stereo": True, **label}, posterior={"upside_down": 0.97, "inverted": 0.99}, batch_id=7)


def _word(**flags: bool) -> SimpleNamespace:
    said = {flag: flags.get(flag) for flag in ("upside_down", "inverted", "swapped")}
    return SimpleNamespace(**said, collection_name="prints", set_by_name="alice", set_at=SAID_AT)


def _curator(**flags: bool) -> SimpleNamespace:
    said = {flag: flags.get(flag) for flag in ("upside_down", "inverted", "swapped")}
    return SimpleNamespace(**said, curator_name="carol")


def _flags(orientation: dict[str, Any]) -> tuple[Any, ...]:
    return orientation["upside_down"], orientation["inverted"], orientation["swapped"], orientation["decided_by"]


AUTO = _step("auto", False, True, False)  # the step decided: a negative, upright, in eye order
ASKED = _step("ask", False, True, True, decided=False)


@pytest.mark.parametrize(
    ("step", "crowd", "word", "curator", "expected"),
    [
        # each source alone
        (AUTO, None, None, None, (False, True, False, "auto")),
        (ASKED, _crowd(upside_down=True, inverted=False, swapped=False), None, None, (True, False, False, "crowd")),
        (None, None, _word(upside_down=False, inverted=False, swapped=False), None, (False, False, False, "operator")),
        # the operator beats the step on the flag it speaks to; the step keeps the others
        (AUTO, None, _word(inverted=False), None, (False, False, False, "operator")),
        # and beats the crowd on its flag; the crowd keeps upside_down
        (
            ASKED,
            _crowd(upside_down=True, inverted=True, swapped=False),
            _word(inverted=False),
            None,
            (True, False, False, "operator"),
        ),
        # a curator beats the operator on the flag the curator sets, and only there
        (AUTO, None, _word(inverted=False, swapped=False), _curator(inverted=True), (False, True, False, "curator")),
        # a curator on another flag: the operator's word stands on its own
        (
            ASKED,
            _crowd(upside_down=False, inverted=True),
            _word(inverted=False),
            _curator(swapped=True),
            (False, False, True, "curator"),
        ),
        # a word on some flags over a step that asked: the rest still wait for people
        (ASKED, None, _word(inverted=False), None, (None, False, None, None)),
        # the operator settles what the crowd left open (the judge did not ask the eye order)
        (ASKED, _crowd(upside_down=False, inverted=False), _word(swapped=False), None, (False, False, False, "operator")),
    ],
)
def test_precedence_flag_by_flag(step, crowd, word, curator, expected) -> None:  # type: ignore[no-untyped-def]
    assert _flags(resolve_orientation(step, crowd, curator, word)) == expected


def test_the_word_in_words_and_what_a_curator_overrides() -> None:
    word = _word(inverted=False, swapped=False)
    used = resolve_orientation(AUTO, None, None, word)
    assert used["source"] == "orientation step (abc123); operator's word for collection prints (by alice, 2026-11-27)"
    assert used["operator_word"] == "Collection prints: known prints, scanned in eye order, said by alice on 2026-11-27"
    assert used["confidence"] == 0.93  # upside_down still rests on the step
    assert used["operator_overridden"] == []
    assert resolve_orientation(None, None, None, _word(upside_down=False, inverted=False, swapped=False))["confidence"] == 1.0
    overridden = resolve_orientation(AUTO, None, _curator(inverted=True), word)
    assert overridden["operator_overridden"] == ["inverted"] and overridden["source"].endswith("curator override (by carol)")
    # Waiting: the flags the word settled are not asked about.
    waiting = resolve_orientation(ASKED, None, None, _word(inverted=False))
    assert waiting["waiting_for"] == "people (the orientation step is not sure of upside_down, swapped)"
    # Callers that pass no word get what they got before.
    assert resolve_orientation(AUTO, None, None)["operator_word"] is None


# ---- the command, its audit trail and bad input ----


def _invoke(runner, *args: str, code: int = 0) -> Any:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["orientation", *args])
    assert result.exit_code == code, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception  # never a traceback
    return result


def _events(app) -> list[Any]:  # type: ignore[no-untyped-def]
    from core.audit import AuditEvent

    with app.app_context():
        rows = list(db.session.scalars(select(AuditEvent).where(AuditEvent.entity == "orientation").order_by(AuditEvent.id)))
        db.session.expunge_all()
        return rows


@pytest.mark.both_databases
def test_set_show_and_clear_a_word_with_its_audit_trail(app, runner, make_card, make_person, card_image) -> None:  # type: ignore[no-untyped-def]
    for crop, collection in ((0, "prints"), (2, "prints"), (4, "other")):  # three different images
        make_card(card_image()[:, crop:], collection=collection, state="pass")
    operator = make_person(username="olga")

    said = json.loads(
        _invoke(runner, "set", "--collection", "prints", "--inverted", "no", "--note", "a box of prints", "--json").stdout
    )
    assert said["changed"] is True and said["collection"] == "prints"
    word = said["word"]
    assert (word["upside_down"], word["inverted"], word["swapped"]) == (None, False, None)
    assert word["says"] == "known prints" and word["note"] == "a box of prints" and word["cards"] == 2
    assert word["set_by_account"] is None and word["set_by"]  # the OS user

    # A second flag by a named operator account; the first flag stays.
    by = _invoke(runner, "set", "--collection", "prints", "--swapped", "NO", "--by", "olga", "--json")
    word = json.loads(by.stdout)["word"]
    assert (word["inverted"], word["swapped"], word["set_by"], word["set_by_account"]) == (False, False, "olga", "olga")
    assert word["says"] == "known prints, scanned in eye order" and word["note"] == ""
    again = json.loads(_invoke(runner, "set", "--collection", "prints", "--swapped", "no", "--by", "olga", "--json").stdout)
    assert again["changed"] is False  # nothing new: nothing written

    shown = json.loads(_invoke(runner, "show", "--json").stdout)
    assert [w["collection"] for w in shown["words"]] == ["prints"]
    assert json.loads(_invoke(runner, "show", "--collection", "other", "--json").stdout) == {"words": []}
    text = _invoke(runner, "show").output
    assert "prints: known prints, scanned in eye order (said by olga on " in text and "2 card(s)" in text

    cleared = _invoke(runner, "set", "--collection", "prints", "--inverted", "clear", "--swapped", "clear", "--json")
    assert json.loads(cleared.stdout) == {"collection": "prints", "changed": True, "word": None}
    assert json.loads(_invoke(runner, "show", "--json").stdout) == {"words": []}
    nothing = _invoke(runner, "set", "--collection", "prints", "--inverted", "clear", "--note", "still nothing", "--json")
    assert json.loads(nothing.stdout)["changed"] is False  # no word to clear: nothing written

    events = _events(app)
    assert [e.action for e in events] == ["collection_word", "collection_word", "collection_word_cleared"]
    assert all(e.card_id is None and e.entity == "orientation" for e in events)
    first, second, last = events
    assert first.actor.endswith("(keystone orientation set)") and first.actor_id is None and first.why == "a box of prints"
    assert first.before == {"collection": "prints", "upside_down": None, "inverted": None, "swapped": None, "note": None}
    assert first.after == {
        "collection": "prints",
        "upside_down": None,
        "inverted": False,
        "swapped": None,
        "note": "a box of prints",
    }
    assert second.actor == "olga" and second.actor_id == operator.id
    assert second.before["inverted"] is False and second.after["swapped"] is False
    assert last.after == {"collection": "prints", "upside_down": None, "inverted": None, "swapped": None, "note": None}


@pytest.mark.both_databases
def test_bad_input_is_a_message_and_a_non_zero_exit(app, runner, make_card, make_person) -> None:  # type: ignore[no-untyped-def]
    make_card(collection="prints", state="pass")
    make_person(username="gone", active=False)
    unknown = _invoke(runner, "set", "--collection", "nope", "--inverted", "no", code=1)
    assert "There is no collection 'nope'; collections: prints" in unknown.output
    as_json = _invoke(runner, "set", "--collection", "nope", "--inverted", "no", "--json", code=1)
    assert json.loads(as_json.stdout) == {"error": "There is no collection 'nope'; collections: prints"}
    bad = _invoke(runner, "set", "--collection", "prints", "--inverted", "maybe", code=2)
    assert "Invalid value for '--inverted'" in bad.output
    nothing = _invoke(runner, "set", "--collection", "prints", code=1)
    assert "Say at least one flag" in nothing.output
    assert (
        "no active account 'gone'"
        in _invoke(runner, "set", "--collection", "prints", "--inverted", "no", "--by", "gone", code=1).output
    )
    assert (
        "no active account 'who'"
        in _invoke(runner, "set", "--collection", "prints", "--inverted", "no", "--by", "who", code=1).output
    )
    long_note = _invoke(runner, "set", "--collection", "prints", "--inverted", "no", "--note", "x" * 2001, code=1)
    assert "at most 2000 characters" in long_note.output
    shown = _invoke(runner, "show", "--collection", "nope", "--json", code=1)
    assert json.loads(shown.stdout)["error"].startswith("There is no collection 'nope'")
    assert _events(app) == [] and json.loads(_invoke(runner, "show", "--json").stdout) == {"words": []}


# ---- the word through the pipeline: the step's inputs, keystone cards, the card pages ----


@pytest.fixture
def prints_card(tmp_path: Path, runner, mount_pair) -> Path:  # type: ignore[no-untyped-def]
    """One real stereo card (Middlebury Motorcycle mounted on a card) in collection ``prints``."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    folder = tmp_path / "scans"
    folder.mkdir()
    Image.fromarray(mount_pair(left, right)).save(folder / "upright.png")
    result = runner.invoke(args=["ingest", str(folder), "--collection", "prints"])
    assert result.exit_code == 0, result.output
    return folder


def _run(runner, *stages: str) -> dict[str, dict[str, Any]]:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["run", "--json", "--stages", ",".join(stages)])
    assert result.exit_code == 0, result.output
    return {report["stage"]: report for report in json.loads(result.stdout)["stages"]}


def _card(runner) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    result = runner.invoke(args=["cards", "--json"])
    assert result.exit_code == 0, result.output
    (card,) = json.loads(result.stdout)["cards"]
    return card


def _step_inputs(app) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    from core.hooks import approved_decisions
    from core.models import Card
    from pipeline.stages.orientation import orientation_inputs

    with app.app_context():
        card = db.session.scalar(select(Card))
        return orientation_inputs(card, approved_decisions([card.id]).get(card.id, {}))


@pytest.mark.both_databases
def test_a_new_word_changes_the_step_inputs_and_the_step_reruns(app, runner, prints_card) -> None:  # type: ignore[no-untyped-def]
    from pipeline.records import inputs_digest

    first = _run(runner, "filter", "orientation")
    assert first["orientation"]["processed"] == 1 and first["orientation"]["chained"] == 1
    without = _step_inputs(app)
    assert set(without) == {"left_box", "right_box"}  # no word: no key, the digest unchanged
    digest = _card(runner)["stages"]["orientation"]["metrics"]["inputs_digest"]
    assert digest == inputs_digest(without)
    assert _run(runner, "orientation")["orientation"]["processed"] == 0

    _invoke(runner, "set", "--collection", "prints", "--inverted", "no", "--swapped", "no")
    with_word = _step_inputs(app)
    assert with_word == {**without, "known_flags": {"inverted": False, "swapped": False}}
    rerun = _run(runner, "filter", "orientation")
    # The step runs again on its own pass (a chain carries no people's decisions) with the word.
    assert rerun["filter"]["processed"] == 0
    assert rerun["orientation"]["processed"] == 1 and rerun["orientation"]["chained"] == 0
    assert _card(runner)["stages"]["orientation"]["metrics"]["inputs_digest"] == inputs_digest(with_word) != digest
    assert _run(runner, "orientation")["orientation"]["processed"] == 0

    _invoke(runner, "set", "--collection", "prints", "--inverted", "clear", "--swapped", "clear")
    assert _run(runner, "orientation")["orientation"]["processed"] == 1
    assert _card(runner)["stages"]["orientation"]["metrics"]["inputs_digest"] == digest


@pytest.mark.both_databases
def test_a_word_before_the_first_run_reaches_a_chained_step(app, runner, prints_card) -> None:  # type: ignore[no-untyped-def]
    """The chain's worker has no database: the driver sends the collection's word with the card
    (pipeline.chains.ChainTask.approved), so the chained step runs with it and is not redone."""
    from pipeline.records import inputs_digest

    _invoke(runner, "set", "--collection", "prints", "--inverted", "no")
    first = _run(runner, "filter", "orientation")
    assert first["orientation"]["processed"] == 1 and first["orientation"]["chained"] == 1
    metrics = _card(runner)["stages"]["orientation"]["metrics"]
    assert metrics["inputs_digest"] == inputs_digest(_step_inputs(app))
    assert "known_flags" in _step_inputs(app)
    assert _run(runner, "filter", "orientation")["orientation"]["processed"] == 0


@pytest.mark.both_databases
def test_cards_and_card_pages_show_the_word_and_a_curator_still_wins(app, runner, client, login, prints_card) -> None:  # type: ignore[no-untyped-def]
    from core.models import Person
    from review.orientation import override_orientation

    curator = login("curator")
    _run(runner, "filter", "orientation")
    _invoke(
        runner,
        "set",
        "--collection",
        "prints",
        "--upside-down",
        "no",
        "--inverted",
        "no",
        "--swapped",
        "no",
        "--by",
        curator.username,
    )
    card = _card(runner)
    assert card["orientation"] == {
        "upside_down": False,
        "inverted": False,
        "swapped": False,
        "decided_by": "operator",
        "confidence": 1.0,
    }
    assert card["stages"]["judge"]["status"] == "skipped"
    assert "operator's word for collection prints" in card["stages"]["judge"]["reason"]

    today = datetime.now(UTC).strftime("%Y-%m-%d")
    sentence = "Collection prints: scanned upright, known prints, scanned in eye order, said by"
    for url in (f"/cards/{card['id']}", f"/review/cards/{card['id']}"):
        page = client.get(url).get_data(as_text=True)
        assert sentence in page and f" on {today}" in page, url
        assert 'id="orientation-decided-by">operator<' in page and "overrides it" not in page

    with app.app_context():
        person = db.session.get(Person, curator.id)
        override_orientation(card["id"], {"inverted": "yes"}, curator=person, note="a negative after all")
    card = _card(runner)
    assert (card["orientation"]["inverted"], card["orientation"]["swapped"], card["orientation"]["decided_by"]) == (
        True,
        False,
        "curator",
    )
    for url in (f"/cards/{card['id']}", f"/review/cards/{card['id']}"):
        page = client.get(url).get_data(as_text=True)
        assert sentence in page and "A curator's decision on this card overrides it</strong> for inverted" in page, url

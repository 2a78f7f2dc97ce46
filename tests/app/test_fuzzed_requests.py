"""Generated hostile requests (Hypothesis) against the crowd API and the main forms: never a 5xx.

The app runs with TESTING on, so an unhandled exception is raised here (with the example that
caused it) rather than turned into a 500 page; every answer must also be a status below 500.
Examples are few and the database is shared between them (the point is the doors, not the
state), so the module stays well under a minute on SQLite and PostgreSQL together.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

FUZZ = settings(
    max_examples=60,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
)

# Numbers a JSON body may carry: plausible pixel coordinates, and the hostile ones (integers
# of hundreds of digits, NaN, infinities, values past 2**53 or a 64-bit integer).
plausible = st.one_of(st.integers(min_value=-50, max_value=700), st.floats(min_value=-50, max_value=700, allow_nan=False))
hostile = st.one_of(
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([2**31, 2**53, 2**53 + 1, 2**63, -(2**63) - 1, 1e300, 5e-324, math.nan, -math.inf]),
)
numbers = st.one_of(plausible, hostile)
text = st.one_of(
    st.text(max_size=30),
    st.sampled_from(["", "\x00", "judge", "crop", "a" * 300, "²", "\ud800"]),
    st.text(st.characters(categories=["Cs"]), min_size=1, max_size=2),
)  # lone surrogates
scalars = st.one_of(st.none(), st.booleans(), numbers, text)
json_values = st.recursive(
    scalars, lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(text, inner, max_size=5)), max_leaves=25
)


@st.composite
def boxes(draw: st.DrawFn) -> Any:
    """Four plausible coordinates (often a box the card holds), one of them hostile, or anything."""
    shape = draw(st.sampled_from(["inside the card", "plausible", "one hostile", "anything"]))
    if shape == "anything":
        return draw(st.one_of(st.lists(st.one_of(numbers, text), max_size=6), json_values))
    if shape == "inside the card":  # the world's crop card is 596 x 200 px
        x0, y0 = draw(st.floats(min_value=0, max_value=290)), draw(st.integers(min_value=0, max_value=90))
        return [x0, y0, x0 + draw(st.floats(min_value=16, max_value=300)), y0 + draw(st.integers(min_value=16, max_value=110))]
    box = draw(st.lists(plausible, min_size=4, max_size=4))
    if shape == "one hostile":
        box[draw(st.integers(min_value=0, max_value=3))] = draw(st.one_of(hostile, text, st.booleans(), st.none()))
    return box


def mostly(common: st.SearchStrategy[Any], rare: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """``common`` four times in five, else ``rare`` (one_of alone would split them evenly)."""
    return st.sampled_from([True, True, True, True, False]).flatmap(lambda usual: common if usual else rare)


answers = mostly(
    st.fixed_dictionaries({"left": boxes(), "right": boxes()}),
    st.one_of(st.fixed_dictionaries({"is_stereo": scalars, "upside_down": scalars, "inverted": scalars}), json_values),
)


def _dump(value: Any) -> str:
    # Python's encoder writes NaN and Infinity (as browsers' JSON.stringify never would) and
    # integers of any length: exactly the bodies the API must refuse with a 400.
    return json.dumps(value, allow_nan=True)


raw_bodies = st.one_of(
    st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
    st.integers(min_value=1, max_value=20000).map(lambda n: "[" * n + "]" * n),
    st.integers(min_value=1, max_value=5000).map(lambda n: '{"a":' * n + "1" + "}" * n),
    st.sampled_from(['{"kind": NaN}', '{"kind": "crop"', "1" * 5000, "\ufeff{}", '"\\ud800"', "{}" * 3]),
)


@st.composite
def crowd_calls(draw: st.DrawFn) -> list[tuple[str, str]]:
    """Up to three API calls: (next | submit | undo, raw JSON body).

    Most bodies have the shape the page sends, with generated values in it (so they get past
    the loader to the checks behind it: the reservation, the key, the boxes); the rest are any
    JSON or not JSON at all.
    """
    shaped = {
        "next": st.fixed_dictionaries({"kind": st.one_of(st.sampled_from(["crop", "judge"]), scalars)}),
        "submit": st.fixed_dictionaries(
            {
                "token": mostly(st.just("<task>"), scalars),
                "answer": answers,
                "key": mostly(st.uuids().map(str), st.one_of(text, scalars)),
            }
        ),
        "undo": st.just({}),
    }
    calls = []
    for _ in range(draw(st.integers(min_value=1, max_value=3))):
        path = draw(st.sampled_from(["submit", "next", "submit", "undo"]))
        body = mostly(shaped[path].map(_dump), st.one_of(json_values.map(_dump), raw_bodies))
        calls.append((path, draw(body)))
    return calls


def new_worker(app, client) -> str:  # type: ignore[no-untyped-def]
    """A newly invited worker's signed API token."""
    import re
    import secrets

    from annotation.providers import InviteProvider

    with app.app_context():
        link = InviteProvider.invite(f"fuzz-{secrets.token_hex(6)}").token
    page = client.get(f"/crowd/invite/{link}?kind=crop").get_data(as_text=True)
    return re.search(r'data-worker-token="([^"]*)"', page).group(1)  # type: ignore[union-attr]


@pytest.mark.both_databases
@FUZZ
@given(calls=crowd_calls())
def test_the_crowd_api_never_answers_5xx(app, client, hostile_world, calls):
    crowd = {"X-Crowd-Token": new_worker(app, client)}  # so every example has a task to answer
    fetched = client.post("/crowd/api/next", headers=crowd, json={"kind": "crop"})
    assert fetched.status_code == 200
    tasks = fetched.get_json()["tasks"]
    task_token = tasks[0]["token"] if tasks else "no-open-task"
    for path, body in calls:
        body = body.replace('"<task>"', json.dumps(task_token))
        response = client.post(
            f"/crowd/api/{path}", headers=crowd, data=body.encode("utf-8", "surrogatepass"), content_type="application/json"
        )
        assert response.status_code < 500, (path, body[:200], response.get_data(as_text=True)[:300])
        assert response.is_json, (path, response.status_code)
        if response.status_code >= 400:
            assert response.get_json()["error"]["message"]


def _fields(draw: st.DrawFn, names: dict[str, st.SearchStrategy[str]]) -> dict[str, str]:
    return {name: value for name, strategy in names.items() if (value := draw(mostly(strategy, st.none()))) is not None}


form_text = st.one_of(st.text(max_size=40), st.sampled_from(["", "\x00", "9" * 400, "-1", "²", "1e400", "NaN", "a" * 6000]))
numeric_text = st.one_of(form_text, st.integers().map(str), st.floats().map(repr))
# "<version>" and "<review>" become the review's current version and id, so decisions get past
# the version check to the decision itself.
version_text = mostly(st.just("<version>"), numeric_text)
coordinate_text = mostly(st.floats(min_value=-10, max_value=600).map(str), numeric_text)


@st.composite
def review_forms(draw: st.DrawFn) -> tuple[str, dict[str, str]]:
    form = draw(st.sampled_from(["decide", "bulk", "dispute", "preview", "login", "people"]))
    if form == "decide":
        fields = _fields(
            draw,
            {
                "choice": st.one_of(
                    form_text, st.sampled_from(["accept", "change:few", "change:x", "send_back", "reject", "change:"])
                ),
                "version": version_text,
                "note": form_text,
                "kind": form_text,
                "action": form_text,
            },
        )
    elif form == "bulk":
        fields = _fields(
            draw,
            {
                "item": mostly(
                    st.builds(lambda v: f"<review>:{v}", version_text),
                    st.builds(lambda a, b: f"{a}:{b}", numeric_text, numeric_text),
                ),
                "action": st.one_of(form_text, st.sampled_from(["accept", "reject", "change"])),
                "grade": form_text,
                "note": form_text,
            },
        )
    elif form == "dispute":
        names = {f"{half}_{corner}": coordinate_text for half in ("left", "right") for corner in ("x0", "y0", "x1", "y1")}
        fields = _fields(draw, {**names, "make_gold": st.sampled_from(["on", "off", ""]), "note": form_text})
    elif form == "preview":
        fields = _fields(
            draw,
            {
                "min_grade": st.one_of(form_text, st.sampled_from(["few", "some"])),
                "formats": st.one_of(form_text, st.sampled_from(["webdataset", "parquet", "folder"])),
                "notes": form_text,
            },
        )
    elif form == "login":
        fields = _fields(draw, {"username": form_text, "password": form_text, "next": form_text})
    else:
        fields = _fields(
            draw,
            {
                "username": form_text,
                "password": form_text,
                "display_name": form_text,
                "roles": st.one_of(form_text, st.sampled_from(["curator", "admin"])),
            },
        )
    return form, fields


@pytest.mark.both_databases
@settings(FUZZ, max_examples=60)
@given(case=review_forms(), with_token=mostly(st.just(True), st.just(False)), query=mostly(st.just(""), form_text))
def test_the_main_forms_never_answer_5xx(app, client, hostile_world, case, with_token, query):
    from sqlalchemy import select

    from core.db import db
    from review.models import CardReview

    form, fields = case
    url = {
        "decide": f"/review/cards/{hostile_world.card_id}/decide",
        "bulk": "/review/bulk",
        "dispute": f"/review/disputes/{hostile_world.aggregate_id}",
        "preview": "/releases/preview",
        "login": "/auth/login",
        "people": "/auth/people",
    }[form]
    if form == "login" and fields.get("password") and fields.get("username"):
        fields["password"] = fields["password"][:12]  # each login hashes: keep the slow path short
    with app.app_context():
        version = db.session.scalar(select(CardReview.version).where(CardReview.id == hostile_world.review_id))
    fields = {
        name: value.replace("<version>", str(version)).replace("<review>", str(hostile_world.review_id))
        for name, value in fields.items()
    }
    if with_token:
        fields["csrf_token"] = hostile_world.csrf
    response = client.post(url, data=fields, query_string={"page": query, "collection": query} if query else None)
    assert response.status_code < 500, (form, fields, response.get_data(as_text=True)[:300])


def test_generated_numbers_include_what_the_loader_must_refuse():
    # The strategies above reach the loader's refusals, or the property would prove nothing.
    from core.json_body import JSONBodyError, parse_json

    refused = []
    for value in (10**400, math.nan, math.inf, -math.inf, 2**53 + 1):
        with pytest.raises(JSONBodyError) as caught:
            parse_json(_dump([value]).encode())
        refused.append(caught.value.description)
    assert all("Expected" in reason for reason in refused)

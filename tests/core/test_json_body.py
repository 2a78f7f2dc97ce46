"""The JSON body loader: what it parses, what it refuses and the sentence it refuses it with."""

from __future__ import annotations

import json

import pytest

from core.json_body import MAX_DEPTH, MAX_SAFE_INTEGER, JSONBodyError, parse_json


def test_ordinary_bodies_parse_as_json_does():
    for raw in (
        '{"token": "abc", "key": "k-12345678", "answer": {"left": [0, 0.5, 280, 200], "right": [1e2, 0, 590, 2e2]}}',
        '{"kind": "crop"}',
        "[]",
        '{"a": [[[[1]]]], "b": null, "c": true, "d": "\\u00e9\\ud83d\\ude00"}',
        f'{{"n": {MAX_SAFE_INTEGER}, "m": {-MAX_SAFE_INTEGER}}}',
    ):
        assert parse_json(raw.encode()) == json.loads(raw)


def test_depth_is_bounded_and_a_probe_deep_enough_to_overflow_the_parser_is_400():
    at_limit = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    assert parse_json(at_limit.encode()) == json.loads(at_limit)
    for raw in (
        "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1),
        '{"a":' * 40 + "1" + "}" * 40,
        '[{"a": [' * 11 + "1" + "]}]" * 11,
        "[" * 100_000 + "]" * 100_000,
        '{"a":' * 100_000,
    ):
        with pytest.raises(JSONBodyError, match=f"Expected JSON nested at most {MAX_DEPTH} levels deep, got "):
            parse_json(raw.encode())
    # Brackets in strings do not count, however many.
    assert parse_json(json.dumps({"note": "[" * 10_000}).encode()) == {"note": "[" * 10_000}
    assert parse_json(json.dumps([["[" * 40]] * 20).encode()) == [["[" * 40]] * 20


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ("[NaN]", "Expected finite numbers in the JSON body, got NaN."),
        ("[Infinity]", "got Infinity."),
        ("[-Infinity]", "got -Infinity."),
        ("[1e400]", "got 1e400 (out of range)."),
        ("[-1.5e309]", "got -1.5e309 (out of range)."),
        (f"[{MAX_SAFE_INTEGER + 1}]", "Expected whole numbers within +-2**53 in the JSON body, got one of 16 digits."),
        ("[" + "9" * 400 + "]", "got one of 400 digits."),
        ("[-" + "1" * 5000 + "]", "got one of 5000 digits."),
    ],
)
def test_numbers_must_be_finite_and_bounded(raw, message):
    with pytest.raises(JSONBodyError) as caught:
        parse_json(raw.encode())
    assert message in caught.value.description
    assert caught.value.code == 400


@pytest.mark.parametrize(
    ("raw", "reason"),
    [
        (b'{"token": "x", "answer": ', "Expecting value at character 25"),
        (b"{'single': 1}", "Expecting property name enclosed in double quotes"),
        (b"[1, 2,]", "Expecting value"),
        (b"\xff\xfe\xfa", "not UTF-8 text"),
        ('{"a": "\\u0000"}'.encode("utf-16"), "not UTF-8 text"),  # a NUL escape in UTF-16 would slip past
        (b"", "Expecting value at character 0"),
        (b'{"a": 1} {"b": 2}', "Extra data"),
        (b'["\x01"]', "Invalid control character"),
    ],
)
def test_malformed_json_says_where(raw, reason):
    with pytest.raises(JSONBodyError) as caught:
        parse_json(raw)
    assert caught.value.description.startswith("Expected a JSON body; this one is malformed (")
    assert reason in caught.value.description


def test_the_loader_refuses_bodies_of_the_wrong_type_and_unstorable_text(app):
    from core.json_body import NotJSONError, load_json_body

    cases = [
        (b"[1, 2]", "application/json", "Expected a JSON object body, got list."),
        (b'"text"', "application/json", "Expected a JSON object body, got str."),
        (b'{"a": ["ok", {"b": "\\u0000"}]}', "application/json", "may not contain NUL characters"),
        (b'{"a": ["\\udbff"]}', "application/json", "may not contain lone surrogates"),
    ]
    for raw, content_type, message in cases:
        with (
            app.test_request_context("/crowd/api/next", method="POST", data=raw, content_type=content_type),
            pytest.raises(JSONBodyError, match=message),
        ):
            load_json_body()
    with app.test_request_context("/crowd/api/next", method="POST", data=b"{}", content_type="text/plain"):
        with pytest.raises(NotJSONError) as caught:
            load_json_body()
        assert caught.value.code == 415
    with app.test_request_context("/review/bulk", method="POST", data=b"[1]", content_type="application/json"):
        assert load_json_body(expect=list) == [1]


# Found by `keystone bench probe`: Flask-WTF reads a JSON body into a form with request.get_json(),
# so a deeply nested array posted to a form (with the page's CSRF token in the X-CSRFToken
# header) was a RecursionError, a 500, and an object holding an object reached the views as a dict.
FORM_ROUTES = [
    ("/auth/login", None),
    ("/auth/people", "admin"),
    ("/releases/preview", "exporter"),
    ("/releases/publish", "exporter"),
]


# Views that read request.form and render the people page (an empty PersonForm) when they refuse.
PEOPLE_ACTIONS = ["/auth/people/2147483647/active", "/auth/people/2147483647/password", "/auth/people/2147483647/roles"]


@pytest.mark.parametrize(("url", "role"), FORM_ROUTES)
@pytest.mark.parametrize(
    "raw",
    ["[" * 5000, '{"username": {"a": 1}, "password": ["x"], "min_grade": {"x": 1}}', '"text"', "[1, 2]"],
    ids=["nested 5000 deep", "objects in fields", "a string", "an array"],
)
def test_a_json_body_posted_to_a_browser_form_is_415_never_a_500(app, client, login, csrf_token, url, role, raw):
    if role:
        login(role)
    token = csrf_token("/auth/people" if role == "admin" else "/releases/" if role else "/auth/login")
    response = client.post(url, data=raw, content_type="application/json", headers={"X-CSRFToken": token})
    assert response.status_code == 415, response.get_data(as_text=True)[:300]
    assert "form" in response.get_data(as_text=True)


@pytest.mark.parametrize("url", PEOPLE_ACTIONS)
@pytest.mark.parametrize("raw", ['{"kind": "judge"', '{"active": "1"}', "[" * 5000], ids=["malformed", "an object", "nested"])
def test_a_json_body_to_a_people_action_is_a_4xx_page_never_a_500(app, client, login, csrf_token, url, raw):
    login("admin")
    response = client.post(url, data=raw, content_type="application/json", headers={"X-CSRFToken": csrf_token("/auth/people")})
    assert 400 <= response.status_code < 500, response.get_data(as_text=True)[:300]

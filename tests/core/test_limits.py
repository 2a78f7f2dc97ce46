"""Hostile input at every door is a 4xx that says why, never a 5xx: ids out of the database's
range, oversized bodies, absurd JSON, bad query strings, wrong methods, an unwritable preview
cache; and what does slip through to an unhandled exception is a logged, bare 500."""

from __future__ import annotations

import io
import logging
import re
import stat
from pathlib import Path

import click
import pytest
from click.testing import CliRunner
from sqlalchemy import func, select
from werkzeug.routing import IntegerConverter

from core.limits import DATABASE_ID_MAX, RECORD_ID, RECORD_IDS, DatabaseIdConverter, parse_positive_int, parse_whole_number

# Past PostgreSQL's INTEGER, past SQLite's 64-bit INTEGER, past a float, past Python's
# 4,300-digit int() limit; and 0, which no id is.
OUT_OF_RANGE_IDS = ["0", "00", str(DATABASE_ID_MAX + 1), str(2**63), "9" * 400, "1" * 5000]
METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")


def _url(rule: str, int_value: str) -> str:
    return re.sub(r"<(?:(\w+)(?:\([^)]*\))?:)?(\w+)>", lambda m: int_value if m.group(1) == "int" else "x", rule)


def _id_rules(app):  # type: ignore[no-untyped-def]
    return [rule for rule in app.url_map.iter_rules() if "<int:" in rule.rule]


# --------------------------------------------------------------------------------------- ids


def test_every_int_in_a_route_is_a_database_id(app):
    rules = _id_rules(app)
    endpoints = {rule.endpoint for rule in rules}
    # The card pages of the catalogue, the review and the viewer, the images, the disputes.
    assert {
        "catalog.card_page",
        "catalog.original_image",
        "catalog.thumb_image",
        "catalog.artifact_image",
        "review.card",
        "review.decide_card",
        "review.history",
        "review.anaglyph",
        "review.dispute",
        "viewer.card_view",
        "viewer.view_file",
    } <= endpoints
    for rule in rules:
        converters = [c for c in rule._converters.values() if isinstance(c, IntegerConverter)]
        assert converters and all(type(c) is DatabaseIdConverter for c in converters), rule.rule
        assert all((c.min, c.max) == (1, DATABASE_ID_MAX) for c in converters), rule.rule


@pytest.mark.both_databases
def test_ids_outside_the_database_range_are_404_on_every_route(app, client, hostile_world):
    for rule in _id_rules(app):
        for value in OUT_OF_RANGE_IDS:
            url = _url(rule.rule, value)
            for method in sorted(rule.methods & set(METHODS)):
                response = client.open(url, method=method, headers={"X-CSRFToken": hostile_world.csrf})
                assert response.status_code == 404, (method, url[:80], response.status_code)


@pytest.mark.both_databases
def test_the_largest_id_both_databases_hold_is_an_ordinary_missing_card(client, hostile_world):
    largest = DATABASE_ID_MAX
    for url in (
        f"/cards/{largest}",
        f"/cards/{largest}/image/thumb",
        f"/review/cards/{largest}",
        f"/viewer/cards/{largest}",
        f"/review/disputes/{largest}",
    ):
        response = client.get(url)
        assert response.status_code == 404, url
        assert str(largest) in response.get_data(as_text=True)
    decided = client.post(
        f"/review/cards/{largest}/decide", json={"action": "accept", "version": 1}, headers={"X-CSRFToken": hostile_world.csrf}
    )
    assert decided.status_code == 404 and "has no review yet" in decided.get_json()["error"]["message"]


def test_a_huge_id_is_a_404_page_that_says_so(client, hostile_world):
    response = client.get("/cards/9223372036854775808")
    assert response.status_code == 404 and response.mimetype == "text/html"
    assert "Not Found" in response.get_data(as_text=True)
    as_json = client.get("/cards/2147483648", headers={"Accept": "application/json"})
    assert as_json.status_code == 404 and as_json.get_json()["error"]["code"] == 404


def test_a_database_id_converter_may_narrow_its_range_but_not_widen_it(app):
    from werkzeug.routing import Map, Rule

    urls = Map(
        [Rule("/a/<int(max=99):n>", endpoint="a"), Rule("/b/<int(max=99999999999):n>", endpoint="b")],
        converters={"int": DatabaseIdConverter},
    ).bind("localhost")
    assert urls.match("/a/99") == ("a", {"n": 99})
    assert urls.match(f"/b/{DATABASE_ID_MAX}") == ("b", {"n": DATABASE_ID_MAX})
    for url in ("/a/100", f"/b/{DATABASE_ID_MAX + 1}", "/a/0"):
        with pytest.raises(Exception, match="404"):
            urls.match(url)
    with pytest.raises(ValueError, match="never negative"):
        Map([Rule("/c/<int(signed=True):n>", endpoint="c")], converters={"int": DatabaseIdConverter})


@pytest.mark.parametrize(
    "value",
    ["0", "-1", "+1", "abc", "1.5", "1_0", "\uff15", "²", "٣", " ", "1e3", str(DATABASE_ID_MAX + 1), "9" * 5000],
)
def test_parse_positive_int_refuses_what_is_no_id(value):
    with pytest.raises(ValueError, match="positive whole number"):
        parse_positive_int(value, "page")


@pytest.mark.parametrize("value", [True, 0, -1, DATABASE_ID_MAX + 1, 2**63, 1.0, None, [1], {"id": 1}])
def test_parse_positive_int_refuses_json_values_that_are_no_id(value):
    with pytest.raises(ValueError, match="positive whole number"):
        parse_positive_int(value, "version")


def test_parse_whole_number_refuses_an_int_too_long_to_print():
    with pytest.raises(ValueError, match="thousands of digits"):
        parse_positive_int(10**5000, "version")


def test_parse_whole_number_keeps_to_its_range():
    assert parse_whole_number("0", "answers", minimum=0, maximum=50) == 0
    assert parse_whole_number(50, "answers", minimum=0, maximum=50) == 50
    for value in ("51", "-1", "1_0", "\uff13"):
        with pytest.raises(ValueError, match="answers to be a whole number from 0 to 50"):
            parse_whole_number(value, "answers", minimum=0, maximum=50)


def test_ids_in_urls_are_ascii_digits_only(app):
    urls = app.url_map.bind("localhost")
    assert urls.match("/cards/7")[1] == {"card_id": 7}
    for url in ("/cards/\uff15", "/cards/\u0663", "/cards/1_0", "/cards/+1", "/review/cards/\uff11"):
        with pytest.raises(Exception, match="404"):
            urls.match(url)


def test_parse_positive_int_reads_ids_in_range():
    assert parse_positive_int(" 42 ", "page") == 42
    assert parse_positive_int("000" + str(DATABASE_ID_MAX), "page") == DATABASE_ID_MAX


@pytest.mark.parametrize("value", ["0", "-1", "1_0", "\uff15", "\u00b2", "", "1.0", str(DATABASE_ID_MAX + 1), "9" * 5000])
def test_a_record_id_on_the_command_line_is_ascii_digits_in_range(value):
    with pytest.raises(click.BadParameter, match=r"Expected a record id \(ASCII digits, 1 to 2147483647\), got '"):
        RECORD_ID.convert(value, None, None)


def test_a_record_id_on_the_command_line_reads_ids_in_range():
    assert RECORD_ID.convert("10", None, None) == 10
    assert RECORD_ID.convert(str(DATABASE_ID_MAX), None, None) == DATABASE_ID_MAX
    assert RECORD_IDS.convert("1,2 3", None, None) == [1, 2, 3]
    assert RECORD_IDS.convert("", None, None) == []


def test_a_bad_record_id_is_a_usage_error_naming_the_argument():
    @click.command()
    @click.argument("batch_id", type=RECORD_ID)
    @click.option("--cards", type=RECORD_IDS, default="")
    def show(batch_id: int, cards: list[int]) -> None:
        click.echo(f"{batch_id} {cards}")

    runner = CliRunner()
    assert runner.invoke(show, ["10", "--cards", "4,5"]).output == "10 [4, 5]\n"
    refused = runner.invoke(show, ["1_0"])
    assert refused.exit_code == 2
    assert "Invalid value for 'BATCH_ID': Expected a record id (ASCII digits, 1 to 2147483647), got '1_0'." in refused.output
    refused = runner.invoke(show, ["1", "--cards", "4,\uff15"])
    assert refused.exit_code == 2 and "Invalid value for '--cards'" in refused.output


# ------------------------------------------------------------------------------ query strings


CATALOGUE_QUERIES = [
    ("page=-1", 400),
    ("page=abc", 400),
    ("page=0", 400),
    ("page=%C2%B2", 400),
    ("page=1e9", 400),
    ("page=" + "9" * 30, 400),
    (f"page={DATABASE_ID_MAX}", 404),
    ("page=2", 404),
    ("collection=" + "9" * 30, 400),
    (f"collection={DATABASE_ID_MAX + 1}", 400),
    (f"collection={DATABASE_ID_MAX}", 404),
    ("state=lost", 400),
    ("stage=paint&status=done", 400),
    ("stage=filter&status=maybe", 400),
    ("state=" + "x" * 5000, 400),
    ("page=1&page=abc", 200),
    ("state=pass&stage=grade&status=done", 200),
]
REVIEW_QUERIES = [
    ("page=-1", 400),
    ("page=abc", 400),
    ("page=%C2%B2", 400),
    ("page=" + "9" * 30, 400),
    (f"page={DATABASE_ID_MAX}", 404),
    ("collection=" + "9" * 30, 400),
    (f"collection={DATABASE_ID_MAX}", 200),
    ("grade=great", 400),
    ("decision=maybe", 400),
    ("reason=" + "x" * 300, 400),
    ("reason=%00", 400),
    ("grade=some&decision=all", 200),
]


@pytest.mark.both_databases
def test_bad_query_strings_are_400_or_404_never_500(client, hostile_world):
    wrong = []
    for path, cases in (
        ("/cards", CATALOGUE_QUERIES),
        ("/review/", REVIEW_QUERIES),
        (f"/review/cards/{hostile_world.card_id}", REVIEW_QUERIES),
    ):
        for query, status in cases:
            if path.startswith("/review/cards/") and (status == 404 or query.startswith("page=")):
                status = 200  # a card page has no pages: it reads the queue's filters, not its page
            response = client.get(f"{path}?{query}")
            if response.status_code != status:
                wrong.append((path, query[:40], response.status_code, status))
            elif status == 400:
                text = response.get_data(as_text=True)
                assert "Expected" in text or "Unknown" in text or "needs a stage" in text or "NUL" in text, query
    assert wrong == []


@pytest.mark.both_databases
def test_review_decisions_with_absurd_versions_and_selections(client, hostile_world):
    url = f"/review/cards/{hostile_world.card_id}/decide"
    for version in ("²", "9" * 5000, "-1", "1.0", ""):
        response = client.post(url, data={"choice": "accept", "version": version, "csrf_token": hostile_world.csrf})
        assert response.status_code == 400 and "version of the review you saw" in response.get_data(as_text=True)
    for version in (2**53, -(2**53), 0, True, "1_0", "\uff11"):  # outside the database's range, or no id at all
        response = client.post(url, json={"action": "accept", "version": version}, headers={"X-CSRFToken": hostile_world.csrf})
        assert response.status_code == 400, response.get_data(as_text=True)
        assert "version of the review you saw" in response.get_json()["error"]["message"]
    response = client.post(
        url, json={"action": "accept", "version": DATABASE_ID_MAX}, headers={"X-CSRFToken": hostile_world.csrf}
    )
    assert response.status_code == 409, response.get_data(as_text=True)  # a version nobody saw
    for item in ("9" * 30 + ":1", "1:" + "9" * 5000, "²:1", "1"):
        response = client.post("/review/bulk", data={"item": item, "action": "accept", "csrf_token": hostile_world.csrf})
        assert response.status_code == 400 and "review:version" in response.get_data(as_text=True)
    not_a_list = client.post(
        "/review/bulk", json={"items": {"review": 1}, "action": "accept"}, headers={"X-CSRFToken": hostile_world.csrf}
    )
    assert not_a_list.status_code == 400 and "list" in not_a_list.get_json()["error"]["message"]
    accepted = client.post(
        url, json={"action": "accept", "version": hostile_world.review_version}, headers={"X-CSRFToken": hostile_world.csrf}
    )
    assert accepted.status_code == 200 and accepted.get_json()["decision"] == "accepted"


@pytest.mark.both_databases
def test_nul_characters_are_400_in_paths_query_strings_forms_and_json(client, csrf_token, hostile_world):
    for url in (
        "/crowd/invite/abc%00def",
        "/releases/1.0%00/README.md",
        "/cards?state=pass%00",
        "/crowd/prolific?PROLIFIC_PID=a%00b&STUDY_ID=s&SESSION_ID=t",
        "/review/?reason=a%00",
    ):
        response = client.get(url)
        assert response.status_code == 400, url
        assert "may not contain NUL characters" in response.get_data(as_text=True)
    login = client.post("/auth/login", data={"username": "admin\x00", "password": "x" * 10, "csrf_token": hostile_world.csrf})
    assert login.status_code == 400 and "NUL" in login.get_data(as_text=True)
    crowd = {"X-Crowd-Token": hostile_world.worker_token}
    for body in ({"kind": "crop\x00"}, {"token": "a\x00", "key": "nul-key-123", "answer": {}}, {"a\x00": 1}):
        response = client.post("/crowd/api/submit", headers=crowd, json=body)
        assert response.status_code == 400
        assert response.get_json()["error"]["message"] == "Text in the JSON body may not contain NUL characters (\\u0000)."


@pytest.mark.both_databases
def test_lone_surrogates_in_json_text_are_400(client, hostile_world):
    # Valid JSON escapes that no database can encode (UnicodeEncodeError on SQLite and PostgreSQL).
    crowd = {"X-Crowd-Token": hostile_world.worker_token}
    for body in (
        '{"token": "\\ud800", "key": "surrogate-1", "answer": {}}',
        '{"token": "x", "key": "\\udfffsurrogate", "answer": {}}',
        '{"kind": "crop", "\\udc80": 1}',
    ):
        response = client.post("/crowd/api/submit", headers=crowd, data=body, content_type="application/json")
        assert response.status_code == 400, body
        assert "lone surrogates" in response.get_json()["error"]["message"]
    paired = client.post(
        "/crowd/api/next", headers=crowd, data='{"kind": "crop", "note": "\\ud83d\\ude00"}', content_type="application/json"
    )
    assert paired.status_code == 200  # a surrogate pair is one ordinary character (an emoji)


@pytest.mark.both_databases
def test_odd_urls_headers_and_cookies_are_4xx(client, hostile_world):
    expected = {
        "/crowd/finish?t=" + "é" * 10: 403,
        "/crowd/mturk?assignmentId=a&hitId=b&workerId=c&turkSubmitTo=http://[::1": 400,
        "/crowd/prolific?PROLIFIC_PID=" + "x" * 10000 + "&STUDY_ID=s&SESSION_ID=t": 400,
        "/static/" + "a" * 5000: 404,
        "/review/review-static/..%2f..%2fviews.py": 404,
        "/releases/" + "1" * 1000 + "/README.md": 404,
        f"/cards/{hostile_world.card_id}/image/" + "s" * 3000 + "/name": 404,
        "/crowd/task/" + "t" * 10000 + "/image": 404,
    }
    for url, status in expected.items():
        assert client.get(url).status_code == status, url[:60]
    for token in ("é" * 100, "a.b.c", "x" * 60000, "", "\x7f"):
        response = client.post("/crowd/api/next", headers={"X-Crowd-Token": token}, json={})
        assert response.status_code == 403 and "worker token" in response.get_json()["error"]["message"]
    thumb = f"/cards/{hostile_world.card_id}/image/thumb"
    for headers in (
        {"Range": "bytes=9999999999999999999999-"},
        {"Range": "bytes=-0"},
        {"If-None-Match": '"' * 1000},
        {"If-Modified-Since": "Mon, 99 Foo 99999 99:99:99 GMT"},
        {"If-Range": "x"},
        {"Accept": "application/json;q=NaN"},
    ):
        assert client.get(thumb, headers=headers).status_code in (200, 206, 416), headers
    client.set_cookie("session", "garbage")
    client.set_cookie("remember_token", "1|" + "a" * 100)
    assert client.get("/cards").status_code == 302  # logged out: to the login page


def test_an_unparseable_next_url_is_ignored(client, hostile_world):
    response = client.get("/auth/login?next=http://[::1")  # logged in: redirects to next or home
    assert response.status_code == 302
    assert "[" not in response.headers["Location"]  # home, not the unparseable target


# ---------------------------------------------------------------------------------- methods


def test_wrong_methods_are_405_on_every_route(app, client, hostile_world):
    checked = 0
    allowed: dict[str, set[str]] = {}  # one address may have a rule per method (a GET beside a POST)
    for rule in app.url_map.iter_rules():
        allowed.setdefault(rule.rule, set()).update(rule.methods or ())
    for rule in app.url_map.iter_rules():
        url = _url(rule.rule, str(hostile_world.card_id))
        for method in METHODS:
            if method in allowed[rule.rule]:
                continue
            response = client.open(url, method=method, headers={"X-CSRFToken": hostile_world.csrf})
            assert response.status_code == 405, (method, url, response.status_code)
            assert response.headers["Allow"]
            checked += 1
    assert checked > 100


# -------------------------------------------------------------------------------- body sizes


def test_a_64_mb_form_is_refused_before_it_is_read(client):
    response = client.post(
        "/auth/login", data=b"username=" + b"x" * (64 * 1024 * 1024), content_type="application/x-www-form-urlencoded"
    )
    assert response.status_code == 413 and response.mimetype == "text/html"
    assert "the limit here is 1,048,576 bytes" in response.get_data(as_text=True)


def test_the_crowd_api_takes_at_most_64_kb(client, hostile_world):
    headers = {"X-Crowd-Token": hostile_world.worker_token}
    padded = '{"kind": "crop", "padding": "' + "x" * (64 * 1024 - 60) + '"}'
    assert len(padded) < 64 * 1024
    assert client.post("/crowd/api/next", headers=headers, data=padded, content_type="application/json").status_code == 200
    for size in (64 * 1024 + 1, 64 * 1024 * 1024):
        response = client.post(
            "/crowd/api/submit", headers=headers, data=b"{" + b" " * size + b"}", content_type="application/json"
        )
        assert response.status_code == 413
        assert response.get_json()["error"]["message"] == (
            f"This request's body is {size + 2:,} bytes; the limit here is 65,536 bytes."
        )


def test_a_chunked_body_is_cut_off_at_the_limit(client, hostile_world):
    # No Content-Length: the server says the stream ends (wsgi.input_terminated), Werkzeug reads
    # it only up to the limit, then answers 413.
    body = b'{"kind": "judge", "padding": "' + b"x" * (200 * 1024) + b'"}'
    response = client.post(
        "/crowd/api/next",
        input_stream=io.BytesIO(body),
        content_type="application/json",
        headers={"X-Crowd-Token": hostile_world.worker_token},
        environ_overrides={"wsgi.input_terminated": True},
    )
    assert response.status_code == 413 and response.get_json()["error"]["code"] == 413


def test_the_limits_come_from_the_environment(monkeypatch, tmp_path):
    from app import create_app

    monkeypatch.setenv("KEYSTONE_MAX_REQUEST_BYTES", "2048")
    monkeypatch.setenv("KEYSTONE_API_MAX_BYTES", "512")
    app = create_app(
        {"SQLALCHEMY_DATABASE_URI": f"sqlite:///{tmp_path / 'k.sqlite3'}", "SECRET_KEY": "x"}, instance_path=tmp_path / "instance"
    )
    assert app.config["MAX_CONTENT_LENGTH"] == 2048 and app.config["KEYSTONE_API_MAX_BYTES"] == 512
    client = app.test_client()
    assert client.post("/crowd/api/next", data="x" * 513, content_type="application/json").status_code == 413
    assert client.post("/auth/login", data={"username": "x" * 2048}).status_code == 413


# ------------------------------------------------------------------------------------- JSON


@pytest.mark.both_databases
def test_deeply_nested_json_is_400_everywhere(client, hostile_world):
    crowd = {"X-Crowd-Token": hostile_world.worker_token}
    nested = "[" * 30000 + "]" * 30000  # 60 KB: under the API's limit, so it is parsed
    for path in ("next", "submit", "undo"):
        response = client.post(f"/crowd/api/{path}", headers=crowd, data=nested, content_type="application/json")
        assert response.status_code == 400
        assert response.get_json()["error"]["message"] == (
            "Expected JSON nested at most 32 levels deep, got one nested too deep to parse."
        )
    shallow_but_too_deep = "[" * 33 + "]" * 33
    response = client.post("/crowd/api/next", headers=crowd, data=shallow_but_too_deep, content_type="application/json")
    assert response.get_json()["error"]["message"] == "Expected JSON nested at most 32 levels deep, got deeper."
    probe = "[" * 100000 + "]" * 100000  # the probe's body: over the API's limit
    assert client.post("/crowd/api/submit", headers=crowd, data=probe, content_type="application/json").status_code == 413
    staff = {"X-CSRFToken": hostile_world.csrf}
    for url in (f"/review/cards/{hostile_world.card_id}/decide", "/review/bulk"):
        response = client.post(url, headers=staff, data=probe, content_type="application/json")
        assert response.status_code == 400 and "nested at most 32 levels" in response.get_json()["error"]["message"]


ABSURD_COORDINATES = [
    ("9" * 400, "whole numbers within +-2**53"),
    ("1" + "0" * 5000, "whole numbers within +-2**53"),
    ("1e400", "got 1e400 (out of range)"),
    ("-Infinity", "got -Infinity"),
    ("NaN", "got NaN"),
    (str(2**53), "inside the 596x200 image"),
    ("1e300", "inside the 596x200 image"),
    ('"100"', "four numbers"),
    ("[100]", "four numbers"),
    ("true", "four numbers"),
    ("null", "four numbers"),
]


@pytest.mark.both_databases
def test_absurd_box_coordinates_are_400_and_store_nothing(app, client, hostile_world):
    from annotation.models import Answer
    from core.db import db

    crowd = {"X-Crowd-Token": hostile_world.worker_token}
    task = client.post("/crowd/api/next", headers=crowd, json={"kind": "crop"}).get_json()["tasks"][0]
    for coordinate, message in ABSURD_COORDINATES:
        body = (
            f'{{"token": "{task["token"]}", "key": "absurd-box-1", '
            f'"answer": {{"left": [0, 0, {coordinate}, 100], "right": [300, 0, 590, 200]}}}}'
        )
        response = client.post("/crowd/api/submit", headers=crowd, data=body, content_type="application/json")
        assert response.status_code == 400, (coordinate[:20], response.get_data(as_text=True)[:300])
        assert message in response.get_json()["error"]["message"], coordinate[:20]
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Answer)) == 0
    good = client.post(
        "/crowd/api/submit",
        headers=crowd,
        json={"token": task["token"], "key": "sane-box-1", "answer": {"left": [0, 0, 280, 200], "right": [300, 0, 590, 200]}},
    )
    assert good.status_code == 201


def test_validate_box_refuses_a_coordinate_no_float_holds():
    from annotation.aggregation import InvalidBoxError, validate_box

    with pytest.raises(InvalidBoxError, match="four finite numbers"):
        validate_box([0, 0, 10**400, 100], (600, 200))
    with pytest.raises(InvalidBoxError, match="too large to print"):
        validate_box([10**5000, 0, 1, 1])
    with pytest.raises(InvalidBoxError, match="four finite numbers"):
        validate_box([0, 0, "wide", 100])


def test_the_crowd_api_says_415_for_a_body_that_is_not_json(client, hostile_world):
    response = client.post("/crowd/api/next", headers={"X-Crowd-Token": hostile_world.worker_token}, data={"kind": "crop"})
    assert response.status_code == 415
    assert response.get_json()["error"]["message"] == "Expected a JSON body (Content-Type: application/json)."


# --------------------------------------------------------------------------- preview cache


def _make_cache_unwritable(data_dir: Path, how: str) -> None:
    previews = data_dir / "previews"
    if how == "file in the way":
        previews.write_bytes(b"not a folder")  # mkdir and every write below it fail, even for root
    else:
        previews.mkdir()
        previews.chmod(stat.S_IRUSR | stat.S_IXUSR)


@pytest.mark.parametrize("how", ["file in the way", "read-only folder"])
def test_images_are_served_when_the_preview_cache_cannot_be_written(app, client, hostile_world, data_dir, caplog, how):
    import os

    if how == "read-only folder" and os.geteuid() == 0:
        pytest.skip("root writes into read-only folders; the file-in-the-way case covers it")
    _make_cache_unwritable(data_dir, how)
    crowd = {"X-Crowd-Token": hostile_world.worker_token}
    task = client.post("/crowd/api/next", headers=crowd, json={"kind": "crop"}).get_json()["tasks"][0]
    with caplog.at_level(logging.WARNING, logger=app.logger.name):
        for url in (
            f"/cards/{hostile_world.card_id}/image/original",
            f"/cards/{hostile_world.card_id}/image/thumb",
            f"/cards/{hostile_world.crop_card_id}/image/thumb",
            task["image_url"],
        ):
            response = client.get(url)
            assert response.status_code == 200, url
            assert response.mimetype == "image/jpeg" and response.data[:2] == b"\xff\xd8"
            assert response.headers["ETag"]
            again = client.get(url, headers={"If-None-Match": response.headers["ETag"]})
            assert again.status_code == 304
    warnings = [r for r in caplog.records if "without their cache" in r.getMessage()]
    assert len(warnings) == 1  # once for the folder, not once per image
    if how == "file in the way":
        assert (data_dir / "previews").read_bytes() == b"not a folder"
    else:
        (data_dir / "previews").chmod(stat.S_IRWXU)
        assert list((data_dir / "previews").iterdir()) == []


def test_thumbnail_from_memory_matches_the_cached_one(app, client, hostile_world, data_dir):
    url = f"/cards/{hostile_world.card_id}/image/thumb"
    cached = client.get(url).data
    assert (data_dir / "previews").is_dir()
    for path in (data_dir / "previews").iterdir():
        path.unlink()
    (data_dir / "previews").rmdir()
    _make_cache_unwritable(data_dir, "file in the way")
    assert client.get(url).data == cached


# ------------------------------------------------------------------------------ catch-all


def test_an_unhandled_exception_is_logged_and_a_bare_500(app, client, caplog):
    def broken() -> str:
        raise RuntimeError("secret internals: /etc/keystone")

    app.add_url_rule("/crowd/api/test-broken", view_func=broken)
    app.add_url_rule("/test-broken", view_func=broken)
    app.config["PROPAGATE_EXCEPTIONS"] = False
    with caplog.at_level(logging.ERROR, logger=app.logger.name):
        api = client.get("/crowd/api/test-broken")
        page = client.get("/test-broken")
    assert api.status_code == 500 and api.get_json()["error"] == {
        "code": 500,
        "name": "Internal Server Error",
        "message": "The server encountered an internal error and was unable to complete your request. "
        "Either the server is overloaded or there is an error in the application.",
    }
    assert page.status_code == 500 and page.mimetype == "text/html"
    for response in (api, page):
        text = response.get_data(as_text=True)
        assert "secret internals" not in text and "Traceback" not in text and "RuntimeError" not in text
    logged = [r for r in caplog.records if r.exc_info and "secret internals" in str(r.exc_info[1])]
    assert len(logged) == 2


def test_an_error_page_that_cannot_render_falls_back_to_a_bare_one(app, client, caplog):
    def broken() -> str:
        raise RuntimeError("the database is gone")

    app.add_url_rule("/test-broken", view_func=broken)
    app.config["PROPAGATE_EXCEPTIONS"] = False
    app.jinja_env.globals["url_for"] = None  # the error page's links cannot be built now
    with caplog.at_level(logging.ERROR, logger=app.logger.name):
        response = client.get("/test-broken")
    assert response.status_code == 500
    html = response.get_data(as_text=True)
    assert "<h1>500 Internal Server Error</h1>" in html and "the database is gone" not in html
    assert any("error page could not be rendered" in r.getMessage() for r in caplog.records)


@pytest.mark.both_databases
def test_a_curators_dispute_answer_with_absurd_coordinates_is_400(client, hostile_world):
    url = f"/review/disputes/{hostile_world.aggregate_id}"
    sane = {
        "left_x0": "0",
        "left_y0": "0",
        "left_x1": "280",
        "left_y1": "200",
        "right_x0": "300",
        "right_y0": "0",
        "right_x1": "590",
        "right_y1": "200",
    }
    for value, message in (
        ("9" * 400, "finite number"),
        ("1e400", "finite number"),
        ("nan", "finite number"),
        ("-inf", "finite number"),
        ("1e300", "inside the 596x200 image"),
        ("²", "a number"),
    ):
        response = client.post(url, data={**sane, "right_x1": value, "csrf_token": hostile_world.csrf})
        assert response.status_code == 400, (value[:20], response.status_code)
        assert message in response.get_data(as_text=True), value[:20]
    resolved = client.post(url, data={**sane, "csrf_token": hostile_world.csrf})
    assert resolved.status_code == 303

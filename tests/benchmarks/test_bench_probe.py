"""``keystone bench probe``: its pieces on their own (default run), and the quick probe of the
served demo end to end (``bench``: the demo build alone takes 25-45 s on the 2-core machine, the
whole quick probe about two minutes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.probe import Answer, app_routes, fill, live_formulas, refused_to_role, role_may, to_login

REPO = Path(__file__).resolve().parents[2]


def test_every_rule_of_the_url_map_is_probed_with_the_roles_its_view_requires(app):
    routes = {(route.endpoint, route.rule): route for route in app_routes(app)}
    assert len(routes) == len(list(app.url_map.iter_rules()))
    by_endpoint = {route.endpoint: route for route in routes.values()}
    assert by_endpoint["exports.publish"].roles == ("exporter",) and by_endpoint["exports.publish"].methods == ("POST",)
    assert by_endpoint["auth.people"].roles == ("admin",) and by_endpoint["auth.people"].methods == ("GET", "POST")
    assert by_endpoint["crowd.new_batch"].roles == ("curator",)
    assert by_endpoint["auth.login"].roles is None and by_endpoint["crowd.api_submit"].roles is None
    assert by_endpoint["catalog.card_page"].arguments == (("card_id", "int"),)
    assert by_endpoint["exports.release_file"].arguments == (("version", "default"), ("name", "path"))


def test_role_may_lets_admins_everywhere_and_anonymous_nowhere_a_role_is_needed(app):
    publish = next(route for route in app_routes(app) if route.endpoint == "exports.publish")
    assert [role_may(publish, role) for role in ("anonymous", "annotator", "curator", "exporter", "admin")] == [
        False,
        False,
        False,
        True,
        True,
    ]
    login = next(route for route in app_routes(app) if route.endpoint == "auth.login")
    assert role_may(login, "anonymous") is None


def test_fill_sends_hostile_parts_as_written():
    assert fill("/cards/<int:card_id>", {"card_id": "\uff15"}) == "/cards/%EF%BC%95"
    assert fill("/cards/<int:card_id>", {"card_id": "1_0"}) == "/cards/1_0"
    assert fill("/releases/<version>/files/<path:name>", {"version": "1.0.0", "name": "../../x.sqlite3"}) == (
        "/releases/1.0.0/files/../../x.sqlite3"
    )
    assert fill("/r/<name>", {"name": "a%00b"}) == "/r/a%00b"  # already encoded: kept


def test_refusals_are_401_403_or_a_redirect_to_the_login_page():
    assert to_login(Answer(302, {"location": "/auth/login?next=%2Freview%2F"}, b""))
    assert to_login(Answer(401, {}, b""))
    assert refused_to_role(Answer(403, {}, b""))
    assert not refused_to_role(Answer(302, {"location": "/releases/1.0.0/"}, b""))
    assert not refused_to_role(Answer(404, {}, b""))


def test_live_formulas_finds_cells_a_spreadsheet_would_run_and_passes_numbers_and_quoted_ones():
    text = 'worker,session,score,note\n\'=HYPERLINK("x"),-session,-3,\'@a\n"=HYPERLINK(""http://x"")", @b,+1.5,"\tx"\n'
    assert live_formulas(text) == ["-session", '=HYPERLINK("http://x")', " @b", "\tx"]


@pytest.mark.bench
def test_the_quick_probe_of_the_served_demo_finds_no_5xx_and_nothing_wrongly_stored(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "app", "bench", "probe", "--quick", "--dir", str(tmp_path / "demo"), "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-3000:]
    report = json.loads(result.stdout)
    assert report["total"]["5xx"] == 0 and report["total"]["wrongly_stored"] == 0, report["families"]
    assert report["total"]["unexpected"] == 0, report["families"]
    assert report["server_tracebacks"] == 0
    families = report["families"]
    assert families["role-by-route"]["requests"] >= 5 * report["routes"]
    assert families["hostile"]["requests"] >= 100
    notes = report["notes"]
    assert notes["publish_race"] == {"statuses": [303, 409], "releases_made": 1}
    assert notes["batch_race"]["batches_made"] == 1 and notes["answer_race"]["answers_stored"] == 1
    assert notes["run_kill"]["recomputed"] == 0 and notes["formula_cells_quoted_in_web_answers_csv"] >= 1

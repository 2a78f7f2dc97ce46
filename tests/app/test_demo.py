"""``keystone demo --no-serve`` builds the demo collection end to end on embedded SQLite."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from click.testing import CliRunner

from app.cli import cli


def test_demo_builds_routes_and_is_rerunnable(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("KEYSTONE_INSTANCE_PATH", str(tmp_path / "default-instance"))
    monkeypatch.setenv("KEYSTONE_DATABASE_URL", "postgresql+psycopg://nobody@/ignored")  # the demo ignores it
    folder = tmp_path / "demo"
    runner = CliRunner()
    result = runner.invoke(cli, ["demo", "--no-serve", "--dir", str(folder), "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert "routed unexpectedly" not in result.output
    assert (folder / "keystone.sqlite3").is_file()
    with sqlite3.connect(folder / "keystone.sqlite3") as connection:
        states = dict(connection.execute("SELECT source_name, state FROM cards").fetchall())
        people = {row[0] for row in connection.execute("SELECT username FROM people")}
    assert len(states) == 11
    assert all(state == "pass" for name, state in states.items() if "motorcycle" in name)
    assert states["demo_back_01.jpg"] in ("culled", "review")  # never passed as a stereo pair
    assert states["demo_mono_02.jpg"] in ("culled", "review")
    assert states["demo_upside_down_01.jpg"] == "pass" and states["demo_inverted_01.jpg"] == "pass"
    assert people == {"admin", "curator", "exporter", "annotator"}
    logins = (folder / "demo-logins.txt").read_text()

    # The rest of the flow: a simulated crowd, grades, a review queue left to try, a release.
    with sqlite3.connect(folder / "keystone.sqlite3") as connection:
        batches = dict(connection.execute("SELECT kind, count(*) FROM crowd_batches GROUP BY kind").fetchall())
        answers = connection.execute("SELECT count(*) FROM crowd_answers").fetchone()[0]
        grades = dict(
            connection.execute("SELECT outcome, count(*) FROM stage_results WHERE stage = 'grade' GROUP BY outcome").fetchall()
        )
        decisions = dict(connection.execute("SELECT decision, count(*) FROM card_reviews GROUP BY decision").fetchall())
        releases = connection.execute("SELECT version, card_count FROM releases").fetchall()
        views = connection.execute("SELECT count(*) FROM stage_results WHERE stage = 'views' AND status = 'done'").fetchone()[0]
    assert batches == {"judge": 1, "crop": 1} and answers >= 20
    # Only cards whose orientation is decided are graded: at most the 8 stereo cards.
    assert 4 <= sum(grades.values()) <= 8 and set(grades) <= {"few", "some", "failure"}
    assert decisions["accepted"] >= 1 and decisions["pending"] >= 1
    assert releases == [("1.0.0", decisions["accepted"])]
    assert views >= 1
    assert "verify: ok" in result.output
    seconds = float(result.output.split("demo built in ")[1].split(" s")[0])
    assert seconds < 60, f"keystone demo took {seconds:.1f} s (must stay under a minute)"
    assert (folder / "releases" / "1.0.0" / "SHA256SUMS").is_file()

    again = runner.invoke(cli, ["demo", "--no-serve", "--dir", str(folder)])
    assert again.exit_code == 0, again.output
    assert "ingested 0 (duplicates 11" in again.output
    assert "filter: processed 0" in again.output
    assert "not published again" in again.output  # same data: no new release
    assert (folder / "demo-logins.txt").read_text() == logins

    listing = runner.invoke(
        cli,
        ["cards", "--json"],
        env={"KEYSTONE_DATABASE_URL": f"sqlite:///{folder / 'keystone.sqlite3'}", "KEYSTONE_DATA_DIR": str(folder / "data")},
    )
    assert listing.exit_code == 0, listing.output
    cards = {card["source"]: card for card in json.loads(listing.stdout)["cards"]}
    assert len(cards) == 11
    # The flow rule: the upside-down and negative cards end up corrected (by the step or the
    # simulated crowd, the eye order by the curator until the judge task asks it) ...
    turned, negative = cards["demo_upside_down_01.jpg"], cards["demo_inverted_01.jpg"]
    assert turned["orientation"]["upside_down"] is True and turned["orientation"]["inverted"] is False
    assert turned["stages"]["rectify"]["metrics"]["orientation"]["applied"][0] == "rotated 180 deg"
    assert negative["orientation"]["inverted"] is True and negative["orientation"]["upside_down"] is False
    assert negative["stages"]["rectify"]["metrics"]["orientation"]["applied"][0] == "intensities inverted"
    # ... one card's orientation is a curator's override, recorded in the audit trail ...
    assert any(card["orientation"]["decided_by"] == "curator" for card in cards.values())
    with sqlite3.connect(folder / "keystone.sqlite3") as connection:
        assert connection.execute("SELECT count(*) FROM audit_events WHERE entity = 'orientation'").fetchone()[0] >= 1
        released = [
            row[0] for row in connection.execute("SELECT card_id FROM card_reviews WHERE decision IN ('accepted', 'changed')")
        ]
    # ... and nothing undecided is graded, accepted or released.
    for card in cards.values():
        if card["orientation"]["decided_by"] is None:
            assert card["stages"]["grade"]["status"] != "done", card["source"]
            assert card["id"] not in released, card["source"]

    # Served again as it was left, without building it (issue 33.11: a plain `keystone serve` opened
    # an empty instance, and reaching the demo took four environment variables).
    assert f"keystone demo --dir {folder.resolve()} --serve-only" in result.output
    served: dict[str, object] = {}

    def fake_serve(app, host, port, with_worker):  # type: ignore[no-untyped-def]
        served.update(database=app.config["SQLALCHEMY_DATABASE_URI"], data=app.config["KEYSTONE_DATA_DIR"], worker=with_worker)

    monkeypatch.setattr("app.serving.serve", fake_serve)
    again = runner.invoke(cli, ["demo", "--serve-only", "--dir", str(folder)])
    assert again.exit_code == 0, again.output
    assert served == {
        "database": f"sqlite:///{folder.resolve() / 'keystone.sqlite3'}",
        "data": str(folder.resolve() / "data"),
        "worker": True,
    }
    assert "processed" not in again.output and "curator / " in again.output
    empty = runner.invoke(cli, ["demo", "--serve-only", "--dir", str(tmp_path / "nothing-here")])
    assert empty.exit_code == 2 and "no demo is built in" in empty.output

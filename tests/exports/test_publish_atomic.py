"""Publishing is atomic with respect to another publish and to the catalogue: of two simultaneous
publishes one is refused with a sentence, and a publish killed between moving its release into
place and recording it leaves nothing that blocks the next one."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from sqlalchemy import select

from core.db import db
from exports.models import Release

REPO = Path(__file__).resolve().parents[2]


def _releases(app) -> list[tuple[str, str]]:  # type: ignore[no-untyped-def]
    with app.app_context():
        return [(r.version, r.path) for r in db.session.scalars(select(Release).order_by(Release.id))]


@pytest.mark.both_databases
def test_two_simultaneous_publishes_of_one_preview_give_one_release_and_one_refusal(
    app, client, login, csrf_token, processed_cards, review_card, tmp_path, post_at_once
) -> None:
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    ids = processed_cards(2)
    review_card(ids[0], "some")
    review_card(ids[1], "some")
    login("exporter")
    form = {"csrf_token": csrf_token("/releases/"), "min_grade": "some", "formats": ["parquet"], "notes": ""}
    html = client.post("/releases/preview", data=form).get_data(as_text=True)
    assert "Would publish 1.0.0" in html
    form["plan_digest"] = re.search(r'name="plan_digest"[^>]*value="([0-9a-f]{64})"', html).group(1)
    form["planned_cards"] = re.search(r'name="planned_cards"[^>]*value="([0-9,]*)"', html).group(1)
    form["planned_version"] = "1.0.0"
    answers = post_at_once("/releases/publish", form, 2)
    assert sorted(r.status_code for r in answers) == [303, 409]
    refused = next(r for r in answers if r.status_code == 409).get_data(as_text=True)
    assert "Nothing was published" in refused or "nothing was published" in refused
    assert [version for version, _ in _releases(app)] == ["1.0.0"]
    assert sorted(p.name for p in (tmp_path / "releases").iterdir()) == ["1.0.0"]


def test_a_publish_while_another_holds_the_folder_is_refused(app, processed_cards, review_card, tmp_path) -> None:
    from exports.release import ReleaseError, publish_release
    from exports.staging import PublishLock

    ids = processed_cards(1)
    review_card(ids[0], "some")
    out = tmp_path / "out"
    out.mkdir()
    held = PublishLock(out)
    try:
        with app.app_context(), pytest.raises(ReleaseError, match="another release is being published"):
            publish_release(out, formats=("parquet",))
    finally:
        held.close()
    assert list(out.iterdir()) == [] and _releases(app) == []
    with app.app_context():
        assert publish_release(out, formats=("parquet",)).version == "1.0.0"


@pytest.mark.both_databases
def test_a_publish_killed_between_moving_and_recording_does_not_block_the_next(
    app, runner, database, processed_cards, review_card, tmp_path
) -> None:
    ids = processed_cards(2)
    review_card(ids[0], "some")
    review_card(ids[1], "some")
    out = tmp_path / "out"
    paused = tmp_path / "paused"
    env = {
        **os.environ,
        "KEYSTONE_DATABASE_URL": database,
        "KEYSTONE_DATA_DIR": app.config["KEYSTONE_DATA_DIR"],
        "KEYSTONE_SECRET_KEY": "test-secret",
        "KEYSTONE_TEST_PAUSE": f"after-move:{paused}",
    }
    child = subprocess.Popen(
        [sys.executable, "-m", "app", "export", "--out", str(out), "--format", "parquet", "--json"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 180
        while not paused.exists():
            assert child.poll() is None, child.stderr.read().decode() if child.stderr else ""
            assert time.monotonic() < deadline, "the export never reached the pause"
            time.sleep(0.1)
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.wait(timeout=30)
        if child.stderr:
            child.stderr.close()
    # What the kill left: the release in place, verified, but not in the catalogue.
    assert (out / "1.0.0" / "SHA256SUMS").is_file() and _releases(app) == []
    assert runner.invoke(args=["verify", str(out / "1.0.0"), "--no-mlcroissant"]).exit_code == 0

    result = runner.invoke(args=["export", "--out", str(out), "--format", "parquet", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["version"] == "1.0.0" and report["cards"] == 2
    assert any("killed after moving it into place" in leftover["reason"] for leftover in report["leftovers_removed"])
    assert _releases(app) == [("1.0.0", str((out / "1.0.0").resolve()))]
    assert sorted(p.name for p in out.iterdir()) == ["1.0.0"]  # no marker, no partial folder
    checked = runner.invoke(args=["verify", str(out / "1.0.0"), "--no-mlcroissant", "--json"])
    assert checked.exit_code == 0, checked.output

"""``keystone bench confirm-grid`` on a small grid: every walk (mouse, keys, touch) stores
exactly what it marked and needs fewer actions than cards. Speed is reported by the command,
not asserted here (a shared 2-core machine makes timed assertions flaky)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from benchmarks.confirm_grid import CHROMIUM, bench_confirm_grid_command

pytestmark = pytest.mark.bench


def test_each_walk_stores_what_it_marked_with_fewer_actions_than_cards(tmp_path: Path) -> None:
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed")
    pytest.importorskip("playwright.sync_api")
    # No shared data: synthetic cards, so the test runs on any machine.
    result = CliRunner().invoke(
        bench_confirm_grid_command, ["--cards", "10", "--gold", "3", "--data", str(tmp_path / "none"), "--json"]
    )
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    assert document["answers"] == {"stored": 3 * 13, "not_as_marked": 0}
    for walk in document["walks"]:
        assert walk["cards"] == 13 and walk["gold"] == 3
        assert walk["actions"] < walk["cards"]
    assert {w["mode"]: w["columns"] >= 2 for w in document["walks"]} == dict.fromkeys(
        ("desktop-mouse", "desktop-keys", "phone-touch"), True
    )

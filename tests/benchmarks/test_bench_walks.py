"""``keystone bench walks``: one short walk (the admin's) against the live test server, at both
screen sizes, and a walk that cannot be done names the step it stopped at. Timings are not
asserted (the benchmark reports them); what was recorded is."""

from __future__ import annotations

import pytest

from benchmarks import walks


@pytest.fixture
def passed_card(make_card, add_stage_result) -> int:  # type: ignore[no-untyped-def]
    card_id = make_card(state="pass")
    add_stage_result(card_id, "rectify", outcome=None)
    return card_id


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_the_admins_walk_from_the_login_page_to_a_card(browser, server, make_person, passed_card, screen) -> None:  # type: ignore[no-untyped-def]
    admin = make_person("admin")
    result = walks.run_walk(browser, server, "admin", screen, admin.password, shots=None, username=admin.username)
    assert result.ok, f"{result.failed_step}: {result.error}"
    assert [step["step"] for step in result.steps] == [
        "open the login page",
        "log in",
        "see the cards by state",
        "show the cards that passed",
        "open a card",
    ]
    assert result.steps[-1]["url"] == f"/cards/{passed_card}"
    # login page, the page after logging in (the cards), the passed cards, the card: redirects not counted
    assert result.documents == 4 and result.navigations == 4
    assert result.seconds is not None and result.seconds > 0
    assert result.server_errors == [] and result.broken_images == []


def test_a_walk_that_cannot_be_done_names_its_step(browser, server, make_person, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr(walks, "STEP_TIMEOUT_MS", 1_500)
    curator = make_person("curator")
    result = walks.run_walk(browser, server, "curator", "desktop", curator.password, shots=None, username=curator.username)
    assert not result.ok and result.seconds is None
    assert result.failed_step == "open the first card"
    assert result.error == "a card link in the queue is not on /review/ (waited 2 s)"
    assert result.seconds_before_failure is not None


def test_the_table_says_what_failed_and_what_was_slow() -> None:
    report = {
        "walks": [
            {
                **walks.asdict(walks.WalkResult(role="exporter", screen="phone", failed_step="verify the release")),
                "error": "the release page /releases/1.0.1/ has no Verify button",
                "seconds_before_failure": 12.4,
                "slow": [{"step": "publish", "method": "POST", "url": "/releases/publish", "kind": "document", "ms": 7091}],
            }
        ]
    }
    table = walks.format_table(report)
    assert "exporter   phone    FAILED  (>12.4)" in table
    assert (
        "exporter / phone: FAILED at step 'verify the release': the release page /releases/1.0.1/ has no Verify button" in table
    )
    assert "exporter / phone: slow (publish): POST /releases/publish [document] 7091 ms" in table

"""The releases page: who may see it and publish, the dry-run preview, publishing with CSRF."""

from __future__ import annotations

import re
from pathlib import Path

import pytest


@pytest.mark.parametrize("role, status", [(None, 302), ("annotator", 403), ("curator", 403), ("exporter", 200), ("admin", 200)])
def test_who_sees_the_releases_page(client, as_role, role, status) -> None:
    as_role(role)
    assert client.get("/releases/").status_code == status


@pytest.mark.parametrize("role", ["annotator", "curator"])
def test_annotators_and_curators_cannot_publish(client, as_role, csrf_token, role) -> None:
    as_role(role)
    token = csrf_token("/")
    response = client.post("/releases/publish", data={"csrf_token": token, "min_grade": "some", "formats": "parquet"})
    assert response.status_code == 403
    response = client.post("/releases/preview", data={"csrf_token": token, "min_grade": "some", "formats": "parquet"})
    assert response.status_code == 403


def test_publishing_needs_the_csrf_token(client, login) -> None:
    login("exporter")
    response = client.post("/releases/publish", data={"min_grade": "some", "formats": "parquet"})
    assert response.status_code == 400


@pytest.mark.both_databases
def test_preview_then_publish_from_the_page(app, client, login, csrf_token, processed_cards, review_card, tmp_path) -> None:
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    ids = processed_cards(2)
    review_card(ids[0], "few")
    review_card(ids[1], "some")
    login("exporter")
    token = csrf_token("/releases/")
    form = {"csrf_token": token, "min_grade": "some", "formats": ["keystonedepth", "parquet"], "notes": "from the web"}

    page = client.post("/releases/preview", data=form)
    assert page.status_code == 200
    html = page.get_data(as_text=True)
    assert "Would publish 1.0.0" in html and "2 cards" in html and "few 1, some 1" in html
    assert "First release: 2 cards in keystonedepth and parquet." in html
    assert not (tmp_path / "releases").exists()

    bad = client.post("/releases/preview", data={**form, "formats": []})
    assert bad.status_code == 400 and "Choose at least one format." in bad.get_data(as_text=True)

    digest = re.search(r'name="plan_digest"[^>]*value="([0-9a-f]{64})"', html).group(1)
    cards = re.search(r'name="planned_cards"[^>]*value="([0-9,]*)"', html).group(1)
    published = client.post(
        "/releases/publish", data={**form, "plan_digest": digest, "planned_version": "1.0.0", "planned_cards": cards}
    )
    assert published.status_code == 303
    listing = client.get("/releases/").get_data(as_text=True)
    assert "Published release 1.0.0: 2 cards" in listing and "from the web" in listing
    assert (tmp_path / "releases" / "1.0.0" / "SHA256SUMS").is_file()
    changelog = client.get("/releases/1.0.0/CHANGELOG.md")
    assert changelog.status_code == 200 and "First release: 2 card(s)." in changelog.get_data(as_text=True)
    assert client.get("/releases/1.0.0/keystone.sqlite3").status_code == 404
    assert client.get("/releases/9.9.9/README.md").status_code == 404

    # The next preview compares with what was just published.
    review_card(ids[1], "few", decision="changed", auto_grade="some")
    html = client.post("/releases/preview", data=form).get_data(as_text=True)
    assert "Would publish 2.0.0" in html and "Against 1.0.0: changes 1 card." in html
    # The changed card by its title and id, linked to its page, with the reason.
    assert re.search(
        rf'<a href="/cards/{ids[1]}">[^<]+</a>\s*<span class="muted">\(#{ids[1]}[^)]*\)</span>: grade changed \(some -&gt; few\)',
        html,
    )

    with app.app_context():
        from sqlalchemy import select

        from core.audit import AuditEvent
        from core.db import db
        from exports.models import Release

        row = db.session.scalar(select(Release))
        assert row.creator is not None and row.creator.username.startswith("exporter")
        assert db.session.scalar(select(AuditEvent.actor).where(AuditEvent.entity == "release")) == row.creator.username
        assert Path(row.path) == (tmp_path / "releases" / "1.0.0").resolve()


def test_exporters_get_a_releases_link(client, login) -> None:
    login("exporter")
    assert 'href="/releases/"' in client.get("/releases/").get_data(as_text=True)


def test_reloading_the_preview_or_publish_address_goes_back_to_the_form(client, login) -> None:
    login("exporter")
    for address in ("/releases/preview", "/releases/publish"):
        response = client.get(address)
        assert response.status_code == 302 and response.headers["Location"].endswith("/releases/"), address
    # The Verify button's address, reloaded: back to the release's page, not a 404 for a file "verify".
    response = client.get("/releases/1.0.0/verify")
    assert response.status_code == 302 and response.headers["Location"].endswith("/releases/1.0.0/")


@pytest.mark.both_databases
@pytest.mark.parametrize("planned_cards", ["²", "1" * 5000, "1,1_0", "\uff15", "9223372036854775808", "1,,x"])
def test_a_stale_plan_with_absurd_card_ids_is_400_not_500(app, client, login, csrf_token, tmp_path, planned_cards) -> None:
    # Issue 32: int() of "²" or of 5,000 digits raised inside the stale-plan comparison (a 500).
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    login("exporter")
    form = {"csrf_token": csrf_token("/releases/"), "min_grade": "some", "formats": ["parquet"], "notes": ""}
    stale = {"plan_digest": "0" * 64, "planned_version": "1.0.0", "planned_cards": planned_cards}
    response = client.post("/releases/publish", data={**form, **stale})
    assert response.status_code == 400, response.status_code
    assert "Preview the release again" in response.get_data(as_text=True)
    assert not (tmp_path / "releases").exists()


def _publish(client, form: dict, version: str) -> str:  # type: ignore[no-untyped-def]
    """Preview ``form`` then publish it as previewed; the preview's HTML."""
    html = client.post("/releases/preview", data=form).get_data(as_text=True)
    digest = re.search(r'name="plan_digest"[^>]*value="([0-9a-f]{64})"', html).group(1)
    cards = re.search(r'name="planned_cards"[^>]*value="([0-9,]*)"', html).group(1)
    published = client.post(
        "/releases/publish", data={**form, "plan_digest": digest, "planned_version": version, "planned_cards": cards}
    )
    assert published.status_code == 303, published.get_data(as_text=True)[:500]
    return html


def test_a_format_only_release_says_so_and_names_its_cards(
    app, client, login, csrf_token, processed_cards, review_card, tmp_path
) -> None:  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    ids = processed_cards(2)
    review_card(ids[0], "few")
    login("exporter")
    form = {"csrf_token": csrf_token("/releases/"), "min_grade": "some", "formats": ["keystonedepth"], "notes": ""}
    _publish(client, form, "1.0.0")

    html = _publish(client, {**form, "formats": ["keystonedepth", "webdataset"]}, "1.0.1")
    assert "Would publish 1.0.1" in html
    assert "Format-only release: adds webdataset; same cards as 1.0.0." in html
    assert "a format added or dropped writes the same cards&#39; data in another form, so it is a patch" in html
    page = client.get("/releases/1.0.1/").get_data(as_text=True)
    assert "Format-only release: adds webdataset; same cards as 1.0.0." in page
    changelog = client.get("/releases/1.0.1/CHANGELOG.md").get_data(as_text=True)
    assert (
        "a patch release (0 added, 0 removed, 0 changed).\n\nFormat-only release: adds webdataset; same cards as 1.0.0.\n"
        in changelog
    )

    # A card added: by its title and id, linked to its page (it was a bare "Added: 7").
    review_card(ids[1], "some")
    html = _publish(client, {**form, "formats": ["keystonedepth", "webdataset"]}, "1.1.0")
    assert "Against 1.0.1: adds 1 card." in html and "Added (1)" in html
    assert re.search(rf'<li><a href="/cards/{ids[1]}">[^<]+</a>\s*<span class="muted">\(#{ids[1]}', html)
    page = client.get("/releases/1.1.0/").get_data(as_text=True)
    assert f'<a href="/cards/{ids[1]}">' in page and "A minor release: it only adds cards" in page


def test_verify_a_release_from_its_page(app, client, login, csrf_token, processed_cards, review_card, tmp_path) -> None:  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    review_card(processed_cards(1)[0], "few")
    login("exporter")
    token = csrf_token("/releases/")
    _publish(client, {"csrf_token": token, "min_grade": "some", "formats": ["keystonedepth"], "notes": ""}, "1.0.0")
    page = client.get("/releases/1.0.0/").get_data(as_text=True)
    assert 'action="/releases/1.0.0/verify#verify"' in page and 'name="csrf_token"' in page

    assert client.post("/releases/1.0.0/verify").status_code == 400  # no CSRF token
    assert client.post("/releases/9.9.9/verify", data={"csrf_token": token}).status_code == 404
    checked = client.post("/releases/1.0.0/verify", data={"csrf_token": token})
    html = checked.get_data(as_text=True)
    assert checked.status_code == 200 and "Release 1.0.0 verified:" in html and "no problem found" in html
    files = int(re.search(r"verified: ([\d,]+) files checked", html).group(1).replace(",", ""))
    assert files == len((tmp_path / "releases" / "1.0.0" / "SHA256SUMS").read_text().splitlines())

    (tmp_path / "releases" / "1.0.0" / "README.md").write_text("tampered\n")
    html = client.post("/releases/1.0.0/verify", data={"csrf_token": token}).get_data(as_text=True)
    assert re.search(r"Release 1\.0\.0 failed verification:\s+1 problem in \d+ files checked", html)
    assert "<code>README.md</code>: sha256 does not match SHA256SUMS (file changed or corrupted)" in html

    app.config["KEYSTONE_VERIFY_TIMEOUT_S"] = 0.01  # no check finishes this fast: it is stopped, and the page says so
    html = client.post("/releases/1.0.0/verify", data={"csrf_token": token}).get_data(as_text=True)
    assert "The check did not finish within 0.01 s and was stopped" in html and "keystone verify" in html

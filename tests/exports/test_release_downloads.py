"""The releases page as exporters use it: the form's defaults work, publish publishes exactly the
previewed plan (or refuses and shows what changed), an identical release is refused, and every
file of a release downloads (one by one or as one streamed tar), with nothing outside it served."""

from __future__ import annotations

import hashlib
import io
import re
import tarfile
from pathlib import Path

import pytest


def _preview(client, form):  # type: ignore[no-untyped-def]
    page = client.post("/releases/preview", data=form)
    html = page.get_data(as_text=True)
    fields = dict(re.findall(r'name="(plan_digest|planned_version|planned_cards)"[^>]*value="([^"]*)"', html))
    return page, html, fields


@pytest.fixture
def exporter_with_cards(app, client, login, csrf_token, processed_cards, review_card, tmp_path):  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    ids = processed_cards(2)
    review_card(ids[0], "few")
    login("exporter")
    token = csrf_token("/releases/")
    return ids, {"csrf_token": token, "min_grade": "some", "formats": ["parquet"], "notes": ""}


def test_the_form_has_no_required_checkbox_and_the_server_asks_for_a_format(client, login, csrf_token) -> None:
    login("exporter")
    page = client.get("/releases/").get_data(as_text=True)
    checkboxes = re.findall(r'<input[^>]*type="checkbox"[^>]*>', page)
    assert len(checkboxes) >= 2 and not any("required" in box for box in checkboxes)
    assert sum("checked" in box for box in checkboxes) >= 1  # the defaults are ticked
    token = csrf_token("/releases/")
    refused = client.post("/releases/preview", data={"csrf_token": token, "min_grade": "some"})
    assert refused.status_code == 400 and "Choose at least one format." in refused.get_data(as_text=True)
    unknown = client.post("/releases/preview", data={"csrf_token": token, "min_grade": "some", "formats": "zip"})
    assert unknown.status_code == 400


def test_publish_refuses_a_changed_plan_and_an_identical_release_and_downloads_match(
    exporter_with_cards, client, review_card
) -> None:
    ids, form = exporter_with_cards
    no_digest = client.post("/releases/publish", data=form)
    assert no_digest.status_code == 400 and "Preview the release first" in no_digest.get_data(as_text=True)

    _, html, planned = _preview(client, form)
    assert "Would publish 1.0.0" in html and planned["planned_cards"] == str(ids[0])
    review_card(ids[1], "some")  # a colleague accepts another card meanwhile
    stale = client.post("/releases/publish", data={**form, **planned})
    text = stale.get_data(as_text=True)
    assert stale.status_code == 409 and "Changed since your preview" in text and f"Cards added: {ids[1]}" in text
    assert not Path(client.application.config["KEYSTONE_RELEASES_DIR"]).exists()

    _, html, planned = _preview(client, form)
    published = client.post("/releases/publish", data={**form, **planned})
    assert published.status_code == 303 and published.headers["Location"].endswith("/releases/1.0.0/")

    _, html, planned = _preview(client, {**form, "notes": "again"})
    assert 'id="identical"' in html and "publish-button" not in html
    with client.application.app_context():  # a tab that previewed before the page hid the button
        from exports.release import plan_release
        from exports.views import plan_digest

        digest = plan_digest(plan_release(min_grade="some", formats=("parquet",), notes="again"))
    again = client.post("/releases/publish", data={**form, "notes": "again", "plan_digest": digest})
    assert again.status_code == 409 and "exactly the same cards, files and formats as release 1.0.0" in again.get_data(
        as_text=True
    )

    _downloads_match_the_release(client)
    _nothing_outside_a_release_is_served(client)


def _downloads_match_the_release(client) -> None:  # type: ignore[no-untyped-def]
    page = client.get("/releases/1.0.0/").get_data(as_text=True)
    links = re.findall(r'href="(/releases/1\.0\.0/files/[^"]+)"', page)
    root = Path(client.application.config["KEYSTONE_RELEASES_DIR"]) / "1.0.0"
    on_disk = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert len(links) == len(on_disk) > 3
    with client.get("/releases/1.0.0/files/SHA256SUMS") as sums:
        assert sums.status_code == 200 and "attachment" in sums.headers["Content-Disposition"]
        lines = sums.get_data(as_text=True).splitlines()
    for line in lines[:3]:
        digest, name = line.split(maxsplit=1)
        with client.get(f"/releases/1.0.0/files/{name.lstrip('*')}") as download:
            assert hashlib.sha256(download.get_data()).hexdigest() == digest

    archive = client.get("/releases/1.0.0/archive.tar")
    assert archive.status_code == 200 and archive.is_streamed
    with tarfile.open(fileobj=io.BytesIO(archive.get_data())) as tar:
        names = sorted(m.name.removeprefix("keystone-1.0.0/") for m in tar.getmembers() if m.isfile())
        assert names == on_disk
        member = tar.extractfile("keystone-1.0.0/SHA256SUMS")
        assert member is not None and member.read() == (root / "SHA256SUMS").read_bytes()


def _nothing_outside_a_release_is_served(client) -> None:  # type: ignore[no-untyped-def]
    for name in [
        "../../../etc/passwd",
        "..%2F..%2Fkeystone.sqlite3",
        "/etc/passwd",
        "nothing-here.txt",
        "%00",
        "data/../../1.0.0",
        "x" * 300,  # longer than a file name may be (ENAMETOOLONG): was a 500, found by `keystone bench probe`
        "data/" + "y" * 256 + "/z",
    ]:
        assert client.get(f"/releases/1.0.0/files/{name}", follow_redirects=True).status_code in (400, 404), name
    assert client.get("/releases/9.9.9/archive.tar").status_code == 404
    assert client.get("/releases/9.9.9/").status_code == 404

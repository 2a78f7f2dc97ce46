"""An exporter in a real browser, on a laptop then on a phone: preview a release with the form's
default choices, publish exactly that preview, download a file of it. No page may scroll sideways."""

from __future__ import annotations

import hashlib
from pathlib import Path


def test_an_exporter_previews_with_defaults_publishes_and_downloads(
    app, server, screen_page, make_person, look, processed_cards, review_card, tmp_path
) -> None:  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    ids = processed_cards(2)
    review_card(ids[0], "few")
    exporter = make_person("exporter")
    for screen, version, cards in (("desktop", "1.0.0", 1), ("phone", "1.1.0", 2)):
        page = screen_page(screen, exporter, accept_downloads=True)
        page.goto(f"{server}/releases/")
        look(page, f"releases-{screen}")
        page.click("#preview-button")  # the defaults, untouched
        page.wait_for_selector("#preview")
        assert f"Would publish {version}" in page.inner_text("#preview")
        assert f"{cards} card{'s' if cards > 1 else ''}" in page.inner_text("#preview")
        look(page, f"release-preview-{screen}")
        page.click("#publish-button")
        page.wait_for_selector(".flash-success")
        assert f"Published release {version}: {cards} card{'s' if cards > 1 else ''}," in page.inner_text(".flash-success")
        assert page.url.endswith(f"/releases/{version}/")
        look(page, f"release-files-{screen}")
        with page.expect_download() as download_info:
            page.click("#files a[href$='/SHA256SUMS']")
        download = download_info.value
        on_disk = tmp_path / "releases" / version / "SHA256SUMS"
        assert hashlib.sha256(Path(download.path()).read_bytes()).digest() == hashlib.sha256(on_disk.read_bytes()).digest()
        page.context.close()
        review_card(ids[1], "some")  # a curator accepts one more card before the next release

"""The app's icon: named by every page and answered at /favicon.ico, so no console shows a 404."""

from __future__ import annotations


def test_favicon_is_served_and_named_by_the_login_page(client):  # type: ignore[no-untyped-def]
    with client.get("/favicon.ico") as icon:
        assert icon.status_code == 200 and icon.mimetype == "image/svg+xml" and icon.data.startswith(b"<svg")
        served = icon.data
    with client.get("/static/favicon.svg") as static:
        assert static.status_code == 200 and static.data == served
    login = client.get("/auth/login")
    assert login.status_code == 200
    assert b'rel="icon" type="image/svg+xml"' in login.data and b"favicon.svg" in login.data

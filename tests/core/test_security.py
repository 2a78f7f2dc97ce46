"""Security headers everywhere, the framing opt-in, and error pages that never show a traceback."""

from __future__ import annotations

import pytest

from core.security import content_security_policy, frameable_by


def assert_security_headers(response, framing: str = "'self'") -> None:  # type: ignore[no-untyped-def]
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    assert response.headers["Referrer-Policy"] == "same-origin"
    csp = response.headers["Content-Security-Policy"]
    assert f"frame-ancestors {framing}" in csp
    assert "default-src 'self'" in csp and "img-src 'self' data: blob:" in csp and "script-src 'self'" in csp


@pytest.mark.parametrize("url", ["/auth/login", "/", "/cards", "/no/such/page", "/static/keystone.css"])
def test_every_response_carries_the_security_headers(client, url):
    with client.get(url) as response:  # closes the static file's handle
        assert_security_headers(response)
        assert response.headers["X-Frame-Options"] == "SAMEORIGIN"


def test_logged_in_pages_carry_the_headers_too(client, login):
    login("admin")
    for url in ("/cards", "/auth/people"):
        response = client.get(url)
        assert response.status_code == 200
        assert_security_headers(response)
        assert response.headers["X-Frame-Options"] == "SAMEORIGIN"


def test_a_frameable_view_names_its_framers_and_drops_x_frame_options(app, client):
    @frameable_by("self", "https://www.mturk.com", "https://workersandbox.mturk.com")
    def framed() -> str:
        return "in a frame"

    app.add_url_rule("/test-framed", view_func=framed)
    response = client.get("/test-framed")
    assert response.status_code == 200
    assert "X-Frame-Options" not in response.headers
    csp = response.headers["Content-Security-Policy"]
    assert "frame-ancestors 'self' https://www.mturk.com https://workersandbox.mturk.com" in csp
    # It may post its form to the framing site (MTurk's externalSubmit), and nowhere else.
    assert "form-action 'self' https://www.mturk.com https://workersandbox.mturk.com" in csp
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    # Other pages are unaffected.
    assert client.get("/auth/login").headers["X-Frame-Options"] == "SAMEORIGIN"


def test_a_frameable_view_keeps_its_policy_on_error_responses(app, client):
    @frameable_by("https://www.mturk.com")
    def framed_but_missing() -> str:
        from flask import abort

        abort(404, "no such assignment")

    app.add_url_rule("/test-framed-404", view_func=framed_but_missing)
    response = client.get("/test-framed-404")
    assert response.status_code == 404 and "no such assignment" in response.get_data(as_text=True)
    assert "X-Frame-Options" not in response.headers
    assert "frame-ancestors https://www.mturk.com" in response.headers["Content-Security-Policy"]


@pytest.mark.parametrize("origin", ["https://mturk.com/path", "https://a.com; script-src *", "mturk.com", "*", ""])
def test_frameable_by_rejects_anything_but_origins(origin):
    with pytest.raises(ValueError, match="Expected an origin"):
        frameable_by(origin)


def test_frameable_by_needs_an_origin():
    with pytest.raises(ValueError):
        frameable_by()


def test_default_policy_only_frames_same_origin():
    policy = content_security_policy()
    assert policy.endswith("frame-ancestors 'self'") and "form-action 'self';" in policy


# --------------------------------------------------------------------------- error pages


def test_404_is_a_small_html_page_with_the_message(client, login):
    login("curator")
    response = client.get("/cards/999999")
    assert response.status_code == 404
    assert response.mimetype == "text/html"
    html = response.get_data(as_text=True)
    assert "There is no card 999999." in html and "<title>404 Not Found" in html
    assert "Traceback" not in html


def test_errors_are_json_when_the_client_prefers_json(client, login):
    login("curator")
    response = client.get("/cards/999999", headers={"Accept": "application/json"})
    assert response.status_code == 404
    assert response.get_json() == {"error": {"code": 404, "name": "Not Found", "message": "There is no card 999999."}}


def test_400_for_a_bad_filter(client, login):
    login("curator")
    response = client.get("/cards?state=lost")
    assert response.status_code == 400
    assert "Unknown state" in response.get_data(as_text=True)


def test_403_says_which_role_is_needed(client, login):
    login("annotator")
    response = client.get("/cards")
    assert response.status_code == 403
    html = response.get_data(as_text=True)
    assert "curators, exporters and admins" in html and "annotator" in html


def test_405_keeps_the_allow_header(client):
    response = client.delete("/auth/login")
    assert response.status_code == 405
    assert "POST" in response.headers["Allow"] and "GET" in response.headers["Allow"]
    assert "Method Not Allowed" in response.get_data(as_text=True)


def test_413_for_a_request_body_over_the_limit(app, client):
    app.config["MAX_CONTENT_LENGTH"] = 64
    response = client.post("/auth/login", data={"username": "x" * 500, "password": "y"})
    assert response.status_code == 413
    assert "Request Entity Too Large" in response.get_data(as_text=True)


def test_500_shows_no_traceback(app, client):
    def broken() -> str:
        raise RuntimeError("secret internals: /etc/keystone")

    app.add_url_rule("/test-broken", view_func=broken)
    app.config["PROPAGATE_EXCEPTIONS"] = False
    app.logger.disabled = True  # the traceback goes to the log, which this test does not need
    try:
        response = client.get("/test-broken")
    finally:
        app.logger.disabled = False
    assert response.status_code == 500
    html = response.get_data(as_text=True)
    assert "secret internals" not in html and "Traceback" not in html and "RuntimeError" not in html
    assert "Internal Server Error" in html
    assert_security_headers(response)

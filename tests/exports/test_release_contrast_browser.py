"""Text contrast on the exporter's pages as Chromium renders them (issue 33.10), at both screen
sizes: axe-core's colour-contrast rule (WCAG 2.1 AA: 4.5:1, 3:1 for large text) over every
visible text element against the background it is drawn on. The stylesheet's declared pairs are
checked in tests/app/test_contrast.py; ``keystone bench walks --contrast`` audits every role's
pages on the demo. Needs axe-core from the repository's package.json (``npm ci``)."""

from __future__ import annotations

import pytest

from benchmarks.contrast import AXE_MISSING, audit_contrast, axe_installed, describe

pytestmark = pytest.mark.skipif(not axe_installed(), reason=AXE_MISSING)


@pytest.mark.parametrize("screen", ["desktop", "phone"])
def test_the_exporters_pages_meet_wcag_aa_contrast(
    app, server, screen_page, make_person, processed_cards, review_card, tmp_path, screen
) -> None:  # type: ignore[no-untyped-def]
    app.config["KEYSTONE_RELEASES_DIR"] = str(tmp_path / "releases")
    review_card(processed_cards(1)[0], "few")
    page = screen_page(screen, bypass_csp=True)  # axe is injected: the CSP would refuse it
    found: dict[str, list[str]] = {}

    def audit(name: str) -> None:
        result = audit_contrast(page)
        found[name] = [describe(v) for v in result["violations"]]

    page.goto(f"{server}/auth/login")
    audit("login")
    exporter = make_person("exporter")
    page.fill("input[name=username]", exporter.username)
    page.fill("input[name=password]", exporter.password)
    page.click("button[type=submit], input[type=submit]")
    page.wait_for_selector("#release-form")
    audit("releases")
    page.click("#preview-button")
    page.wait_for_selector("#preview")
    audit("preview")
    page.click("#publish-button")
    page.wait_for_selector(".flash-success")
    audit("release page")
    page.click("#verify-button")
    page.wait_for_selector("#verify-result")
    assert "Release 1.0.0 verified:" in page.inner_text("#verify-result")
    audit("release page, verified")
    page.goto(f"{server}/reports/")
    audit("report")
    assert set(found) == {"login", "releases", "preview", "release page", "release page, verified", "report"}
    failures = [f"{name}: {line}" for name, lines in found.items() for line in lines]
    assert not failures, "text below WCAG AA contrast:\n" + "\n".join(failures)


def test_the_audit_finds_text_below_the_ratio_on_its_effective_background(browser) -> None:  # type: ignore[no-untyped-def]
    page = browser.new_page()
    page.set_content(
        '<body style="background:#ffffff">'
        '<p id="grey" style="color:#777777">4.48:1, just below 4.5</p>'
        '<p id="darker" style="color:#767676">4.54:1, just above</p>'
        '<div style="background:#1a7f37"><span><b id="on-green" style="color:#000000">black on the pass green: 4.1:1</b></span></div>'
        '<p id="large" style="color:#777777;font-size:24px">large text needs 3:1 only</p>'
        "</body>"
    )
    result = audit_contrast(page)
    flagged = {v["selector"]: v for v in result["violations"]}
    assert set(flagged) == {"#grey", "#on-green"}
    assert flagged["#grey"]["ratio"] == pytest.approx(4.48, abs=0.02) and flagged["#grey"]["expected"] == "4.5:1"
    # the background comes from the ancestor that has one
    assert flagged["#on-green"]["background"] == "#1a7f37"
    page.close()

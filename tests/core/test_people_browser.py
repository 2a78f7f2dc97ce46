"""An admin in a real browser: deactivate a person on the people page (laptop and phone), who
then cannot log in; and every staff page, at phone width, fits the screen (no sideways scroll)."""

from __future__ import annotations


def test_an_admin_deactivates_a_person_who_then_cannot_log_in(app, server, screen_page, make_person, look) -> None:  # type: ignore[no-untyped-def]
    admin = make_person("admin")
    for screen, name in (("desktop", "ann"), ("phone", "bob")):
        person = make_person("annotator", username=name)
        page = screen_page(screen, admin)
        page.goto(f"{server}/auth/people")
        look(page, f"people-{screen}")
        row = page.locator(f"tr[data-username='{name}']")
        row.locator("summary").click()
        look(page, f"people-manage-{screen}")
        row.locator("button:has-text('Deactivate')").click()
        page.wait_for_selector(f".flash-success:has-text('{name} is deactivated')")
        assert "deactivated" in page.locator(f"tr[data-username='{name}']").inner_text()

        other = screen_page(screen, person)  # tries to log in
        assert "/auth/login" in other.url
        assert "This account is disabled" in other.inner_text("main")
        look(other, f"login-refused-{screen}")


def test_staff_pages_fit_a_phone(app, server, screen_page, make_person, look, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch
    from review.tasks import sync_reviews

    card_id = make_card(card_image(), state="culled")
    graded = make_card(card_image()[:, 1:], state="pass")
    add_stage_result(
        graded,
        "grade",
        outcome="some",
        reason="some: a long reason " * 8,
        metrics={"uncertainty": 0.5, "reasons": ["some: a long reason " * 8]},
    )
    with app.app_context():
        sync_reviews()
        create_batch([graded], "judge", 2, 0.0)
    page = screen_page("phone", make_person("admin"))
    for name, path in [
        ("catalogue", "/"),
        ("cards", "/cards"),
        ("card", f"/cards/{card_id}"),
        ("review-culled", f"/review/cards/{card_id}"),
        ("review-graded", f"/review/cards/{graded}"),
        ("reports", "/reports/"),
        ("batches", "/crowd/batches"),
        ("releases", "/releases/"),
        ("people", "/auth/people"),
        ("history", f"/review/cards/{graded}/history"),
    ]:
        response = page.goto(f"{server}{path}")
        assert response is not None and response.status == 200, (name, response and response.status)
        look(page, f"phone-{name}")
    page.goto(f"{server}/review/cards/{card_id}")
    state = page.inner_text("#card-state")
    assert "culled" in state and "Run the grade stage" not in state

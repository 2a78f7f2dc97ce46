"""Logging in and out, the role check every staff view uses, and the admin's people page.

``current_user`` is loaded in a short read-only transaction and detached from the session,
so loading it never takes SQLite's write lock and never leaves a transaction open that a
view's own :func:`app.db.read_only` block would collide with. Its columns and roles are
loaded; to reference the person in a row you write, use ``current_user.id``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar
from urllib.parse import urlsplit

from flask import Blueprint, Flask, abort, current_app, flash, redirect, render_template, request, url_for
from flask_login import current_user, login_user, logout_user
from flask_wtf import FlaskForm
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from werkzeug.security import check_password_hash, generate_password_hash
from werkzeug.wrappers import Response
from wtforms import HiddenField, PasswordField, SelectMultipleField, StringField, SubmitField
from wtforms.validators import DataRequired, Length, Regexp
from wtforms.widgets import CheckboxInput, ListWidget

from .db import db, read_only
from .extensions import login_manager
from .models import ROLES, Person
from .people import create_person
from .security import prefers_json

bp = Blueprint("auth", __name__, url_prefix="/auth")

F = TypeVar("F", bound=Callable[..., Any])

MIN_PASSWORD_LENGTH = 8  # as `keystone users add`
# Checked against when the username is unknown, so a wrong name costs as long as a wrong password.
_DUMMY_HASH = generate_password_hash("keystone-no-such-person")


@login_manager.user_loader
def load_person(person_id: str) -> Person | None:
    try:
        key = int(person_id)
    except ValueError:
        return None
    if db.session().in_transaction():
        return db.session.get(Person, key)
    with read_only():
        person = db.session.get(Person, key)
        if person is not None:
            db.session.expunge(person)  # keeps its loaded columns and roles past the rollback
    return person


@login_manager.unauthorized_handler
def unauthorized() -> Any:
    if prefers_json():
        abort(401, "Log in to use this page.")
    if request.accept_mimetypes.accept_html:  # not for <img> fetches: they would pile up messages
        flash(login_manager.login_message, "info")
    return redirect(url_for("auth.login", next=request.full_path.rstrip("?")))


def role_required(*roles: str) -> Callable[[F], F]:
    """Anonymous people are sent to log in; logged-in people without one of ``roles`` get 403.

    Admins pass every check (:meth:`Person.has_role`).
    """
    unknown = set(roles) - set(ROLES)
    if not roles or unknown:
        raise ValueError(f"Expected roles from {', '.join(ROLES)}, got {', '.join(sorted(unknown)) or 'none'}")

    def decorate(view: F) -> F:
        @functools.wraps(view)
        def wrapped(*args: Any, **kwargs: Any) -> Any:
            if not current_user.is_authenticated:
                return login_manager.unauthorized()
            if not current_user.has_role(*roles):
                allowed = [f"{role}s" for role in dict.fromkeys([*roles, "admin"])]
                who = ", ".join(allowed[:-1]) + f" and {allowed[-1]}" if len(allowed) > 1 else allowed[0]
                have = ", ".join(sorted(current_user.roles)) or "no role"
                abort(403, f"This page is for {who}; you are signed in as {current_user.username} ({have}).")
            return view(*args, **kwargs)

        return wrapped  # type: ignore[return-value]

    return decorate


@dataclass(frozen=True)
class NavLink:
    label: str
    endpoint: str
    roles: tuple[str, ...]
    order: int = 50


def add_nav_link(app: Flask, label: str, endpoint: str, *roles: str, order: int = 50) -> None:
    """Show a link in the top bar to people with one of ``roles`` (admins see all links).

    Call it from a blueprint's ``record_once`` so each feature owns its own entry.
    """
    app.extensions.setdefault("keystone_nav", []).append(NavLink(label, endpoint, roles, order))


@bp.app_template_global()
def nav_links() -> list[dict[str, Any]]:
    if not current_user.is_authenticated:
        return []
    here = (request.endpoint or "").split(".")[0]
    links = sorted(current_app.extensions.get("keystone_nav", []), key=lambda link: (link.order, link.label))
    return [
        {"label": link.label, "url": url_for(link.endpoint), "active": link.endpoint.split(".")[0] == here}
        for link in links
        if current_user.has_role(*link.roles)
    ]


bp.record_once(lambda state: add_nav_link(state.app, "People", "auth.people", "admin", order=90))


def safe_next(target: str | None) -> str | None:
    """``target`` if it is a path on this site, else None: no open redirects through ``next``."""
    if not target:
        return None
    target = target.strip()
    # Browsers treat a backslash like a slash, so "/\evil.com" would mean "//evil.com".
    if "\\" in target or any(ord(ch) < 32 for ch in target):
        return None
    parts = urlsplit(target)
    if parts.scheme or parts.netloc or not target.startswith("/") or target.startswith("//"):
        return None
    return target


class LoginForm(FlaskForm):
    username = StringField("Username", validators=[DataRequired(), Length(max=120)])
    password = PasswordField("Password", validators=[DataRequired()])
    next = HiddenField()
    submit = SubmitField("Log in")


class LogoutForm(FlaskForm):
    submit = SubmitField("Log out")


class MultiCheckboxField(SelectMultipleField):
    widget = ListWidget(prefix_label=False)
    option_widget = CheckboxInput()


class PersonForm(FlaskForm):
    username = StringField(
        "Username",
        validators=[
            DataRequired(),
            Length(max=120),
            Regexp(r"^[A-Za-z0-9._@-]+$", message="Use letters, digits and . _ @ - only."),
        ],
    )
    display_name = StringField("Display name", validators=[Length(max=200)])
    password = PasswordField(
        "Password",
        validators=[DataRequired(), Length(min=MIN_PASSWORD_LENGTH, message=f"Use at least {MIN_PASSWORD_LENGTH} characters.")],
    )
    roles = MultiCheckboxField("Roles", choices=list(ROLES),
                               validators=[DataRequired(message="Choose at least one role.")])
    submit = SubmitField("Add person")


def home_url() -> str:
    return url_for("catalog.index")


@bp.route("/login", methods=["GET", "POST"])
def login() -> Any:
    form = LoginForm()
    if request.method == "GET":
        form.next.data = request.args.get("next", "")
    if current_user.is_authenticated and request.method == "GET":
        return redirect(safe_next(form.next.data) or home_url())
    if form.validate_on_submit():
        with read_only():
            person = db.session.scalar(select(Person).where(Person.username == form.username.data.strip()))
            if person is not None:
                db.session.expunge(person)
        if person is None:
            check_password_hash(_DUMMY_HASH, form.password.data)
        elif person.check_password(form.password.data):
            if login_user(person):
                return redirect(safe_next(form.next.data) or home_url())
            form.form_errors.append("This account is disabled; ask an admin.")
            return render_template("auth/login.html", form=form), 403
        form.form_errors.append("Wrong username or password.")
        return render_template("auth/login.html", form=form), 200
    return render_template("auth/login.html", form=form), (400 if form.errors else 200)


@bp.route("/logout", methods=["POST"])
def logout() -> Response:
    # CSRFProtect checks the token on every POST before this runs: no one can log you out
    # from another site.
    logout_user()
    flash("You are logged out.", "info")
    return redirect(url_for("auth.login"))


@bp.route("/people", methods=["GET", "POST"])
@role_required("admin")
def people() -> Any:
    form = PersonForm()
    status = 200
    if form.validate_on_submit():
        try:
            person = create_person(form.username.data.strip(), form.password.data, list(form.roles.data),
                                   (form.display_name.data or "").strip())
        except IntegrityError:
            db.session.rollback()
            form.username.errors.append(f"A person called {form.username.data.strip()!r} already exists.")
            status = 409
        else:
            flash(f"Added {person.username} ({', '.join(sorted(person.roles))}).", "success")
            return redirect(url_for("auth.people"))
    elif form.errors:
        status = 400
    with read_only():
        everyone = list(db.session.scalars(select(Person).order_by(Person.username)))
        return render_template("auth/people.html", form=form, people=everyone, roles=ROLES), status

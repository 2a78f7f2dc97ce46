"""Logging in and out, the role check every staff view uses, and the admin's people page.

``current_user`` is loaded in a short read-only transaction and detached from the session,
so loading it never takes SQLite's write lock and never leaves a transaction open that a
view's own :func:`core.db.read_only` block would collide with. Its columns and roles are
loaded; to reference the person in a row you write, use ``current_user.id``.

Sessions end on the server, not only in the browser. A login stores the person's
``session_version`` and the login time in the (signed) session; the loader refuses a session
whose version is older than the person's (logging out, a new password and deactivation raise
it) or that is older than ``PERMANENT_SESSION_LIFETIME`` (``KEYSTONE_SESSION_HOURS``), so a
copied cookie stops working at logout. Wrong passwords are throttled per account and per
client address (:mod:`core.login_throttle`); every login, failure, lockout, logout and refused
session is written to the append-only ``auth_events`` trail.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, TypeVar

from flask import (
    Blueprint,
    Flask,
    abort,
    current_app,
    flash,
    make_response,
    redirect,
    render_template,
    request,
    session,
    url_for,
)
from flask_login import current_user, login_user, logout_user
from sqlalchemy import func, select, update
from werkzeug.security import check_password_hash, generate_password_hash
from werkzeug.wrappers import Response
from wtforms import (
    HiddenField,
    PasswordField,
    SelectMultipleField,
    StringField,
    SubmitField,
)
from wtforms.validators import DataRequired, Length, Regexp
from wtforms.widgets import CheckboxInput, ListWidget

from core.db import db, one_writer, read_only
from core.extensions import login_manager
from core.json_body import BrowserForm
from core.limits import parse_positive_int
from core.login_throttle import (
    Lockout,
    ThrottlePolicy,
    client_address,
    clock,
    give_back_attempt,
    reserve_attempt,
)
from core.models import ROLES, AuthEvent, Person
from core.people import (
    PeopleError,
    create_person,
    person_history,
    reset_password,
    set_active,
    set_roles,
)
from core.security import prefers_json, safe_next

bp = Blueprint("auth", __name__, url_prefix="/auth")

F = TypeVar("F", bound=Callable[..., Any])

MIN_PASSWORD_LENGTH = 8  # as `keystone users add`
# Checked against when the username is unknown, so a wrong name costs as long as a wrong password.
_DUMMY_HASH = generate_password_hash("keystone-no-such-person")


# Keys this module adds to the session beside Flask-Login's ``_user_id``.
SESSION_VERSION_KEY = "_keystone_session_version"
LOGIN_AT_KEY = "_keystone_login_at"  # seconds since the epoch, UTC
# Why the loader refused a session, for the message on the login page (request-scoped).
SESSION_ENDED_ENVIRON_KEY = "keystone.session_ended"
SESSION_EXPIRED_MESSAGE = "Your session expired: log in again."
SESSION_ENDED_MESSAGE = "Your session has ended (logged out, or the password changed): log in again."


def session_refusal(person: Person, version: object, login_at: object, now: datetime, lifetime: timedelta) -> str | None:
    """Why the session holding ``version`` and ``login_at`` may not act as ``person``, or None."""
    if not person.active:
        return "account disabled"
    if not isinstance(version, int) or version != person.session_version:
        return "session ended"  # logged out, a new password, or a session from before versions
    if not isinstance(login_at, (int, float)) or now.timestamp() - login_at > lifetime.total_seconds():
        return "session expired"
    return None


def _forget_login() -> None:
    for key in ("_user_id", "_fresh", "_id", SESSION_VERSION_KEY, LOGIN_AT_KEY):
        session.pop(key, None)


def record_auth_event(
    action: str, username: str, *, person_id: int | None = None, address: str = "", reason: str = "", at: datetime | None = None
) -> AuthEvent:
    """Add a sign-in event to the current session (committed with the change it describes)."""
    event_row = AuthEvent(
        action=action, username=username[:120], person_id=person_id, address=address, reason=reason, at=at or clock()
    )
    db.session.add(event_row)
    return event_row


@login_manager.user_loader
def load_person(person_id: str) -> Person | None:
    try:
        key = parse_positive_int(person_id, "person")  # from the signed session, read as strictly as any id
    except ValueError:
        return None
    in_transaction = db.session().in_transaction()
    if in_transaction:
        person = db.session.get(Person, key)
    else:
        with read_only():
            person = db.session.get(Person, key)
            if person is not None:
                db.session.expunge(person)  # keeps its loaded columns and roles past the rollback
    if person is None:
        return None
    now = clock()
    refusal = session_refusal(
        person, session.get(SESSION_VERSION_KEY), session.get(LOGIN_AT_KEY), now, current_app.permanent_session_lifetime
    )
    if refusal is None:
        return person
    _forget_login()
    request.environ[SESSION_ENDED_ENVIRON_KEY] = refusal
    # A loader called inside a view's transaction must not commit it; everywhere else (the role
    # check, templates) the refusal goes on the trail: a stale session is what a copied cookie
    # replayed after logout looks like.
    if not in_transaction:
        with one_writer():
            record_auth_event(
                "session_refused", person.username, person_id=person.id, address=client_address(), reason=refusal, at=now
            )
            db.session.commit()
    return None


@login_manager.unauthorized_handler
def unauthorized() -> Any:
    if prefers_json():
        abort(401, "Log in to use this page.")
    ended = request.environ.get(SESSION_ENDED_ENVIRON_KEY)
    if request.accept_mimetypes.accept_html:  # not for <img> fetches: they would pile up messages
        message = {"session expired": SESSION_EXPIRED_MESSAGE, "session ended": SESSION_ENDED_MESSAGE}.get(
            ended or "", login_manager.login_message
        )
        flash(message, "info")
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
    home_of: tuple[str, ...] = ()  # the roles whose work starts here (where they land after logging in)


def add_nav_link(app: Flask, label: str, endpoint: str, *roles: str, order: int = 50, home_of: tuple[str, ...] = ()) -> None:
    """Show a link in the top bar to people with one of ``roles`` (admins see all links);
    ``home_of``: the roles that land on it after logging in (:func:`role_home`).

    Call it from a blueprint's ``record_once`` so each feature owns its own entry.
    """
    app.extensions.setdefault("keystone_nav", []).append(NavLink(label, endpoint, roles, order, home_of))


def _links() -> list[NavLink]:
    return sorted(current_app.extensions.get("keystone_nav", []), key=lambda link: (link.order, link.label))


def role_home() -> str | None:
    """Where the logged-in person's work starts: the first top-bar link (in bar order) that is
    the landing page of one of their own roles (a curator's Review, an exporter's Releases, an
    annotator's My tasks, an admin's Cards); None for someone with no role."""
    mine = current_user.roles
    return next((url_for(link.endpoint) for link in _links() if mine.intersection(link.home_of)), None)


@bp.app_template_global()
def nav_links() -> list[dict[str, Any]]:
    if not current_user.is_authenticated:
        return []
    links = [link for link in _links() if current_user.has_role(*link.roles)]
    # One link is current: the one for this very page, else the first of its feature's (Crowd
    # and My tasks are both the crowd's, and were both highlighted).
    endpoint = request.endpoint or ""
    current = next((link for link in links if link.endpoint == endpoint), None) or next(
        (link for link in links if link.endpoint.split(".")[0] == endpoint.split(".")[0]), None
    )
    return [{"label": link.label, "url": url_for(link.endpoint), "active": link is current} for link in links]


bp.record_once(lambda state: add_nav_link(state.app, "People", "auth.people", "admin", order=90))


class LoginForm(BrowserForm):
    username = StringField("Username", validators=[DataRequired(), Length(max=120)])
    password = PasswordField("Password", validators=[DataRequired()])
    next = HiddenField()
    submit = SubmitField("Log in")


class MultiCheckboxField(SelectMultipleField):
    widget = ListWidget(prefix_label=False)
    option_widget = CheckboxInput()


class PersonForm(BrowserForm):
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
    roles = MultiCheckboxField("Roles", choices=list(ROLES), validators=[DataRequired(message="Choose at least one role.")])
    submit = SubmitField("Add person")


def home_url() -> str:
    return url_for("catalog.index")


def _locked_out(form: LoginForm, lockout: Lockout) -> Response:
    who = "this account" if lockout.scope == "account" else "your network address"
    minutes = f"{lockout.minutes} minute{'s' if lockout.minutes != 1 else ''}"
    form.form_errors.append(f"Too many wrong passwords for {who}: logging in is paused. Try again in {minutes}.")
    response = make_response(render_template("auth/login.html", form=form), 429)
    response.headers["Retry-After"] = str(lockout.retry_after_s)
    return response


def _log_in(person: Person, username: str, address: str, policy: ThrottlePolicy, now: datetime) -> None:
    with one_writer():
        give_back_attempt(username, address, policy, now)
        record_auth_event("login", person.username, person_id=person.id, address=address, at=now)
        db.session.commit()
    session.clear()  # nothing from before the login (a planted session) survives it
    login_user(person)
    session.permanent = True  # the cookie expires with the session, not with the browser
    session[SESSION_VERSION_KEY] = person.session_version
    session[LOGIN_AT_KEY] = int(now.timestamp())


@bp.route("/login", methods=["GET", "POST"])
def login() -> Any:
    form = LoginForm()
    if request.method == "GET":
        form.next.data = request.args.get("next", "")
    if current_user.is_authenticated and request.method == "GET":
        return redirect(safe_next(form.next.data) or home_url())
    if not form.validate_on_submit():
        return render_template("auth/login.html", form=form), (400 if form.errors else 200)
    username, address, now = form.username.data.strip(), client_address(), clock()
    policy = ThrottlePolicy.from_config(current_app.config)
    # Counted before the password is checked, so concurrent guesses cannot outrun the count.
    with one_writer():
        lockout = reserve_attempt(username, address, policy, now)
        if lockout is not None:
            record_auth_event(
                "login_throttled",
                username,
                address=address,
                at=now,
                reason=f"{lockout.scope}: {lockout.failures} wrong passwords in the window; "
                f"retry after {lockout.retry_after_s} s",
            )
        db.session.commit()
    if lockout is not None:
        return _locked_out(form, lockout)
    with read_only():
        # Usernames are unique ignoring case (migration 0013), so "Admin" finds admin; an exact
        # match first keeps the common case on the plain unique index.
        person = db.session.scalar(select(Person).where(Person.username == username)) or db.session.scalar(
            select(Person).where(func.lower(Person.username) == func.lower(username))
        )
        if person is not None:
            db.session.expunge(person)
    if person is None:
        check_password_hash(_DUMMY_HASH, form.password.data)
        failure = "unknown username"
    elif not person.check_password(form.password.data):
        failure = "wrong password"
    elif not person.is_active:
        failure = "account disabled"
    else:
        _log_in(person, username, address, policy, now)
        return redirect(safe_next(form.next.data) or home_url())
    with one_writer():
        record_auth_event(
            "login_failed", username, person_id=person.id if person else None, address=address, reason=failure, at=now
        )
        db.session.commit()
    if failure == "account disabled":
        form.form_errors.append("This account is disabled; ask an admin.")
        return render_template("auth/login.html", form=form), 403
    form.form_errors.append("Wrong username or password.")
    return render_template("auth/login.html", form=form), 200


@bp.route("/logout", methods=["POST"])
def logout() -> Response:
    # CSRFProtect checks the token on every POST before this runs: no one can log you out
    # from another site.
    if current_user.is_authenticated:
        person_id, username = current_user.id, current_user.username
        with one_writer():
            # Raising the version ends this session on the server: a copy of the cookie made
            # before now is refused by the loader. (It ends the person's other sessions too.)
            db.session.execute(update(Person).where(Person.id == person_id).values(session_version=Person.session_version + 1))
            record_auth_event("logout", username, person_id=person_id, address=client_address())
            db.session.commit()
    logout_user()
    session.clear()
    flash("You are logged out.", "info")
    return redirect(url_for("auth.login"))


@bp.route("/people", methods=["GET", "POST"])
@role_required("admin")
def people() -> Any:
    form = PersonForm()
    status = 200
    if form.validate_on_submit():
        try:
            person = create_person(
                form.username.data.strip(), form.password.data, list(form.roles.data), (form.display_name.data or "").strip()
            )
        except PeopleError as exc:
            form.username.errors.append(exc.message)
            status = exc.status
        else:
            flash(f"Added {person.username} ({', '.join(sorted(person.roles))}).", "success")
            return redirect(url_for("auth.people"))
    elif form.errors:
        status = 400
    return _people_page(form, status)


def _people_page(
    form: PersonForm | None = None, status: int = 200, *, error: str | None = None, one_time: tuple[str, str] | None = None
) -> Any:
    with read_only():
        everyone = list(db.session.scalars(select(Person).order_by(Person.username)))
        history = {person.id: person_history(person.id, limit=5) for person in everyone}
        return render_template(
            "auth/people.html",
            form=form or PersonForm(formdata=None),
            people=everyone,
            roles=ROLES,
            history=history,
            error=error,
            one_time=one_time,
            min_password=MIN_PASSWORD_LENGTH,
        ), status


def _admin() -> Person:
    return current_user._get_current_object()  # type: ignore[no-any-return]


@bp.errorhandler(PeopleError)
def people_error(error: PeopleError) -> Any:
    db.session.rollback()
    return _people_page(status=error.status, error=error.message)


@bp.route("/people/<int:person_id>/active", methods=["POST"])
@role_required("admin")
def person_active(person_id: int) -> Response:
    wanted = request.form.get("active", "")
    if wanted not in ("0", "1"):
        raise PeopleError(f"Expected active=0 or active=1, got {wanted[:20]!r}")
    person = set_active(person_id, wanted == "1", actor=_admin())
    flash(
        f"{person.username} is {'active again' if person.active else 'deactivated: their sessions ended and they cannot log in'}.",
        "success",
    )
    return redirect(url_for("auth.people"), code=303)


@bp.route("/people/<int:person_id>/password", methods=["POST"])
@role_required("admin")
def person_password(person_id: int) -> Any:
    typed = request.form.get("password") or ""
    person, generated = reset_password(person_id, actor=_admin(), password=typed or None, min_length=MIN_PASSWORD_LENGTH)
    if generated is None:
        flash(f"New password set for {person.username}; their sessions ended.", "success")
        return redirect(url_for("auth.people"), code=303)
    # Shown once, in this response only: never in a redirect's flash (the session cookie is signed, not secret).
    response = make_response(_people_page(one_time=(person.username, generated))[0])
    response.headers["Cache-Control"] = "no-store"
    return response


@bp.route("/people/<int:person_id>/roles", methods=["POST"])
@role_required("admin")
def person_roles(person_id: int) -> Response:
    person = set_roles(person_id, request.form.getlist("roles"), actor=_admin())
    flash(f"{person.username} now has the roles {', '.join(sorted(person.roles))}.", "success")
    return redirect(url_for("auth.people"), code=303)

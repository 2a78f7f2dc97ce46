"""``keystone bench walks``: each role's main job walked in a real browser, from the login page to
the job done, timed, on a laptop with the keyboard and on a phone with touch.

What runs: the demo built by ``keystone demo --no-serve --dir D`` is copied (the walks change it:
they answer tasks, decide cards, publish a release) once per screen into a temporary folder, and
served there by ``python -m app demo --dir COPY --serve-only`` in a child process, exactly as
``keystone demo --serve-only`` and ``keystone serve`` serve by default (gunicorn's workers and the
background worker). Before it is served, two crowd batches are added to the copy for the
annotator (three cards to judge, one to crop: the demo's own batches are all answered).

Headless Debian Chromium (Playwright, never a downloaded browser) then walks, in this order (the
exporter first, so the cards the curator and the annotator change do not change its release):

* ``exporter``: log in, land on Releases, tick a format the last release lacks, preview, publish,
  and have the release verified from its page (``Verify``);
* ``curator``: log in, land on the review queue, open the first card, decide three cards (accept
  where accepting is open, else reject);
* ``annotator``: log in (the login sends an annotator to their invite link), judge three cards,
  crop one;
* ``admin``: log in, see the cards by run state, open a card and see its stages.

On ``desktop`` (1366 x 800) the walk types and presses keys (the task pages' Enter, the review
page's ``a``/``r``, Enter on a focused link or button, Space on a checkbox); on ``phone``
(390 x 844, touch, mobile) it taps. Elements are found by role, label and text, so a walk
survives layout changes; a failure names its step.

Recorded per role and screen: seconds from the loaded login page to the job done (screenshots and
checks excluded), page loads (main-frame ``framenavigated`` events, and full document responses:
redirects are not counted), console errors and uncaught page errors, responses >= 500, broken
images (loaded with ``naturalWidth`` 0, checked on each step's page) and every response from the
server that took more than :data:`SLOW_MS` (request sent to first byte, Chromium's timing), with
its URL and milliseconds.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import click

REPO_ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]
SLOW_MS = 300.0
ROLES = ("exporter", "curator", "annotator", "admin")
SCREENS: dict[str, dict[str, Any]] = {
    "desktop": {"viewport": {"width": 1366, "height": 800}},
    "phone": {"viewport": {"width": 390, "height": 844}, "has_touch": True, "is_mobile": True, "device_scale_factor": 2},
}
STEP_TIMEOUT_MS = 30_000
PUBLISH_TIMEOUT_MS = 120_000  # a publish writes the release's files
JUDGED_CARDS = 3
CROPPED_CARDS = 1
DECIDED_CARDS = 3
BROKEN_IMAGES_JS = """() => Array.from(document.images)
  .filter(i => i.getAttribute('src') && i.complete && i.naturalWidth === 0)
  .map(i => i.currentSrc || i.src)"""


class StepFailed(Exception):
    """A step of a walk could not be done; the message says what was missing."""


@dataclass
class WalkResult:
    """One role's walk on one screen."""

    role: str
    screen: str
    ok: bool = False
    failed_step: str | None = None
    error: str | None = None
    seconds: float | None = None
    seconds_before_failure: float | None = None  # from the login to the start of the failed step
    navigations: int = 0
    documents: int = 0
    steps: list[dict[str, Any]] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)
    server_errors: list[str] = field(default_factory=list)
    broken_images: list[str] = field(default_factory=list)
    slow: list[dict[str, Any]] = field(default_factory=list)
    contrast: list[dict[str, Any]] = field(default_factory=list)  # with --contrast: axe-core's violations per page


# ---------------------------------------------------------------------------------------------
# The served copy of the demo


def read_logins(folder: Path) -> dict[str, str]:
    """``role -> password`` from the demo's ``demo-logins.txt``."""
    logins_file = folder / "demo-logins.txt"
    if not logins_file.is_file():
        raise click.ClickException(f"{logins_file} is missing: build the demo with `keystone demo --no-serve --dir {folder}`")
    pairs = (line.split(" ", 1) for line in logins_file.read_text().splitlines() if " " in line)
    return {name: password.strip() for name, password in pairs}


def demo_config(folder: Path) -> dict[str, Any]:
    """The app config ``keystone demo --dir folder`` serves with."""
    return {
        "SQLALCHEMY_DATABASE_URI": f"sqlite:///{folder / 'keystone.sqlite3'}",
        "KEYSTONE_DATA_DIR": str(folder / "data"),
        "KEYSTONE_RELEASES_DIR": str(folder / "releases"),
    }


def copy_demo(source: Path, into: Path) -> Path:
    """A copy of the built demo the walks may change (its database files, store and releases).
    Release paths are recorded absolute in the database, so they are pointed at the copy."""
    if not (source / "keystone.sqlite3").is_file():
        raise click.ClickException(f"no demo is built in {source}: run `python -m app demo --no-serve --dir {source}` first")
    target = into / "demo"
    shutil.copytree(source, target, symlinks=True)
    import sqlite3

    with sqlite3.connect(target / "keystone.sqlite3") as connection:
        connection.execute("UPDATE releases SET path = replace(path, ?, ?)", (str(source.resolve()), str(target)))
    return target


def add_annotator_batches(folder: Path) -> dict[str, list[int]]:
    """A judge batch of :data:`JUDGED_CARDS` stereo cards and a crop batch of :data:`CROPPED_CARDS`,
    one answer each and no gold, so the demo's annotator has work (the demo's batches are answered)."""
    from sqlalchemy import select

    from annotation.batches import create_batch
    from app import create_app
    from core.db import db
    from core.models import Card

    app = create_app(demo_config(folder), instance_path=folder / "instance")
    with app.app_context():
        ids = list(db.session.scalars(select(Card.id).where(Card.state == "pass").order_by(Card.id)))
        if len(ids) < JUDGED_CARDS + CROPPED_CARDS:
            raise click.ClickException(
                f"the demo has {len(ids)} passed cards; the annotator's walk needs {JUDGED_CARDS + CROPPED_CARDS}"
            )
        judged, cropped = ids[:JUDGED_CARDS], ids[JUDGED_CARDS : JUDGED_CARDS + CROPPED_CARDS]
        create_batch(judged, "judge", n=1, gold_rate=0.0)
        create_batch(cropped, "crop", n=1, gold_rate=0.0)
        db.session.commit()
        db.session.remove()
        db.engine.dispose()
    return {"judge": judged, "crop": cropped}


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextmanager
def served(folder: Path, port: int, log: Path) -> Iterator[str]:
    """``python -m app demo --dir folder --serve-only`` in its own process group; yields the base URL."""
    with log.open("w") as out:
        server = subprocess.Popen(
            [sys.executable, "-m", "app", "demo", "--dir", str(folder), "--serve-only", "--port", str(port)],
            cwd=REPO_ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if server.poll() is not None:
                raise click.ClickException(f"the demo server exited ({server.returncode}): {log.read_text()[-2000:]}")
            try:
                with urllib.request.urlopen(f"{base}/auth/login", timeout=2) as answer:
                    if answer.status == 200:
                        break
            except (urllib.error.URLError, OSError):
                pass
            if time.monotonic() > deadline:
                raise click.ClickException(f"the demo server did not answer on {base} within 60 s: {log.read_text()[-2000:]}")
            time.sleep(0.25)
        yield base
    finally:
        if server.poll() is None:
            os.killpg(server.pid, signal.SIGTERM)
            try:
                server.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()


# ---------------------------------------------------------------------------------------------
# One walk


class Walk:
    """A page for one role on one screen, with what it records. ``act`` presses or taps."""

    def __init__(self, page: Any, base: str, result: WalkResult, shots: Path | None, contrast: bool = False) -> None:
        self.page, self.base, self.result, self.shots, self.contrast = page, base, result, shots, contrast
        self.touch = result.screen == "phone"
        self.started: float | None = None
        self.paused = 0.0  # seconds spent on checks and screenshots, taken off the walk's time
        self.step_name = ""
        self.step_count = 0
        page.set_default_timeout(STEP_TIMEOUT_MS)  # read at run time: a test may shorten it
        page.on("framenavigated", self._navigated)
        page.on("response", self._response)
        page.on("console", self._console)
        page.on("pageerror", lambda error: result.console_errors.append(f"{self.step_name}: uncaught {error}"))

    # -- what is recorded
    def _navigated(self, frame: Any) -> None:
        if frame == self.page.main_frame:
            self.result.navigations += 1

    def _response(self, response: Any) -> None:
        request = response.request
        if request.resource_type == "document" and response.frame == self.page.main_frame and not 300 <= response.status < 400:
            self.result.documents += 1
        if response.status >= 500:
            self.result.server_errors.append(f"{self.step_name}: {response.status} {request.method} {self._short(response.url)}")
        if response.url.startswith(self.base):
            timing = request.timing
            server_ms = timing.get("responseStart", -1) - timing.get("requestStart", -1)
            if timing.get("requestStart", -1) >= 0 and server_ms > SLOW_MS:
                self.result.slow.append(
                    {
                        "step": self.step_name,
                        "url": self._short(response.url),
                        "method": request.method,
                        "kind": request.resource_type,
                        "ms": round(server_ms),
                    }
                )

    def _console(self, message: Any) -> None:
        if message.type == "error":
            where = message.location.get("url", "") if message.location else ""
            self.result.console_errors.append(f"{self.step_name}: {message.text} ({self._short(where)})")

    def _short(self, url: str) -> str:
        return url[len(self.base) :] if url.startswith(self.base) else url

    # -- steps
    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        self.step_name = name
        began = time.monotonic()
        try:
            yield
        except StepFailed:
            self._note_failure(began)
            raise
        except Exception as exc:  # Playwright's timeouts and errors: say which step they stopped
            first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            self._note_failure(began)
            raise StepFailed(f"{first_line}") from exc
        finally:
            self.result.steps.append(
                {"step": name, "seconds": round(time.monotonic() - began, 3), "url": self._short(self.page.url)}
            )
            self._check_page(name)

    def _note_failure(self, step_began: float) -> None:
        if self.started is not None:
            self.result.seconds_before_failure = round(step_began - self.started - self.paused, 2)

    def _check_page(self, name: str) -> None:
        began = time.monotonic()
        try:
            self.page.wait_for_load_state("load", timeout=10_000)
            for src in self.page.evaluate(BROKEN_IMAGES_JS):
                entry = f"{self._short(self.page.url)}: {self._short(src)}"
                if entry not in self.result.broken_images:
                    self.result.broken_images.append(entry)
            if self.contrast:
                self._audit_contrast(name)
            if self.shots is not None:
                self.step_count += 1
                slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
                path = self.shots / f"{self.result.role}-{self.result.screen}-{self.step_count:02d}-{slug}.png"
                self.page.screenshot(path=str(path))  # the window as seen: a phone page is metres long
        except Exception:  # a page that is gone or busy is not checked; the walk's own steps say what failed
            pass
        self.paused += time.monotonic() - began

    def _audit_contrast(self, name: str) -> None:
        from benchmarks.contrast import audit_contrast

        where = self._short(self.page.url).split("?")[0]
        seen = {(entry["page"], entry["selector"]) for entry in self.result.contrast}
        for violation in audit_contrast(self.page)["violations"]:
            if (where, violation["selector"]) not in seen:
                self.result.contrast.append({"page": where, "step": name, **violation})

    def act(self, locator: Any, key: str = "Enter") -> None:
        """Press ``key`` on ``locator`` (desktop) or tap it (phone)."""
        locator.wait_for(state="visible")
        if self.touch:
            locator.tap()
        else:
            locator.focus()
            self.page.keyboard.press(key)

    def tick(self, checkbox: Any) -> None:
        if not checkbox.is_checked():
            self.act(checkbox, key="Space")

    def expect(self, locator: Any, what: str, timeout_ms: int | None = None) -> Any:
        timeout_ms = timeout_ms or STEP_TIMEOUT_MS
        try:
            locator.first.wait_for(state="visible", timeout=timeout_ms)
        except Exception as exc:
            raise StepFailed(f"{what} is not on {self._short(self.page.url)} (waited {timeout_ms / 1000:.0f} s)") from exc
        return locator.first

    def log_in(self, username: str, password: str) -> None:
        page = self.page
        with self.step("open the login page"):
            page.goto(f"{self.base}/")
            self.expect(page.get_by_label("Username"), "the login form's Username field")
        self.started = time.monotonic()
        self.paused = 0.0
        with self.step("log in"):
            page.get_by_label("Username").fill(username)
            page.get_by_label("Password").fill(password)
            submit = page.get_by_role("button", name="Log in")
            with page.expect_navigation():
                if self.touch:
                    submit.tap()
                else:
                    page.get_by_label("Password").press("Enter")
            if page.get_by_label("Password").count():
                raise StepFailed(f"still on the login page after logging in as {username}")

    def done(self) -> None:
        assert self.started is not None
        self.result.seconds = round(time.monotonic() - self.started - self.paused, 2)
        self.result.ok = True


# ---------------------------------------------------------------------------------------------
# The roles' walks


def walk_exporter(walk: Walk) -> None:
    page = walk.page
    with walk.step("reach releases"):
        if "/releases/" not in page.url:
            walk.act(page.get_by_role("link", name="Releases"))
        walk.expect(page.get_by_role("heading", name="Releases"), "the Releases heading")
    with walk.step("choose a new format"):
        boxes = page.get_by_role("group", name="Formats").get_by_role("checkbox")
        if not boxes.count():
            boxes = page.locator("#release-form").get_by_role("checkbox")
        unticked = [box for box in boxes.all() if not box.is_checked()]
        if not unticked:
            raise StepFailed("every format is already ticked: no format-only release to make")
        # webdataset when offered: the cheapest format the demo's first release lacks
        chosen = next((box for box in unticked if (box.get_attribute("value") or "") == "webdataset"), unticked[0])
        walk.tick(chosen)
    with walk.step("preview"):
        walk.act(page.get_by_role("button", name=re.compile(r"^Preview")))
        walk.expect(page.get_by_role("button", name=re.compile(r"^Publish ")), "the Publish button of the preview")
    with walk.step("publish"):
        publish = page.get_by_role("button", name=re.compile(r"^Publish "))
        version = (publish.text_content() or "").replace("Publish", "").strip()
        with page.expect_navigation(timeout=PUBLISH_TIMEOUT_MS):
            walk.act(publish)
        walk.expect(page.get_by_text(f"Published release {version}"), f"the message 'Published release {version}'")
    with walk.step("verify the release"):
        verify = page.get_by_role("button", name=re.compile(r"^Verify"))
        if not verify.count():
            raise StepFailed(f"the release page {walk._short(page.url)} has no Verify button")
        walk.act(verify)
        walk.expect(
            page.get_by_text(re.compile(r"\bverified\b|\bpassed\b", re.I)),
            "the verification's result",
            timeout_ms=PUBLISH_TIMEOUT_MS,
        )


def walk_curator(walk: Walk) -> None:
    page = walk.page
    with walk.step("reach the review queue"):
        if "/review/" not in page.url:
            walk.act(page.get_by_role("link", name="Review"))
        walk.expect(page.get_by_role("heading", name="Review"), "the Review heading")
    with walk.step("open the first card"):
        first = walk.expect(page.get_by_role("link", name=re.compile(r"^#\d+ ")), "a card link in the queue")
        walk.act(first)
        walk.expect(page.get_by_role("button", name=re.compile(r"^Reject")), "the card page's Reject button")
    for number in range(1, DECIDED_CARDS + 1):
        with walk.step(f"decide card {number}"):
            if "/review/cards/" not in page.url:
                walk.act(walk.expect(page.get_by_role("link", name=re.compile(r"^#\d+ ")), "a card link in the queue"))
            accept = page.get_by_role("button", name=re.compile(r"^Accept"))
            choice, key = (
                (accept, "a")
                if accept.count() and accept.is_enabled()
                else (page.get_by_role("button", name=re.compile(r"^Reject")), "r")
            )
            walk.expect(choice, f"the card page's {key == 'a' and 'Accept' or 'Reject'} button")
            before = page.url
            with page.expect_navigation():
                if walk.touch:
                    choice.tap()
                else:
                    page.locator("body").press(key)
            if page.url == before and page.get_by_role("alert").count():
                raise StepFailed(f"the decision was refused: {page.get_by_role('alert').first.text_content()}")


def walk_annotator(walk: Walk) -> None:
    page = walk.page

    def close_help() -> None:
        start = page.get_by_role("button", name="Start")
        if start.count() and start.is_visible():
            walk.act(start)

    def answered() -> int:
        return int((page.locator("#answered").text_content() or "0").strip() or 0)

    def submit_one(image_name: str) -> None:
        close_help()
        walk.expect(page.get_by_role("img", name=image_name), f"the image '{image_name}'")
        count = answered()
        submit = page.get_by_role("button", name=re.compile(r"^Submit"))
        walk.expect(submit, "the Submit button")
        if walk.touch:
            submit.tap()
        else:
            page.keyboard.press("Enter")
        deadline = time.monotonic() + STEP_TIMEOUT_MS / 1000
        while True:
            try:
                if answered() > count:
                    return
            except Exception:  # the page is navigating to the next kind of task
                return
            alert = page.get_by_role("alert")
            if alert.count() and alert.first.is_visible() and (alert.first.text_content() or "").strip():
                raise StepFailed(f"the answer was refused: {alert.first.text_content()}")
            if time.monotonic() > deadline:
                raise StepFailed(f"'Answers given' stayed at {count} after submitting")
            page.wait_for_timeout(50)

    with walk.step("reach the tasks"):
        walk.expect(page.get_by_role("heading", name=re.compile("stereo card")), "the judge task's heading")
    for number in range(1, JUDGED_CARDS + 1):
        with walk.step(f"judge card {number}"):
            submit_one("The stereo card to judge")
    with walk.step("crop a card"):
        walk.expect(page.get_by_role("heading", name="Fit each box to its photo"), "the crop task's heading (after the judging)")
        submit_one("The stereo card to crop")


def walk_admin(walk: Walk) -> None:
    page = walk.page
    states = page.get_by_role("navigation", name="Card states")
    with walk.step("see the cards by state"):
        if not re.search(r"/cards/?$", page.url):
            walk.act(page.get_by_role("link", name="Cards"))
        walk.expect(page.get_by_role("heading", name="Cards"), "the Cards heading")
        walk.expect(states.get_by_role("link", name=re.compile(r"^pass \d+")), "the count of cards that passed")
    with walk.step("show the cards that passed"):
        with page.expect_navigation():
            walk.act(states.get_by_role("link", name=re.compile(r"^pass \d+")))
    with walk.step("open a card"):
        card = walk.expect(page.get_by_role("link", name=re.compile(r"^Card \d+")), "a card that passed")
        walk.act(card)
        walk.expect(page.get_by_role("heading", name="Rectification"), "the card's Rectification section")
        walk.expect(page.get_by_text(re.compile(r"^\s*done\b")), "a stage marked done")


WALKS: dict[str, Callable[[Walk], None]] = {
    "exporter": walk_exporter,
    "curator": walk_curator,
    "annotator": walk_annotator,
    "admin": walk_admin,
}


def run_walk(
    browser: Any,
    base: str,
    role: str,
    screen: str,
    password: str,
    shots: Path | None,
    contrast: bool = False,
    username: str | None = None,
) -> WalkResult:
    """``role``'s walk on ``screen`` against the app at ``base``, logging in as ``username``
    (default: the demo's login named after the role)."""
    result = WalkResult(role=role, screen=screen)
    # The contrast audit injects axe-core, which the pages' CSP would refuse.
    context = browser.new_context(**SCREENS[screen], bypass_csp=contrast)
    try:
        walk = Walk(context.new_page(), base, result, shots, contrast)
        try:
            walk.log_in(username or role, password)
            WALKS[role](walk)
            walk.done()
        except StepFailed as failed:
            result.failed_step, result.error = walk.step_name, str(failed)
    finally:
        context.close()
    return result


def run_walks(
    demo: Path,
    roles: tuple[str, ...] = ROLES,
    screens: tuple[str, ...] = tuple(SCREENS),
    shots: Path | None = None,
    echo: Callable[[str], None] = click.echo,
    contrast: bool = False,
) -> dict[str, Any]:
    """Every role's walk on every screen, each screen on its own served copy of ``demo``."""
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        raise click.ClickException("Debian's chromium is not installed (apt install chromium)")
    logins = read_logins(demo)
    missing = [role for role in roles if role not in logins]
    if missing:
        raise click.ClickException(f"{demo / 'demo-logins.txt'} has no login for {', '.join(missing)}")
    if shots is not None:
        shots.mkdir(parents=True, exist_ok=True)
    results: list[WalkResult] = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            for screen in screens:
                with tempfile.TemporaryDirectory(prefix=f"keystone-walks-{screen}-") as scratch:
                    folder = copy_demo(demo, Path(scratch))
                    if "annotator" in roles:
                        add_annotator_batches(folder)
                    with served(folder, free_port(), Path(scratch) / "server.log") as base:
                        for role in roles:
                            result = run_walk(browser, base, role, screen, logins[role], shots, contrast)
                            echo(
                                f"{role:<10} {screen:<8} "
                                + (
                                    f"done in {result.seconds:.2f} s"
                                    if result.ok
                                    else f"FAILED at '{result.failed_step}': {result.error}"
                                )
                            )
                            results.append(result)
        finally:
            browser.close()
    return {
        "demo": str(demo),
        "slow_ms": SLOW_MS,
        "screens": {name: SCREENS[name] for name in screens},
        "walks": [asdict(result) for result in results],
    }


def seconds(walk: dict[str, Any]) -> str:
    """A walk's seconds for the table: ``(>N)`` for a failed walk, N the seconds up to its failed step."""
    if walk["seconds"] is not None:
        return f"{walk['seconds']:.2f}"
    return f"(>{walk['seconds_before_failure']:.1f})" if walk.get("seconds_before_failure") is not None else "-"


def format_table(report: dict[str, Any]) -> str:
    lines = [
        f"{'role':<10} {'screen':<8} {'result':<7} {'seconds':>7} {'loads':>5} {'docs':>4} {'console':>7} {'5xx':>3} "
        f"{'broken':>6} {'slow':>4} {'contrast':>8}",
    ]
    for walk in report["walks"]:
        lines.append(
            f"{walk['role']:<10} {walk['screen']:<8} {'done' if walk['ok'] else 'FAILED':<7} "
            f"{seconds(walk):>7} {walk['navigations']:>5} {walk['documents']:>4} "
            f"{len(walk['console_errors']):>7} {len(walk['server_errors']):>3} {len(walk['broken_images']):>6} {len(walk['slow']):>4} "
            f"{len(walk.get('contrast', [])):>8}"
        )
    lines.append("")
    lines.append("seconds: from the loaded login page to the job done, checks and screenshots excluded; (>N): failed after N s")
    lines.append("loads: main-frame navigations; docs: full document responses (redirects not counted)")
    lines.append(f"slow: responses whose server time (request sent to first byte) was over {SLOW_MS:.0f} ms")
    for walk in report["walks"]:
        label = f"{walk['role']} / {walk['screen']}"
        if not walk["ok"]:
            lines.append(f"{label}: FAILED at step '{walk['failed_step']}': {walk['error']}")
        for error in walk["console_errors"]:
            lines.append(f"{label}: console error: {error}")
        for error in walk["server_errors"]:
            lines.append(f"{label}: server error: {error}")
        for image in walk["broken_images"]:
            lines.append(f"{label}: broken image: {image}")
        for found in walk.get("contrast", []):
            lines.append(
                f"{label}: contrast {found['ratio']}:1 < {found['expected']} on {found['page']} ({found['step']}): "
                f"{found['selector']} ({found['colour']} on {found['background']}, {found['font']})"
            )
        for slow in walk["slow"]:
            lines.append(f"{label}: slow ({slow['step']}): {slow['method']} {slow['url']} [{slow['kind']}] {slow['ms']} ms")
    return "\n".join(lines)


@click.command("walks")
@click.option(
    "--dir",
    "demo",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("keystone-demo"),
    show_default=True,
    help="A demo built by `keystone demo --no-serve --dir D` (copied, never changed).",
)
@click.option("--role", "roles", multiple=True, type=click.Choice(ROLES), help="Walk only these roles (repeatable; default all).")
@click.option("--screen", "screens", multiple=True, type=click.Choice(tuple(SCREENS)), help="Only these screens (default both).")
@click.option(
    "--shots", type=click.Path(file_okay=False, path_type=Path), default=None, help="Save a screenshot of each step's page here."
)
@click.option(
    "--contrast",
    is_flag=True,
    help="Also audit the text contrast of each step's page with axe-core (WCAG AA; needs `npm ci`); a violation fails the run.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
@click.option(
    "--save", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the JSON results to this file."
)
def bench_walks_command(
    demo: Path,
    roles: tuple[str, ...],
    screens: tuple[str, ...],
    shots: Path | None,
    contrast: bool,
    as_json: bool,
    save: Path | None,
) -> None:
    """Each role's main job walked in headless Chromium from the login page, timed, on a laptop
    (keyboard) and a phone (touch), against a served copy of a built demo."""
    chosen_roles = tuple(role for role in ROLES if role in roles) if roles else ROLES
    chosen_screens = tuple(screen for screen in SCREENS if screen in screens) if screens else tuple(SCREENS)
    if contrast:
        from benchmarks.contrast import AXE_MISSING, axe_installed

        if not axe_installed():
            raise click.ClickException(AXE_MISSING)
    report = run_walks(
        demo.resolve(),
        chosen_roles,
        chosen_screens,
        shots,
        echo=(lambda _line: None) if as_json else click.echo,
        contrast=contrast,
    )
    if save is not None:
        save.write_text(json.dumps(report, indent=2) + "\n")
    click.echo(json.dumps(report, indent=2) if as_json else "\n" + format_table(report))
    if not all(walk["ok"] and not walk["contrast"] for walk in report["walks"]):
        sys.exit(1)

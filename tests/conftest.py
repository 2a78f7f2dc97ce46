"""Fixtures shared by the suite: an app on a throwaway database, its client and CLI runner.

Tests marked ``both_databases`` run once on SQLite and once on PostgreSQL when a server
binary (``initdb``/``pg_ctl``) is on the machine: a throwaway cluster is started for the
session in a temporary folder, on a unix socket, then stopped. No mocks.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import os
import pwd
import re
import shutil
import stat
import subprocess
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import select

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", REPO.parent / "shared" / "data"))


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "both_databases: run on SQLite and on PostgreSQL when available")


def find_pg_bin() -> Path | None:
    candidates = [os.environ.get("KEYSTONE_PG_BIN", "")]
    candidates += sorted((str(p) for p in Path("/usr/lib/postgresql").glob("*/bin")), reverse=True)
    which = shutil.which("pg_ctl")
    if which:
        candidates.append(str(Path(which).resolve().parent))
    for candidate in candidates:
        if candidate and (Path(candidate) / "initdb").exists() and (Path(candidate) / "pg_ctl").exists():
            return Path(candidate)
    return None


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "database" in metafunc.fixturenames:
        backends = ["sqlite"]
        if metafunc.definition.get_closest_marker("both_databases"):
            backends.append("postgresql")
        metafunc.parametrize("database", backends, indirect=True)


class PostgresCluster:
    """initdb + pg_ctl in a temporary folder; listens only on a unix socket in that folder."""

    def __init__(self, bin_dir: Path) -> None:
        self.bin_dir = bin_dir
        self.root = Path(tempfile.mkdtemp(prefix="keystone-pg-"))
        self.data = self.root / "data"
        self.socket_dir = self.root
        self.user = "keystone"
        self._run_as: list[str] = []
        if os.geteuid() == 0:
            # initdb refuses to run as root: run the server as an unprivileged account.
            account = "postgres" if _user_exists("postgres") else "nobody"
            self._run_as = ["runuser", "-u", account, "--"]
            uid = pwd.getpwnam(account).pw_uid
            gid = pwd.getpwnam(account).pw_gid
            os.chown(self.root, uid, gid)
        self._names = itertools.count()

    def _run(self, *args: str) -> None:
        subprocess.run([*self._run_as, *args], check=True, capture_output=True, timeout=120)

    def start(self) -> None:
        self._run(str(self.bin_dir / "initdb"), "-D", str(self.data), "-U", self.user, "--auth=trust", "-E", "UTF8", "--no-sync")
        options = f"-c listen_addresses='' -c unix_socket_directories={self.socket_dir} -c fsync=off -c max_connections=200"
        self._run(str(self.bin_dir / "pg_ctl"), "-D", str(self.data), "-o", options, "-l", str(self.root / "log"), "-w", "start")

    def stop(self) -> None:
        try:
            self._run(str(self.bin_dir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://{self.user}@/{database}?host={self.socket_dir}"

    def create_database(self) -> str:
        import psycopg

        name = f"keystone_test_{os.getpid()}_{next(self._names)}"
        with psycopg.connect(f"host={self.socket_dir} user={self.user} dbname=postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return name


def _user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    bin_dir = find_pg_bin()
    if bin_dir is None:
        pytest.skip("no PostgreSQL server binaries (initdb, pg_ctl) on this machine")
    cluster = PostgresCluster(bin_dir)
    cluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def database(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A SQLAlchemy URL for an empty database of the requested backend."""
    backend = getattr(request, "param", "sqlite")
    if backend == "postgresql":
        cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
        return cluster.url(cluster.create_database())
    return f"sqlite:///{tmp_path / 'keystone.sqlite3'}"


@pytest.fixture
def app(database: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    from app import create_app
    from app.schema import upgrade
    from core.db import db

    monkeypatch.setenv("KEYSTONE_INSTANCE_PATH", str(tmp_path / "instance"))
    application = create_app(
        {
            "TESTING": True,
            "SQLALCHEMY_DATABASE_URI": database,
            "KEYSTONE_DATA_DIR": str(tmp_path / "data"),
            "SECRET_KEY": "test-secret",
        }
    )
    with application.app_context():
        upgrade(db.engine)
    yield application
    with application.app_context():
        db.session.remove()
        db.engine.dispose()


@pytest.fixture
def client(app):  # type: ignore[no-untyped-def]
    return app.test_client()


@pytest.fixture
def runner(app):  # type: ignore[no-untyped-def]
    """A CLI runner bound to the test app whose ``invoke(args=[...])`` runs ``keystone`` commands."""
    from flask.testing import FlaskCliRunner

    from app.cli import cli

    class KeystoneCliRunner(FlaskCliRunner):
        def invoke(self, cli_group=None, args=None, **kwargs):  # type: ignore[no-untyped-def,override]
            return super().invoke(cli_group or cli, args, **kwargs)

    return KeystoneCliRunner(app)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``$KEYSTONE_SHARED_DATA`` or ``../shared/data`` beside the checkout; skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} not present: real-data tests need ../shared/data")
    return SHARED_DATA


# ---- factories for web-app tests (people, stored cards, stage results, logging in) ----
# They are fixtures (tests/ is not a package, so test modules cannot import helpers). Cards are
# real images (Middlebury Motorcycle, shipped with scikit-image) written into the test app's
# data dir the way ingest stores them; rows are inserted directly. CSRF stays on: helpers post
# the token they read from the page, as a browser would.

PASSWORD = "correct horse battery"
CARD_HALF = (296, 200)  # (width, height) of each photo in the default test card
GUTTER = 12

_CSRF_INPUT = re.compile(r'<input[^>]*name="csrf_token"[^>]*value="([^"]+)"')


def stereo_card_array(half: tuple[int, int] = CARD_HALF, gutter: int = GUTTER) -> np.ndarray:
    """Motorcycle's left and right views side by side on a grey gutter, ``(H, W, 3)`` uint8."""
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    views = [np.asarray(Image.fromarray(view).resize(half, Image.Resampling.BOX)) for view in (left, right)]
    strip = np.full((half[1], gutter, 3), 200, np.uint8)
    return np.concatenate([views[0], strip, views[1]], axis=1)


def encode(image: np.ndarray, fmt: str = "PNG") -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format=fmt)
    return buffer.getvalue()


@dataclass(frozen=True)
class PersonInfo:
    id: int
    username: str
    password: str
    roles: tuple[str, ...]


@pytest.fixture
def data_dir(app) -> Path:  # type: ignore[no-untyped-def]
    return Path(app.config["KEYSTONE_DATA_DIR"])


@pytest.fixture
def card_image() -> Callable[..., np.ndarray]:
    return stereo_card_array


@pytest.fixture
def make_person(app) -> Callable[..., PersonInfo]:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Person

    counter = iter(range(1, 10_000))

    def make(*roles: str, username: str | None = None, password: str = PASSWORD, active: bool = True) -> PersonInfo:
        name = username or f"{'-'.join(roles) or 'nobody'}-{next(counter)}"
        with app.app_context():
            person = Person(username=name, display_name=name.title(), active=active)
            person.set_password(password)
            for role in roles:
                person.grant(role)
            db.session.add(person)
            db.session.commit()
            return PersonInfo(person.id, name, password, tuple(roles))

    return make


@pytest.fixture
def make_card(app, data_dir: Path) -> Callable[..., int]:  # type: ignore[no-untyped-def]
    """Store an image as ingest would (``originals/<hash[:2]>/<hash><suffix>``, read-only); return the card id."""
    from core.db import db
    from core.models import Card, Collection

    def make(
        image: np.ndarray | None = None,
        *,
        payload: bytes | None = None,
        suffix: str = ".png",
        collection: str = "test-collection",
        state: str = "ingested",
        accession: str | None = None,
        metadata: dict[str, Any] | None = None,
        source_name: str | None = None,
    ) -> int:
        if payload is None:
            image = stereo_card_array() if image is None else image
            payload = encode(image, {".png": "PNG", ".tif": "TIFF", ".jpg": "JPEG"}[suffix])
        content_hash = hashlib.sha256(payload).hexdigest()
        relative = Path("originals") / content_hash[:2] / f"{content_hash}{suffix}"
        target = data_dir / relative
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(payload)
        target.chmod(stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
        with Image.open(io.BytesIO(payload)) as probe:
            width, height, fmt = probe.width, probe.height, probe.format or "unknown"
        with app.app_context():
            group = db.session.scalar(select(Collection).where(Collection.name == collection))
            if group is None:
                group = Collection(name=collection)
            card = Card(
                collection=group,
                content_hash=content_hash,
                stored_path=str(relative),
                source_name=source_name or f"scan-{content_hash[:8]}{suffix}",
                source_path=f"/scans/{content_hash[:8]}{suffix}",
                accession=accession,
                width=width,
                height=height,
                image_format=fmt,
                byte_size=len(payload),
                source_metadata=metadata or {},
                state=state,
            )
            db.session.add(card)
            db.session.commit()
            return card.id

    return make


@pytest.fixture
def add_stage_result(app, data_dir: Path) -> Callable[..., int]:  # type: ignore[no-untyped-def]
    """Record a stage result for a card; for the filter, write its two halves as PNG artifacts."""
    from core.db import db
    from core.models import Card, StageResult
    from pipeline.io import read_image, write_png

    def add(
        card_id: int,
        stage: str = "filter",
        *,
        status: str = "done",
        outcome: str | None = "pass",
        reason: str | None = None,
        param_hash: str = "0123456789abcdef",
        metrics: dict[str, Any] | None = None,
        artifacts: dict[str, str] | None = None,
        update_state: bool = True,
    ) -> int:
        with app.app_context():
            card = db.session.get(Card, card_id)
            assert card is not None
            if stage == "filter" and status == "done" and artifacts is None:
                image = read_image(data_dir / card.stored_path)
                height, width = image.shape[:2]
                gutter = GUTTER if width == 2 * CARD_HALF[0] + GUTTER else 0
                half = (width - gutter) // 2
                left_box = [0, 0, half, height]
                right_box = [half + gutter, 0, 2 * half + gutter, height]
                work = Path("derived") / card.content_hash[:2] / card.content_hash / stage / param_hash
                artifacts = {}
                for name, (x0, y0, x1, y1) in (("left", left_box), ("right", right_box)):
                    write_png(data_dir / work / f"{name}.png", image[y0:y1, x0:x1])
                    artifacts[name] = str(work / f"{name}.png")
                metrics = {
                    "good_match_fraction": 0.2341,
                    "good_matches": 512,
                    "keypoints_left": 2187,
                    "keypoints_right": 2204,
                    "denominator": "keypoints_left",
                    "detect_seconds": 0.081,
                    "match_seconds": 0.034,
                    "left_box": left_box,
                    "right_box": right_box,
                    "card_size": [card.width, card.height],
                    "split_method": "similarity",
                    **(metrics or {}),
                }
            row = StageResult(
                card_id=card_id,
                stage=stage,
                param_hash=param_hash,
                status=status,
                outcome=outcome,
                reason=reason or (outcome if status == "done" else None),
                metrics=metrics or {},
                artifacts=artifacts or {},
                seconds=0.21,
                code_version="0.1.0",
            )
            db.session.add(row)
            if update_state and stage == "filter":
                card.state = outcome if status == "done" and outcome else "failed"
            db.session.commit()
            return row.id

    return add


@pytest.fixture
def csrf_token(client) -> Callable[[str], str]:  # type: ignore[no-untyped-def]
    """The CSRF token from a form on the page at ``url`` (redirects followed), as a browser would send it."""

    def token(url: str = "/auth/login") -> str:
        page = client.get(url, follow_redirects=True)
        match = _CSRF_INPUT.search(page.get_data(as_text=True))
        assert match, f"no csrf_token field on {url} (status {page.status_code})"
        return match.group(1)

    return token


@pytest.fixture
def login(client, make_person, csrf_token) -> Callable[..., PersonInfo]:  # type: ignore[no-untyped-def]
    """Create a person with ``roles`` and log in through the real form (CSRF token included)."""

    def do(*roles: str, **person: Any) -> PersonInfo:
        info = make_person(*roles, **person)
        response = client.post(
            "/auth/login",
            data={"username": info.username, "password": info.password, "csrf_token": csrf_token("/auth/login")},
        )
        assert response.status_code == 302, response.get_data(as_text=True)
        return info

    return do


@pytest.fixture
def as_role(login) -> Callable[[str | None], PersonInfo | None]:  # type: ignore[no-untyped-def]
    """Log in with one role, or stay anonymous for ``None``."""

    def do(role: str | None) -> PersonInfo | None:
        return login(role) if role else None

    return do


# ---- real-browser tests: the app under a threaded WSGI server, Debian's headless Chromium ----

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# --use-angle/--enable-unsafe-swiftshader: WebGL without a GPU (ANGLE on SwiftShader), which
# Chromium only allows when asked; the 3D viewer's test needs it, the others do not mind it.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]


@pytest.fixture
def server(app) -> Iterator[str]:  # type: ignore[no-untyped-def]
    """The test app served on a free loopback port; yields its base URL."""
    import threading

    from werkzeug.serving import make_server

    httpd = make_server("127.0.0.1", 0, app, threaded=True)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_port}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=10)


@pytest.fixture
def browser() -> Iterator[Any]:
    """Debian's Chromium driven by Playwright (never a downloaded browser)."""
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (apt install chromium)")
    playwright_api = pytest.importorskip("playwright.sync_api")
    with playwright_api.sync_playwright() as playwright:
        instance = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield instance
        finally:
            instance.close()


# The two screens every role's path is walked on: a laptop and a phone (touch).
SCREENS: dict[str, dict[str, Any]] = {
    "desktop": {"viewport": {"width": 1366, "height": 800}},
    "phone": {"viewport": {"width": 390, "height": 844}, "has_touch": True, "is_mobile": True, "device_scale_factor": 2},
}


@pytest.fixture
def screen_page(browser, server) -> Callable[..., Any]:  # type: ignore[no-untyped-def]
    """A page in a fresh browser context (its own cookies) sized as one of :data:`SCREENS`,
    logged in as ``person`` through the real form when one is given."""

    def open_page(screen: str, person: Any = None, **context: Any) -> Any:
        page = browser.new_context(**SCREENS[screen], **context).new_page()
        if person is not None:
            page.goto(f"{server}/auth/login")
            page.fill("input[name=username]", person.username)
            page.fill("input[name=password]", person.password)
            page.click("input[type=submit], button[type=submit]")
            page.wait_for_load_state()
        return page

    return open_page


@pytest.fixture
def look() -> Callable[[Any, str], None]:
    """Check a page as a person would first notice: it must not scroll sideways. With
    ``KEYSTONE_SHOTS=DIR`` a full-page screenshot goes to ``DIR/<name>.png`` to look at."""

    def check(page: Any, name: str) -> None:
        content, window = page.evaluate("[document.documentElement.scrollWidth, window.innerWidth]")
        shots = os.environ.get("KEYSTONE_SHOTS")
        if shots:
            Path(shots).mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(Path(shots) / f"{name}.png"), full_page=True)
        assert content <= window, f"{name} scrolls sideways: {content} px of content in a {window} px window"

    return check


def _wait_until(page: Any, expression: str, timeout_s: float = 15.0) -> None:
    """Poll a page expression from Python: Playwright's string ``wait_for_function`` compiles the
    predicate with ``new Function``, which the app's Content-Security-Policy (no 'unsafe-eval')
    may refuse, while ``page.evaluate`` runs through the debugging protocol."""
    import time

    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {expression}")
        page.wait_for_timeout(50)


@pytest.fixture
def wait_until() -> Callable[..., None]:
    return _wait_until


@pytest.fixture
def decide_orientation(app) -> Callable[..., list[int]]:  # type: ignore[no-untyped-def]
    """Record a curator's orientation override on cards (all cards when none are named), as a
    curator who knows how the test's cards were made would: the flow rule keeps a card whose
    orientation is undecided out of rectification, and the orientation step asks people about
    most synthetic cards. Returns the card ids."""
    from core.db import db
    from core.models import Card
    from review.models import OrientationOverride

    def decide(
        card_ids: list[int] | None = None, *, upside_down: bool = False, inverted: bool = False, swapped: bool = False
    ) -> list[int]:
        with app.app_context():
            ids = card_ids if card_ids is not None else list(db.session.scalars(select(Card.id).order_by(Card.id)))
            for card_id in ids:
                row = db.session.scalar(select(OrientationOverride).where(OrientationOverride.card_id == card_id))
                if row is None:
                    row = OrientationOverride(card_id=card_id, note="test: the card's making is known")
                    db.session.add(row)
                row.upside_down, row.inverted, row.swapped = upside_down, inverted, swapped
            db.session.commit()
        return ids

    return decide


@pytest.fixture
def add_crop_dispute(app) -> Callable[..., tuple[int, int]]:  # type: ignore[no-untyped-def]
    """A crop batch on a card whose two invited annotators disagree on the right box, and its
    aggregate waiting for a curator; returns (batch id, aggregate id). The defaults fit a
    604 x 200 px card; ``right_x0``, ``right_x1s`` (one per annotator) and ``consensus_x1`` move
    the right boxes for another width."""
    from annotation.batches import create_batch
    from annotation.models import Aggregate, Answer, BatchItem
    from annotation.workers import get_or_create_worker
    from core.db import db

    def add(
        card_id: int, *, right_x0: int = 310, right_x1s: tuple[int, int] = (600, 470), consensus_x1: int = 535
    ) -> tuple[int, int]:
        with app.app_context():
            batch = create_batch([card_id], "crop", 2, 0.0)
            item = db.session.scalar(select(BatchItem).where(BatchItem.batch_id == batch.id))
            for n, right_x1 in enumerate(right_x1s):
                db.session.add(
                    Answer(
                        item_id=item.id,
                        worker_id=get_or_create_worker("invite", f"w{n}").id,
                        idempotency_key=f"card-{card_id}-key-{n}",
                        payload={"left": [0, 0, 280, 200], "right": [right_x0, 0, right_x1, 200]},
                    )
                )
            aggregate = Aggregate(
                batch_id=batch.id,
                card_id=card_id,
                kind="crop",
                state="needs_curator",
                answers=2,
                label={"left": [0, 0, 280, 200], "right": [right_x0, 0, consensus_x1, 200]},
                reasons="right box: mean IoU 0.58 < 0.7",
            )
            db.session.add(aggregate)
            db.session.commit()
            return batch.id, aggregate.id

    return add


# Two photos mounted as a card, a card with real views for the 3D viewer, and a world with
# something behind every door for the hostile-input tests.
def _mounted(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    gap = np.full((left.shape[0], 24, 3), (214, 200, 170), np.uint8)
    return np.concatenate([left, gap, right], axis=1)


@pytest.fixture(scope="session")
def mount_pair() -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``mount_pair(left, right)``: two RGB photos of one height side by side on a buff card
    with a 24 px gutter, as the test cards of ``keystone run`` are made."""
    return _mounted


@pytest.fixture
def make_card_with_views(app, data_dir, make_card, add_stage_result) -> Callable[..., tuple[int, Any]]:  # type: ignore[no-untyped-def]
    """A stored card whose latest views result is the real output of ``views_task`` on the
    Motorcycle pair at ``width`` px with its ground-truth disparity; returns (card id, record)."""
    import cv2
    from skimage import data

    from pipeline.io import write_npy, write_png
    from pipeline.records import CardTask
    from pipeline.stages.views import views_task
    from pipeline.view_synthesis import ViewsStageParams

    def make(width: int = 160, grade: str = "few") -> tuple[int, Any]:
        left, _, disp = data.stereo_motorcycle()
        scale = width / left.shape[1]
        size = (width, round(left.shape[0] * scale))
        view = cv2.resize(np.asarray(left), size, interpolation=cv2.INTER_AREA)
        d = cv2.resize(np.asarray(disp, np.float32), size, interpolation=cv2.INTER_NEAREST) * scale
        write_png(data_dir / "rect" / "left.png", view)
        write_npy(data_dir / "rect" / "disparity_left.npy", np.where(np.isfinite(d), d, np.nan).astype(np.float32))
        card_id = make_card(state="pass")
        task = CardTask(
            card_id=card_id,
            content_hash="c" * 64,
            image_path="",
            work_dir=str(data_dir / "derived" / "views"),
            data_dir=str(data_dir),
            inputs={
                "left": "rect/left.png",
                "disparity_left": "rect/disparity_left.npy",
                "focal_px": 3979.911 * scale,
                "grade": grade,
            },
        )
        record = views_task(task, ViewsStageParams(preview_side=120, preview_frames=4))
        assert record.status == "done", record.reason
        add_stage_result(
            card_id,
            "views",
            status="done",
            outcome=None,
            param_hash=record.param_hash,
            metrics=record.metrics,
            artifacts=record.artifacts,
        )
        return card_id, record

    return make


@dataclass(frozen=True)
class World:
    """A small served app with something behind every door (see :func:`hostile_world`)."""

    card_id: int  # filter-passed, graded and in the review queue
    review_id: int
    review_version: int
    crop_card_id: int  # in a crop batch wanting 1,000 answers per item
    aggregate_id: int  # a disputed crowd aggregate on crop_card_id
    worker_token: str  # a crowd worker's signed API token
    csrf: str  # the logged-in admin's CSRF token


@pytest.fixture
def hostile_world(app, client, login, csrf_token, make_card, add_stage_result, card_image, decide_orientation) -> World:  # type: ignore[no-untyped-def]
    """An admin logged in on ``client``, a reviewable card, a crop batch, a worker and a dispute."""
    import re

    from sqlalchemy import select

    from annotation.batches import create_batch
    from annotation.models import Aggregate
    from annotation.providers import InviteProvider
    from core.db import db
    from review.models import CardReview
    from review.tasks import sync_reviews

    image = card_image()
    card_id = make_card(image, state="pass")
    add_stage_result(card_id, "filter")
    add_stage_result(card_id, "grade", outcome="some", metrics={"uncertainty": 0.4, "reasons": ["fringes"]})
    decide_orientation([card_id])  # the flow rule: only a card with a decided orientation can be accepted
    crop_card_id = make_card(image[:, 8:], state="review")  # 596 x 200 px
    with app.app_context():
        sync_reviews()
        review_id, version = db.session.execute(
            select(CardReview.id, CardReview.version).where(CardReview.card_id == card_id)
        ).one()
        batch = create_batch([crop_card_id], "crop", 1000, 0.0)  # room for many workers' answers
        aggregate = Aggregate(
            batch_id=batch.id,
            card_id=crop_card_id,
            kind="crop",
            state="needs_curator",
            answers=2,
            label={"left": [0, 0, 280, 200], "right": [300, 0, 590, 200]},
            reasons="disputed",
        )
        db.session.add(aggregate)
        db.session.commit()
        aggregate_id = aggregate.id
        link = InviteProvider.invite("probe-worker").token
    page = client.get(f"/crowd/invite/{link}?kind=crop").get_data(as_text=True)
    worker_token = re.search(r'data-worker-token="([^"]*)"', page).group(1)  # type: ignore[union-attr]
    login("admin")
    return World(card_id, review_id, version, crop_card_id, aggregate_id, worker_token, csrf_token("/cards"))


@pytest.fixture
def post_at_once(app, client) -> Callable[..., list[Any]]:  # type: ignore[no-untyped-def]
    """POST the same form ``times`` times at the same moment, each from its own test client
    holding ``client``'s session (a double click, two exporters on one preview); the responses."""
    import threading

    def post(url: str, form: dict[str, Any], times: int) -> list[Any]:
        cookie = client.get_cookie("session")
        barrier, answers = threading.Barrier(times), []

        def one() -> None:
            own = app.test_client()
            own.set_cookie(cookie.key, cookie.value)
            barrier.wait()
            answers.append(own.post(url, data=form))

        threads = [threading.Thread(target=one) for _ in range(times)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        return answers

    return post


# ---- a IIIF server on loopback (catalogue/iiif_ingest.py, exports/formats/iiif.py) ----


@pytest.fixture
def iiif_server(tmp_path: Path) -> Iterator[Any]:
    """A level-0 static IIIF server on loopback (benchmarks.iiif_server.StaticIiif), closed after the test."""
    from benchmarks.iiif_server import StaticIiif

    served = StaticIiif(tmp_path / "iiif-root")
    yield served
    served.close()

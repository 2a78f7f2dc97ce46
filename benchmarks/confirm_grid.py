"""``keystone bench confirm-grid``: a timed walk through one confirm grid in headless Chromium.

What runs: a throwaway instance (SQLite, a data dir) holding real cards (the shared NYPL and
Keystone-Mast cards with hand-drawn photo areas, each as scanned, turned, negative and with
its photos exchanged: :func:`benchmarks.orientation_flow.make_variants`; without ../shared/data,
synthetic cards from the Motorcycle pair). ``--cards`` of them become ``confirm`` cards whose
proposed orientation is their truth, except ``--wrong-rate`` of them, proposed wrong on one
flag (what a person must tap); the rest are decided cards, the gold material. One confirm batch,
grids of all the confirm cards plus ``--gold`` gold cards. The app is served by werkzeug's
threaded server in this process; Debian's Chromium walks one grid three times, each as a new
worker, marking exactly the wrong cards (the proposal's wrong flag, each gold card's answer):

* ``desktop-mouse`` (1366 x 800): a click on each wrong toggle, a click on Submit;
* ``desktop-keys`` (1366 x 800): the shortest arrow-key path to each wrong card, U / N / D, Enter;
* ``phone-touch`` (390 x 844, touch): a tap on each wrong toggle, a tap on Submit; the grid is
  longer than the screen, so ``swipes`` counts the screens a person scrolls through.

Measured per walk: ``load_s`` (the page opened until every picture is decoded; the first walk
makes the pictures, later walks mostly find them cached), ``act_s`` (the scripted marking and
the submit until the next grid, or the finished screen, is shown), ``submit_s`` (the grid's
submit request alone), actions per card, and the answers checked in the database. A script
marks cards in milliseconds, so its cards per minute are the machine's ceiling, not a
person's: ``person_estimate`` adds the stated seconds a person spends looking at a card and
per action (assumptions, not a measurement with people), for the grid and for the one-card
judge task (one page per card: at least one action a card).

    python -m benchmarks.confirm_grid [--json] [--shots DIR] [--cards 30] [--gold 3]
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click
import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("KEYSTONE_SHARED_DATA", REPO.parent / "shared" / "data"))
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update"]
FLAGS = ("upside_down", "inverted", "swapped")
KEYS = {"upside_down": "u", "inverted": "n", "swapped": "d"}
SCREENS: dict[str, dict[str, Any]] = {
    "desktop": {"viewport": {"width": 1366, "height": 800}},
    "phone": {"viewport": {"width": 390, "height": 844}, "has_touch": True, "is_mobile": True, "device_scale_factor": 2},
}
# A person's time, for the estimate only (stated, not measured): a glance that tells a right
# card from a wrong one, and one deliberate click, tap or key press.
GLANCE_S = 0.6
ACTION_S = 0.8


def _scans(data: Path, out: Path) -> dict[str, dict[str, Any]]:
    """Four variants of every real card (file name -> truth flags and photo boxes)."""
    from .orientation_flow import make_variants, shared_cards

    cards = shared_cards(data) if (data / "stereocards").is_dir() else []
    if not cards:
        from simulation.cards import make_stereo_card

        folder = out.parent / "synthetic"
        folder.mkdir(parents=True, exist_ok=True)
        for index in range(8):
            card = make_stereo_card(7, index)
            Image.fromarray(card.image).save(folder / f"synthetic-{index}.png")
            left, right = card.truth["photo_boxes"]
            cards.append((f"synthetic-{index}", folder / f"synthetic-{index}.png", (tuple(left), tuple(right))))
    return make_variants(cards, out)


def build(root: Path, data: Path, n_cards: int, n_gold: int, wrong_rate: float) -> tuple[Any, dict[int, dict[str, Any]]]:
    """The instance: cards ingested, their filter and orientation results written, one confirm
    batch. Returns the app and, per confirm card, what the walk must mark (flag or None)."""
    from annotation.batches import confirm_gold, create_batch
    from app import create_app
    from app.schema import upgrade
    from catalogue.ingest import ingest
    from core.db import db
    from core.models import Card, StageResult

    app = create_app(
        {
            "SQLALCHEMY_DATABASE_URI": f"sqlite:///{root / 'keystone.sqlite3'}",
            "KEYSTONE_DATA_DIR": str(root / "data"),
            "SECRET_KEY": "bench-confirm-grid",
            "KEYSTONE_CROWD_GRID_SIZE": n_cards + n_gold,
            "KEYSTONE_CROWD_GRID_GOLD": n_gold,
        }
    )
    truths = _scans(data, root / "scans")
    if len(truths) < n_cards + n_gold:
        raise click.ClickException(f"only {len(truths)} scans for {n_cards} cards and {n_gold} gold")
    marks: dict[int, dict[str, Any]] = {}
    with app.app_context():
        upgrade(db.engine)
        ingest([root / "scans"], data_dir=root / "data", max_pixels=int(app.config["KEYSTONE_MAX_PIXELS"]))
        cards = {c.source_name: c for c in db.session.scalars(db.select(Card))}
        names = sorted(cards)
        # Interleave the variants so the grid mixes cards; every n-th confirm card is proposed wrong.
        order = sorted(names, key=lambda name: (truths[name]["variant"] != "original", name))
        confirm, known = order[:n_cards], order[n_cards:]
        every = max(1, round(1 / wrong_rate)) if wrong_rate > 0 else 0
        for name in names:
            card, truth = cards[name], truths[name]
            left, right = [list(map(int, box)) for box in truth["boxes"]]
            flags = dict(truth["flags"])
            wrong_flag = None
            if name in confirm and every and confirm.index(name) % every == every - 1:
                wrong_flag = FLAGS[(confirm.index(name) // every) % 3]
            proposed = {**flags, **({wrong_flag: not flags[wrong_flag]} if wrong_flag else {})}
            outcome = "confirm" if name in confirm else "auto"
            card.state = "pass"
            metrics = {"left_box": left, "right_box": right, "card_size": [card.width, card.height]}
            db.session.add(
                StageResult(card_id=card.id, stage="filter", param_hash="bench", status="done", outcome="pass", metrics=metrics)
            )
            orientation = {
                "decision": outcome,
                "confidence": 0.7 if outcome == "confirm" else 0.999,
                "proposed": proposed,
                "flags": {f: {"p": float(proposed[f]), "decided": outcome == "auto", "value": proposed[f]} for f in FLAGS},
                "photo_left_box": left,
                "photo_right_box": right,
            }
            db.session.add(
                StageResult(
                    card_id=card.id, stage="orientation", param_hash="bench", status="done", outcome=outcome, metrics=orientation
                )
            )
            if name in confirm:
                marks[card.id] = {"flag": wrong_flag, "name": name}
        db.session.commit()
        confirm_ids = [cards[name].id for name in confirm]
        gold, shown = confirm_gold(exclude=confirm_ids, count=max(n_gold, len(known)))
        create_batch(confirm_ids, "confirm", 3, 0.0, gold=gold, shown=shown)
    return app, marks


@contextmanager
def served(app: Any) -> Iterator[str]:
    import logging

    from werkzeug.serving import make_server

    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # one line per picture otherwise
    httpd = make_server("127.0.0.1", 0, app, threaded=True)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_port}"
    finally:
        httpd.shutdown()
        thread.join(timeout=10)


def _wait(page: Any, expression: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise click.ClickException(f"timed out waiting for {expression}")
        page.wait_for_timeout(20)


def _on_screen(app: Any, page: Any) -> list[tuple[int, bool, dict[str, bool] | None]]:
    from annotation.models import Reservation
    from core.db import db

    sources = page.evaluate("[...document.querySelectorAll('#grid img')].map(i => i.src)")
    tokens = [src.split("/task/")[1].split("/")[0] for src in sources]
    with app.app_context():
        rows = {
            r.token: (r.item.card_id, r.item.is_gold, r.item.gold_answer)
            for r in db.session.scalars(db.select(Reservation).where(Reservation.token.in_(tokens)))
        }
    return [rows[t] for t in tokens]


def walk(app: Any, browser: Any, server: str, mode: str, marks: dict[int, dict[str, Any]], shots: Path | None) -> dict[str, Any]:
    """One worker opens the grid, marks what is wrong in ``mode`` and submits; timings and counts."""
    from annotation.providers import InviteProvider

    screen = "phone" if mode == "phone-touch" else "desktop"
    with app.app_context():
        link = f"{server}/crowd/invite/{InviteProvider.invite(f'bench-{mode}').token}?kind=confirm"
    page = browser.new_context(**SCREENS[screen]).new_page()
    page.add_init_script("try { localStorage.setItem('keystone-grid-help-seen', '1'); } catch (e) {}")
    started = time.perf_counter()
    page.goto(link)
    _wait(page, "document.querySelectorAll('#grid .grid-card').length > 0")
    _wait(page, "[...document.querySelectorAll('#grid img')].every(i => i.complete && i.naturalWidth > 0)")
    load_s = time.perf_counter() - started
    items = _on_screen(app, page)
    wanted = []
    for card_id, is_gold, gold_answer in items:
        if is_gold:
            wanted.append([f for f in FLAGS if (gold_answer or {}).get(f)])
        else:
            wanted.append([marks[card_id]["flag"]] if marks[card_id]["flag"] else [])
    columns = page.evaluate(
        "(() => { const c = [...document.querySelectorAll('#grid .grid-card')]; return c.filter(e => e.offsetTop === c[0].offsetTop).length; })()"
    )
    page_height = page.evaluate("document.documentElement.scrollHeight")
    if shots:
        page.screenshot(path=str(shots / f"confirm-grid-{mode}.png"))
    actions = 0
    here = 0
    started = time.perf_counter()
    for index, flags in enumerate(wanted):
        for flag in flags:
            if mode == "desktop-keys":
                rows, cols = index // columns - here // columns, index % columns - here % columns
                for key, count in (
                    ("ArrowDown" if rows > 0 else "ArrowUp", abs(rows)),
                    ("ArrowRight" if cols > 0 else "ArrowLeft", abs(cols)),
                ):
                    for _ in range(count):
                        page.keyboard.press(key)
                        actions += 1
                here = index
                page.keyboard.press(KEYS[flag])
            else:
                button = page.locator(f"#grid .grid-card >> nth={index}").locator(f"[data-flag={flag}]")
                button.tap() if mode == "phone-touch" else button.click()
            actions += 1
    if shots:
        page.screenshot(path=str(shots / f"confirm-grid-{mode}-marked.png"), full_page=True)
    sent = time.perf_counter()
    with page.expect_response(lambda response: response.url.endswith("/crowd/api/grid/submit")):
        if mode == "desktop-keys":
            page.keyboard.press("Enter")
        elif mode == "phone-touch":
            page.tap("#submit-answer")
        else:
            page.click("#submit-answer")
    submit_s = time.perf_counter() - sent
    actions += 1
    _wait(page, "!document.getElementById('finished').hidden")
    act_s = time.perf_counter() - started
    if shots:
        page.screenshot(path=str(shots / f"confirm-grid-{mode}-done.png"))
    page.context.close()
    cards = len(items)
    swipes = max(0, math.ceil(page_height / SCREENS[screen]["viewport"]["height"]) - 1) if screen == "phone" else 0
    return {
        "mode": mode,
        "cards": cards,
        "gold": sum(1 for _, g, _ in items if g),
        "marked": sum(1 for flags in wanted if flags),
        "columns": columns,
        "load_s": round(load_s, 3),
        "act_s": round(act_s, 3),
        "submit_s": round(submit_s, 3),
        "actions": actions,
        "swipes": swipes,
        "actions_per_card": round(actions / cards, 3),
        "machine_cards_per_minute": round(60 * cards / (load_s + act_s), 1),
        "person_estimate": _estimate(cards, actions + swipes, sum(len(flags) for flags in wanted)),
    }


def _estimate(cards: int, actions: int, taps: int) -> dict[str, Any]:
    """Seconds a person would take with the stated glance and action times: in the grid, a
    glance a card plus the walk's actions; in one-card judge tasks, a glance, the same taps and
    one Submit a card (page turns not counted, which favours the judge task)."""
    grid_s = cards * GLANCE_S + actions * ACTION_S
    judge_s = cards * (GLANCE_S + ACTION_S) + taps * ACTION_S
    return {
        "assumed_glance_s": GLANCE_S,
        "assumed_action_s": ACTION_S,
        "grid_cards_per_minute": round(60 * cards / grid_s, 1),
        "judge_task_cards_per_minute": round(60 * cards / judge_s, 1),
    }


def _check_answers(app: Any, marks: dict[int, dict[str, Any]]) -> dict[str, Any]:
    from annotation.models import Answer, BatchItem
    from core.db import db

    wrong = 0
    with app.app_context():
        stored = db.session.execute(db.select(Answer, BatchItem).join(BatchItem, Answer.item_id == BatchItem.id)).all()
        for answer, item in stored:
            expected = dict(item.gold_answer) if item.is_gold else {f: marks[item.card_id]["flag"] == f for f in FLAGS}
            wrong += answer.payload != expected
    return {"stored": len(stored), "not_as_marked": wrong}


def picture_cost(app: Any) -> dict[str, Any]:
    """Server seconds to make one grid picture from its card's display preview, cold and cached."""
    from annotation import grid_pictures
    from annotation.grids import card_photo_boxes
    from annotation.models import BatchItem
    from catalogue.views import ensure_previews
    from core.db import db

    grid_pictures._pictures.clear()
    cold, warm = [], []
    with app.app_context():
        items = db.session.scalars(db.select(BatchItem)).all()
        for item in items:
            card = item.card
            left, right = card_photo_boxes(card)
            key = grid_pictures.picture_key(card.content_hash, left, right, item.shown or {})

            def load(card: Any = card) -> np.ndarray:
                with Image.open(ensure_previews(card.content_hash, card.stored_path)["display"]) as image:
                    return np.asarray(image.convert("RGB"))

            for bucket in (cold, warm):
                started = time.perf_counter()
                data = grid_pictures.grid_picture(key, load, card.width, left, right, item.shown or {})
                bucket.append(time.perf_counter() - started)
            sizes = len(data)
    return {
        "pictures": len(cold),
        "cold_ms_median": round(1000 * float(np.median(cold)), 1),
        "cold_ms_max": round(1000 * max(cold), 1),
        "cached_ms_median": round(1000 * float(np.median(warm)), 3),
        "jpeg_bytes_last": sizes,
    }


@click.command("confirm-grid")
@click.option("--cards", "n_cards", type=click.IntRange(4, 45), default=30, show_default=True, help="Confirm cards in the grid.")
@click.option("--gold", "n_gold", type=click.IntRange(0, 8), default=3, show_default=True, help="Gold cards hidden in it.")
@click.option("--wrong-rate", type=click.FloatRange(0.0, 1.0), default=0.1, show_default=True, help="Share proposed wrong.")
@click.option("--data", type=click.Path(path_type=Path), default=DEFAULT_DATA, show_default=True, help="The shared data folder.")
@click.option("--shots", type=click.Path(file_okay=False, path_type=Path), default=None, help="Save screenshots here.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def bench_confirm_grid_command(
    n_cards: int, n_gold: int, wrong_rate: float, data: Path, shots: Path | None, as_json: bool
) -> None:
    """A timed walk through one confirm grid: cards per minute and actions per card."""
    from playwright.sync_api import sync_playwright

    if shots:
        shots.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="keystone-confirm-grid-") as folder:
        app, marks = build(Path(folder), data, n_cards, n_gold, wrong_rate)
        with served(app) as server, sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                walks = [
                    walk(app, browser, server, mode, marks, shots) for mode in ("desktop-mouse", "desktop-keys", "phone-touch")
                ]
            finally:
                browser.close()
        document = {
            "cards_source": "shared real cards" if (data / "stereocards").is_dir() else "synthetic cards",
            "walks": walks,
            "answers": _check_answers(app, marks),
            "pictures": picture_cost(app),
        }
    if as_json:
        click.echo(json.dumps(document))
        return
    for w in walks:
        click.echo(
            f"{w['mode']}: {w['cards']} cards ({w['gold']} gold, {w['marked']} marked), {w['columns']} columns; "
            f"load {w['load_s']} s, marking + submit {w['act_s']} s (submit request {w['submit_s']} s); "
            f"{w['actions']} actions + {w['swipes']} swipes "
            f"= {w['actions_per_card']} actions a card; machine {w['machine_cards_per_minute']} cards/min; "
            f"person (estimate) {w['person_estimate']['grid_cards_per_minute']} cards/min in a grid vs "
            f"{w['person_estimate']['judge_task_cards_per_minute']} in one-card judge tasks"
        )
    click.echo(f"answers: {document['answers']}; pictures: {document['pictures']}")


if __name__ == "__main__":
    bench_confirm_grid_command()

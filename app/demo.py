"""``keystone demo``: build a demo collection end to end on an embedded SQLite catalogue, then serve.

Needs nothing outside the install: the cards are made from real photographs that ship with
scikit-image (the Middlebury 2014 Motorcycle stereo pair and its single images), mounted,
toned and damaged like antique cards, plus broken ones (mono card, card back, upside-down,
inverted). Rerunning is cheap: ingest sees duplicates and the stages skip finished work.
"""

from __future__ import annotations

import os
import secrets
import time
from pathlib import Path

import click
from sqlalchemy import select

DEMO_ROLES = ("admin", "curator", "exporter", "annotator")


def _demo_logins(folder: Path) -> dict[str, str]:
    """Random passwords made on the first run, kept (mode 600) so reruns print the same ones."""
    logins_file = folder / "demo-logins.txt"
    if logins_file.exists():
        pairs = (line.split(" ", 1) for line in logins_file.read_text().splitlines() if " " in line)
        return {name: password for name, password in pairs}
    logins = {role: secrets.token_urlsafe(9) for role in DEMO_ROLES}
    fd = os.open(logins_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.writelines(f"{name} {password}\n" for name, password in logins.items())
    return logins


def _card_ids_by_name() -> dict[str, int]:
    from core.db import db
    from core.models import Card

    return {Path(name).stem: card_id for card_id, name in db.session.execute(select(Card.id, Card.source_name))}


def _true_orientation(card) -> dict:  # type: ignore[no-untyped-def]
    """How a demo card was made: the upside-down card is the whole scan turned (its eyes are
    in order once turned back), the inverted one a negative; none has its eyes swapped."""
    return {"upside_down": bool(card.truth.get("upside_down")), "inverted": bool(card.truth.get("inverted")), "swapped": False}


def seed_demo_crowd(cards: list, echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """A simulated crowd (noisy workers and a spammer) answers through the real task code: it
    judges every card waiting for people (the filter's review band and the cards whose
    orientation the orientation step could not decide, whatever their band) plus the
    upside-down and inverted cards, so their corrections come from the crowd unless the step
    decided them, and draws crop boxes on three stereo cards. Gold items carry known answers.
    Leaves the aggregates approved or waiting for a curator."""
    from annotation.aggregation import QUESTIONS
    from annotation.models import Batch
    from annotation.simulate import seed_simulated_crowd
    from core.db import db
    from runs.card_state import waiting_for_people

    if db.session.scalar(select(Batch.id).limit(1)) is not None:
        return {"note": "crowd batches exist already: not seeded again"}
    ids = _card_ids_by_name()
    by_name = {card.name: card for card in cards if card.name in ids}

    def judgement(card) -> dict:  # type: ignore[no-untyped-def]
        truth = {"is_stereo": card.kind in ("stereo", "upside_down", "inverted"), **_true_orientation(card)}
        return {question: truth[question] for question in QUESTIONS}  # the questions the judge task asks

    waiting = {card_id for ids_ in waiting_for_people().values() for card_id in ids_}
    to_judge = [c for c in by_name.values() if c.kind in ("back", "upside_down", "inverted") or ids[c.name] in waiting]
    stereo = [c for c in by_name.values() if c.kind == "stereo"]
    # Gold covers the rarer answer too (a mono card is no stereo pair): Dawid-Skene learns each
    # worker's confusion from gold, and all-"yes" gold teaches it nothing about "no".
    mono = [c for c in by_name.values() if c.kind == "mono"]
    known = [c for c in stereo if c not in to_judge][-2:]  # gold must not be a card being asked about
    judge = seed_simulated_crowd(
        # Five answers per card from seven workers: the gold can no longer cover the rare
        # answers (the upside-down and inverted cards are asked about themselves), and with
        # four answers half the judgements waited for a curator on "inverted" (posterior
        # 0.54-0.94); with five all eight were approved (seeds 1-3 measured).
        [ids[c.name] for c in to_judge],
        kind="judge",
        workers=7,
        n=5,
        seed=1,
        truth={ids[c.name]: judgement(c) for c in to_judge},
        gold={ids[c.name]: judgement(c) for c in [*mono, *known]},
    )
    boxed = stereo[:3]
    crop = seed_simulated_crowd(
        [ids[c.name] for c in boxed],
        kind="crop",
        workers=6,
        seed=2,
        truth={ids[c.name]: {"left": _shrunk(c.truth["left_box"]), "right": _shrunk(c.truth["right_box"])} for c in boxed},
        gold={ids[c.name]: {"left": _shrunk(c.truth["left_box"]), "right": _shrunk(c.truth["right_box"])} for c in stereo[3:5]},
    )
    for summary in (judge, crop):
        echo(
            f"crowd {summary['kind']}: batch {summary['batch']}, {summary['answers']} answers, "
            f"approved {summary['approved']}, waiting for a curator {summary['needs_curator']}, "
            f"flagged workers {summary['flagged_workers']}"
        )
    return {"judge": judge, "crop": crop, "waiting_before": sorted(waiting)}


def override_demo_orientation(cards: list, echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """The demo curator decides one card's orientation on its page: a card whose orientation the
    step decided automatically and wrongly (the demo knows how its cards were made: the step's
    ground-plane cue turns over on close-ups without ground), else the first stereo card the
    step and the crowd left undecided (a disputed judgement is left for you to try), else the
    last stereo card (confirming what is known)."""
    from core.db import db
    from core.hooks import approved_decisions
    from core.models import Card, Person
    from pipeline.decided_orientation import card_orientation
    from review.models import OrientationOverride
    from review.orientation import override_orientation
    from runs.card_state import waiting_for_people

    if db.session.scalar(select(OrientationOverride.id).limit(1)) is not None:
        return {"note": "an orientation override exists already: not made again"}
    ids = _card_ids_by_name()
    by_id = {ids[c.name]: c for c in cards if c.name in ids}
    stereo = [card_id for card_id, c in by_id.items() if c.kind in ("stereo", "upside_down", "inverted")]
    undecided = [card_id for card_id in waiting_for_people()["orientation"] if card_id in stereo]
    approved = approved_decisions(stereo)
    wrong = []
    for candidate in sorted(stereo):
        used = card_orientation(db.session.get(Card, candidate), approved.get(candidate, {}))
        truth = _true_orientation(by_id[candidate])
        if used["decided_by"] is not None and any(used[flag] != truth[flag] for flag in truth):
            wrong.append(candidate)
            echo(
                f"orientation: card {candidate} ({by_id[candidate].name}) was decided by {used['decided_by']} as "
                + ", ".join(f"{flag} {used[flag]}" for flag in truth)
                + ": wrong"
            )
    card_id = wrong[0] if wrong else undecided[0] if undecided else max(stereo)
    card = db.session.get(Card, card_id)
    curator = db.session.scalar(select(Person).where(Person.username == "curator"))
    for other in wrong[1:]:  # every wrong decision is corrected before anything is rectified
        override_orientation(
            other, _true_orientation(by_id[other]), curator=curator, note="demo: the curator corrected the orientation"
        )
    after = override_orientation(
        card_id, _true_orientation(by_id[card_id]), curator=curator, note="demo: the curator looked at the card"
    )
    echo(
        f"orientation: the demo curator decided card {card_id} ({card.source_name}): "
        + ", ".join(f"{flag} {after[flag]}" for flag in ("upside_down", "inverted", "swapped"))
        + f"; {len(undecided) - 1 if undecided else 0} other card(s) still wait for people"
    )
    # Until the judge task asks the eye order, a crowd judgement leaves ``swapped`` undecided
    # where the step was not sure of it: the curator answers that one question on those cards
    # (the crowd's upside-down and inverted answers stand).
    eye_order = []
    for candidate in sorted(stereo):
        if candidate == card_id:
            continue
        used = card_orientation(db.session.get(Card, candidate), approved_decisions([candidate]).get(candidate, {}))
        # Only the flags nobody decided (one the crowd's answers left undecided; all three on a card
        # whose judgement the crowd disputes): the curator's answer is the demo's truth.
        missing = {flag: value for flag, value in _true_orientation(by_id[candidate]).items() if used[flag] is None}
        if missing:
            override_orientation(
                candidate, missing, curator=curator, note="demo: the curator looked at the card and its depth in colours"
            )
            eye_order.append(candidate)
    if eye_order:
        echo(
            f"orientation: the demo curator decided what was left undecided on {len(eye_order)} card(s) (a flag the "
            "crowd left undecided, or a disputed judgement)"
        )
    return {
        "card": card_id,
        "orientation": after,
        "was_undecided": card_id in undecided,
        "wrong_before": wrong,
        "eye_order_by_curator": eye_order,
    }


def _shrunk(box: list, margin: float = 0.03) -> list[float]:
    """A photo's box pulled in by ``margin`` of its size: the artifact-free area people draw."""
    x0, y0, x1, y1 = (float(v) for v in box)
    dx, dy = margin * (x1 - x0), margin * (y1 - y0)
    return [round(x0 + dx), round(y0 + dy), round(x1 - dx), round(y1 - dy)]


def curate_demo(echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """The demo curator accepts the automatic grade of the cards the grader is surest of and
    leaves the rest (and any disputed crowd answer) in the review queue to try by hand."""
    from core.db import db
    from core.models import Person
    from review.models import CardReview
    from review.tasks import decide, sync_reviews
    from runs.card_state import card_states

    sync_reviews()
    curator = db.session.scalar(select(Person).where(Person.username == "curator"))
    pending = list(
        db.session.scalars(
            select(CardReview)
            .where(CardReview.decision == "pending", CardReview.auto_grade.in_(("few", "some")))
            .order_by(CardReview.uncertainty.asc(), CardReview.card_id)
        )
    )
    already = db.session.scalar(select(CardReview.id).where(CardReview.decision != "pending").limit(1))
    accepted = []
    if already is None:
        # A card whose crowd judgement or crop is disputed, or whose orientation is undecided,
        # cannot be accepted: it waits for you.
        states = card_states([review.card for review in pending])
        undisputed = [review for review in pending if not states[review.card_id].blockers]
        for review in undisputed[: max(1, len(pending) // 2)]:
            decide(
                review.id, "accept", expected_version=review.version, curator=curator, note="demo: accepted by the demo script"
            )
            accepted.append(review.card_id)
    left = db.session.scalar(select(db.func.count()).select_from(CardReview).where(CardReview.decision == "pending"))
    echo(f"review: the demo curator accepted {len(accepted)} grade(s); {left} card(s) wait in /review")
    return {"accepted": accepted, "pending": left}


def release_demo(folder: Path, echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """Publish a release of the accepted cards (unless one with the same data exists) and verify it."""
    from flask import current_app

    from core.db import db
    from core.models import Person
    from exports.release import ReleaseError, plan_release, publish_release
    from exports.verify import verify_release

    releases = Path(current_app.config.get("KEYSTONE_RELEASES_DIR") or folder / "releases")
    plan = plan_release(min_grade="some")
    exporter = db.session.scalar(select(Person).where(Person.username == "exporter"))
    if plan.cards and plan.changes.get("kind") == "patch":
        # A rerun of the demo: the same cards with the same data are already released.
        echo(f"release: the same data as release {plan.changes.get('previous_version')}; not published again")
        return {"version": plan.changes.get("previous_version"), "verified": None}
    try:
        report = publish_release(releases, min_grade="some", notes="Demo collection", actor=exporter, actor_label="keystone demo")
    except ReleaseError as exc:
        echo(f"release: not published: {exc}")
        return {"version": None, "error": str(exc)}
    verified = verify_release(report.path)
    echo(
        f"release {report.version}: {report.cards} cards, {report.files} files in {report.path}; "
        f"verify: {'ok' if verified.ok else verified.problems}"
    )
    return {
        "version": report.version,
        "path": report.path,
        "cards": report.cards,
        "verified": verified.ok,
        "problems": verified.problems,
    }


def build_demo(folder: Path, workers: int = 2, echo=click.echo) -> dict:  # type: ignore[no-untyped-def]
    """Make the cards, ingest them, run the stages, add demo people; returns a summary."""
    from app.schema import ensure_schema
    from catalogue.ingest import ingest
    from core.db import db
    from core.models import Card, Person
    from core.people import create_person
    from runs.executors import make_executor
    from runs.loop import run_stage
    from runs.specs import available_stages
    from simulation.cards import make_demo_cards, write_demo_cards

    clock = time.perf_counter()
    scans = folder / "scans"
    cards = make_demo_cards(seed=0)
    write_demo_cards(cards, scans)
    echo(f"made {len(cards)} demo cards in {scans}")

    data_dir = folder / "data"
    data_dir.mkdir(parents=True, exist_ok=True)
    ensure_schema(db.engine)
    report = ingest(
        [scans], data_dir=data_dir, collection_name="demo", metadata_csv=scans / "metadata.csv", max_pixels=10_000_000
    )
    echo(f"ingested {len(report.ingested)} (duplicates {len(report.duplicates)}, rejected {len(report.rejected)})")
    for entry in report.rejected:
        echo(f"  rejected {entry['path']}: {entry['reason']}")

    logins = _demo_logins(folder)
    for role in DEMO_ROLES:
        if db.session.scalar(select(Person).where(Person.username == role)) is None:
            create_person(role, logins[role], [role], display_name=f"Demo {role}")

    stage_reports, crowd, override = [], {}, {}
    with make_executor("local", workers, None) as executor:
        for name, spec in available_stages().items():
            if name == "rectify":
                # Between the orientation step and rectification, as in production: the crowd
                # judges the cards waiting for people (and the broken ones) and draws boxes on a
                # few; a curator decides one card's orientation on its page.
                crowd = seed_demo_crowd(cards, echo)
                override = override_demo_orientation(cards, echo)
            stage_report = run_stage(spec, data_dir=data_dir, executor=executor)
            stage_reports.append(stage_report.as_json())
            echo(
                f"{spec.name}: processed {stage_report.processed} in {stage_report.seconds:.1f} s, "
                f"outcomes {stage_report.outcomes}, failed {stage_report.failed}"
            )

    review = curate_demo(echo)
    release = release_demo(folder, echo)

    expected = {card.name: card.expected_filter for card in cards}
    rows = []
    for card in db.session.scalars(select(Card).order_by(Card.id)):
        stem = Path(card.source_name).stem
        filter_result = card.latest_results().get("filter")
        outcome = filter_result.outcome if filter_result else None
        rows.append(
            {
                "id": card.id,
                "source": card.source_name,
                "outcome": outcome,
                "fraction": filter_result.metrics.get("good_match_fraction") if filter_result else None,
                "expected": list(expected.get(stem, ())),
                "as_expected": outcome in expected.get(stem, (outcome,)),
            }
        )
    echo(f"{'card':<32} {'filter':<8} {'fraction':>9}  expected")
    for row in rows:
        fraction = f"{100 * row['fraction']:.2f} %" if row["fraction"] is not None else "-"
        mark = "" if row["as_expected"] else "   <- unexpected"
        echo(f"{row['source']:<32} {row['outcome']!s:<8} {fraction:>9}  {'/'.join(row['expected'])}{mark}")
    return {
        "cards": rows,
        "stages": stage_reports,
        "crowd": crowd,
        "orientation_override": override,
        "review": review,
        "release": release,
        "logins": logins,
        "seconds": time.perf_counter() - clock,
    }


@click.command("demo")
@click.option("--no-serve", is_flag=True, help="Stop after building and processing the demo collection.")
@click.option(
    "--dir",
    "folder",
    type=click.Path(path_type=Path, file_okay=False),
    default=Path("keystone-demo"),
    show_default=True,
    help="Folder for the demo's catalogue, store and scans.",
)
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=5000, show_default=True, type=int)
@click.option("--workers", default=2, show_default=True, type=click.IntRange(1, 64))
@click.option(
    "--worker/--no-worker",
    "with_worker",
    default=True,
    show_default=True,
    help="Serve with the background worker that recomputes as people decide (as keystone serve).",
)
@click.option(
    "--serve-only",
    is_flag=True,
    help="Serve the demo built before in --dir (by keystone demo --no-serve), without building it again.",
)
def demo_command(no_serve: bool, folder: Path, host: str, port: int, workers: int, with_worker: bool, serve_only: bool) -> None:
    """Build the demo collection end to end (embedded SQLite in --dir), then serve the app.

    A demo built with --no-serve is served again, as it was left, by `keystone demo --dir D
    --serve-only` (its catalogue, store and releases all live in D)."""
    from app import create_app
    from app.serving import serve

    if no_serve and serve_only:
        raise click.UsageError("--no-serve and --serve-only ask for opposite things; give one")
    folder = folder.resolve()
    if serve_only and not (folder / "keystone.sqlite3").is_file():
        raise click.UsageError(f"no demo is built in {folder}: run `keystone demo --dir {folder}` (or with --no-serve) first")
    folder.mkdir(parents=True, exist_ok=True)
    app = create_app(
        {
            "SQLALCHEMY_DATABASE_URI": f"sqlite:///{folder / 'keystone.sqlite3'}",
            "KEYSTONE_DATA_DIR": str(folder / "data"),
            "KEYSTONE_RELEASES_DIR": str(folder / "releases"),
        },
        instance_path=folder / "instance",
    )
    if serve_only:
        logins = folder / "demo-logins.txt"
        click.echo(f"serving the demo built in {folder}")
        if logins.is_file():
            click.echo(
                "logins (from demo-logins.txt): "
                + ", ".join(" / ".join(line.split()) for line in logins.read_text().splitlines())
            )
        serve(app, host=host, port=port, with_worker=with_worker)
        return
    with app.app_context():
        summary = build_demo(folder, workers=workers)
    click.echo(f"demo built in {summary['seconds']:.1f} s in {folder}")
    click.echo("logins (also in demo-logins.txt): " + ", ".join(f"{k} / {v}" for k, v in summary["logins"].items()))
    unexpected = [row["source"] for row in summary["cards"] if not row["as_expected"]]
    if unexpected:
        click.echo(f"warning: {len(unexpected)} card(s) routed unexpectedly: {', '.join(unexpected)}", err=True)
    if no_serve:
        click.echo(f"serve it again later with: keystone demo --dir {folder} --serve-only")
    else:
        serve(app, host=host, port=port, with_worker=with_worker)

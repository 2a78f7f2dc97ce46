"""``keystone report``, ``keystone grade fit|show`` and ``keystone orientation set|show|fit``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
from flask.cli import with_appcontext


@click.command("report")
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON document.")
@with_appcontext
def report_command(as_json: bool) -> None:
    """Grade distribution per collection beside the paper's 23 / 49 / 28 %, agreement of the
    automatic grades with curators, and crowd agreement per batch."""
    from core.console import emit_json, ensure_database

    from .report import build_report

    ensure_database()
    report = build_report()
    if as_json:
        emit_json(report)
        return
    click.echo(render_text(report))


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def render_text(report: dict[str, Any]) -> str:
    paper = report["paper"]["fractions"]
    lines = [
        f"Grades (few / some / failure); paper, {report['paper']['sample']} cards: "
        + " / ".join(_percent(paper[g]) for g in ("few", "some", "failure"))
    ]
    for entry in report["collections"]:
        auto, curated = entry["automatic"], entry["curated"]
        lines.append(f"  {entry['collection']}: {entry['cards']} cards")
        for label, block in (("automatic", auto), ("curated", curated)):
            counts = block["counts"]
            if sum(counts.values()):
                lines.append(
                    f"    {label:9s} "
                    + " / ".join(f"{counts[g]} ({_percent(block['fractions'][g])})" for g in ("few", "some", "failure"))
                )
        lines.append("    decisions " + ", ".join(f"{k} {v}" for k, v in entry["decisions"].items()))
    block = report["automatic_vs_curator"]
    lines.append(
        f"Automatic grade vs curators: {block['labels']} labels, accuracy {_percent(block['accuracy'])}, "
        f"Cohen's kappa {block['cohen_kappa'] if block['cohen_kappa'] is not None else '-'}"
    )
    basis = block.get("labels_from") or {}
    lines.append(
        f"    from {basis.get('accepted', 0)} accepted automatic grade(s) (agreeing by construction) "
        f"and {basis.get('changed', 0)} changed by a curator"
    )
    if block["labels"]:
        lines.append("    curator \\ automatic   few  some  failure")
        for grade, row in zip(block["order"], block["confusion"]):
            lines.append(f"    {grade:20s} " + "  ".join(f"{v:4d}" for v in row))
    model = report["grade_model"]
    if model is not None:
        held = model["held_out"]
        lines.append(
            f"Grade model {model['id']}: fitted on {model['fitted_on']} curator labels; held-out accuracy "
            f"{_percent(held.get('accuracy'))}, kappa {held.get('cohen_kappa', '-')}"
        )
    for batch in report["crowd"]:
        figures = "; ".join(
            f"{part}: " + ", ".join(f"{name} {value:.2f}" for name, value in values.items() if value is not None)
            for part, values in batch["agreement"].items()
        )
        lines.append(
            f"Crowd batch {batch['batch']} ({batch['kind']}, {batch['items']} items, "
            f"{batch['answers']} answers): {figures or 'not enough answers'}"
        )
    return "\n".join(lines)


@click.group("grade")
def grade_group() -> None:
    """The automatic grader: show its thresholds, refit them to curator labels."""


@grade_group.command("show")
@click.option("--json", "as_json", is_flag=True, help="Print the active thresholds as JSON.")
@with_appcontext
def grade_show_command(as_json: bool) -> None:
    """Print the thresholds the grade stage uses now (fitted ones, or the defaults)."""
    from core.console import emit_json, ensure_database

    from .grading import active_grade_params

    ensure_database()
    params, model = active_grade_params()
    document = {"model": None if model is None else model.id, "thresholds": params.thresholds.to_dict()}
    if as_json:
        emit_json(document)
    else:
        click.echo(f"thresholds from {'grade model ' + str(model.id) if model else 'the defaults'}:")
        for name, value in document["thresholds"].items():
            click.echo(f"  {name}: {value}")


@grade_group.command("fit")
@click.option(
    "--from-bench",
    "bench_file",
    type=click.Path(path_type=Path, dir_okay=False, exists=True),
    help="Fit to the true error in this `keystone bench grade --json` output instead of curator labels.",
)
@click.option(
    "--few-below",
    default=25.0,
    show_default=True,
    type=click.FloatRange(0, 100),
    help="With --from-bench: a card under this true bad-2 (percent) should grade few.",
)
@click.option(
    "--failure-above",
    default=50.0,
    show_default=True,
    type=click.FloatRange(0, 100),
    help="With --from-bench: a card over this true bad-2 (percent) should grade failure.",
)
@click.option(
    "--folds", default=5, show_default=True, type=click.IntRange(2, 20), help="Cross-validation folds for the held-out agreement."
)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--dry-run", is_flag=True, help="Report the fit without saving the thresholds.")
@click.option("--json", "as_json", is_flag=True, help="Print the fit report as one JSON document.")
@with_appcontext
def grade_fit_command(
    bench_file: Path | None, few_below: float, failure_above: float, folds: int, seed: int, dry_run: bool, as_json: bool
) -> None:
    """Refit the grade thresholds to the curators' labels so far (or, with --from-bench, to the
    true error of bench cards) and report their agreement on labels they were not fitted on.
    Then `keystone run --stages grade` regrades with them."""
    import json

    from core.console import emit_json, ensure_database, fail

    from .grading import GradingError, fit_from_bench, fit_from_curators

    ensure_database()
    try:
        if bench_file is not None:
            try:
                bench = json.loads(bench_file.read_text())
            except (OSError, ValueError) as exc:
                raise GradingError(f"{bench_file}: not readable JSON ({exc})") from exc
            document = fit_from_bench(
                bench, few_below=few_below, failure_above=failure_above, folds=folds, seed=seed, save=not dry_run
            )
        else:
            document = fit_from_curators(folds=folds, seed=seed, save=not dry_run)
    except GradingError as exc:
        fail(str(exc), as_json)
    if as_json:
        emit_json(document)
        return
    held = document["held_out"]
    what = "bench cards (labels from true bad-2)" if bench_file is not None else "curator labels"
    click.echo(f"fitted on {document['labels']} {what} ({folds}-fold cross-validation)")
    click.echo(
        f"held-out accuracy {_percent(held.get('accuracy'))}, Cohen's kappa {held.get('cohen_kappa')}; "
        f"default thresholds on the same labels: accuracy {_percent(document['baseline'].get('accuracy'))}"
    )
    for change in document.get("changed", []):
        click.echo(f"  {change}")
    click.echo("saved as grade model " + str(document["model"]) if document.get("model") else "not saved (--dry-run)")


@click.group("orientation")
def orientation_group() -> None:
    """Card orientation: an operator's word for a whole collection (known prints, scanned in eye
    order), which a curator's decision on one card overrides."""


FLAG_CHOICE = click.Choice(["yes", "no", "clear"], case_sensitive=False)
FLAG_VALUES: dict[str, bool | None] = {"yes": True, "no": False, "clear": None}


def _word_line(word: dict[str, Any]) -> str:
    covered = f"{word['cards']} card(s)" + (
        f", a curator overrides it on {word['overridden_on_cards']}" if word["overridden_on_cards"] else ""
    )
    note = f"; note: {word['note']}" if word["note"] else ""
    return f"{word['collection']}: {word['says']} (said by {word['set_by']} on {word['set_at'][:10]}; {covered}){note}"


@orientation_group.command("set")
@click.option("--collection", "collection_name", required=True, help="The collection the word is for (every card of it).")
@click.option(
    "--upside-down", "upside_down", type=FLAG_CHOICE, help="The scans are turned 180 deg (yes), upright (no), or clear the word."
)
@click.option("--inverted", type=FLAG_CHOICE, help="The cards are negatives (yes), known prints (no), or clear the word.")
@click.option(
    "--swapped", type=FLAG_CHOICE, help="The photos are in the other eye's place (yes), scanned in eye order (no), or clear."
)
@click.option("--by", "by_username", help="The operator's account (username); default: the OS user running the command.")
@click.option("--note", help="Why (the source of the knowledge); shown with the word and kept in the audit trail.")
@click.option("--json", "as_json", is_flag=True, help="Print the word now in force as one JSON document.")
@with_appcontext
def orientation_set_command(
    collection_name: str,
    upside_down: str | None,
    inverted: str | None,
    swapped: str | None,
    by_username: str | None,
    note: str | None,
    as_json: bool,
) -> None:
    """Say, for every card of a collection, what is known of its orientation, flag by flag: e.g.
    `--inverted no` for a collection known to be prints, `--swapped no` for one scanned in eye
    order; `clear` takes a flag back. Each card's orientation takes the word over the crowd's and
    the orientation step's, and a curator's decision on one card overrides it. The next
    `keystone run` reruns the orientation step on the collection with the word as given."""
    import getpass

    from sqlalchemy import select

    from core.console import emit_json, ensure_database, fail
    from core.db import db
    from core.models import Person

    from .operator_word import set_collection_orientation
    from .tasks import ReviewError

    ensure_database()
    given = {"upside_down": upside_down, "inverted": inverted, "swapped": swapped}
    flags = {flag: FLAG_VALUES[value.lower()] for flag, value in given.items() if value is not None}
    person = None
    if by_username is not None:
        person = db.session.scalar(select(Person).where(Person.username == by_username))
        if person is None or not person.active:
            fail(f"There is no active account {by_username!r} (--by names an operator's username)", as_json)
        by_name = person.username
    else:
        try:
            by_name = getpass.getuser()
        except (KeyError, OSError):  # no name for this uid (a bare container)
            by_name = "keystone orientation set"
    try:
        outcome = set_collection_orientation(collection_name, flags, by=person, by_name=by_name, note=note)
    except ReviewError as exc:
        fail(exc.message, as_json)
    if as_json:
        emit_json(outcome)
        return
    word = outcome["word"]
    if word is None:
        click.echo(f"{outcome['collection']}: no word in force{'' if outcome['changed'] else ' (unchanged)'}")
    else:
        click.echo(_word_line(word) + ("" if outcome["changed"] else " (unchanged)"))
    if outcome["changed"]:
        click.echo("The next `keystone run` reruns the orientation step on the collection's cards with it.")


@orientation_group.command("show")
@click.option("--collection", "collection_name", help="Only this collection's word.")
@click.option("--json", "as_json", is_flag=True, help="Print the words as one JSON document.")
@with_appcontext
def orientation_show_command(collection_name: str | None, as_json: bool) -> None:
    """List the operators' words in force, a line per collection."""
    from core.console import emit_json, ensure_database, fail
    from core.db import read_only

    from .operator_word import collection_words
    from .tasks import ReviewError

    ensure_database()
    try:
        with read_only():
            words = collection_words(collection_name)
    except ReviewError as exc:
        fail(exc.message, as_json)
    if as_json:
        emit_json({"words": words})
        return
    for word in words:
        click.echo(_word_line(word))
    if not words:
        click.echo("no operator's word in force" + (f" for {collection_name}" if collection_name else ""))


@orientation_group.command("fit")
@click.option("--collection", "collection_name", help="Refit on this collection's cards only (default: every collection).")
@click.option(
    "--folds", default=5, show_default=True, type=click.IntRange(2, 20), help="Cross-validation folds (grouped by card)."
)
@click.option("--seed", default=0, show_default=True, type=int)
@click.option("--dry-run", is_flag=True, help="Report the refit without saving it.")
@click.option("--json", "as_json", is_flag=True, help="Print the fit report as one JSON document.")
@with_appcontext
def orientation_fit_command(collection_name: str | None, folds: int, seed: int, dry_run: bool, as_json: bool) -> None:
    """Refit the orientation step's learned upright / positive heads on the collection's own cards
    whose orientation was decided (by people, or by the step with a wide margin), and report
    held-out accuracy before and after. Saved refits are versioned; the next `keystone run`
    reruns the orientation step on the collection with the new head and lists what changed."""
    from core.console import emit_json, ensure_database, fail

    from .upright_fit import UprightFitError, fit_collection

    ensure_database()
    try:
        document = fit_collection(collection_name, folds=folds, seed=seed, save=not dry_run)
    except UprightFitError as exc:
        fail(str(exc), as_json)
    if as_json:
        emit_json(document)
        return
    click.echo(f"fitted on {document['cards']} decided cards of {collection_name or 'every collection'} ({folds}-fold, by card)")
    for kind, info in document["heads"].items():
        if "before" not in info:
            click.echo(f"  {kind}: kept ({info.get('kept')})")
            continue
        before, after = info["before"], info["after"]
        click.echo(
            f"  {kind}: held-out accuracy {_percent(before['accuracy'])} -> {_percent(after['accuracy'])} "
            f"({after['n']} photos; L2 {info['l2']:g})"
        )
    click.echo(f"{len(document['would_change'])} card decision(s) would change on the next run")
    click.echo(f"saved as head {document['head_after']}" if document["saved"] else "not saved (--dry-run)")


def register_cli(group: click.Group) -> None:
    """Add this feature's top-level commands to ``group`` (the ``keystone`` command)."""
    for command in (report_command, grade_group, orientation_group):
        group.add_command(command)

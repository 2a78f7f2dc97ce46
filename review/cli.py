"""``keystone report`` and ``keystone grade fit|show``."""

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
    from app.console import emit_json, ensure_database

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
    from app.console import emit_json, ensure_database

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

    from app.console import emit_json, ensure_database, fail

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


def register_cli(group: click.Group) -> None:
    """Add this feature's top-level commands to ``group`` (the ``keystone`` command)."""
    for command in (report_command, grade_group):
        group.add_command(command)

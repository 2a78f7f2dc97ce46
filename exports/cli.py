"""``keystone export``, ``keystone verify`` and ``keystone bench export``."""

from __future__ import annotations

from pathlib import Path

import click
from flask.cli import with_appcontext

from .formats import default_format_names, registered_formats
from .records import RELEASABLE_GRADES


@click.command("export")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder that holds the releases; this one is written to OUT/<version>.",
)
@click.option(
    "--min-grade",
    type=click.Choice(list(RELEASABLE_GRADES)),
    default="some",
    show_default=True,
    help="Lowest curator grade released (few > some; failure is never released).",
)
@click.option(
    "--format",
    "formats",
    default=",".join(default_format_names()),
    show_default=True,
    help="Comma-separated layouts: " + "; ".join(f"{fmt.name} ({fmt.description})" for fmt in registered_formats()) + ".",
)
@click.option("--dry-run", is_flag=True, help="Show what would go in, what changed and the version; write nothing.")
@click.option("--notes", default="", help="Release notes (README and the releases page).")
@click.option("--json", "as_json", is_flag=True, help="Print the release report as one JSON document.")
@with_appcontext
def export_command(out_dir: Path, min_grade: str, formats: str, dry_run: bool, notes: str, as_json: bool) -> None:
    """Write a versioned, verifiable dataset release of the curator-accepted cards.

    Layouts: KeystoneDepth folders (PNG + EXR), Parquet shards for Hugging Face datasets,
    WebDataset tars; always croissant.json, README.md (dataset card), CHANGELOG.md, SHA256SUMS.
    Exits 1 when no accepted card is ready to release.
    """
    from core.console import emit_json, ensure_database, fail, progress_bar, say

    from .formats import parse_formats
    from .release import ReleaseError, plan_release, publish_release

    try:
        chosen = parse_formats(formats)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--format") from exc
    ensure_database()
    try:
        if dry_run:
            report = plan_release(min_grade=min_grade, formats=chosen, notes=notes)
            if report.cards == 0:
                # Say why each accepted card was left out: that is what the operator must act on.
                left_out = "; ".join(f"card {row['card_id']}: {row['reason']}" for row in report.excluded[:20])
                more = f" (and {len(report.excluded) - 20} more)" if len(report.excluded) > 20 else ""
                raise ReleaseError(
                    f"no curator-accepted cards at or above grade {min_grade!r} are ready to release"
                    + (f"; left out: {left_out}{more}" if left_out else "")
                )
        else:
            with progress_bar("export", enabled=not as_json) as progress:
                report = publish_release(out_dir, min_grade=min_grade, formats=chosen, notes=notes, progress=progress)
    except ReleaseError as exc:
        fail(str(exc), as_json)
    if as_json:
        emit_json(report.as_json())
        return
    changes = report.changes
    summary = f"{len(changes['added'])} added, {len(changes['removed'])} removed, {len(changes['changed'])} changed" + (
        f" since {changes['previous_version']}" if changes["previous_version"] else ""
    )
    grades = ", ".join(f"{k} {v}" for k, v in report.grades.items())
    if dry_run:
        say(f"would write release {report.version} ({changes['kind']}): {report.cards} cards ({grades}); {summary}", as_json)
    else:
        say(
            f"wrote release {report.version} to {report.path}: {report.cards} cards ({grades}), {report.files} files, "
            f"{report.bytes / 1e6:.1f} MB in {report.seconds:.1f} s; {summary}",
            as_json,
        )
    for entry in report.excluded:
        say(f"  not released: card {entry['card_id']}: {entry['reason']}", as_json)
    for leftover in report.leftovers_removed:
        say(
            f"  removed {leftover['path']} ({leftover['bytes'] / 1e6:.1f} MB), left by an interrupted export: "
            f"{leftover['reason']}",
            as_json,
        )


@click.command("verify")
@click.argument("path", type=click.Path(path_type=Path))
@click.option(
    "--no-mlcroissant",
    is_flag=True,
    help="Skip mlcroissant's own validation (it takes ~100 s and 1.6 GB for 90,000 files); "
    "checksums and the Croissant file list are still checked.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON document.")
def verify_command(path: Path, no_mlcroissant: bool, as_json: bool) -> None:
    """Check a release: every checksum, the Croissant file, the Parquet schema, and that every
    listed file exists and every file present is listed. Exits 1 naming each problem."""
    from core.console import emit_json

    from .verify import verify_release

    report = verify_release(path, validate_croissant=not no_mlcroissant)
    if as_json:
        emit_json(report.as_json())
    else:
        for problem in report.problems:
            click.echo(f"{problem['path']}: {problem['problem']}", err=True)
        click.echo(
            f"{'OK' if report.ok else 'FAILED'}: {report.checked} files checked, {len(report.problems)} problem(s) in {path}"
        )
    if not report.ok:
        raise SystemExit(1)


def register_cli(group: click.Group) -> None:
    """Add this feature's top-level commands to ``group`` (the ``keystone`` command)."""
    for command in (export_command, verify_command):
        group.add_command(command)

"""``keystone bench grade-real``: the automatic grade on real cards beside a careful person's and the paper's.

Every stereo card under ``<data>/stereocards`` (NYPL full cards, Keystone-Mast raw scans, JPS pairs,
and pre-split pairs, which are put side by side with a 24 px gutter) goes through the real stage
tasks (filter, rectify, disparity, grade; :func:`benchmarks.grade.run_pipeline_on_scan`). The
labels file (default ``<data>/labels/careful_grades.csv``: ``file``, ``grade`` few / some /
failure or empty, ``reason``) is used only to *check* the grade: nothing is fitted to it.

Report: the automatic distribution over every card the pipeline graded, the person's over the
labelled cards, the paper's 23 / 49 / 28 % (711 cards), agreement (count, Cohen's kappa, confusion,
and how often the grade is the more lenient), and per card the grade, its nearest threshold and
the person's reason. Cards the pipeline stopped (culled, rectification failed) count as failure
in the agreement, with their status shown.
"""

from __future__ import annotations

import csv
import json
import tempfile
from pathlib import Path
from typing import Any

import click
import numpy as np

from benchmarks.grade import outcome_of, run_pipeline_on_scan

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CARD_FOLDERS = ("full_cards", "keystone_mast_raw_scans", "cropped_pairs/jps")
CARD_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".jps"}
GRADES = ("few", "some", "failure")


def real_cards(data: Path) -> list[tuple[str, list[Path]]]:
    """``(name, files)`` per card: one file for a scan, two for a pre-split pair (left, right).
    Names are paths under ``stereocards/`` as the labels file writes them."""
    root = data / "stereocards"
    cards: list[tuple[str, list[Path]]] = []
    for folder in CARD_FOLDERS:
        directory = root / folder
        if directory.is_dir():
            cards += [
                (f"{folder}/{path.name}", [path]) for path in sorted(directory.iterdir()) if path.suffix.lower() in CARD_SUFFIXES
            ]
    pairs = root / "cropped_pairs"
    if pairs.is_dir():
        for directory in sorted(p for p in pairs.iterdir() if p.is_dir() and p.name != "jps"):
            lefts = sorted(directory.glob("*l-image.*"))
            for left in lefts:
                right = left.with_name(left.name.replace("l-image", "r-image"))
                if right.is_file():
                    cards.append((f"cropped_pairs/{directory.name}/{left.name} + {right.name}", [left, right]))
    return cards


def read_labels(path: Path) -> dict[str, dict[str, str]]:
    """``{file: row}`` of the labels CSV (rows with an empty grade are kept: they have reasons)."""
    if not path.is_file():
        return {}
    with path.open(newline="") as handle:
        return {row["file"].strip(): row for row in csv.DictReader(handle) if row.get("file")}


def _scan_of(files: list[Path], folder: Path) -> Path:
    """The card as one scan: the file itself, or a pre-split pair side by side (24 px gutter)."""
    if len(files) == 1:
        return files[0]
    from pipeline.io import read_image, write_png

    left, right = read_image(files[0]), read_image(files[1])
    height = max(left.shape[0], right.shape[0])

    def pad(view: np.ndarray) -> np.ndarray:
        return np.pad(
            view,
            ((0, height - view.shape[0]), (0, 0), (0, 0)) if view.ndim == 3 else ((0, height - view.shape[0]), (0, 0)),
            constant_values=255,
        )

    gutter = np.full((height, 24, *left.shape[2:]), 255, np.uint8)
    scan = folder / "card.png"
    folder.mkdir(parents=True, exist_ok=True)
    write_png(scan, np.concatenate([pad(left), gutter, pad(right)], axis=1))
    return scan


def _fractions(counts: dict[str, int]) -> dict[str, float | None]:
    total = sum(counts.values())
    return {g: (round(counts[g] / total, 4) if total else None) for g in GRADES}


def grade_real_cards(data: Path, labels_path: Path, grade_params: Any = None) -> dict[str, Any]:
    from pipeline.grading import agreement, paper_distribution

    labels = read_labels(labels_path)
    results = []
    with tempfile.TemporaryDirectory(prefix="keystone-grade-real-") as scratch:
        for index, (name, files) in enumerate(real_cards(data)):
            folder = Path(scratch) / f"card{index}"
            run = run_pipeline_on_scan(_scan_of(files, folder), folder, grade_params)
            outcome = outcome_of(run)
            row = labels.get(name, {})
            person = (row.get("grade") or "").strip() or None
            results.append(
                {
                    "file": name,
                    "grade": outcome["grade"],
                    "uncertainty": outcome["uncertainty"],
                    "nearest": outcome["nearest"],
                    "reason": outcome["reason"],
                    "person": person if person in GRADES else None,
                    "person_reason": row.get("reason"),
                }
            )
    automatic = {g: sum(r["grade"] == g for r in results) for g in GRADES}
    labelled = [r for r in results if r["person"] is not None]

    def as_level(grade: str | None) -> int:
        return GRADES.index(grade) if grade in GRADES else 2

    person_counts = {g: sum(r["person"] == g for r in labelled) for g in GRADES}
    auto_on_labelled = {g: sum(r["grade"] == g for r in labelled) for g in GRADES}
    figures = agreement([GRADES.index(r["person"]) for r in labelled], [as_level(r["grade"]) for r in labelled])
    lenient = sum(as_level(r["grade"]) < GRADES.index(r["person"]) for r in labelled)
    harsher = sum(as_level(r["grade"]) > GRADES.index(r["person"]) for r in labelled)
    return {
        "results": results,
        "summary": {
            "cards": len(results),
            "graded": sum(automatic.values()),
            "stopped": len(results) - sum(automatic.values()),
            "automatic": {"counts": automatic, "fractions": _fractions(automatic)},
            "labelled": len(labelled),
            "automatic_on_labelled": {"counts": auto_on_labelled, "fractions": _fractions(auto_on_labelled)},
            "person": {"counts": person_counts, "fractions": _fractions(person_counts)},
            "paper": {"fractions": paper_distribution(), "sample": 711},
            "agreement": {
                "agreed": int(np.trace(np.asarray(figures["confusion"]))),
                "of": len(labelled),
                "cohen_kappa": figures["cohen_kappa"],
                "confusion": figures["confusion"],
                "order": list(GRADES),
                "grade_more_lenient": lenient,
                "grade_harsher": harsher,
            },
        },
    }


@click.command("grade-real")
@click.option(
    "--data",
    type=click.Path(path_type=Path, file_okay=False),
    default=DEFAULT_DATA,
    show_default=True,
    help="A folder with stereocards/ (and labels/careful_grades.csv).",
)
@click.option(
    "--labels",
    "labels_path",
    type=click.Path(path_type=Path, dir_okay=False),
    help="Labels CSV (file, grade, reason); default <data>/labels/careful_grades.csv.",
)
@click.option(
    "--thresholds",
    "thresholds_file",
    type=click.Path(path_type=Path, dir_okay=False, exists=True),
    help="Grade with these thresholds (JSON as `keystone grade show --json` prints).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_grade_real_command(data: Path, labels_path: Path | None, thresholds_file: Path | None, as_json: bool) -> None:
    """The automatic grade on real cards: its distribution beside a careful person's and the
    paper's 23 / 49 / 28 %, and its agreement with the person (labels only check, never fit)."""
    from pipeline.errors import PipelineError
    from pipeline.grading import GradeParams, GradeThresholds

    if not (data / "stereocards").is_dir():
        raise click.ClickException(f"{data}: no stereocards/ folder")
    params = None
    if thresholds_file is not None:
        try:
            document = json.loads(thresholds_file.read_text())
            params = GradeParams(GradeThresholds.from_dict(document.get("thresholds", document)))
        except (ValueError, PipelineError) as exc:
            raise click.ClickException(f"{thresholds_file}: {exc}") from exc
    report = grade_real_cards(data, labels_path or data / "labels" / "careful_grades.csv", params)
    if as_json:
        click.echo(json.dumps(report, indent=2, allow_nan=False))
        return
    for r in report["results"]:
        near = r["nearest"] or {}
        shown = f"{near.get('measurement')} {near.get('value')} vs {near.get('threshold')}" if near else "-"
        click.echo(f"{r['file'][:58]:<58} {r['grade']:<16} person {r['person'] or '-':<8} nearest {shown}")
    s = report["summary"]

    def show(block: dict[str, Any]) -> str:
        return " / ".join(f"{block['counts'][g]} ({100 * (block['fractions'][g] or 0):.0f} %)" for g in GRADES)

    click.echo(f"\n{s['cards']} cards, {s['graded']} graded, {s['stopped']} stopped by the pipeline")
    click.echo(f"automatic, all graded:   {show(s['automatic'])}")
    click.echo(f"automatic, labelled:     {show(s['automatic_on_labelled'])}")
    click.echo(f"careful person:          {show(s['person'])}")
    click.echo("paper (711 cards):       " + " / ".join(f"{100 * v:.0f} %" for v in s["paper"]["fractions"].values()))
    a = s["agreement"]
    click.echo(
        f"agreement {a['agreed']}/{a['of']}, Cohen's kappa {a['cohen_kappa']}; the grade more lenient "
        f"{a['grade_more_lenient']}, harsher {a['grade_harsher']}"
    )

"""``keystone check-homographies``: distortion metrics and a verdict for rectifying homographies.

Reads KeystoneDepth ``.mat`` files (row-vector convention), their ``homographies.json`` and the
project's own JSON; the work is done by :mod:`pipeline.homography_quality`. Needs no database
and no app context (the group may still provide one).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import click

from pipeline import homography_quality as hq


def _parse_size(value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        w, h = (float(v) for v in value.lower().split("x"))
    except ValueError as exc:
        raise click.BadParameter("expected WIDTHxHEIGHT, e.g. 610x771") from exc
    if not (w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
        raise click.BadParameter("width and height must be positive")
    return w, h


def check_paths(
    paths: list[str], size: tuple[float, float] | None = None
) -> tuple[list[dict[str, Any]], list[dict[str, str]], bool]:
    """Results for every pair under ``paths`` (files, or folders searched recursively).

    An unreadable file gives one ``{"id", "path", "error"}`` entry and the others go on. JSON files
    met while scanning a folder that are not homography documents at all are listed in
    ``skipped`` (``{"path", "reason"}``) instead. Returns (results, skipped, any_error)."""
    results: list[dict[str, Any]] = []
    skipped: list[dict[str, str]] = []
    failed = False
    for arg in paths:
        in_folder = Path(arg).is_dir()
        for path in hq.iter_homography_files([arg]):
            try:
                pairs = hq.read_homographies(path)
            except hq.NotHomographyDocument as exc:
                if in_folder:
                    skipped.append({"path": str(path), "reason": exc.reason})
                    continue
                results.append({"id": hq.parse_id(path), "path": str(path), "error": exc.reason})
                failed = True
                continue
            except hq.HomographyReadError as exc:
                results.append({"id": hq.parse_id(path), "path": str(path), "error": exc.reason})
                failed = True
                continue
            for pair in pairs:
                try:
                    result = hq.assess(pair, size=size)
                except ValueError as exc:  # e.g. a matrix the metrics refuse
                    results.append({"id": pair.id, "path": str(path), "error": str(exc)})
                    failed = True
                    continue
                result["metrics"]["source"] = str(path)
                results.append(result)
    return results, skipped, failed


def _fmt(v: Any, spec: str) -> str:
    return "-" if v is None else format(v, spec)


@click.command("check-homographies")
@click.argument("paths", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option(
    "--size",
    "size_text",
    metavar="WxH",
    default=None,
    help="Image size of the view the homographies apply to, when the files carry none "
    f"(default: {hq.DEFAULT_SIZE[0]}x{hq.DEFAULT_SIZE[1]}, a typical KeystoneDepth crop).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def check_homographies_command(paths: tuple[str, ...], size_text: str | None, as_json: bool) -> None:
    """Distortion metrics and a good / border / bad verdict per rectifying homography pair.

    PATH is a KeystoneDepth <id>_rectification_mats.mat (tl, tr; row vectors), their
    homographies.json, the project's own JSON (H_l, H_r, width, height, convention), or a folder
    searched recursively. Exit status 1 when any file could not be read.
    """
    size = _parse_size(size_text)
    results, skipped, failed = check_paths(list(paths), size)
    if not results and not failed:
        failed = True
        results.append(
            {
                "id": None,
                "path": ", ".join(paths),
                "error": "no .mat or .json files found",
            }
        )
    if as_json:
        model = hq.SHIPPED_MODEL
        document = {"results": results, "skipped": skipped, "model": model.to_dict()}
        click.echo(json.dumps(document, indent=2, allow_nan=False))
    else:
        click.echo(
            f"{'id':<8} {'verdict':<7} {'corner':>7} {'midline':>8} {'aspect':>7} {'proj':>5} {'rot':>5} {'lr_dy':>6}  bounded"
        )
        for r in results:
            if "error" in r:
                click.echo(f"{r['id']!s:<8} ERROR   {r['error']} ({r['path']})")
                continue
            m = r["metrics"]
            click.echo(
                f"{r['id']:<8} {r['verdict']:<7} {_fmt(m['max_corner_disp'], '7.4f')} "
                f"{_fmt(m['max_midline_dev_deg'], '8.3f')} {_fmt(m['max_aspect_dev'], '7.4f')} "
                f"{_fmt(m['min_projective_log10'], '5.2f')} {_fmt(m['max_rotation_deg'], '5.2f')} "
                f"{_fmt(m['lr_row_spread'], '6.4f')}  {'yes' if m['bounded'] else 'NO'}"
            )
        counts = {v: sum(1 for r in results if r.get("verdict") == v) for v in hq.VERDICTS}
        errors = sum(1 for r in results if "error" in r)
        click.echo(
            f"{len(results)} item(s): {counts['good']} good, {counts['border']} border, "
            f"{counts['bad']} bad, {errors} error(s). corner = max corner displacement / diagonal "
            f"(verdict feature), midline = |angle - 90| deg, aspect = |log aspect change|, "
            f"proj = -log10 projective norm, rot = rotation deg, lr_dy = left-right row spread / height."
        )
    if failed:
        raise SystemExit(1)

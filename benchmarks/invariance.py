"""``keystone bench invariance``: the same card at every size and in every format, one answer.

Each card of ``--cards`` (default: the shared NYPL cards) is rescaled to each of ``--scales``
(area filter down, bicubic up: an upscaled copy stands for a scan made at a higher resolution
of the same print) and saved as each of ``--formats`` (``png``, ``jpegQ`` at quality Q, ``faded``:
a faded print as PNG, see :func:`faded`). The
variants are ingested into a throwaway instance and taken through ``keystone run`` with the
default stages, exactly as an operator would (subprocesses of this checkout's ``keystone``), and
``keystone cards --json`` is read back.

Per card it reports each stage's outcome on every variant (the filter's ``pass``/``review``/
``culled``, the orientation flags and who decided them, the rectification verdict, the grade)
and whether they agree, and how far each grade measurement moves across the variants (min, max
and the spread max - min in the measurement's own unit). The table is the issue's "card x size x
format -> outcome"; ``--json`` gives it as one document.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

DEFAULT_SCALES = (0.25, 0.5, 1.0, 2.0, 4.0)
DEFAULT_FORMATS = ("png", "jpeg75", "jpeg95")
# The grade measurements whose movement is reported (units in pipeline.grading.measurements).
TRACKED = (
    "good_match_fraction",
    "dy_p95_px",
    "row_misalignment_px",
    "coverage",
    "lr_consistency",
    "confident_fraction",
    "disparity_range_rel",
    "textured_fraction",
    "photometric_error_rel",
    "depth_order",
    "streak_fraction",
    "sky_near_fraction",
)


def _shared_cards() -> Path:
    return Path(__file__).resolve().parents[2] / "shared" / "data" / "stereocards" / "full_cards"


def faded(image: np.ndarray, floor: float = 185.0, kept: float = 0.22, seed: int = 0) -> np.ndarray:
    """A faded, yellowed print (BGR as OpenCV reads it): the range squeezed to ``kept`` of itself
    above ``floor`` grey levels, less blue, a little grain (sigma 1.5 grey levels)."""
    rng = np.random.default_rng(seed)
    out = floor + image.astype(np.float32) * kept
    if out.ndim == 3:
        out[..., 0] *= 0.93
    out += rng.normal(0.0, 1.5, out.shape).astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def variant_name(stem: str, scale: float, fmt: str) -> str:
    """``<stem>__x<scale>__<fmt>.<ext>``: the card, the scale and the format, readable back."""
    ext = "png" if fmt in ("png", "faded") else "jpg"
    return f"{stem}__x{scale:g}__{fmt}.{ext}"


def parse_variant(name: str) -> tuple[str, float, str] | None:
    stem = Path(name).stem
    parts = stem.rsplit("__", 2)
    if len(parts) != 3 or not parts[1].startswith("x"):
        return None
    return parts[0], float(parts[1][1:]), parts[2]


def write_variants(cards: list[Path], scales: tuple[float, ...], formats: tuple[str, ...], out: Path) -> list[Path]:
    """Every card at every scale in every format under ``out``; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for card in cards:
        image = cv2.imread(str(card), cv2.IMREAD_COLOR)
        if image is None:
            raise click.ClickException(f"cannot read {card}")
        h, w = image.shape[:2]
        for scale in scales:
            size = (max(1, round(w * scale)), max(1, round(h * scale)))
            resized = (
                image if scale == 1 else cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
            )
            for fmt in formats:
                target = out / variant_name(card.stem, scale, fmt)
                if fmt == "png":
                    ok = cv2.imwrite(str(target), resized)
                elif fmt == "faded":
                    ok = cv2.imwrite(str(target), faded(resized))
                elif fmt.startswith("jpeg") and fmt[4:].isdigit():
                    ok = cv2.imwrite(str(target), resized, [cv2.IMWRITE_JPEG_QUALITY, int(fmt[4:])])
                else:
                    raise click.BadParameter(f"unknown format {fmt!r}: png, faded (a faded print, PNG) or jpegQ (e.g. jpeg90)")
                if not ok:
                    raise click.ClickException(f"cannot write {target}")
                written.append(target)
    return written


def _keystone(args: list[str], env: dict[str, str]) -> dict[str, Any]:
    done = subprocess.run([sys.executable, "-m", "app", *args], env=env, capture_output=True, text=True, check=False)
    if done.returncode not in (0, 1) or not done.stdout.strip():
        raise click.ClickException(f"keystone {' '.join(args)} exited {done.returncode}: {done.stderr[-2000:]}")
    return dict(json.loads(done.stdout))


def outcome(card: dict[str, Any]) -> dict[str, Any]:
    """One card's answer at every stage, in the words the table compares."""
    stages = card.get("stages", {})

    def status(name: str) -> str:
        entry = stages.get(name) or {}
        return str(entry.get("status") or "pending")

    filter_entry = stages.get("filter") or {}
    filter_outcome = (filter_entry.get("metrics") or {}).get("outcome") or status("filter")
    orientation = card.get("orientation") or {}
    flags = "".join(
        letter if orientation.get(flag) else "-" for flag, letter in (("upside_down", "U"), ("inverted", "I"), ("swapped", "S"))
    )
    rectify = stages.get("rectify") or {}
    rectify_verdict = status("rectify")
    if rectify_verdict == "failed":
        rectify_verdict += ": " + str(rectify.get("reason") or "").split(":")[0]
    grade = stages.get("grade") or {}
    grade_metrics = grade.get("metrics") or {}
    return {
        "filter": str(filter_outcome),
        "orientation": f"{flags} {orientation.get('decided_by') or 'undecided'}",
        "rectify": rectify_verdict,
        "grade": str(grade.get("outcome") or status("grade")),
        "measurements": {k: grade_metrics.get(k) for k in TRACKED},
    }


def summarise(cards: list[dict[str, Any]]) -> dict[str, Any]:
    by_card: dict[str, dict[str, Any]] = defaultdict(dict)
    for card in cards:
        parsed = parse_variant(str(card.get("source") or ""))
        if parsed is None:
            continue
        stem, scale, fmt = parsed
        by_card[stem][f"x{scale:g} {fmt}"] = outcome(card)
    summary: dict[str, Any] = {}
    for stem, variants in sorted(by_card.items()):
        agree = {
            stage: len({v[stage] for v in variants.values()}) == 1 for stage in ("filter", "orientation", "rectify", "grade")
        }
        spread = {}
        for name in TRACKED:
            values = [v["measurements"][name] for v in variants.values() if isinstance(v["measurements"].get(name), (int, float))]
            if values:
                spread[name] = {
                    "min": round(min(values), 4),
                    "max": round(max(values), 4),
                    "spread": round(max(values) - min(values), 4),
                }
        summary[stem] = {"variants": variants, "agree": agree, "spread": spread}
    return summary


@click.command("invariance")
@click.option(
    "--cards",
    "cards_dir",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Folder of cards (default: the shared NYPL cards).",
)
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N cards (by name).")
@click.option(
    "--scales", default=",".join(f"{s:g}" for s in DEFAULT_SCALES), show_default=True, help="Comma-separated scale factors."
)
@click.option(
    "--formats",
    default=",".join(DEFAULT_FORMATS),
    show_default=True,
    help="Comma-separated: png, jpegQ (quality Q), faded (the card faded to 22 % of its range, as PNG).",
)
@click.option("--workers", type=click.IntRange(min=1), default=2, show_default=True)
@click.option(
    "--keep",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Keep the instance in this folder; when it already holds a run, only report it again.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def bench_invariance_command(
    cards_dir: Path | None, limit: int | None, scales: str, formats: str, workers: int, keep: Path | None, as_json: bool
) -> None:
    """The same card at every size and in every format through ingest and the default stages."""
    cards_dir = cards_dir or _shared_cards()
    if not cards_dir.is_dir():
        raise click.ClickException(f"no cards at {cards_dir} (pass --cards DIR)")
    cards = sorted(p for p in cards_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))[:limit]
    scale_values = tuple(float(s) for s in scales.split(",") if s.strip())
    format_values = tuple(f.strip() for f in formats.split(",") if f.strip())
    root = keep or Path(tempfile.mkdtemp(prefix="keystone-invariance-"))
    root.mkdir(parents=True, exist_ok=True)
    reuse = keep is not None and (root / "keystone.sqlite3").exists() and (root / "variants").is_dir()
    files = (
        sorted((root / "variants").iterdir()) if reuse else write_variants(cards, scale_values, format_values, root / "variants")
    )
    env = {
        **os.environ,
        "KEYSTONE_DATABASE_URL": f"sqlite:///{root / 'keystone.sqlite3'}",
        "KEYSTONE_DATA_DIR": str(root / "data"),
        "KEYSTONE_RELEASES_DIR": str(root / "releases"),
        "KEYSTONE_INSTANCE_PATH": str(root / "instance"),
    }
    clock = time.perf_counter()
    if reuse:
        ingest: dict[str, Any] = {}
    else:
        ingest = _keystone(["ingest", str(root / "variants"), "--json"], env)
        _keystone(["run", "--workers", str(workers), "--json"], env)
    seconds = time.perf_counter() - clock
    listed = _keystone(["cards", "--json"], env)
    summary = summarise(list(listed.get("cards", [])))
    document = {
        "cards": len(cards),
        "variants": len(files),
        "rejected_at_ingest": ingest.get("rejected", []),
        "seconds": round(seconds, 1),
        "scales": list(scale_values),
        "formats": list(format_values),
        "instance": str(root),
        "by_card": summary,
    }
    if as_json:
        click.echo(json.dumps(document, indent=2, sort_keys=True))
        return
    for stem, entry in summary.items():
        click.echo(f"\n{stem}  agree: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in entry["agree"].items()))
        for key, v in sorted(entry["variants"].items(), key=lambda kv: (float(kv[0].split()[0][1:]), kv[0])):
            m = v["measurements"]
            row = m.get("row_misalignment_px")
            dy = m.get("dy_p95_px")
            click.echo(
                f"  {key:<14} filter {v['filter']:<7} orient {v['orientation']:<12} rectify {v['rectify'][:40]:<40} "
                f"grade {v['grade']:<8} rows {row if row is None else f'{row:.2f}'} dy {dy if dy is None else f'{dy:.2f}'}"
            )
    agreeing = sum(all(e["agree"].values()) for e in summary.values())
    click.echo(f"\n{agreeing}/{len(summary)} cards get one answer at every stage over {len(files)} variants ({seconds:.0f} s)")
    if ingest.get("rejected"):
        click.echo(f"rejected at ingest: {ingest['rejected']}")

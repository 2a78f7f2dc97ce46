"""Stereo inputs at ingest: MPO files, left/right file pairs, JPS and side-by-side eye order.

Called from :func:`catalogue.ingest.ingest` (one hook) with the files found there; it turns the stereo
ones into cards and hands back the rest:

* an **MPO** with two frames (or more: the first two are the stereo pair, as 3D cameras write
  them, left first) becomes one card;
* **left/right pairs** become one card: matched by name (``<stem>_L``/``_R``, ``<stem>L``/``R``,
  ``-left``/``-right``, case-insensitive, any separator ``_ - . space``) or listed in a
  ``--pairs`` CSV (columns ``left``, ``right``; relative paths from the CSV's folder);
* **JPS** files, and every other file when ``--sbs-order`` is given, are side-by-side images
  whose eye order is ``cross`` (right view on the left: the JPS convention and the default for
  ``.jps``) or ``parallel``.

Originals are stored as they came (content-addressed, read-only) and never modified. The card
image the pipeline reads (``Card.stored_path``) is always parallel side by side (left view on
the left): for an MPO, a pair or a cross-eyed file it is a derived PNG stored under
``derived/stereo_inputs/`` (its hash is the card's ``content_hash``); a parallel side-by-side
file is read as it is. ``Card.stereo_source`` records the kind, the originals with their hashes,
the eye order and an automatic check of it (:func:`pipeline.stereo_formats.eye_order_evidence`),
which only informs: a disagreement is reported with the card, never acted on.

A bad pair (a missing view, views of wildly different sizes, an MPO with one frame, an
unreadable file) is rejected with a reason and the rest of the batch goes on.
"""

from __future__ import annotations

import csv
import hashlib
import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from catalogue.originals import card_with_hash, database_reason, discard_original, duplicate_entry, sha256_file, store_original
from core.db import db
from core.models import Card
from pipeline.errors import ImageReadError

EYE_ORDERS = ("cross", "parallel")
JPS_DEFAULT_ORDER = "cross"  # the JPS convention: right view on the left half, for cross-eyed viewing
MPO_SUFFIX = ".mpo"
# Views whose width or height differ by more than this factor are not one stereo pair.
MAX_PAIR_SIZE_RATIO = 1.25
_SEPARATORS = re.compile(r"([_\-. ]+)")
_EXPLICIT_EYES = {"l": "left", "left": "left", "r": "right", "right": "right"}


@dataclass(frozen=True)
class StereoOptions:
    """What the operator said: a pairs CSV and the eye order of side-by-side files."""

    pairs_csv: Path | None = None
    sbs_order: str | None = None  # None: JPS files are cross, other files are ordinary scans

    def __post_init__(self) -> None:
        if self.sbs_order is not None and self.sbs_order not in EYE_ORDERS:
            raise ValueError(f"Expected an eye order of {' or '.join(EYE_ORDERS)}, got {self.sbs_order!r}")


@dataclass
class StereoPlan:
    """Files sorted into stereo groups; ``singles`` go on to the ordinary ingest."""

    pairs: list[tuple[Path, Path, str]] = field(default_factory=list)  # (left, right, how matched)
    mpos: list[Path] = field(default_factory=list)
    side_by_side: list[tuple[Path, str, str]] = field(default_factory=list)  # (file, eye order, why that order)
    singles: list[Path] = field(default_factory=list)
    rejected: list[dict[str, str]] = field(default_factory=list)


# ---- grouping (pure: names and paths only) ----------------------------------------------------


def eye_markers(path: Path) -> list[tuple[str, str, bool]]:
    """``(pair key, eye, explicit)`` for every place in the file's stem that names an eye.

    Markers are whole tokens between separators (``_L``, ``-right``, `` left``) or a bare letter
    glued to the stem after a digit (``7995l-image``) or as a capital after a lower-case letter
    or digit (``cardL``). The key is the name with the marker replaced, so the two views of a
    pair share it. ``explicit`` is true only for a whole-token marker that ends the stem
    (``scan_L``, ``scan-left``): only such a file, when its twin is missing, is refused as half a
    pair; a lone ``R`` inside a title ("Views of the R. River") stays an ordinary scan."""
    stem = path.stem
    parts = _SEPARATORS.split(stem)  # tokens at even indexes, separators at odd ones
    found: list[tuple[str, str, bool]] = []
    suffix = path.suffix.lower()
    for index in range(0, len(parts), 2):
        token = parts[index]
        eye = _EXPLICIT_EYES.get(token.lower())
        if eye is not None and len(parts) > 1:
            key = "".join(parts[:index] + ["*"] + parts[index + 1 :]).lower()
            found.append((f"{key}{suffix}", eye, index == len(parts) - 1))
            continue
        bare = re.fullmatch(r"(.*\d)([lLrR])", token) or re.fullmatch(r"(.*[a-z0-9])([LR])", token)
        if bare is not None:
            eye = "left" if bare.group(2).lower() == "l" else "right"
            key = "".join(parts[:index] + [bare.group(1) + "*"] + parts[index + 1 :]).lower()
            found.append((f"{key}{suffix}", eye, False))
    return found


def read_pairs_csv(path: Path) -> tuple[list[tuple[Path, Path, int]], list[dict[str, str]]]:
    """Rows ``(left, right, row number)`` of a pairs CSV, and a rejection per bad row.

    The header must name ``left`` and ``right`` (case-insensitive); relative paths are taken
    from the CSV's folder. Raises ``OSError``/``ValueError`` when the file itself is unusable."""
    text = path.read_text(encoding="utf-8-sig")
    reader = csv.DictReader(io.StringIO(text))
    columns = {name.strip().lower(): name for name in reader.fieldnames or []}
    if "left" not in columns or "right" not in columns:
        raise ValueError(f"expected a header with 'left' and 'right' columns, got {reader.fieldnames or 'none'}")
    rows: list[tuple[Path, Path, int]] = []
    rejected: list[dict[str, str]] = []
    for number, row in enumerate(reader, start=2):
        left, right = (str(row.get(columns[side]) or "").strip() for side in ("left", "right"))
        if not left or not right:
            rejected.append({"path": f"{path}:{number}", "reason": f"pairs row {number} needs both a left and a right path"})
            continue
        resolved = [Path(value) if Path(value).is_absolute() else path.parent / value for value in (left, right)]
        missing = [str(p) for p in resolved if not p.is_file()]
        if missing:
            rejected.append(
                {
                    "path": f"{path}:{number}",
                    "reason": f"pairs row {number}: one view of the pair is missing ({', '.join(missing)})",
                }
            )
            continue
        rows.append((resolved[0], resolved[1], number))
    return rows, rejected


def plan_stereo(files: list[Path], options: StereoOptions) -> StereoPlan:
    """Sort discovered files into pairs, MPOs, side-by-side files and ordinary singles."""
    plan = StereoPlan()
    used: set[Path] = set()
    if options.pairs_csv is not None:
        try:
            rows, rejected = read_pairs_csv(options.pairs_csv)
        except (OSError, ValueError, UnicodeDecodeError, csv.Error) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            plan.rejected.append({"path": str(options.pairs_csv), "reason": f"cannot read the pairs CSV: {reason}"})
            rows, rejected = [], []
        plan.rejected.extend(rejected)
        for left, right, number in rows:
            plan.pairs.append((left, right, f"pairs CSV row {number}"))
            used.update({left.resolve(), right.resolve()})
    remaining = [path for path in files if path.resolve() not in used]

    by_key: dict[str, dict[str, list[Path]]] = {}
    explicit: dict[Path, bool] = {}
    for path in remaining:
        if path.suffix.lower() == MPO_SUFFIX:
            continue
        for key, eye, is_explicit in eye_markers(path):
            by_key.setdefault(key, {"left": [], "right": []})[eye].append(path)
            explicit[path] = explicit.get(path, False) or is_explicit
    paired: set[Path] = set()
    for key, sides in sorted(by_key.items()):
        lefts = [p for p in sides["left"] if p not in paired]
        rights = [p for p in sides["right"] if p not in paired]
        if len(lefts) == 1 and len(rights) == 1 and lefts[0] != rights[0]:
            plan.pairs.append((lefts[0], rights[0], f"file names ({key.replace('*', '<eye>')})"))
            paired.update({lefts[0], rights[0]})

    for path in remaining:
        if path in paired:
            continue
        suffix = path.suffix.lower()
        if suffix == MPO_SUFFIX:
            plan.mpos.append(path)
        elif explicit.get(path):
            eye = next(e for _k, e, x in eye_markers(path) if x)
            other = "right" if eye == "left" else "left"
            plan.rejected.append(
                {
                    "path": str(path),
                    "reason": f"named as the {eye} view of a pair, but no {other} view "
                    "with the same name was given (give both files, or list them in --pairs)",
                }
            )
        elif suffix == ".jps":
            order = options.sbs_order or JPS_DEFAULT_ORDER
            plan.side_by_side.append((path, order, "--sbs-order" if options.sbs_order else "JPS convention (default)"))
        elif options.sbs_order is not None:
            plan.side_by_side.append((path, options.sbs_order, "--sbs-order"))
        else:
            plan.singles.append(path)
    return plan


# ---- building the card image ------------------------------------------------------------------


def pair_side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The two views side by side, left first, on a common height (the shorter view padded with
    black at the bottom). Raises ``ValueError`` when their sizes differ by more than
    :data:`MAX_PAIR_SIZE_RATIO` in width or height: not one pair."""
    from pipeline.stereo_formats import as_rgb

    left, right = as_rgb(left), as_rgb(right)
    (lh, lw), (rh, rw) = left.shape[:2], right.shape[:2]
    if max(lw, rw) > MAX_PAIR_SIZE_RATIO * min(lw, rw) or max(lh, rh) > MAX_PAIR_SIZE_RATIO * min(lh, rh):
        raise ValueError(f"the views' sizes differ too much for one pair: {lw} x {lh} and {rw} x {rh} px")
    height = max(lh, rh)
    padded = [np.pad(view, ((0, height - view.shape[0]), (0, 0), (0, 0))) for view in (left, right)]
    return np.ascontiguousarray(np.concatenate(padded, axis=1))


def read_mpo_views(path: Path, max_pixels: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(left, right, frame count) of an MPO: frames 0 and 1 as RGB. Raises ``ImageReadError``
    for a file that is not an MPO with at least two frames of one size."""
    from PIL import Image, UnidentifiedImageError

    from pipeline.io import probe_image

    probe_image(path, max_pixels=max_pixels)  # size cap and readability, before decoding frames
    try:
        with Image.open(path) as image:
            frames = int(getattr(image, "n_frames", 1))
            if frames < 2:
                raise ImageReadError(f"an MPO with {frames} frame: a stereo MPO holds two (left, then right)")
            image.seek(0)
            left = np.asarray(image.convert("RGB"))
            image.seek(1)
            right = np.asarray(image.convert("RGB"))
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as exc:
        raise ImageReadError(f"cannot read the MPO's frames: {exc}") from exc
    if left.shape != right.shape:
        raise ImageReadError(
            f"the MPO's two frames differ in size: {left.shape[1]} x {left.shape[0]} and {right.shape[1]} x {right.shape[0]}"
        )
    return left, right, frames


def _encode_png(image: np.ndarray) -> bytes:
    """PNG with fixed settings and no metadata: the same pixels give the same bytes (and hash)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG", compress_level=3)
    return buffer.getvalue()


# ---- storing ----------------------------------------------------------------------------------


def _store_derived(payload: bytes, content_hash: str, data_dir: Path) -> Path:
    """Store the derived card image read-only under ``derived/stereo_inputs/`` (atomic)."""
    import os
    import stat

    from pipeline.io import atomic_write

    relative = Path("derived") / "stereo_inputs" / content_hash[:2] / f"{content_hash}.png"
    target = data_dir / relative
    if target.exists():
        return relative
    with atomic_write(target) as out:
        out.write(payload)
        out.flush()
        os.fsync(out.fileno())
        os.fchmod(out.fileno(), stat.S_IRUSR | stat.S_IRGRP | stat.S_IROTH)
    return relative


def _original_entry(role: str, path: Path, data_dir: Path) -> dict[str, Any]:
    content_hash = sha256_file(path)
    relative = store_original(path, content_hash, data_dir)
    return {
        "role": role,
        "source_name": path.name,
        "source_path": str(path.resolve()),
        "sha256": content_hash,
        "stored_path": str(relative),
        "bytes": path.stat().st_size,
    }


def _eye_check(left: np.ndarray, right: np.ndarray, stored_order: str) -> dict[str, Any]:
    """The automatic check of the declared order, on the halves as the card image holds them."""
    from pipeline.stereo_formats import StereoFormatError, eye_order_evidence

    try:
        evidence = eye_order_evidence(left, right).as_json()
    except StereoFormatError as exc:
        return {"suggests": "unknown", "why": str(exc)}
    # The card image is always parallel; evidence for "cross" on it means the declared order is doubtful.
    evidence["agrees"] = None if evidence["suggests"] == "unknown" else evidence["suggests"] == "parallel"
    evidence["declared"] = stored_order
    return evidence


def _add_card(
    collection_id: int,
    *,
    image: np.ndarray | None,
    stored: dict[str, Any] | None,
    data_dir: Path,
    source_name: str,
    source_path: str,
    stereo: dict[str, Any],
    report: Any,
    report_path: str,
) -> None:
    """Store the card image (derived PNG from ``image``, or an original ``stored`` as it is) and
    add the card; a duplicate by content is reported as one, like any ingest."""
    if image is not None:
        payload = _encode_png(image)
        content_hash = hashlib.sha256(payload).hexdigest()
        existing = db.session.scalar(select(Card).where(Card.content_hash == content_hash))
        if existing is not None:
            report.duplicates.append(duplicate_entry(Path(report_path), existing))
            return
        relative = _store_derived(payload, content_hash, data_dir)
        width, height, image_format, byte_size = image.shape[1], image.shape[0], "PNG", len(payload)
    else:
        assert stored is not None
        content_hash, relative = stored["sha256"], Path(stored["stored_path"])
        existing = db.session.scalar(select(Card).where(Card.content_hash == content_hash))
        if existing is not None:
            report.duplicates.append(duplicate_entry(Path(report_path), existing))
            return
        width, height, image_format, byte_size = stored["width"], stored["height"], stored["format"], stored["bytes"]
    card = Card(
        collection_id=collection_id,
        content_hash=content_hash,
        stored_path=str(relative),
        source_name=source_name,
        source_path=source_path,
        width=int(width),
        height=int(height),
        image_format=image_format,
        byte_size=int(byte_size),
        source_metadata={},
        stereo_source=stereo,
    )
    db.session.add(card)
    try:
        db.session.commit()
    except SQLAlchemyError as exc:
        # As catalogue.ingest: a race on the same bytes (IntegrityError) makes this a duplicate; a
        # database that refuses the write (a full disk) rejects the card and its stored image goes.
        db.session.rollback()
        existing = card_with_hash(content_hash)
        if existing is not None:
            report.duplicates.append(duplicate_entry(Path(report_path), existing))
            return
        # The card image and the originals stored for it: no card points at them now (an
        # original that is some card's own image stays).
        stored_here = {str(relative)} | {
            entry["stored_path"] for entry in stereo.get("originals", []) if card_with_hash(entry["sha256"]) is None
        }
        removed = all([discard_original(data_dir / path) for path in sorted(stored_here)])
        report.rejected.append(
            {
                "path": report_path,
                "reason": "not recorded: the catalogue database refused the "
                f"write ({database_reason(exc)}); "
                + ("the stored copy was removed" if removed else f"the stored copy {relative} could not be removed"),
            }
        )
        return
    entry: dict[str, Any] = {
        "id": card.id,
        "path": report_path,
        "content_hash": content_hash,
        "stereo": {
            "kind": stereo["kind"],
            "eye_order": stereo.get("eye_order"),
            "eye_order_check": stereo.get("eye_order_check"),
        },
    }
    report.ingested.append(entry)


def _ingest_pair(
    left_path: Path, right_path: Path, how: str, collection_id: int, data_dir: Path, max_pixels: int, report: Any
) -> None:
    from pipeline.io import read_image

    label = f"{left_path} + {right_path}"
    try:
        left, right = read_image(left_path, max_pixels), read_image(right_path, max_pixels)
        image = pair_side_by_side(left, right)
        originals = [_original_entry("left", left_path, data_dir), _original_entry("right", right_path, data_dir)]
    except (ImageReadError, ValueError) as exc:  # unreadable view, or views too different to be one pair
        report.rejected.append({"path": label, "reason": f"pair not ingested: {exc}"})
        return
    except OSError as exc:
        report.rejected.append({"path": label, "reason": f"pair not ingested: cannot store: {exc.strerror or exc}"})
        return
    stereo = {
        "kind": "pair",
        "matched_by": how,
        "eye_order": "parallel",
        "originals": originals,
        "view_sizes": [[int(v.shape[1]), int(v.shape[0])] for v in (left, right)],
        "eye_order_check": _eye_check(left, right, "parallel"),
    }
    _add_card(
        collection_id,
        image=image,
        stored=None,
        data_dir=data_dir,
        source_name=left_path.name,
        source_path=str(left_path.resolve()),
        stereo=stereo,
        report=report,
        report_path=label,
    )


def _ingest_mpo(path: Path, collection_id: int, data_dir: Path, max_pixels: int, report: Any) -> None:
    try:
        left, right, frames = read_mpo_views(path, max_pixels)
        originals = [_original_entry("mpo", path, data_dir)]
    except ImageReadError as exc:
        report.rejected.append({"path": str(path), "reason": str(exc)})
        return
    except OSError as exc:
        report.rejected.append({"path": str(path), "reason": f"cannot store: {exc.strerror or exc}"})
        return
    stereo = {
        "kind": "mpo",
        "frames": frames,
        "frames_used": [0, 1],
        "eye_order": "parallel",
        "originals": originals,
        "eye_order_check": _eye_check(left, right, "parallel"),
    }
    _add_card(
        collection_id,
        image=pair_side_by_side(left, right),
        stored=None,
        data_dir=data_dir,
        source_name=path.name,
        source_path=str(path.resolve()),
        stereo=stereo,
        report=report,
        report_path=str(path),
    )


def _ingest_side_by_side(
    path: Path, order: str, why: str, collection_id: int, data_dir: Path, max_pixels: int, report: Any
) -> None:
    from pipeline.io import probe_image, read_image
    from pipeline.stereo_formats import StereoFormatError, split_side_by_side

    try:
        info = probe_image(path, max_pixels=max_pixels)
        image = read_image(path, max_pixels)
        left, right = split_side_by_side(image, order)
        original = _original_entry("side_by_side", path, data_dir)
    except (ImageReadError, StereoFormatError) as exc:
        report.rejected.append({"path": str(path), "reason": str(exc)})
        return
    except OSError as exc:
        report.rejected.append({"path": str(path), "reason": f"cannot store: {exc.strerror or exc}"})
        return
    stereo = {
        "kind": "side_by_side",
        "eye_order": order,
        "eye_order_from": why,
        "originals": [original],
        "eye_order_check": _eye_check(left, right, order),
    }
    if order == "parallel":  # the file is already what the pipeline reads: no derived copy
        image, stored = None, {**original, "width": info.width, "height": info.height, "format": info.format}
    else:
        image, stored = np.ascontiguousarray(np.concatenate([left, right], axis=1)), None
    _add_card(
        collection_id,
        image=image,
        stored=stored,
        data_dir=data_dir,
        source_name=path.name,
        source_path=str(path.resolve()),
        stereo=stereo,
        report=report,
        report_path=str(path),
    )


def ingest_stereo_inputs(
    files: list[Path], options: StereoOptions, collection_id: int, data_dir: Path, max_pixels: int, report: Any
) -> list[Path]:
    """Ingest the stereo inputs among ``files`` (see the module docstring), adding to ``report``
    (``ingested``, ``duplicates``, ``rejected``); return the files left for the ordinary ingest."""
    plan = plan_stereo(files, options)
    report.rejected.extend(plan.rejected)
    for left, right, how in plan.pairs:
        _ingest_pair(left, right, how, collection_id, data_dir, max_pixels, report)
    for path in plan.mpos:
        _ingest_mpo(path, collection_id, data_dir, max_pixels, report)
    for path, order, why in plan.side_by_side:
        _ingest_side_by_side(path, order, why, collection_id, data_dir, max_pixels, report)
    return plan.singles

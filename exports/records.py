"""What a release holds per card, and how two releases compare: plain data, no database.

:class:`ReleaseCard` carries one card's facts and the absolute paths of its files; the query
module (:mod:`exports.catalogue`) makes them, the writers consume them one at a time. The
*manifest entry* of a card is the small set of facts that decide whether its released data
changed (the scan, its metadata, the crop boxes, the stage parameters, the grade, and for a
card released with views, its views result); comparing
the manifest with the previous release's gives the semantic version and the CHANGELOG.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# Best first; "failure" is never released.
RELEASABLE_GRADES: tuple[str, ...] = ("few", "some")
VIEWS_FOLDER = "views"
RELEASED_DECISIONS: tuple[str, ...] = ("accepted", "changed")
# The views stage's artifacts a released card's views are made of (pipeline.stages.views).
VIEW_NAMES: tuple[str, ...] = ("v0", "v1", "v2", "v3", "v4")
VIEW_ARTIFACTS: tuple[str, ...] = (*VIEW_NAMES, *(f"{name}_depth" for name in VIEW_NAMES), "scene", "preview")
FIRST_VERSION = "1.0.0"

# Manifest parts and how a change of each reads in the CHANGELOG.
PART_WORDS: dict[str, str] = {
    "original": "original scan replaced",
    "metadata": "museum metadata changed",
    "grade": "grade changed",
    "decision": "review decision changed",
    "rectify": "rectification parameter hash changed",
    "rectify_inputs": "crop boxes or orientation (rectification inputs) changed",
    "disparity": "disparity parameter hash changed",
    "grade_params": "grader thresholds (grade parameter hash) changed",
    "code": "pipeline code version changed",
    "views": "views re-synthesised (views parameter hash, inputs or code version changed)",
}


def grades_at_or_above(min_grade: str) -> tuple[str, ...]:
    """``few`` -> (few,); ``some`` -> (few, some). Failure is refused: it is never released."""
    if min_grade not in RELEASABLE_GRADES:
        raise ValueError(
            f"Expected a minimum grade of {' or '.join(RELEASABLE_GRADES)}, got {min_grade!r} "
            "(cards graded failure are never released)"
        )
    return RELEASABLE_GRADES[: RELEASABLE_GRADES.index(min_grade) + 1]


def card_key(card_id: int) -> str:
    """The card's name in every layout: a zero-padded number like KeystoneDepth's ``04733``.

    Dot-free on purpose: WebDataset groups tar members by the text before the first dot, and
    accession numbers (``1996.0009.17827``) are full of dots.
    """
    return f"{card_id:05d}"


def short_hash(document: Any) -> str:
    return hashlib.sha256(json.dumps(document, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class ReleaseCard:
    """One card as released. Paths are absolute; boxes are ``[x0, y0, x1, y1]`` in pixels of the
    (orientation-corrected) card; matrices are nested lists, column-vector convention
    (``x' ~ H x``), see ``rectification["convention"]``."""

    card_id: int
    accession: str | None
    collection: str
    source_name: str
    content_hash: str
    original: Path
    width: int
    height: int
    metadata: dict[str, Any]
    museum_url: str | None
    grade: str
    decision: str
    auto_grade: str | None
    orientation: list[str]  # corrections applied to derived images: "rotated 180 deg", "intensities inverted"
    rectification: dict[str, Any]  # H_l, H_r, K, R, t, size, left_box, right_box, convention, ...
    rectified_left: Path
    rectified_right: Path
    disparity_left: Path  # float32 .npy, rectified-view pixels, x_right = x_left - d
    disparity_right: Path
    depth_512: Path  # float32 .npy, 512 x 512, depth up to scale
    stages: dict[str, dict[str, Any]]  # stage -> {param_hash, code_version, status, inputs_digest}
    crowd: dict[str, dict[str, Any]] = field(default_factory=dict)  # task kind -> {batch, answers}
    # The views component: artifact name (VIEW_ARTIFACTS) -> absolute path, empty when the card has
    # none; ``views_note`` is None when the release has no views component, else "done" or why not.
    views: dict[str, Path] = field(default_factory=dict)
    views_note: str | None = None
    # How the card image was made from stereo inputs (an MPO, a left/right pair, a JPS): the
    # originals with their sha256, the eye order and its check; None for an ordinary scan.
    stereo_source: dict[str, Any] | None = None
    # What the curator's acceptance was given and when, and the inputs digest each released
    # stage would be given at release time (keystone verify checks the release against them).
    acceptance: dict[str, Any] | None = None
    # Where the card came from when it was ingested from a IIIF canvas (cards.iiif_source), and
    # what the release's IIIF manifest says on that canvas (exports.formats.iiif): the boxes as
    # scanned (rectify's ``scanned_boxes``), the orientation used and who decided it, the grade's reasons.
    iiif_source: dict[str, Any] | None = None
    annotation_facts: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return card_key(self.card_id)

    @property
    def left_box(self) -> list[int]:
        return [int(v) for v in self.rectification["left_box"]]

    @property
    def right_box(self) -> list[int]:
        return [int(v) for v in self.rectification["right_box"]]

    def manifest_entry(self) -> dict[str, Any]:
        """The facts whose change makes a changed card, plus their digest."""
        parts = {
            "original": self.content_hash[:16],
            "metadata": short_hash({"accession": self.accession, "metadata": self.metadata}),
            "grade": self.grade,
            "decision": self.decision,
            "rectify": self.stages.get("rectify", {}).get("param_hash"),
            "rectify_inputs": self.stages.get("rectify", {}).get("inputs_digest"),
            "disparity": self.stages.get("disparity", {}).get("param_hash"),
            "grade_params": self.stages.get("grade", {}).get("param_hash"),
            "code": self.stages.get("disparity", {}).get("code_version"),
        }
        if self.views:
            # Only cards with views carry the part, so releases without views keep their digests.
            views = self.stages.get("views", {})
            parts["views"] = short_hash({k: views.get(k) for k in ("param_hash", "code_version", "inputs_digest")})
        return {**parts, "digest": short_hash(parts)}

    def record(self) -> dict[str, Any]:
        """The card's metadata as one JSON-safe document (``cards.jsonl``, WebDataset ``.json``)."""
        return {
            "key": self.key,
            "card_id": self.card_id,
            "accession": self.accession,
            "collection": self.collection,
            "source_name": self.source_name,
            "original_sha256": self.content_hash,
            "original_size": [self.width, self.height],
            "museum_url": self.museum_url,
            "metadata": self.metadata,
            "grade": self.grade,
            "review_decision": self.decision,
            "automatic_grade": self.auto_grade,
            "orientation_corrections": self.orientation,
            "left_box": self.left_box,
            "right_box": self.right_box,
            "rectification": {k: self.rectification.get(k) for k in RECTIFICATION_KEYS if k in self.rectification},
            "pipeline": self.stages,
            "crowd": self.crowd,
            "digest": self.manifest_entry()["digest"],
            **({} if self.views_note is None else {"views": self.views_record()}),
            **({} if self.stereo_source is None else {"stereo_source": released_stereo_source(self.stereo_source)}),
            **({} if self.acceptance is None else {"acceptance": self.acceptance}),
            **({} if self.iiif_source is None else {"iiif": released_iiif_source(self.iiif_source)}),
        }

    def views_record(self) -> dict[str, Any]:
        """Where the card's views are in the release (``views/<key>``), or why it has none."""
        if self.views:
            return {"folder": f"{VIEWS_FOLDER}/{self.key}", "why_not": None}
        return {"folder": None, "why_not": self.views_note}


def released_iiif_source(source: dict[str, Any]) -> dict[str, Any]:
    """Where a card came from in the museum's IIIF: manifest, canvas, image service, the size fetched."""
    keys = (
        "manifest",
        "canvas",
        "canvas_width",
        "canvas_height",
        "service",
        "service_version",
        "fetched_width",
        "fetched_height",
    )
    return {key: source.get(key) for key in keys}


def released_stereo_source(source: dict[str, Any]) -> dict[str, Any]:
    """A card's stereo source as released: no path of the ingesting machine, only names and hashes."""
    originals = [
        {k: original.get(k) for k in ("role", "source_name", "sha256", "bytes")} for original in source.get("originals") or []
    ]
    return {**{k: v for k, v in source.items() if k != "originals"}, "originals": originals}


RECTIFICATION_KEYS: tuple[str, ...] = (
    "convention",
    "H_l",
    "H_r",
    "K",
    "R",
    "t",
    "size",
    "left_box",
    "right_box",
    "disparity_min",
    "disparity_max",
    "dy_median",
    "dy_p95",
    "swapped",
    "warp_needed",
    "implied_pose",
)


@dataclass(frozen=True)
class Changes:
    """Cards added, removed and changed against the previous release (ids), with reasons."""

    added: list[int]
    removed: list[int]
    changed: dict[int, list[str]]  # card id -> reasons in words
    previous_version: str | None

    @property
    def kind(self) -> str:
        """``major`` (anything removed or changed), ``minor`` (only added), ``patch`` (same data)."""
        if self.previous_version is None:
            return "first"
        if self.removed or self.changed:
            return "major"
        return "minor" if self.added else "patch"

    def as_json(self) -> dict[str, Any]:
        return {
            "previous_version": self.previous_version,
            "kind": self.kind,
            "added": self.added,
            "removed": self.removed,
            "changed": [{"card_id": card_id, "why": why} for card_id, why in sorted(self.changed.items())],
        }


def compare_manifests(
    previous: dict[str, dict[str, Any]] | None, current: dict[str, dict[str, Any]], previous_version: str | None
) -> Changes:
    """Diff two manifests (``{str(card id): manifest entry}``) into a :class:`Changes`."""
    if previous is None:
        return Changes(added=sorted(int(k) for k in current), removed=[], changed={}, previous_version=None)
    added = sorted(int(k) for k in current.keys() - previous.keys())
    removed = sorted(int(k) for k in previous.keys() - current.keys())
    changed: dict[int, list[str]] = {}
    for key in current.keys() & previous.keys():
        now, before = current[key], previous[key]
        if now.get("digest") == before.get("digest"):
            continue
        why = [_why(part, before.get(part), now.get(part)) for part in PART_WORDS if now.get(part) != before.get(part)]
        changed[int(key)] = why or ["content digest changed"]
    return Changes(added=added, removed=removed, changed=changed, previous_version=previous_version)


def _why(part: str, before: Any, now: Any) -> str:
    if part == "views" and before is None:
        return f"views added (views digest {now})"
    if part == "views" and now is None:
        return f"views removed (views digest {before}: no finished views result, or no views component in this release)"
    return f"{PART_WORDS[part]} ({before} -> {now})"


def next_version(previous: str | None, kind: str) -> str:
    """Semantic version after ``previous`` for a change of ``kind`` (first release: 1.0.0)."""
    if previous is None or kind == "first":
        return FIRST_VERSION
    major, minor, patch = (int(part) for part in previous.split("."))
    if kind == "major":
        return f"{major + 1}.0.0"
    if kind == "minor":
        return f"{major}.{minor + 1}.0"
    return f"{major}.{minor}.{patch + 1}"

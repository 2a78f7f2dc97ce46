"""``croissant.json``: Croissant 1.1 metadata with the Responsible-AI (RAI) fields.

Every file of the release except ``croissant.json`` and ``SHA256SUMS`` (which lists this file,
so cannot be listed in it) is a ``cr:FileObject`` with its sha256; the ``cards`` record set
reads ``cards.jsonl``, which every release has whatever formats were chosen; each format adds
the record sets that describe its own files (:meth:`exports.formats.ReleaseFormat.record_sets`,
e.g. ``views`` reading ``views/views.jsonl``) and the MIME types of its file suffixes.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import IO, Any

CROISSANT_VERSION = "http://mlcommons.org/croissant/1.1"

CONTEXT: dict[str, Any] = {
    "@language": "en",
    "@vocab": "https://schema.org/",
    "citeAs": "cr:citeAs",
    "column": "cr:column",
    "conformsTo": "dct:conformsTo",
    "cr": "http://mlcommons.org/croissant/",
    "rai": "http://mlcommons.org/croissant/RAI/",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "dct": "http://purl.org/dc/terms/",
    "equivalentProperty": "cr:equivalentProperty",
    "examples": {"@id": "cr:examples", "@type": "@json"},
    "extract": "cr:extract",
    "field": "cr:field",
    "fileProperty": "cr:fileProperty",
    "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet",
    "format": "cr:format",
    "includes": "cr:includes",
    "isLiveDataset": "cr:isLiveDataset",
    "jsonPath": "cr:jsonPath",
    "key": "cr:key",
    "md5": "cr:md5",
    "parentField": "cr:parentField",
    "path": "cr:path",
    "recordSet": "cr:recordSet",
    "references": "cr:references",
    "regex": "cr:regex",
    "repeated": "cr:repeated",
    "replace": "cr:replace",
    "samplingRate": "cr:samplingRate",
    "sc": "https://schema.org/",
    "separator": "cr:separator",
    "source": "cr:source",
    "subField": "cr:subField",
    "transform": "cr:transform",
}

# File suffix -> MIME type common to several formats; a format adds its own (``encodings``).
ENCODINGS: dict[str, str] = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".tif": "image/tiff",
    ".tiff": "image/tiff",
    ".exr": "image/x-exr",
    ".json": "application/json",
    ".jsonl": "application/jsonlines",
    ".md": "text/markdown",
    ".webp": "image/webp",
    ".gif": "image/gif",
}

# (field name, schema.org / Croissant type, description) of the ``cards`` record set.
CARD_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("key", "sc:Text", "Card name in every layout: the zero-padded card id (file names, WebDataset keys)."),
    ("card_id", "sc:Integer", "The card's id in the catalogue."),
    ("accession", "sc:Text", "The museum's accession number, where known."),
    ("collection", "sc:Text", "The collection the scan was ingested into."),
    ("museum_url", "sc:URL", "The museum's page for the card, where known."),
    ("grade", "sc:Text", "Final grade after curator review: few (artifacts) or some (artifacts)."),
    ("review_decision", "sc:Text", "Curator decision: accepted (automatic grade stands) or changed."),
    ("automatic_grade", "sc:Text", "The automatic grader's verdict before review."),
    ("digest", "sc:Text", "Digest of the facts that make this card's data (scan, boxes, parameters, grade)."),
)


def _encoding(path: str, encodings: Mapping[str, str]) -> str:
    suffix = "." + path.rsplit(".", 1)[-1].lower() if "." in path else ""
    return encodings.get(suffix) or ENCODINGS.get(suffix, "application/octet-stream")


def file_id(path: str) -> str:
    return "file/" + path


def file_object(path: str, sha: str, size: int, encodings: Mapping[str, str] | None = None) -> dict[str, Any]:
    return {
        "@type": "cr:FileObject",
        "@id": file_id(path),
        "name": path,
        "contentUrl": path,
        "contentSize": f"{size} B",
        "encodingFormat": _encoding(path, encodings or {}),
        "sha256": sha,
    }


DISTRIBUTION_MARK = "@@distribution@@"


def write_croissant(handle: IO[bytes], files: dict[str, tuple[str, int]], **document: Any) -> None:
    """Write :func:`croissant_document` to ``handle`` with the file list streamed entry by entry,
    so a release of 100,000 files never holds the whole JSON text in memory. The bytes equal
    ``json.dumps(doc, indent=2, sort_keys=True, ensure_ascii=False) + "\n"``."""
    head = croissant_document(**document, files={})
    head["distribution"] = DISTRIBUTION_MARK
    text = json.dumps(head, indent=2, sort_keys=True, ensure_ascii=False) + "\n"
    before, after = text.split(json.dumps(DISTRIBUTION_MARK), 1)
    handle.write(before.encode())
    if not files:
        handle.write(b"[]")
    for number, (path, (sha, size)) in enumerate(sorted(files.items())):
        entry = json.dumps(file_object(path, sha, size, document.get("encodings")), indent=2, sort_keys=True, ensure_ascii=False)
        indented = "\n".join("    " + line for line in entry.splitlines())
        handle.write((("[\n" if number == 0 else ",\n") + indented).encode())
    if files:
        handle.write(b"\n  ]")
    handle.write(after.encode())


def jsonl_record_set(name: str, fields: Sequence[tuple[str, str, str]], description: str) -> dict[str, Any]:
    """A RecordSet read from the release's ``<name>/<name>.jsonl`` index, one field per column
    (``fields``: name, schema.org / Croissant type, description)."""
    return {
        "@type": "cr:RecordSet",
        "@id": name,
        "name": name,
        "description": description,
        "key": {"@id": f"{name}/key"},
        "field": [
            {
                "@type": "cr:Field",
                "@id": f"{name}/{field}",
                "name": field,
                "description": field_description,
                "dataType": kind,
                "source": {"fileObject": {"@id": file_id(f"{name}/{name}.jsonl")}, "extract": {"column": field}},
            }
            for field, kind, field_description in fields
        ],
    }


PUBLIC_DOMAIN_MARK = "https://creativecommons.org/publicdomain/mark/1.0/"


def release_licence(rights: Mapping[str, int], card_count: int) -> str | list[str]:
    """The release's licence: the museums' own rights statements, unchanged (``rights``: statement
    URL -> cards carrying it), plus the public domain mark for cards that came with none."""
    statements = sorted(rights)
    if sum(rights.values()) < card_count or not statements:
        statements.append(PUBLIC_DOMAIN_MARK)
    return statements[0] if len(statements) == 1 else statements


def croissant_document(
    *,
    version: str,
    date: str,
    files: dict[str, tuple[str, int]],
    card_count: int,
    grade_counts: dict[str, int],
    crowd: dict[str, Any],
    notes: str,
    name: str = "keystone-stereographs",
    record_sets: Sequence[dict[str, Any]] = (),
    encodings: Mapping[str, str] | None = None,
    rights: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """The Croissant JSON-LD document (``files``: relative path -> (sha256, bytes)); ``record_sets``
    (the formats' own, after ``cards``) and ``encodings`` (suffix -> MIME type beyond
    :data:`ENCODINGS`) come from the release's formats."""
    distribution = [file_object(path, sha, size, encodings) for path, (sha, size) in sorted(files.items())]
    fields = [
        {
            "@type": "cr:Field",
            "@id": f"cards/{field}",
            "name": field,
            "description": description,
            "dataType": kind,
            "source": {"fileObject": {"@id": file_id("cards.jsonl")}, "extract": {"column": field}},
        }
        for field, kind, description in CARD_FIELDS
    ]
    cards = {
        "@type": "cr:RecordSet",
        "@id": "cards",
        "name": "cards",
        "description": f"One record per released card ({card_count} cards).",
        "key": {"@id": "cards/key"},
        "field": fields,
    }
    answers = crowd.get("answers_per_card")
    return {
        "@context": CONTEXT,
        "@type": "sc:Dataset",
        "conformsTo": CROISSANT_VERSION,
        "name": name,
        "description": (
            "Rectified antique stereo pairs with rectification transforms, camera parameters, left and right "
            "disparity maps and 512 x 512 depth maps (up to scale), graded for artifacts and reviewed by curators, "
            "after KeystoneDepth (Luo et al.). " + (notes.strip() if notes else "")
        ).strip(),
        "version": version,
        "datePublished": date,
        "license": release_licence(rights or {}, card_count),
        "url": "https://github.com/keystone-stereo/keystone",
        "creator": {"@type": "sc:Organization", "name": "Keystone curators"},
        "keywords": ["stereo", "stereograph", "disparity", "depth estimation", "cultural heritage", "KeystoneDepth"],
        "citeAs": (
            "@inproceedings{luo2020keystonedepth, title={KeystoneDepth: History in 3D}, "
            "author={Luo, Xuan and Kong, Yanmeng and Lawrence, Jason and Martin-Brualla, Ricardo and "
            "Seitz, Steven M.}, booktitle={International Conference on 3D Vision (3DV)}, year={2020}}"
        ),
        "isLiveDataset": False,
        "rai:dataCollection": (
            "Scans of antique stereo cards with their museum catalogue records (accession, title, date, creator, "
            "publisher, place, URL). Each scan is stored once by content hash and never modified."
        ),
        "rai:dataCollectionType": "Secondary data: digitised museum holdings",
        "rai:dataAnnotationProtocol": (
            "Crowd workers judged each card (stereo pair or not, upside down, inverted intensities) and drew the "
            "largest artifact-free crop box on each half; answers were aggregated per card (Dawid-Skene for "
            "judgements, consensus for boxes) and disputed aggregates went to a curator. An automatic grader "
            "scored each rectified pair (few artifacts / some artifacts / failure) and curators accepted or "
            "changed every grade in this release."
        ),
        "rai:dataAnnotationPlatform": "Keystone's own crowd task pages (invite links and Prolific-style study links)",
        "rai:annotationsPerItem": (
            f"{answers:.2f} crowd answers per card on average"
            if answers is not None
            else "no crowd answers: boxes from the automatic split, grades by curators"
        ),
        "rai:dataAnnotationAnalysis": (
            "Agreement per crowd batch (Krippendorff's alpha for judgements, IoU for boxes) and agreement of the "
            "automatic grade with curators are reported by `keystone report`."
        ),
        "rai:machineAnnotationTools": "SIFT filtering, Loop-Zhang rectification, dense optical flow disparity (OpenCV)",
        "rai:dataPreprocessingProtocol": (
            "Orientation corrections (rotate 180 deg, invert) are applied to derived images only; views are cropped "
            "to the aligned crowd boxes and rectified; disparity is the horizontal flow between rectified views."
        ),
        "rai:dataBiases": (
            "Stereo cards over-represent tourist sites, exhibitions and studio scenes chosen by commercial "
            "publishers (1850s-1960s); their captions reflect the views of their time. Cards graded failure are "
            f"never released, so hard scenes are under-represented. Grades here: {grade_counts}."
        ),
        "rai:dataLimitations": (
            "Depth is up to scale (unknown baseline); disparity maps are estimated, not measured, and are unknown "
            "(NaN) where no match was found. Pairs are never perfectly rectified."
        ),
        "rai:personalSensitiveInformation": (
            "Historic photographs may show identifiable people, now deceased; no personal data of annotators is "
            "released (crowd answers appear only as counts per card)."
        ),
        "rai:dataUseCases": "Stereo matching and monocular depth on historic photographs; novel view synthesis.",
        "rai:dataReleaseMaintenancePlan": (
            "Semantic versions: patch = same data re-serialised, minor = cards added, major = cards removed or "
            "changed; every release has a CHANGELOG against the one before and a SHA256SUMS file."
        ),
        "distribution": distribution,
        "recordSet": [cards, *record_sets],
    }

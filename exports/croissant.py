"""``croissant.json``: Croissant 1.1 metadata with the Responsible-AI (RAI) fields.

Every file of the release except ``croissant.json`` and ``SHA256SUMS`` (which lists this file,
so cannot be listed in it) is a ``cr:FileObject`` with its sha256; the ``cards`` record set
reads ``cards.jsonl``, which every release has whatever formats were chosen; with the views
component, the ``views`` record set reads ``views/views.jsonl`` (one record per card with views).
"""

from __future__ import annotations

import json
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

ENCODINGS = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".tif": "image/tiff",
    ".tiff": "image/tiff",
    ".exr": "image/x-exr",
    ".json": "application/json",
    ".jsonl": "application/jsonlines",
    ".parquet": "application/x-parquet",
    ".tar": "application/x-tar",
    ".md": "text/markdown",
    ".webp": "image/webp",
    ".gif": "image/gif",
    ".mpo": "image/mpo",
    ".jps": "image/x-jps",
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


# (field name, type, description) of the ``views`` record set (``views/views.jsonl``).
VIEW_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("key", "sc:Text", "The card's key (as in cards): its views are in views/<key>/."),
    ("card_id", "sc:Integer", "The card's id in the catalogue."),
    (
        "folder",
        "sc:Text",
        (
            "Folder of v0.png..v4.png (8-bit grey, or RGB for a colour card), v0_depth.exr..v4_depth.exr (float32 depth, baseline 1), "
            "views.json (cameras) and preview.webp."
        ),
    ),
    ("width", "sc:Integer", "Width of the five views in pixels."),
    ("height", "sc:Integer", "Height of the five views in pixels."),
    ("focal_px", "sc:Float", "Focal length of the reference view v0 in pixels."),
    ("quad_radius", "sc:Float", "Distance of the corner cameras v1..v4 from the quad's centre, baseline units."),
    ("preview", "sc:Text", "Path of the animated parallax preview (WebP)."),
)


# (field name, type, description) of the ``stereo`` record set (``stereo/stereo.jsonl``).
STEREO_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("key", "sc:Text", "The card's key (as in cards): its stereo files are in stereo/<key>/."),
    ("card_id", "sc:Integer", "The card's id in the catalogue."),
    ("width", "sc:Integer", "Width of one rectified view in pixels."),
    ("height", "sc:Integer", "Height of one rectified view in pixels."),
    ("anaglyph", "sc:Text", "Path of the red-cyan anaglyph (JPEG, Dubois least squares)."),
    ("wiggle_gif", "sc:Text", "Path of the animated wiggle (GIF), in-between views synthesised from the disparity."),
    ("wiggle_webp", "sc:Text", "Path of the animated wiggle (WebP)."),
    ("sbs_full", "sc:Text", "Path of the full side-by-side image, parallel (left view on the left)."),
    ("sbs_half", "sc:Text", "Path of the half side-by-side image, parallel, each view at half width."),
    ("jps", "sc:Text", "Path of the JPS file, cross-eyed (right view on the left)."),
    ("mpo", "sc:Text", "Path of the MPO file, left view first."),
)


def _encoding(path: str) -> str:
    suffix = "." + path.rsplit(".", 1)[-1].lower() if "." in path else ""
    return ENCODINGS.get(suffix, "application/octet-stream")


def _file_id(path: str) -> str:
    return "file/" + path


def file_object(path: str, sha: str, size: int) -> dict[str, Any]:
    return {
        "@type": "cr:FileObject",
        "@id": _file_id(path),
        "name": path,
        "contentUrl": path,
        "contentSize": f"{size} B",
        "encodingFormat": _encoding(path),
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
        entry = json.dumps(file_object(path, sha, size), indent=2, sort_keys=True, ensure_ascii=False)
        indented = "\n".join("    " + line for line in entry.splitlines())
        handle.write((("[\n" if number == 0 else ",\n") + indented).encode())
    if files:
        handle.write(b"\n  ]")
    handle.write(after.encode())


def _jsonl_record_set(name: str, fields: Any, description: str) -> dict[str, Any]:
    """A RecordSet read from the release's ``<name>/<name>.jsonl`` index, one field per column."""
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
                "source": {"fileObject": {"@id": _file_id(f"{name}/{name}.jsonl")}, "extract": {"column": field}},
            }
            for field, kind, field_description in fields
        ],
    }


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
    views_count: int | None = None,
    stereo_count: int | None = None,
) -> dict[str, Any]:
    """The Croissant JSON-LD document (``files``: relative path -> (sha256, bytes));
    ``views_count`` (cards with views) is given when the release has the views component."""
    distribution = [file_object(path, sha, size) for path, (sha, size) in sorted(files.items())]
    fields = [
        {
            "@type": "cr:Field",
            "@id": f"cards/{field}",
            "name": field,
            "description": description,
            "dataType": kind,
            "source": {"fileObject": {"@id": _file_id("cards.jsonl")}, "extract": {"column": field}},
        }
        for field, kind, description in CARD_FIELDS
    ]
    record_sets = [
        {
            "@type": "cr:RecordSet",
            "@id": "cards",
            "name": "cards",
            "description": f"One record per released card ({card_count} cards).",
            "key": {"@id": "cards/key"},
            "field": fields,
        }
    ]
    if views_count is not None:
        record_sets.append(
            _jsonl_record_set(
                "views",
                VIEW_FIELDS,
                f"The five GD images per card (reference view v0 and quad corners v1..v4, KeystoneDepth "
                f"section 5) for {views_count} of {card_count} cards; one record per card with views.",
            )
        )
    if stereo_count is not None:
        record_sets.append(
            _jsonl_record_set(
                "stereo",
                STEREO_FIELDS,
                f"Viewing files of the rectified pair (anaglyph, wiggles, side-by-side, JPS, MPO) for "
                f"{stereo_count} of {card_count} cards; one record per card with them.",
            )
        )
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
        "license": "https://creativecommons.org/publicdomain/mark/1.0/",
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
        "recordSet": record_sets,
    }

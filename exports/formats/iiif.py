"""``iiif``: the release as a IIIF Presentation 3 manifest (``iiif/manifest.json``), to give back to
the museums whose viewers (Mirador, Universal Viewer) read IIIF.

One canvas per released card. A card ingested from a museum's IIIF canvas keeps that canvas's
id and size and paints the museum's own Image API service, so the annotations land on the
museum's canvas; any other card gets a canvas of its own painting the release's copy of the scan.
On each canvas, as Web Annotations (motivation ``commenting``, the text a viewer shows):

* the left-eye and right-eye crop boxes, ``FragmentSelector`` ``xywh=`` in the canvas's
  coordinates: the boxes the pipeline cut, as scanned (rectify's ``scanned_boxes``: a card turned
  180 deg has its boxes turned back), scaled by canvas size / fetched image size;
* the grade, the curator's decision and the grader's reasons, on the whole canvas;
* the orientation used (turned, inverted, eyes swapped) and who decided it;
* the rectified left and right views and the depth map (motivation ``supplementing``).

The card's rights statement, required statement, homepage and catalogue fields go on its canvas
unchanged. Ids are absolute URLs under ``KEYSTONE_RELEASE_BASE_URL`` (where the release folder
will be served; ``https://keystone.invalid/release/`` when unset, to be replaced on publication).
Resources another chosen format already wrote (``keystonedepth``'s scan, rectified views and depth
EXR) are pointed at, not copied; otherwise they are written under ``iiif/resources/<id>/``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..writers import CardPayload, FileLedger, encode_exr
from .base import ReleaseFormat, WriteContext
from .registry import release_format

MANIFEST = "iiif/manifest.json"
ANNOTATIONS = "iiif/annotations"
RESOURCES = "iiif/resources"
PRESENTATION_3 = "http://iiif.io/api/presentation/3/context.json"
BASE_URL_VARIABLE = "KEYSTONE_RELEASE_BASE_URL"
DEFAULT_BASE_URL = "https://keystone.invalid/release/"
MEDIA_FRAGMENTS = "http://www.w3.org/TR/media-frags/"
EYES = (("left_eye", "left_box", "Left-eye view"), ("right_eye", "right_box", "Right-eye view"))


def base_url() -> str:
    url = os.environ.get(BASE_URL_VARIABLE) or DEFAULT_BASE_URL
    return url if url.endswith("/") else url + "/"


def _text(value: str) -> dict[str, list[str]]:
    return {"en": [value]}


def scanned_box(card_facts: dict[str, Any], box: list[int], eye: str, orientation: list[str], size: tuple[int, int]) -> list[int]:
    """The box the pipeline cut for ``eye`` in the scan's own pixels: rectify's ``scanned_boxes``
    where recorded, else the oriented box turned back (a 180 deg turn is its own inverse)."""
    recorded = (card_facts.get("scanned_boxes") or {}).get(eye)
    if recorded:
        return [int(v) for v in recorded]
    if "rotated 180 deg" in orientation:
        width, height = size
        return [width - box[2], height - box[3], width - box[0], height - box[1]]
    return [int(v) for v in box]


def canvas_fragment(box: list[int], scale: tuple[float, float], canvas_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """``[x0, y0, x1, y1]`` in image pixels -> ``(x, y, w, h)`` in canvas coordinates, inside the canvas."""
    sx, sy = scale
    width, height = canvas_size
    x0, y0 = max(0, round(box[0] * sx)), max(0, round(box[1] * sy))
    x1, y1 = min(width, round(box[2] * sx)), min(height, round(box[3] * sy))
    return x0, y0, x1 - x0, y1 - y0


class IiifWriter:
    """Builds the manifest a card at a time; writes it (and one annotation page per card) at close."""

    def __init__(self, ledger: FileLedger, scratch: Path) -> None:
        self.ledger, self.scratch = ledger, scratch
        self.base = base_url()
        self.canvases: list[dict[str, Any]] = []
        self.rights: dict[str, int] = {}
        self.from_museum = 0

    def _url(self, relative: str) -> str:
        return self.base + relative

    def _resource(self, payload: CardPayload, existing: str, own: str, data: bytes | None) -> str:
        """The URL of a file of the release: another format's copy if written, else our own."""
        if existing in self.ledger.files:
            return self._url(existing)
        if own not in self.ledger.files:
            self.ledger.write_bytes(own, data if data is not None else b"")
        return self._url(own)

    def add(self, payload: CardPayload) -> None:
        card, key = payload.card, payload.card.key
        source = card.iiif_source
        own = f"{RESOURCES}/{key}"
        if source and source.get("canvas") and source.get("service"):
            self.from_museum += 1
            canvas_id = source["canvas"]
            canvas_size = (int(source["canvas_width"]), int(source["canvas_height"]))
            fetched = (int(source.get("fetched_width") or card.width), int(source.get("fetched_height") or card.height))
            version = int(source.get("service_version") or 3)
            service_full = (int(source.get("service_width") or fetched[0]), int(source.get("service_height") or fetched[1]))
            painting_body: dict[str, Any] = {
                "id": f"{source['service']}/full/max/0/default.jpg"
                if version == 3
                else f"{source['service']}/full/full/0/default.jpg",
                "type": "Image",
                "format": "image/jpeg",
                "width": service_full[0],
                "height": service_full[1],
                "service": [
                    {"id": source["service"], "type": "ImageService3", "profile": "level0"}
                    if version == 3
                    else {"@id": source["service"], "@type": "ImageService2", "profile": "http://iiif.io/api/image/2/level0.json"}
                ],
            }
            part_of = [{"id": source["manifest"], "type": "Manifest"}] if source.get("manifest") else []
        else:
            canvas_id = self._url(f"iiif/canvas/{key}")
            canvas_size = fetched = (card.width, card.height)
            scan = self._resource(
                payload, f"original/{key}{payload.original_suffix}", f"{own}/original{payload.original_suffix}", payload.original
            )
            painting_body = {
                "id": scan,
                "type": "Image",
                "format": _image_type(payload.original_suffix),
                "width": card.width,
                "height": card.height,
            }
            part_of = []
        scale = (canvas_size[0] / fetched[0], canvas_size[1] / fetched[1])
        page_id = self._url(f"{ANNOTATIONS}/{key}.json")
        annotations = self._box_annotations(payload, canvas_id, canvas_size, scale, page_id)
        annotations.append(self._grade_annotation(payload, canvas_id, page_id))
        annotations.append(self._orientation_annotation(payload, canvas_id, page_id))
        annotations += self._supplementing(payload, canvas_id, page_id, own)
        page = {"id": page_id, "type": "AnnotationPage", "items": annotations}
        self.ledger.write_bytes(f"{ANNOTATIONS}/{key}.json", _dump({"@context": PRESENTATION_3, **page}))
        canvas: dict[str, Any] = {
            "id": canvas_id,
            "type": "Canvas",
            "label": _text(str(card.metadata.get("title") or card.source_name)),
            "width": canvas_size[0],
            "height": canvas_size[1],
            "metadata": [
                {"label": _text(str(name)), "value": {"none": [str(value)]}}
                for name, value in sorted(card.metadata.items())
                if value not in (None, "") and not isinstance(value, dict | list)
            ]
            + [{"label": _text("Keystone card"), "value": {"none": [key]}}],
            "items": [
                {
                    "id": self._url(f"iiif/canvas/{key}/page"),
                    "type": "AnnotationPage",
                    "items": [
                        {
                            "id": self._url(f"iiif/canvas/{key}/painting"),
                            "type": "Annotation",
                            "motivation": "painting",
                            "body": painting_body,
                            "target": canvas_id,
                        }
                    ],
                }
            ],
            "annotations": [page],
        }
        rights = card.metadata.get("rights")
        if isinstance(rights, str) and rights.startswith(("http://", "https://")):
            canvas["rights"] = rights  # unchanged: the museum's statement is the museum's
            self.rights[rights] = self.rights.get(rights, 0) + 1
        statement = card.metadata.get("required_statement")
        if isinstance(statement, str) and statement:
            label, _, value = statement.partition(": ")
            canvas["requiredStatement"] = {"label": _text(label if value else "Attribution"), "value": _text(value or label)}
        if card.museum_url:
            canvas["homepage"] = [
                {"id": card.museum_url, "type": "Text", "label": _text("The museum's record"), "format": "text/html"}
            ]
        if part_of:
            canvas["partOf"] = part_of
        self.canvases.append(canvas)

    def _box_annotations(
        self, payload: CardPayload, canvas_id: str, canvas_size: tuple[int, int], scale: tuple[float, float], page_id: str
    ) -> list[dict[str, Any]]:
        card, annotations = payload.card, []
        facts = card.annotation_facts
        for eye, attribute, title in EYES:
            box = scanned_box(facts, getattr(card, attribute), eye, card.orientation, (card.width, card.height))
            x, y, w, h = canvas_fragment(box, scale, canvas_size)
            annotations.append(
                {
                    "id": f"{page_id}#{eye}",
                    "type": "Annotation",
                    "motivation": "commenting",
                    "body": {
                        "type": "TextualBody",
                        "format": "text/plain",
                        "language": "en",
                        "value": f"{title}: the crop Keystone rectified ({facts.get('box_source') or 'boxes from the filter split'})",
                    },
                    "target": _fragment_target(canvas_id, (x, y, w, h)),
                }
            )
        return annotations

    def _grade_annotation(self, payload: CardPayload, canvas_id: str, page_id: str) -> dict[str, Any]:
        card = payload.card
        reasons = card.annotation_facts.get("grade_reasons") or []
        decided = {"accepted": "accepted by a curator", "changed": "set by a curator"}.get(card.decision, card.decision)
        automatic = f"; automatic grade {card.auto_grade}" if card.auto_grade and card.auto_grade != card.grade else ""
        text = f"Grade: {card.grade} artifacts ({decided}{automatic})." + (
            " Grader's reasons: " + "; ".join(str(r) for r in reasons) + "." if reasons else ""
        )
        return _whole_canvas_comment(f"{page_id}#grade", canvas_id, text)

    def _orientation_annotation(self, payload: CardPayload, canvas_id: str, page_id: str) -> dict[str, Any]:
        card = payload.card
        used = card.annotation_facts.get("orientation_used") or {}
        flags = {"upside_down": "upside down", "inverted": "a negative", "swapped": "eyes swapped"}
        found = [words for flag, words in flags.items() if used.get(flag)]
        facts = card.annotation_facts
        who = {"auto": "the orientation step", "crowd": "the crowd", "curator": "a curator", "operator": "an operator"}
        decided = who.get(str(facts.get("orientation_decided_by")), "the orientation step")
        if facts.get("orientation_source"):
            decided += f" ({facts['orientation_source']})"
        text = (
            "Orientation: "
            + (", ".join(found) if found else "upright, positive, eyes in order")
            + f"; decided by {decided}."
            + (" Keystone applied: " + ", ".join(card.orientation) + "." if card.orientation else "")
        )
        return _whole_canvas_comment(f"{page_id}#orientation", canvas_id, text)

    def _supplementing(self, payload: CardPayload, canvas_id: str, page_id: str, own: str) -> list[dict[str, Any]]:
        key = payload.card.key
        rectified = [
            (
                "rectified-left",
                "Rectified left view",
                self._resource(
                    payload, f"processed/rectified/rectified_LR/{key}L.png", f"{own}/rectified_left.png", payload.rectified_left
                ),
            ),
            (
                "rectified-right",
                "Rectified right view",
                self._resource(
                    payload, f"processed/rectified/rectified_LR/{key}R.png", f"{own}/rectified_right.png", payload.rectified_right
                ),
            ),
        ]
        depth_own = f"{own}/depth_512.exr"
        depth_existing = f"processed/depth_512/{key}.exr"
        if depth_existing not in self.ledger.files and depth_own not in self.ledger.files:
            self.ledger.write_bytes(depth_own, encode_exr(payload.depth_512, self.scratch))
        depth = self._url(depth_existing if depth_existing in self.ledger.files else depth_own)
        annotations = [
            {
                "id": f"{page_id}#{name}",
                "type": "Annotation",
                "motivation": "supplementing",
                "body": {"id": url, "type": "Image", "format": "image/png", "label": _text(label)},
                "target": canvas_id,
            }
            for name, label, url in rectified
        ]
        annotations.append(
            {
                "id": f"{page_id}#depth",
                "type": "Annotation",
                "motivation": "supplementing",
                "body": {
                    "id": depth,
                    "type": "Dataset",
                    "format": "image/x-exr",
                    "label": _text("Depth map, 512 x 512, up to scale (float32 EXR, channel Y)"),
                },
                "target": canvas_id,
            }
        )
        return annotations

    def close(self) -> None:
        manifest: dict[str, Any] = {
            "@context": PRESENTATION_3,
            "id": self._url(MANIFEST),
            "type": "Manifest",
            "label": _text("Keystone stereographs"),
            "summary": _text(
                "Stereo cards graded by Keystone: on each card, the left and right crop boxes, the grade and its reasons, "
                "the orientation used, and the rectified views and depth map."
            ),
            "items": self.canvases,
        }
        if len(self.rights) == 1:
            manifest["rights"] = next(iter(self.rights))
        self.ledger.write_bytes(MANIFEST, _dump(manifest))

    def summary(self) -> dict[str, Any] | None:
        return {"canvases": len(self.canvases), "from_museum_iiif": self.from_museum, "rights": dict(sorted(self.rights.items()))}


def _fragment_target(canvas_id: str, xywh: tuple[int, int, int, int]) -> dict[str, Any]:
    return {
        "type": "SpecificResource",
        "source": {"id": canvas_id, "type": "Canvas"},
        "selector": {"type": "FragmentSelector", "conformsTo": MEDIA_FRAGMENTS, "value": "xywh={},{},{},{}".format(*xywh)},
    }


def _whole_canvas_comment(annotation_id: str, canvas_id: str, text: str) -> dict[str, Any]:
    return {
        "id": annotation_id,
        "type": "Annotation",
        "motivation": "commenting",
        "body": {"type": "TextualBody", "format": "text/plain", "language": "en", "value": text},
        "target": canvas_id,
    }


def _image_type(suffix: str) -> str:
    return {".png": "image/png", ".tif": "image/tiff", ".tiff": "image/tiff", ".webp": "image/webp"}.get(suffix, "image/jpeg")


def _dump(document: dict[str, Any]) -> bytes:
    return json.dumps(document, indent=1, ensure_ascii=False, sort_keys=False).encode()


def check_manifest(document: dict[str, Any]) -> list[str]:
    """Problems with a release's manifest: what iiif-prezi3's Presentation 3 model refuses, and
    every annotation whose ``xywh`` is not inside its canvas (or targets another canvas)."""
    from iiif_prezi3 import Manifest
    from pydantic import ValidationError

    problems: list[str] = []
    try:
        Manifest(**document)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first.get("loc", ()))
        problems.append(
            f"not a valid IIIF Presentation 3 manifest ({exc.error_count()} problems; first at {where}: {first.get('msg')})"
        )
        return problems
    for canvas in document.get("items") or []:
        width, height = canvas.get("width") or 0, canvas.get("height") or 0
        for page in canvas.get("annotations") or []:
            for annotation in page.get("items") or [] if isinstance(page, dict) else []:
                target = annotation.get("target")
                source = target.get("source") if isinstance(target, dict) else target
                source_id = source.get("id") if isinstance(source, dict) else source
                if source_id != canvas["id"]:
                    problems.append(f"annotation {annotation.get('id')} targets {source_id}, not its canvas {canvas['id']}")
                    continue
                if not isinstance(target, dict):
                    continue
                value = str((target.get("selector") or {}).get("value") or "")
                try:
                    x, y, w, h = (int(v) for v in value.removeprefix("xywh=").split(","))
                except ValueError:
                    problems.append(f"annotation {annotation.get('id')}: selector {value!r} is not xywh=x,y,w,h")
                    continue
                if not (0 <= x and 0 <= y and w > 0 and h > 0 and x + w <= width and y + h <= height):
                    problems.append(f"annotation {annotation.get('id')}: {value} is not inside the {width} x {height} canvas")
    return problems


@release_format
class IiifFormat(ReleaseFormat):
    name = "iiif"
    description = "a IIIF Presentation 3 manifest: crop boxes, grades and orientation as annotations on each card's canvas"
    order = 90  # after the formats whose files it points at
    default = True

    def writer(self, context: WriteContext) -> IiifWriter:
        return IiifWriter(context.ledger, context.scratch)

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        museum = (summary or {}).get("from_museum_iiif", 0)
        return [
            f"- `{MANIFEST}`: a IIIF Presentation 3 manifest for Mirador or Universal Viewer, one canvas per card "
            f"({museum} on the museum's own canvas and image service): the left and right crop boxes (`xywh=` in the "
            "canvas's coordinates), the grade and its reasons and the orientation as annotations, the rectified views "
            f"and depth map as supplementing resources; `{ANNOTATIONS}/<id>.json`: each card's annotation page.",
        ]

    def changelog(self, summary: dict[str, Any] | None) -> list[str]:
        if not summary:
            return []
        return [
            "",
            "### IIIF",
            "",
            f"- {summary['canvases']} canvases in `{MANIFEST}`, {summary['from_museum_iiif']} of them the museum's own.",
        ]

    def verify(self, root: Path, listed: dict[str, str], problems: Any) -> None:
        if MANIFEST not in listed:
            return
        try:
            document = json.loads((root / MANIFEST).read_text())
        except (OSError, ValueError) as exc:
            problems.problem(MANIFEST, f"unreadable: {exc}")
            return
        for problem in check_manifest(document):
            problems.problem(MANIFEST, problem)
        base = str(document.get("id", "")).removesuffix(MANIFEST)
        for canvas in document.get("items") or []:
            for page in canvas.get("annotations") or []:
                for annotation in page.get("items") or []:
                    body = annotation.get("body") or {}
                    url = body.get("id") if isinstance(body, dict) else None
                    if isinstance(url, str) and base and url.startswith(base) and url.removeprefix(base) not in listed:
                        problems.problem(MANIFEST, f"annotation {annotation.get('id')} points at {url}, not in the release")

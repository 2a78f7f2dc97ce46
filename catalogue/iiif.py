"""Reading IIIF: Presentation manifests and collections (3.0 and 2.1), Image API services (3 and 2).

A museum publishes a stereo card as a Presentation manifest whose canvases paint an image served
by an Image API service. This module turns such a document into :class:`IiifCanvas` records (the
canvas and manifest ids, the canvas size, the image service, the manifest's catalogue fields)
and chooses which size of the image to fetch from the service's ``info.json``. Nothing here
touches the database; :mod:`catalogue.iiif_ingest` stores what is fetched like any original.

Presentation 3 documents are validated with iiif-prezi3's models (the IIIF community's own);
2.1 documents are read by a small reader here (prezi3 reads only 3.0) that maps them onto the
same fields the 3.0 reader fills: ``license`` -> ``rights``, ``attribution`` ->
``requiredStatement``, ``related`` -> ``homepage``.

Only ``http`` and ``https`` URLs are ever fetched: a ``file://`` (or any other scheme) inside a
manifest is refused, so a manifest cannot make ingest read files on this machine. Loopback and
private addresses are allowed: a museum's server may sit on the same network (and the tests'
does on loopback).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from catalogue.metadata import ACCESSION_COLUMNS, CANONICAL

PRESENTATION_3 = "http://iiif.io/api/presentation/3/context.json"
IMAGE_3 = "http://iiif.io/api/image/3/context.json"
MAX_DOCUMENT_BYTES = 20 << 20  # a manifest of thousands of canvases is a few MB
MAX_COLLECTION_DEPTH = 4  # collections of collections of manifests; deeper is a loop or a mistake


class IiifError(ValueError):
    """A document or service that cannot be used, with a reason for people."""


@dataclass(frozen=True)
class ImageService:
    id: str  # the service's base URI, without /info.json
    version: int  # Image API 2 or 3


@dataclass(frozen=True)
class IiifCanvas:
    """One canvas of a manifest whose image may be a stereo card."""

    canvas_id: str
    manifest_id: str
    index: int  # 0-based position in the manifest
    width: int  # canvas coordinate space, as the manifest declares it
    height: int
    service: ImageService | None  # None: the canvas paints no image through an Image API service
    image_id: str | None  # the painted image resource itself
    label: str
    record: dict[str, Any]  # catalogue fields (title, date, rights, url, ...) and every metadata pair
    accession: str | None = None
    rights: str | None = None
    problem: str | None = None  # why it cannot be ingested (then ``service`` may be None)


@dataclass
class ReadDocument:
    """A manifest's canvases, or a collection's member manifest URIs (and their problems)."""

    kind: str  # "manifest" or "collection"
    id: str
    version: int
    canvases: list[IiifCanvas] = field(default_factory=list)
    members: list[str] = field(default_factory=list)


def is_url(text: str) -> bool:
    return bool(re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", text))


def is_iiif_source(raw: object) -> bool:
    """A URL, or a ``.json`` file: what ingest reads as a IIIF manifest or collection."""
    text = str(raw)
    return is_url(text) or text.lower().endswith(".json")


def check_fetchable(url: str) -> str:
    """``url`` if ingest may fetch it (http or https with a host); raises :class:`IiifError`."""
    parts = urlsplit(url)
    if parts.scheme.lower() not in ("http", "https"):
        raise IiifError(f"only http and https URLs are fetched, got a {parts.scheme or 'relative'} URL {url!r}")
    if not parts.hostname:
        raise IiifError(f"URL without a host: {url!r}")
    return url


def parse_json(data: bytes, where: str) -> dict[str, Any]:
    if len(data) > MAX_DOCUMENT_BYTES:
        raise IiifError(f"{where} is {len(data):,} bytes, over the {MAX_DOCUMENT_BYTES:,} a IIIF document may be")
    try:
        document = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise IiifError(f"{where} is not JSON: {exc}") from None
    if not isinstance(document, dict):
        raise IiifError(f"{where} is JSON but not an object")
    return document


def presentation_version(document: dict[str, Any]) -> int:
    contexts = document.get("@context")
    text = json.dumps(contexts) if contexts is not None else ""
    if "presentation/3" in text:
        return 3
    if "presentation/2" in text:
        return 2
    raise IiifError("not a IIIF Presentation document: its @context names neither Presentation 3 nor 2")


def read_document(document: dict[str, Any]) -> ReadDocument:
    """A manifest's canvases or a collection's members; raises :class:`IiifError` for a bad one."""
    version = presentation_version(document)
    return _read_v3(document) if version == 3 else _read_v2(document)


# ---- Presentation 3 ----


def _language_text(value: Any) -> str:
    """A language map (``{"en": ["..."]}``) as one string: English, else ``none``, else the first."""
    if isinstance(value, str):
        return value
    if not isinstance(value, dict) or not value:
        return ""
    for key in ("en", "none", *value.keys()):
        texts = value.get(key)
        if texts:
            return "; ".join(str(t) for t in (texts if isinstance(texts, list) else [texts]))
    return ""


def _validate_v3(document: dict[str, Any]) -> None:
    """Load the document into iiif-prezi3's model: a document it refuses is a bad manifest."""
    from iiif_prezi3 import Collection, Manifest
    from pydantic import ValidationError

    model = Collection if document.get("type") == "Collection" else Manifest
    try:
        model(**document)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first.get("loc", ())) or "the document"
        raise IiifError(
            f"not a valid IIIF Presentation 3 {model.__name__.lower()} ({exc.error_count()} problems; first at {where}: {first.get('msg')})"
        ) from None
    except (TypeError, ValueError) as exc:
        raise IiifError(f"not a valid IIIF Presentation 3 {model.__name__.lower()}: {exc}") from None


def _read_v3(document: dict[str, Any]) -> ReadDocument:
    kind = document.get("type")
    if kind not in ("Manifest", "Collection"):
        raise IiifError(f"expected a Presentation 3 Manifest or Collection, got type {kind!r}")
    if not isinstance(document.get("id"), str):
        raise IiifError(f"the {kind.lower()} has no id")
    _validate_v3(document)
    if kind == "Collection":
        members = [item["id"] for item in document.get("items") or [] if item.get("type") in ("Manifest", "Collection")]
        return ReadDocument("collection", document["id"], 3, members=members)
    record, accession, rights = _record_v3(document)
    canvases = []
    for index, canvas in enumerate(document.get("items") or []):
        if canvas.get("type") != "Canvas":
            continue
        canvases.append(_canvas_v3(canvas, document["id"], index, record, accession, rights))
    return ReadDocument("manifest", document["id"], 3, canvases=canvases)


def _record_v3(document: dict[str, Any]) -> tuple[dict[str, Any], str | None, str | None]:
    pairs = [(_language_text(p.get("label")), _language_text(p.get("value"))) for p in document.get("metadata") or []]
    required = document.get("requiredStatement") or {}
    homepage = document.get("homepage") or []
    homepage_id = (homepage[0] if isinstance(homepage, list) and homepage else homepage or {}).get("id")
    return _record(
        label=_language_text(document.get("label")),
        pairs=pairs,
        nav_date=document.get("navDate"),
        rights=document.get("rights"),
        required=(_language_text(required.get("label")), _language_text(required.get("value"))) if required else None,
        homepage=homepage_id,
        manifest_id=document["id"],
    )


def _canvas(
    canvas_id: str,
    manifest_id: str,
    index: int,
    size: tuple[Any, Any],
    service: Any,
    image_id: Any,
    label: str,
    record: dict[str, Any],
    accession: str | None,
    rights: str | None,
    problem: str | None,
) -> IiifCanvas:
    """One canvas as either version reads it; a width or height that is not a positive whole
    number is the canvas's problem (and both are 0)."""
    width, height = size
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        problem = f"the canvas has no usable width and height (got {width!r} x {height!r})"
        width = height = 0
    return IiifCanvas(
        canvas_id=canvas_id,
        manifest_id=manifest_id,
        index=index,
        width=width,
        height=height,
        service=service,
        image_id=image_id,
        label=label,
        record={**record, "iiif_canvas": canvas_id, "canvas_label": label},
        accession=accession,
        rights=rights,
        problem=problem,
    )


def _canvas_v3(
    canvas: dict[str, Any], manifest_id: str, index: int, record: dict[str, Any], accession: str | None, rights: str | None
) -> IiifCanvas:
    width, height = canvas.get("width"), canvas.get("height")
    label = _language_text(canvas.get("label")) or f"canvas {index + 1}"
    body = _first_painting_body_v3(canvas)
    service = image_id = None
    problem = None
    if body is None:
        problem = "the canvas paints no image"
    else:
        image_id = body.get("id")
        service = _service_of(body.get("service"))
        if service is None:
            problem = "the canvas's image has no IIIF Image API service"
    return _canvas(
        canvas["id"], manifest_id, index, (width, height), service, image_id, label, record, accession, rights, problem
    )


def _first_painting_body_v3(canvas: dict[str, Any]) -> dict[str, Any] | None:
    for page in canvas.get("items") or []:
        for annotation in page.get("items") or []:
            if annotation.get("motivation") not in ("painting", ["painting"]):
                continue
            body = annotation.get("body")
            if isinstance(body, list):
                body = body[0] if body else None
            if isinstance(body, dict) and body.get("type") == "Choice":
                choices = body.get("items") or []
                body = choices[0] if choices else None
            if isinstance(body, dict) and body.get("type", "Image") == "Image":
                return body
    return None


def _service_of(services: Any) -> ImageService | None:
    """The first Image API service among ``services`` (a list or one object, 2 or 3 style)."""
    for service in services if isinstance(services, list) else [services] if services else []:
        if not isinstance(service, dict):
            continue
        kind = str(service.get("type") or service.get("@type") or "")
        context = json.dumps(service.get("@context") or "")
        profile = json.dumps(service.get("profile") or "")
        service_id = service.get("id") or service.get("@id")
        if not isinstance(service_id, str):
            continue
        if kind == "ImageService3" or "image/3" in context:
            return ImageService(service_id.rstrip("/"), 3)
        if kind == "ImageService2" or "image/2" in context or "image/2" in profile:
            return ImageService(service_id.rstrip("/"), 2)
    return None


# ---- Presentation 2.1 ----


def _v2_text(value: Any) -> str:
    """A 2.1 property value: a string, ``{"@value": ...}``, or a list of either (English first)."""
    if isinstance(value, str):
        return value
    if isinstance(value, dict):
        return str(value.get("@value") or "")
    if isinstance(value, list) and value:
        english = [v for v in value if isinstance(v, dict) and str(v.get("@language", "")).startswith("en")]
        return "; ".join(_v2_text(v) for v in (english or value) if _v2_text(v))
    return ""


def _v2_id(value: Any) -> str | None:
    if isinstance(value, list):
        value = value[0] if value else None
    if isinstance(value, dict):
        value = value.get("@id")
    return value if isinstance(value, str) else None


def _read_v2(document: dict[str, Any]) -> ReadDocument:
    kind = document.get("@type")
    document_id = document.get("@id")
    if kind not in ("sc:Manifest", "sc:Collection"):
        raise IiifError(f"expected a Presentation 2.1 sc:Manifest or sc:Collection, got @type {kind!r}")
    if not isinstance(document_id, str):
        raise IiifError(f"the {kind} has no @id")
    if kind == "sc:Collection":
        members = [m.get("@id") for m in (document.get("manifests") or []) + (document.get("collections") or [])]
        members += [m.get("@id") for m in document.get("members") or [] if m.get("@type") in ("sc:Manifest", "sc:Collection")]
        return ReadDocument("collection", document_id, 2, members=[m for m in members if isinstance(m, str)])
    sequences = document.get("sequences")
    if not isinstance(sequences, list) or not sequences or not isinstance(sequences[0], dict):
        raise IiifError("a Presentation 2.1 manifest needs a sequence of canvases")
    pairs = [(_v2_text(p.get("label")), _v2_text(p.get("value"))) for p in document.get("metadata") or [] if isinstance(p, dict)]
    attribution = _v2_text(document.get("attribution"))
    record, accession, rights = _record(
        label=_v2_text(document.get("label")),
        pairs=pairs,
        nav_date=document.get("navDate"),
        rights=_v2_id(document.get("license")),
        required=("Attribution", attribution) if attribution else None,
        homepage=_v2_id(document.get("related")),
        manifest_id=document_id,
    )
    canvases = []
    for index, canvas in enumerate(sequences[0].get("canvases") or []):
        if not isinstance(canvas, dict) or not isinstance(canvas.get("@id"), str):
            continue
        canvases.append(_canvas_v2(canvas, document_id, index, record, accession, rights))
    return ReadDocument("manifest", document_id, 2, canvases=canvases)


def _canvas_v2(
    canvas: dict[str, Any], manifest_id: str, index: int, record: dict[str, Any], accession: str | None, rights: str | None
) -> IiifCanvas:
    width, height = canvas.get("width"), canvas.get("height")
    label = _v2_text(canvas.get("label")) or f"canvas {index + 1}"
    images = canvas.get("images") or []
    resource = images[0].get("resource") if images and isinstance(images[0], dict) else None
    service = image_id = problem = None
    if not isinstance(resource, dict):
        problem = "the canvas paints no image"
    else:
        if resource.get("@type") == "oa:Choice":
            resource = resource.get("default") or {}
        image_id = resource.get("@id")
        service = _service_of(resource.get("service"))
        if service is None:
            problem = "the canvas's image has no IIIF Image API service"
    return _canvas(
        canvas["@id"], manifest_id, index, (width, height), service, image_id, label, record, accession, rights, problem
    )


# ---- the catalogue record ----


def _record(
    *,
    label: str,
    pairs: list[tuple[str, str]],
    nav_date: Any,
    rights: Any,
    required: tuple[str, str] | None,
    homepage: Any,
    manifest_id: str,
) -> tuple[dict[str, Any], str | None, str | None]:
    """The card's catalogue fields: every metadata pair under its own label, the canonical keys the
    rest of the tool reads (``title``, ``date``, ``url``, ...), and the rights as given."""
    record: dict[str, Any] = {}
    for name, value in pairs:
        if name and value:
            record[name] = value if name not in record else f"{record[name]}; {value}"
    lowered = {name.strip().lower(): value for name, value in record.items()}
    for key, aliases in CANONICAL.items():
        for alias in aliases:
            if alias in lowered and key not in record:
                record[key] = lowered[alias]
    if label:
        record["title"] = label
    if isinstance(nav_date, str) and nav_date:
        record["nav_date"] = nav_date
        record.setdefault("date", nav_date[:10])
    rights_text = rights if isinstance(rights, str) and rights else None
    if rights_text:
        record["rights"] = rights_text
    if required:
        record["required_statement"] = f"{required[0]}: {required[1]}" if required[0] else required[1]
        record.setdefault("credit_line", required[1])
    if isinstance(homepage, str) and homepage:
        record["url"] = homepage
    record["iiif_manifest"] = manifest_id
    accession = next((lowered[name] for name in ACCESSION_COLUMNS if lowered.get(name)), None)
    if accession:
        record["accession"] = accession
    return record, accession, rights_text


# ---- Image API ----


@dataclass(frozen=True)
class ImageRequest:
    url: str
    width: int  # what the service will send
    height: int
    full_width: int  # the image's own size in the service
    full_height: int


def _image_limits(info: dict[str, Any]) -> tuple[int | None, int | None, int | None, int]:
    """(maxWidth, maxHeight, maxArea, compliance level) from an info.json of either version."""
    limits: dict[str, Any] = dict(info)
    level = 0
    profile = info.get("profile")
    for entry in profile if isinstance(profile, list) else [profile]:
        if isinstance(entry, dict):
            limits.update({k: v for k, v in entry.items() if k in ("maxWidth", "maxHeight", "maxArea")})
        elif isinstance(entry, str):
            match = re.search(r"level([012])", entry)
            if match:
                level = max(level, int(match.group(1)))
    if isinstance(profile, str) and profile in ("level0", "level1", "level2"):
        level = int(profile[-1])

    def positive(name: str) -> int | None:
        value = limits.get(name)
        return value if isinstance(value, int) and value > 0 else None

    return positive("maxWidth"), positive("maxHeight"), positive("maxArea"), level


def choose_image_request(service: ImageService, info: dict[str, Any], max_pixels: int) -> ImageRequest:
    """The largest image the service will send within its own limits (maxWidth, maxHeight,
    maxArea) and the project's pixel cap. A level-0 service sends only its full size and the
    ``sizes`` it lists; a level-1 or 2 service scales to any size. Raises :class:`IiifError` when
    no size fits (a level-0 image over the cap)."""
    width, height = info.get("width"), info.get("height")
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise IiifError(f"info.json has no usable width and height (got {width!r} x {height!r})")
    max_width, max_height, max_area, level = _image_limits(info)
    if max_width is not None and max_height is None:
        max_height = max_width  # Image API 3, 5.3: maxHeight defaults to maxWidth
    area_cap = min(max_pixels, max_area) if max_area else max_pixels

    def fits(w: int, h: int) -> bool:
        return w * h <= area_cap and (max_width is None or w <= max_width) and (max_height is None or h <= max_height)

    if fits(width, height):
        path = "full/max/0/default.jpg" if service.version == 3 else "full/full/0/default.jpg"
        return ImageRequest(f"{service.id}/{path}", width, height, width, height)
    candidates: list[tuple[int, int]] = []
    for size in info.get("sizes") or []:
        if isinstance(size, dict) and isinstance(size.get("width"), int) and isinstance(size.get("height"), int):
            candidates.append((size["width"], size["height"]))
    if level >= 1:
        scale = 1.0
        if max_width is not None:
            scale = min(scale, max_width / width)
        if max_height is not None:
            scale = min(scale, max_height / height)
        scale = min(scale, math.sqrt(area_cap / (width * height)))
        candidates.append((max(1, math.floor(width * scale)), max(1, math.floor(height * scale))))
    usable = sorted((c for c in candidates if fits(*c)), key=lambda c: c[0] * c[1])
    if not usable:
        reason = (
            f"{width}x{height} = {width * height:,} pixels is over the pixel cap of {max_pixels:,}"
            if width * height > max_pixels
            else f"{width}x{height} is over the service's own limits"
        )
        raise IiifError(f"{reason} and the service (level {level}) offers no smaller size that fits")
    w, h = usable[-1]
    size = f"{w},{h}" if service.version == 3 else f"{w},"
    return ImageRequest(f"{service.id}/full/{size}/0/default.jpg", w, h, width, height)

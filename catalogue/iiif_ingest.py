"""Ingest from IIIF: each canvas of a manifest (or of every manifest of a collection) becomes a card.

Its image is fetched through the Image API at the largest size the service and the pixel cap
allow (:func:`catalogue.iiif.choose_image_request`), hashed, and stored like any original
(:func:`catalogue.originals.store_original`); the manifest's catalogue fields become the card's
record and the manifest and canvas ids stay on the card (``cards.iiif_canvas_id``, unique, and
``cards.iiif_source``) so a release can point back at the museum's canvas.

Resumable as file ingest is: each card is committed on its own, a canvas already on a card is not
fetched again, and a fetched image whose bytes a card already holds is a duplicate (the canvas id
is then kept on that card if it had none). Every problem (a bad manifest, a canvas without an
Image API service, a 404, a server slower than the timeout, an image over the pixel cap) is a
``rejected`` entry naming the manifest or canvas, and the rest goes on.
"""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from catalogue.iiif import (
    MAX_COLLECTION_DEPTH,
    MAX_DOCUMENT_BYTES,
    IiifCanvas,
    IiifError,
    ImageRequest,
    check_fetchable,
    choose_image_request,
    is_url,
    parse_json,
    read_document,
)
from catalogue.originals import HASH_CHUNK, card_with_hash, database_reason, discard_original, store_original
from core.db import db
from core.models import Card
from pipeline.errors import ImageReadError
from pipeline.io import probe_image
from pipeline.split import MIN_HEIGHT, MIN_WIDTH

if TYPE_CHECKING:
    import requests


class IngestReport(Protocol):
    """What ingest reports into (catalogue.ingest.IngestReport; named here, not imported, so the
    two modules do not import each other)."""

    ingested: list[dict[str, Any]]
    duplicates: list[dict[str, Any]]
    rejected: list[dict[str, str]]


IMAGE_SUFFIXES_BY_TYPE = {"image/jpeg": ".jpg", "image/png": ".png", "image/tiff": ".tif", "image/webp": ".webp"}


@dataclass(frozen=True)
class FetchOptions:
    """How patient ingest is with a museum's server."""

    timeout_s: float = 30.0  # connect and between-bytes read timeout of one request
    retries: int = 2  # more tries after a connection error, a timeout, 429 or 5xx (with backoff)
    image_seconds: float = 600.0  # the most one image download may take, however it trickles
    max_image_bytes: int = 2 << 30


class FetchError(Exception):
    """A request that failed, with the reason for people."""


class IiifClient:
    """requests with urllib3's Retry: timeouts on every request, bounded retries with backoff,
    only http(s) URLs (:func:`catalogue.iiif.check_fetchable`)."""

    def __init__(self, options: FetchOptions) -> None:
        import requests
        from requests.adapters import HTTPAdapter
        from urllib3.util.retry import Retry

        self.options = options
        retry = Retry(
            total=options.retries,
            connect=options.retries,
            read=options.retries,
            status=options.retries,
            backoff_factor=0.2,
            status_forcelist=(429, 500, 502, 503, 504),
            allowed_methods=frozenset({"GET"}),
            raise_on_status=False,
            respect_retry_after_header=False,  # a server asking for an hour would stall the whole ingest
        )
        self.session = requests.Session()
        self.session.trust_env = False  # no proxies or .netrc from the environment
        adapter = HTTPAdapter(max_retries=retry)
        self.session.mount("http://", adapter)
        self.session.mount("https://", adapter)
        self.session.headers["User-Agent"] = "keystone-ingest (IIIF)"

    def close(self) -> None:
        self.session.close()

    def _get(self, url: str, *, accept: str) -> requests.Response:
        import requests

        check_fetchable(url)
        try:
            response = self.session.get(url, timeout=self.options.timeout_s, stream=True, headers={"Accept": accept})
        except requests.RequestException as exc:
            raise FetchError(_request_reason(exc, url, self.options)) from None
        if response.status_code != 200:
            response.close()
            raise FetchError(f"HTTP {response.status_code} {response.reason or ''} from {url}".replace("  ", " "))
        return response

    def get_json(self, url: str) -> dict[str, Any]:
        import requests

        response = self._get(url, accept="application/ld+json, application/json")
        try:
            data = _read_limited(response, MAX_DOCUMENT_BYTES, self.options)
        except requests.RequestException as exc:
            raise FetchError(_request_reason(exc, url, self.options)) from None
        finally:
            response.close()
        return parse_json(data, url)

    def download(self, url: str, folder: Path) -> tuple[Path, str, str]:
        """Stream ``url`` into a new file in ``folder``; returns (path, sha256, the image's file suffix)."""
        import requests

        response = self._get(url, accept="image/*")
        content_type = (response.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        suffix = IMAGE_SUFFIXES_BY_TYPE.get(content_type) or _url_suffix(url)
        # A hidden .tmp name: a download killed halfway is cleared by the next `keystone run`
        # (runs.leftovers), as a killed file ingest's copy is.
        fd, name = tempfile.mkstemp(dir=folder, prefix=".iiif-", suffix=".tmp")
        digest, size, started = hashlib.sha256(), 0, time.monotonic()
        try:
            with os.fdopen(fd, "wb") as out:
                for chunk in response.iter_content(HASH_CHUNK):
                    size += len(chunk)
                    if size > self.options.max_image_bytes:
                        raise FetchError(f"the image from {url} is over {self.options.max_image_bytes:,} bytes")
                    if time.monotonic() - started > self.options.image_seconds:
                        raise FetchError(f"the image from {url} took over {self.options.image_seconds:.0f} s to arrive")
                    digest.update(chunk)
                    out.write(chunk)
        except requests.RequestException as exc:
            Path(name).unlink(missing_ok=True)
            raise FetchError(_request_reason(exc, url, self.options)) from None
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
        finally:
            response.close()
        return Path(name), digest.hexdigest(), suffix


def _read_limited(response: requests.Response, limit: int, options: FetchOptions) -> bytes:
    chunks, size = [], 0
    for chunk in response.iter_content(HASH_CHUNK):
        size += len(chunk)
        if size > limit:
            raise FetchError(f"the document is over {limit:,} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _url_suffix(url: str) -> str:
    match = re.search(r"\.(jpe?g|png|tiff?|webp)$", url.split("?")[0].lower())
    return "." + match.group(1).replace("jpeg", "jpg") if match else ".jpg"


def _request_reason(exc: Exception, url: str, options: FetchOptions) -> str:
    """Why a request failed, in words: a timeout says how long it waited and how often."""
    text, chain = "", exc
    seen = 0
    while chain is not None and seen < 6:
        text += f" {type(chain).__name__} {chain}"
        chain = (
            chain.__cause__
            or chain.__context__
            or (chain.args[0] if chain.args and isinstance(chain.args[0], Exception) else None)
        )
        seen += 1
    tries = options.retries + 1
    if "timed out" in text.lower() or "timeout" in text.lower():
        return f"no answer from {url} within the {options.timeout_s:g} s timeout ({tries} tries)"
    if "too many" in text.lower() and "error responses" in text.lower():
        return f"the server kept failing for {url} ({tries} tries)"
    if "refused" in text.lower():
        return f"cannot connect to {url}: connection refused ({tries} tries)"
    return f"cannot fetch {url}: {type(exc).__name__}"


def gather_canvases(sources: list[str], client: IiifClient, report: IngestReport) -> list[IiifCanvas]:
    """Every canvas of the manifests named (URLs or local files), collections followed to their
    manifests; a document that cannot be read is rejected by its URL or path, the rest goes on."""
    canvases: list[IiifCanvas] = []
    seen: set[str] = set()

    def visit(source: str, depth: int) -> None:
        if source in seen:
            return
        seen.add(source)
        try:
            document = read_document(_load(source, client))
        except (IiifError, FetchError) as exc:
            report.rejected.append({"path": source, "reason": f"IIIF: {exc}"})
            return
        if document.kind == "manifest":
            if not document.canvases:
                report.rejected.append({"path": source, "reason": "IIIF: the manifest has no canvases"})
            canvases.extend(document.canvases)
            return
        if depth >= MAX_COLLECTION_DEPTH:
            report.rejected.append({"path": source, "reason": f"IIIF: collections nested over {MAX_COLLECTION_DEPTH} deep"})
            return
        if not document.members:
            report.rejected.append({"path": source, "reason": "IIIF: the collection lists no manifests"})
        for member in document.members:
            visit(member, depth + 1)

    for source in sources:
        visit(source, 0)
    return canvases


def _load(source: str, client: IiifClient) -> dict[str, Any]:
    if is_url(source):
        return client.get_json(source)
    path = Path(source)
    try:
        if path.stat().st_size > MAX_DOCUMENT_BYTES:
            raise IiifError(f"{source} is over {MAX_DOCUMENT_BYTES:,} bytes")
        data = path.read_bytes()
    except FileNotFoundError:
        raise IiifError("no such file") from None
    except OSError as exc:
        raise IiifError(f"cannot read it: {exc.strerror or exc}") from None
    return parse_json(data, source)


def ingest_canvases(
    canvases: list[IiifCanvas],
    client: IiifClient,
    *,
    collection_id: int,
    data_dir: Path,
    max_pixels: int,
    report: IngestReport,
    on_canvas: Callable[[str], None] | None = None,
) -> None:
    staging = data_dir / "originals" / ".iiif-downloads"
    staging.mkdir(parents=True, exist_ok=True)
    for canvas in canvases:
        ingest_canvas(
            canvas, client, collection_id=collection_id, data_dir=data_dir, max_pixels=max_pixels, report=report, staging=staging
        )
        if on_canvas is not None:
            on_canvas(canvas.canvas_id)


def ingest_canvas(
    canvas: IiifCanvas,
    client: IiifClient,
    *,
    collection_id: int,
    data_dir: Path,
    max_pixels: int,
    report: IngestReport,
    staging: Path,
) -> None:
    def reject(reason: str) -> None:
        report.rejected.append({"path": canvas.canvas_id, "reason": f"IIIF: {reason}"})

    if canvas.problem is not None or canvas.service is None:
        reject(canvas.problem or "the canvas's image has no IIIF Image API service")
        return
    try:
        existing = db.session.scalar(select(Card).where(Card.iiif_canvas_id == canvas.canvas_id))
    except SQLAlchemyError as exc:
        db.session.rollback()
        reject(f"not ingested: the catalogue database cannot be read ({database_reason(exc)})")
        return
    if existing is not None:
        report.duplicates.append(
            {
                "path": canvas.canvas_id,
                "card_id": existing.id,
                "reason": f"canvas already ingested as card {existing.id}; nothing to do",
            }
        )
        return
    try:
        info = client.get_json(f"{canvas.service.id}/info.json")
        request = choose_image_request(canvas.service, info, max_pixels)
        downloaded, content_hash, suffix = client.download(request.url, staging)
    except (IiifError, FetchError) as exc:
        reject(str(exc))
        return
    try:
        _store_canvas(canvas, request, downloaded, suffix, content_hash, collection_id, data_dir, max_pixels, report)
    finally:
        downloaded.unlink(missing_ok=True)


def _iiif_source(canvas: IiifCanvas, request: ImageRequest, width: int, height: int) -> dict[str, Any]:
    assert canvas.service is not None
    return {
        "manifest": canvas.manifest_id,
        "canvas": canvas.canvas_id,
        "canvas_index": canvas.index,
        "canvas_width": canvas.width,
        "canvas_height": canvas.height,
        "canvas_label": canvas.label,
        "service": canvas.service.id,
        "service_version": canvas.service.version,
        "image": canvas.image_id,
        "fetched": request.url,
        "fetched_width": width,  # the stored original's pixels: a crop box maps to the canvas by canvas_width / fetched_width
        "fetched_height": height,
        "service_width": request.full_width,
        "service_height": request.full_height,
        "rights": canvas.rights,
    }


def _store_canvas(
    canvas: IiifCanvas,
    request: ImageRequest,
    downloaded: Path,
    suffix: str,
    content_hash: str,
    collection_id: int,
    data_dir: Path,
    max_pixels: int,
    report: IngestReport,
) -> None:
    def reject(reason: str) -> None:
        report.rejected.append({"path": canvas.canvas_id, "reason": f"IIIF: {reason}"})

    existing = card_with_hash(content_hash)
    if existing is not None:
        _keep_canvas_on(existing, canvas, request)
        report.duplicates.append(
            {
                "path": canvas.canvas_id,
                "card_id": existing.id,
                "reason": f"same content as card {existing.id} ({existing.source_name}); nothing to do",
            }
        )
        return
    try:
        info = probe_image(downloaded, max_pixels=max_pixels)
        if info.width < MIN_WIDTH or info.height < MIN_HEIGHT:
            raise ImageReadError(
                f"too small to be a stereo card: {info.width}x{info.height} px "
                f"(the smallest card the pipeline splits is {MIN_WIDTH}x{MIN_HEIGHT} px)"
            )
        relative = store_original(downloaded, content_hash, data_dir, suffix=suffix)
    except ImageReadError as exc:
        reject(f"the image from {request.url}: {exc}")
        return
    except OSError as exc:
        reject(f"cannot store the image: {exc.strerror or exc}")
        return
    service_name = canvas.service.id.rstrip("/").rsplit("/", 1)[-1] if canvas.service else "canvas"
    card = Card(
        collection_id=collection_id,
        content_hash=content_hash,
        stored_path=str(relative),
        source_name=f"{service_name}{suffix}",
        source_path=request.url,
        accession=canvas.accession,
        width=info.width,
        height=info.height,
        image_format=info.format,
        byte_size=info.byte_size,
        source_metadata=dict(canvas.record),
        iiif_canvas_id=canvas.canvas_id,
        iiif_source=_iiif_source(canvas, request, info.width, info.height),
    )
    try:
        db.session.add(card)
        db.session.commit()
    except SQLAlchemyError as exc:
        db.session.rollback()
        # Another ingest stored the same bytes or the same canvas meanwhile: its card stands.
        existing = card_with_hash(content_hash) or db.session.scalar(select(Card).where(Card.iiif_canvas_id == canvas.canvas_id))
        if existing is not None:
            report.duplicates.append(
                {"path": canvas.canvas_id, "card_id": existing.id, "reason": f"same canvas or content as card {existing.id}"}
            )
            return
        removed = discard_original(data_dir / relative)
        reject(
            f"not recorded: the catalogue database refused the write ({database_reason(exc)}); "
            + ("the stored copy was removed" if removed else f"the stored copy {relative} could not be removed")
        )
        return
    report.ingested.append({"id": card.id, "path": canvas.canvas_id, "content_hash": content_hash})


def _keep_canvas_on(card: Card, canvas: IiifCanvas, request: ImageRequest) -> None:
    """A card ingested from a file before: the canvas it also is goes on it, so a release can
    point back at the museum's canvas (its catalogue record is left as it was)."""
    if card.iiif_canvas_id is not None:
        return
    try:
        card.iiif_canvas_id = canvas.canvas_id
        card.iiif_source = _iiif_source(canvas, request, card.width, card.height)
        db.session.commit()
    except SQLAlchemyError:
        db.session.rollback()

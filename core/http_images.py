"""Serving images with caching headers, for every feature's image routes.

An image URL carries ``?v=<url_version(etag)>``: a response to the current version is cacheable
for a year (``immutable``); any other URL must revalidate with its ETag, so a rerun stage never
leaves a stale image pinned in a browser (RFC 9111 sections 5.2.2.5 and 5.2.2.4 for
``immutable``'s companions ``max-age`` and ``no-cache``; RFC 8246 for ``immutable``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from flask import request
from werkzeug.wrappers import Response

CACHE_FOREVER = "private, max-age=31536000, immutable"
CACHE_REVALIDATE = "private, no-cache"


def url_version(etag: str) -> str:
    """The ``v`` query value that pins a URL to one ETag (16 hex digits of its SHA-256)."""
    return hashlib.sha256(etag.encode()).hexdigest()[:16]


def cache_headers(response: Response, etag: str) -> None:
    """Cache-Control for an image whose current ETag is ``etag``: forever when the request's
    ``v`` names that ETag, revalidate otherwise."""
    pinned = request.args.get("v") == url_version(etag)
    response.headers["Cache-Control"] = CACHE_FOREVER if pinned else CACHE_REVALIDATE
    response.headers.pop("Expires", None)


def not_modified(etag: str) -> Response | None:
    """A 304 with the caching headers when the browser already holds ``etag``, else None."""
    if request.if_none_match.contains(etag):
        response = Response(status=304)
        response.set_etag(etag)
        cache_headers(response, etag)
        return response
    return None


def send_image(image: Path | bytes, mimetype: str, etag: str) -> Response:
    """An image from a file or, when the preview cache could not be written, from memory, with
    its ETag, Last-Modified (for a file), range support and caching headers."""
    # Display images are small (<= 1600 px previews, stage previews), so they are sent from
    # memory: no file handle outlives the request whatever the server or client does.
    response = Response(image if isinstance(image, bytes) else image.read_bytes(), mimetype=mimetype)
    response.set_etag(etag)
    if isinstance(image, Path):
        response.last_modified = image.stat().st_mtime
    response = response.make_conditional(request, accept_ranges=True)
    cache_headers(response, etag)
    return response

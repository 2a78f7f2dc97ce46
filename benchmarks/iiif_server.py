"""A museum's IIIF on loopback: a level-0 static Image API tree and Presentation manifests (3.0
and 2.1) under a folder, served by ``http.server.ThreadingHTTPServer`` in a thread on 127.0.0.1.

Used by the IIIF tests (the ``iiif_server`` fixture) and ``keystone bench iiif``; nothing here
reaches outside the machine.
"""

from __future__ import annotations

import http.server
import json
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image


class StaticIiif:
    """A level-0 static IIIF Image API tree and Presentation manifests under ``root``, served on
    loopback by ``http.server.ThreadingHTTPServer`` in a thread: what a museum's static IIIF host
    serves, with knobs for what goes wrong (a path that answers slowly) and a count of requests."""

    def __init__(self, root: Path) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.delays: dict[str, float] = {}  # path -> seconds to wait before answering
        self.requests: list[str] = []
        served = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                path = self.path.split("?")[0]
                served.requests.append(path)
                delay = served.delays.get(path)
                if delay:
                    time.sleep(delay)
                super().do_GET()

            def guess_type(self, path: Any) -> str:
                return "application/ld+json" if str(path).endswith(".json") else super().guess_type(path)

            def log_message(self, *args: Any) -> None:
                pass

        class Server(http.server.ThreadingHTTPServer):
            def handle_error(self, request: Any, client_address: Any) -> None:
                pass  # a client that hung up (the killed ingest, a timed-out request): nothing to report

        self.server = Server(("127.0.0.1", 0), partial(Handler, directory=str(root)))
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    def add_image(self, name: str, image: np.ndarray, *, version: int = 3, **limits: Any) -> str:
        """Write ``image/<name>/`` as a level-0 tree (info.json and the full-size JPEG at the
        version's path); ``limits`` go into info.json (maxWidth, ...). Returns the service id."""
        service = f"{self.url}/image/{name}"
        folder = self.root / "image" / name
        full = "full/max/0" if version == 3 else "full/full/0"
        (folder / full).mkdir(parents=True, exist_ok=True)
        Image.fromarray(image).save(folder / full / "default.jpg", format="JPEG", quality=95)
        height, width = image.shape[:2]
        if version == 3:
            info: dict[str, Any] = {
                "@context": "http://iiif.io/api/image/3/context.json",
                "id": service,
                "type": "ImageService3",
                "protocol": "http://iiif.io/api/image",
                "profile": "level0",
                "width": width,
                "height": height,
                **limits,
            }
        else:
            info = {
                "@context": "http://iiif.io/api/image/2/context.json",
                "@id": service,
                "protocol": "http://iiif.io/api/image",
                "profile": ["http://iiif.io/api/image/2/level0.json", limits]
                if limits
                else "http://iiif.io/api/image/2/level0.json",
                "width": width,
                "height": height,
            }
        (folder / "info.json").write_text(json.dumps(info))
        return service

    def add_document(self, name: str, document: dict[str, Any]) -> str:
        (self.root / name).parent.mkdir(parents=True, exist_ok=True)
        (self.root / name).write_text(json.dumps(document))
        return f"{self.url}/{name}"

    def manifest_v3(
        self, name: str, label: str, canvases: list[tuple[str, int, int, str | None]], **extra: Any
    ) -> dict[str, Any]:
        """A Presentation 3 manifest at ``<url>/<name>``; each canvas is (id suffix, width,
        height, image service id or None for an image without a service)."""
        manifest_id = f"{self.url}/{name}"
        items = []
        for suffix, width, height, service in canvases:
            canvas_id = f"{manifest_id}/canvas/{suffix}"
            body: dict[str, Any] = {
                "id": f"{service or self.url + '/plain/' + suffix}/full/max/0/default.jpg",
                "type": "Image",
                "format": "image/jpeg",
                "width": width,
                "height": height,
            }
            if service is not None:
                body["service"] = [{"id": service, "type": "ImageService3", "profile": "level0"}]
            items.append(
                {
                    "id": canvas_id,
                    "type": "Canvas",
                    "label": {"en": [f"{label}, {suffix}"]},
                    "width": width,
                    "height": height,
                    "items": [
                        {
                            "id": f"{canvas_id}/page",
                            "type": "AnnotationPage",
                            "items": [
                                {
                                    "id": f"{canvas_id}/page/painting",
                                    "type": "Annotation",
                                    "motivation": "painting",
                                    "body": body,
                                    "target": canvas_id,
                                }
                            ],
                        }
                    ],
                }
            )
        return {
            "@context": "http://iiif.io/api/presentation/3/context.json",
            "id": manifest_id,
            "type": "Manifest",
            "label": {"en": [label]},
            "items": items,
            **extra,
        }

    def manifest_v2(
        self, name: str, label: str, canvases: list[tuple[str, int, int, str | None]], **extra: Any
    ) -> dict[str, Any]:
        manifest_id = f"{self.url}/{name}"
        items = []
        for suffix, width, height, service in canvases:
            canvas_id = f"{manifest_id}/canvas/{suffix}"
            resource: dict[str, Any] = {
                "@id": f"{service or self.url + '/plain/' + suffix}/full/full/0/default.jpg",
                "@type": "dctypes:Image",
                "format": "image/jpeg",
                "width": width,
                "height": height,
            }
            if service is not None:
                resource["service"] = {
                    "@context": "http://iiif.io/api/image/2/context.json",
                    "@id": service,
                    "profile": "http://iiif.io/api/image/2/level0.json",
                }
            items.append(
                {
                    "@id": canvas_id,
                    "@type": "sc:Canvas",
                    "label": f"{label}, {suffix}",
                    "width": width,
                    "height": height,
                    "images": [{"@type": "oa:Annotation", "motivation": "sc:painting", "resource": resource, "on": canvas_id}],
                }
            )
        return {
            "@context": "http://iiif.io/api/presentation/2/context.json",
            "@id": manifest_id,
            "@type": "sc:Manifest",
            "label": label,
            "sequences": [{"@type": "sc:Sequence", "canvases": items}],
            **extra,
        }

"""``keystone bench iiif``: IIIF in and out on real cards served on loopback, end to end.

The cards of ``--cards-dir`` (default: the real NYPL cards in shared/data/stereocards/full_cards)
are served as a museum would: a level-0 static Image API tree, one manifest per card (even ones
Presentation 3, odd ones 2.1, with label, metadata, rights, attribution and homepage), all in
one Presentation 3 collection, on 127.0.0.1. Then, on a throwaway instance:

1. ``keystone ingest COLLECTION`` in a child process, killed (SIGKILL) while the image after
   ``--kill-after`` is on its way, and run again: each canvas must be one card.
2. With ``--release``: an operator's word that the scans are upright positives in eye order,
   ``keystone run`` (the default stages), every card the grader passed accepted, a release with
   the default formats, ``keystone verify``, and each crop box of ``iiif/manifest.json`` compared
   with the crop the pipeline released (the canvas's ``xywh`` cut from the served image).

Prints figures: canvases, cards, seconds, refusals with their reasons, boxes on the right pixels.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CARDS = Path(os.environ.get("KEYSTONE_SHARED_DATA", REPO.parent / "shared" / "data")) / "stereocards" / "full_cards"
RIGHTS = "https://creativecommons.org/publicdomain/mark/1.0/"


def serve_cards(
    folder: Path, root: Path, canvas_scale: int = 1, faults: bool = False
) -> tuple[Any, str, list[str], dict[str, np.ndarray]]:
    """A StaticIiif serving every image of ``folder`` (canvases ``canvas_scale`` times the served
    size, as a museum whose canvas is its master scan's); ``faults`` adds a manifest whose canvases
    a museum's server lets down (a 404, no service, over the pixel cap) and a manifest that is gone.
    Returns (server, collection URL, canvas ids that should become cards, images as served)."""
    from PIL import Image

    from benchmarks.iiif_server import StaticIiif

    server = StaticIiif(root)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))
    manifests, canvases, images = [], [], {}
    for number, path in enumerate(files):
        with Image.open(path) as opened:
            array = np.asarray(opened.convert("RGB"))
        version = 3 if number % 2 == 0 else 2
        service = server.add_image(path.stem, array, version=version)
        images[path.stem] = np.asarray(
            Image.open(root / "image" / path.stem / ("full/max/0" if version == 3 else "full/full/0") / "default.jpg").convert(
                "RGB"
            )
        )
        name = f"manifests/{path.stem}.json"
        canvas = [(path.stem, array.shape[1] * canvas_scale, array.shape[0] * canvas_scale, service)]
        title = path.stem.removeprefix("nypl_").replace("_", " ")
        if version == 3:
            document = server.manifest_v3(
                name,
                title,
                canvas,
                metadata=[{"label": {"en": ["Source file"]}, "value": {"none": [path.name]}}],
                rights=RIGHTS,
                requiredStatement={"label": {"en": ["Attribution"]}, "value": {"en": ["The New York Public Library"]}},
                homepage=[
                    {
                        "id": f"https://digitalcollections.example.org/items/{path.stem}",
                        "type": "Text",
                        "label": {"en": ["Record"]},
                    }
                ],
            )
        else:
            document = server.manifest_v2(
                name,
                title,
                canvas,
                metadata=[{"label": "Source file", "value": path.name}],
                license=RIGHTS,
                attribution="The New York Public Library",
                related=f"https://digitalcollections.example.org/items/{path.stem}",
            )
        manifests.append(server.add_document(name, document))
        canvases.append(f"{server.url}/{name}/canvas/{path.stem}")
    if faults:
        over_cap = server.add_image("over-cap", np.full((1, 1, 3), 128, np.uint8))
        info = root / "image" / "over-cap" / "info.json"
        info.write_text(info.read_text().replace('"width": 1,', '"width": 24000,').replace('"height": 1', '"height": 13000'))
        broken = [
            ("gone", 2000, 1000, f"{server.url}/image/gone"),
            ("no-service", 2000, 1000, None),
            ("over-cap", 24000, 13000, over_cap),
        ]
        manifests.append(
            server.add_document("manifests/faults.json", server.manifest_v3("manifests/faults.json", "Faults", broken))
        )
        manifests.append(f"{server.url}/manifests/withdrawn.json")
    collection = server.add_document(
        "collection.json",
        {
            "@context": "http://iiif.io/api/presentation/3/context.json",
            "id": f"{server.url}/collection.json",
            "type": "Collection",
            "label": {"en": ["Stereo cards"]},
            "items": [{"id": url, "type": "Manifest", "label": {"en": [Path(url).stem]}} for url in manifests],
        },
    )
    return server, collection, canvases, images


def _ingest(command: list[str], env: dict[str, str]) -> tuple[dict[str, Any], float, int]:
    started = time.perf_counter()
    done = subprocess.run(command, env=env, cwd=REPO, capture_output=True, text=True, timeout=1800, check=False)
    seconds = time.perf_counter() - started
    try:
        return json.loads(done.stdout), seconds, done.returncode
    except ValueError:
        raise click.ClickException(f"ingest printed no JSON (exit {done.returncode}): {done.stderr[-2000:]}") from None


def run_bench(
    cards_dir: Path, kill_after: int | None, release: bool, work: Path, canvas_scale: int = 1, faults: bool = False
) -> dict[str, Any]:
    server, collection, canvas_ids, images = serve_cards(cards_dir, work / "iiif", canvas_scale, faults)
    try:
        (work / "instance").mkdir()
        env = {
            **os.environ,
            "KEYSTONE_INSTANCE_PATH": str(work / "instance"),
            "KEYSTONE_DATA_DIR": str(work / "data"),
            "KEYSTONE_DATABASE_URL": f"sqlite:///{work / 'instance' / 'keystone.sqlite3'}",
            "KEYSTONE_SECRET_KEY": "bench",
            "PYTHONPATH": str(REPO),
        }
        command = [sys.executable, "-m", "app", "ingest", collection, "--json"]
        kill_after = len(canvas_ids) // 2 if kill_after is None else kill_after
        images_requested = [p for p in server.requests]  # manifests only so far
        held = None
        if 0 < kill_after < len(canvas_ids):
            held = f"/image/{Path(canvas_ids[kill_after]).name}/"
            server.delays.update({f"{held}full/max/0/default.jpg": 60.0, f"{held}full/full/0/default.jpg": 60.0})
        started = time.perf_counter()
        killed_at = None
        if held is not None:
            with subprocess.Popen(command, env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as first:
                for _ in range(3000):  # 300 s at most
                    if any(p.startswith(held) and p.endswith("default.jpg") for p in server.requests) or first.poll() is not None:
                        break
                    time.sleep(0.1)
                first.send_signal(signal.SIGKILL)
                first.wait(timeout=30)
            killed_at = time.perf_counter() - started
            server.delays.clear()
        with sqlite3.connect(work / "instance" / "keystone.sqlite3") as connection:
            cards_after_kill = connection.execute("SELECT count(*) FROM cards").fetchone()[0]
        report, rerun_seconds, exit_code = _ingest(command, env)
        with sqlite3.connect(work / "instance" / "keystone.sqlite3") as connection:
            per_canvas = dict(connection.execute("SELECT iiif_canvas_id, count(*) FROM cards GROUP BY iiif_canvas_id").fetchall())
            titles = dict(
                connection.execute("SELECT iiif_canvas_id, json_extract(source_metadata, '$.title') FROM cards").fetchall()
            )
        again, again_seconds, _ = _ingest(command, env)
        result: dict[str, Any] = {
            "canvases": len(canvas_ids),
            "killed_after_seconds": None if killed_at is None else round(killed_at, 2),
            "cards_after_kill": cards_after_kill,
            "rerun": {
                "ingested": report["ingested"],
                "duplicates": report["duplicates"],
                "rejected": report["rejected"],
                "exit_code": exit_code,
                "seconds": round(rerun_seconds, 2),
            },
            "third_run": {"ingested": again["ingested"], "duplicates": again["duplicates"], "seconds": round(again_seconds, 2)},
            "cards": sum(per_canvas.values()),
            "canvases_on_more_than_one_card": sorted(c for c, n in per_canvas.items() if n != 1),
            "canvases_without_card": sorted(set(canvas_ids) - set(per_canvas)),
            "canvas_scale": canvas_scale,
            "image_requests": sum(1 for p in server.requests if p.endswith("default.jpg")),
            "titles": titles,
            "requests_before_ingest": len(images_requested),
        }
        if release:
            result["release"] = _release(work, env, images)
        return result
    finally:
        server.close()


def _release(work: Path, env: dict[str, str], images: dict[str, np.ndarray]) -> dict[str, Any]:
    """Run the pipeline on the ingested cards, accept what the grader passed, release, verify, and
    check each box of the release's IIIF manifest against the crop the pipeline released."""

    def keystone(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "app", *args], env=env, cwd=REPO, capture_output=True, text=True, timeout=3600, check=False
        )

    from PIL import Image

    word = keystone("orientation", "set", "--collection", "default", "--upside-down", "no", "--inverted", "no", "--swapped", "no")
    if word.returncode != 0:
        raise click.ClickException(f"orientation set failed: {word.stderr[-2000:]}")
    started = time.perf_counter()
    ran = keystone("run", "--json")
    run_seconds = time.perf_counter() - started
    keystone(
        "users", "add", "bench-curator", "--role", "curator", "--password", "bench-curator-password", "--name", "Bench curator"
    )
    accepted = keystone_python(env, ACCEPT_PASSED)
    out = work / "releases"
    exported = keystone("export", "--out", str(out), "--json")
    if exported.returncode != 0:
        return {
            "run_seconds": round(run_seconds, 1),
            "run_exit": ran.returncode,
            "accepted": accepted,
            "export_error": exported.stdout[-2000:] + exported.stderr[-2000:],
        }
    report = json.loads(exported.stdout)
    root = Path(report["path"])
    verified = keystone("verify", str(root), "--json")
    manifest = json.loads((root / "iiif" / "manifest.json").read_text())
    checked, exact, worst = 0, 0, 0
    for canvas in manifest["items"]:
        name = canvas["id"].rsplit("/", 1)[-1]
        image = images[name]
        key = next(m["value"]["none"][0] for m in canvas["metadata"] if m["label"]["en"] == ["Keystone card"])
        for annotation in canvas["annotations"][0]["items"]:
            eye = annotation["id"].rsplit("#", 1)[-1]
            if eye not in ("left_eye", "right_eye"):
                continue
            x, y, w, h = (int(v) for v in annotation["target"]["selector"]["value"].removeprefix("xywh=").split(","))
            sx, sy = canvas["width"] / image.shape[1], canvas["height"] / image.shape[0]
            region = image[round(y / sy) : round((y + h) / sy), round(x / sx) : round((x + w) / sx)]
            cropped = np.asarray(
                Image.open(root / "cropped" / "cropped_full_LR" / f"{key}{'L' if eye == 'left_eye' else 'R'}.png").convert("RGB")
            )
            checked += 1
            if region.shape == cropped.shape:
                difference = int(np.abs(region.astype(int) - cropped.astype(int)).max())
                worst = max(worst, difference)
                exact += difference == 0
            else:
                worst = 255
    return {
        "run_seconds": round(run_seconds, 1),
        "run_exit": ran.returncode,
        "accepted": accepted,
        "released_cards": report["cards"],
        "version": report["version"],
        "verify_exit": verified.returncode,
        "verify": json.loads(verified.stdout) if verified.stdout.strip().startswith("{") else verified.stdout[-1000:],
        "canvases_in_manifest": len(manifest["items"]),
        "boxes_checked": checked,
        "boxes_on_exact_pixels": exact,
        "worst_pixel_difference": worst,
        "croissant_license": json.loads((root / "croissant.json").read_text())["license"],
        "manifest": str(root / "iiif" / "manifest.json"),
    }


ACCEPT_PASSED = """
import json
from sqlalchemy import select
from app import create_app
from core.db import db
from core.models import Person
from review.models import CardReview
from review.tasks import decide, sync_reviews
app = create_app()
with app.app_context():
    sync_reviews()
    curator = db.session.scalar(select(Person).where(Person.username == "bench-curator"))
    outcome = {"accepted": [], "left": {}}
    for review in db.session.scalars(select(CardReview).order_by(CardReview.card_id)):
        if review.decision == "pending" and review.auto_grade in ("few", "some"):
            decide(review.id, "accept", expected_version=review.version, curator=curator, note="bench: accepted as graded")
            outcome["accepted"].append(review.card_id)
        else:
            outcome["left"][review.card_id] = review.auto_grade or review.decision
    print(json.dumps(outcome))
"""


def keystone_python(env: dict[str, str], code: str) -> Any:
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True, timeout=600, check=False
    )
    if done.returncode != 0:
        return {"error": done.stderr[-2000:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


@click.command("iiif")
@click.option("--cards-dir", type=click.Path(path_type=Path, file_okay=False), default=DEFAULT_CARDS, show_default=True)
@click.option(
    "--kill-after", type=int, default=None, help="Kill the first ingest while this image is on its way (default: half)."
)
@click.option("--release/--no-release", default=True, show_default=True, help="Run the pipeline, release and check the boxes.")
@click.option("--canvas-scale", type=click.IntRange(1, 8), default=2, show_default=True, help="Canvas size / served image size.")
@click.option("--faults/--no-faults", default=False, show_default=True, help="Add canvases and a manifest that fail.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON document.")
def bench_iiif_command(
    cards_dir: Path, kill_after: int | None, release: bool, canvas_scale: int, faults: bool, as_json: bool
) -> None:
    """IIIF in and out on cards served on loopback: a killed ingest and its rerun, then a release
    whose manifest's crop boxes are checked against the pipeline's crops."""
    if not cards_dir.is_dir():
        raise click.ClickException(f"{cards_dir} not present: give --cards-dir")
    with tempfile.TemporaryDirectory(prefix="keystone-bench-iiif-") as folder:
        result = run_bench(cards_dir, kill_after, release, Path(folder), canvas_scale, faults)
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    rerun = result["rerun"]
    click.echo(
        f"{result['canvases']} canvases; first ingest killed after {result['killed_after_seconds']} s with "
        f"{result['cards_after_kill']} cards; rerun: {rerun['ingested']} ingested, {rerun['duplicates']} duplicates, "
        f"{len(rerun['rejected'])} rejected in {rerun['seconds']} s; {result['cards']} cards in all"
    )
    for entry in rerun["rejected"]:
        click.echo(f"  rejected {entry['path']}: {entry['reason']}")
    if "release" in result:
        click.echo(json.dumps(result["release"], indent=1))

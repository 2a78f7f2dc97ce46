"""`keystone ingest` from IIIF: manifests (3.0 and 2.1) and collections served on loopback by a
level-0 static Image API tree (the ``iiif_server`` fixture), cards from the demo's synthetic
scans; a kill halfway and a rerun, and every way a museum's server can let us down."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def demo_scans() -> list[np.ndarray]:
    """Four of the demo's synthetic stereo cards (simulation.cards), made once for the module."""
    from simulation.cards import make_stereo_card

    return [make_stereo_card(seed=7, index=i).image for i in range(4)]


def _cards(app) -> list:  # type: ignore[no-untyped-def]
    from core.db import db
    from core.models import Card

    with app.app_context():
        cards = list(db.session.scalars(select(Card).order_by(Card.id)))
        db.session.expunge_all()
        return cards


def test_manifests_of_both_versions_become_cards_with_their_catalogue_records(app, runner, iiif_server, demo_scans):
    first = iiif_server.add_image("card-1", demo_scans[0], version=3)
    second = iiif_server.add_image("card-2", demo_scans[1], version=2)
    height, width = demo_scans[0].shape[:2]
    v3 = iiif_server.manifest_v3(
        "m/one.json",
        "Niagara Falls from the Canadian side",
        [("front", width * 2, height * 2, first)],
        metadata=[
            {"label": {"en": ["Creator"]}, "value": {"none": ["Kilburn Brothers"]}},
            {"label": {"en": ["Accession Number"]}, "value": {"none": ["1996.0009.17827"]}},
        ],
        navDate="1875-01-01T00:00:00Z",
        rights="http://rightsstatements.org/vocab/NoC-US/1.0/",
        requiredStatement={"label": {"en": ["Attribution"]}, "value": {"en": ["The Example Museum"]}},
        homepage=[{"id": "https://museum.example.org/objects/17827", "type": "Text", "label": {"en": ["Object page"]}}],
    )
    v2 = iiif_server.manifest_v2(
        "m/two.json",
        "Broadway, New York",
        [("front", width, height, second)],
        metadata=[{"label": "Date", "value": "ca. 1890"}, {"label": "Publisher", "value": "Underwood & Underwood"}],
        license="https://creativecommons.org/publicdomain/mark/1.0/",
        attribution="The Example Library",
        related="https://library.example.org/items/42",
    )
    urls = [iiif_server.add_document("m/one.json", v3), iiif_server.add_document("m/two.json", v2)]
    result = runner.invoke(args=["ingest", *urls, "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert (report["ingested"], report["duplicates"], report["rejected"]) == (2, 0, [])

    one, two = _cards(app)
    assert one.iiif_canvas_id == f"{urls[0]}/canvas/front"
    assert (one.width, one.height) == (width, height)
    assert one.accession == "1996.0009.17827"
    assert one.source_metadata["title"] == "Niagara Falls from the Canadian side"
    assert one.source_metadata["creator"] == "Kilburn Brothers"
    assert one.source_metadata["date"] == "1875-01-01"
    assert one.source_metadata["rights"] == "http://rightsstatements.org/vocab/NoC-US/1.0/"
    assert one.source_metadata["required_statement"] == "Attribution: The Example Museum"
    assert one.source_metadata["url"] == "https://museum.example.org/objects/17827"
    assert one.iiif_source["manifest"] == urls[0]
    assert one.iiif_source["service"] == first and one.iiif_source["service_version"] == 3
    assert (one.iiif_source["canvas_width"], one.iiif_source["fetched_width"]) == (width * 2, width)
    assert one.iiif_source["fetched"] == f"{first}/full/max/0/default.jpg"

    assert two.iiif_source["fetched"] == f"{second}/full/full/0/default.jpg"
    assert two.source_metadata["title"] == "Broadway, New York"
    assert two.source_metadata["date"] == "ca. 1890"
    assert two.source_metadata["publisher"] == "Underwood & Underwood"
    assert two.source_metadata["rights"] == "https://creativecommons.org/publicdomain/mark/1.0/"
    assert two.source_metadata["credit_line"] == "The Example Library"
    assert two.source_metadata["url"] == "https://library.example.org/items/42"
    # the stored original is the bytes the service sent, stored like any file's
    data_dir = Path(app.config["KEYSTONE_DATA_DIR"])
    served = iiif_server.root / "image" / "card-1" / "full" / "max" / "0" / "default.jpg"
    assert (data_dir / one.stored_path).read_bytes() == served.read_bytes()


def test_a_collection_is_followed_to_its_manifests_and_a_rerun_fetches_nothing_twice(app, runner, iiif_server, demo_scans):
    h, w = demo_scans[0].shape[:2]
    services = [iiif_server.add_image(f"c{i}", demo_scans[i]) for i in range(2)]
    manifests = [
        iiif_server.add_document(f"c/{i}.json", iiif_server.manifest_v3(f"c/{i}.json", f"Card {i}", [("f", w, h, services[i])]))
        for i in range(2)
    ]
    collection = iiif_server.add_document(
        "c/all.json",
        {
            "@context": "http://iiif.io/api/presentation/3/context.json",
            "id": f"{iiif_server.url}/c/all.json",
            "type": "Collection",
            "label": {"en": ["Stereo cards"]},
            "items": [{"id": url, "type": "Manifest", "label": {"en": [f"Card {i}"]}} for i, url in enumerate(manifests)],
        },
    )
    first = runner.invoke(args=["ingest", collection, "--json"])
    assert first.exit_code == 0, first.output
    assert json.loads(first.output)["ingested"] == 2
    images_before = sum(1 for path in iiif_server.requests if path.endswith("default.jpg"))
    again = json.loads(runner.invoke(args=["ingest", collection, "--json"]).output)
    assert (again["ingested"], again["duplicates"]) == (0, 2)
    assert all("canvas already ingested" in entry["reason"] for entry in again["duplicate_files"])
    assert sum(1 for path in iiif_server.requests if path.endswith("default.jpg")) == images_before == 2


def test_an_ingest_interrupted_mid_run_and_rerun_leaves_each_canvas_once(app, runner, iiif_server, demo_scans):
    """An exception after the second canvas (a crash mid-run), then the same command again."""
    from catalogue.ingest import ingest
    from core.db import db
    from core.models import Card

    h, w = demo_scans[0].shape[:2]
    services = [iiif_server.add_image(f"k{i}", demo_scans[i]) for i in range(4)]
    url = iiif_server.add_document(
        "k.json", iiif_server.manifest_v3("k.json", "Four cards", [(f"c{i}", w, h, services[i]) for i in range(4)])
    )

    class Crash(Exception):
        pass

    done: list[str] = []

    def crash_after_two(canvas_id: str) -> None:
        done.append(canvas_id)
        if len(done) == 2:
            raise Crash

    with app.app_context(), pytest.raises(Crash):
        ingest([url], data_dir=Path(app.config["KEYSTONE_DATA_DIR"]), max_pixels=10**8, on_file=crash_after_two)
    assert len(_cards(app)) == 2
    rerun = json.loads(runner.invoke(args=["ingest", url, "--json"]).output)
    assert (rerun["ingested"], rerun["duplicates"], rerun["rejected"]) == (2, 2, [])
    with app.app_context():
        per_canvas = db.session.execute(select(Card.iiif_canvas_id, func.count()).group_by(Card.iiif_canvas_id)).all()
    assert sorted(per_canvas) == [(f"{url}/canvas/c{i}", 1) for i in range(4)]


def test_an_ingest_killed_halfway_and_rerun_leaves_each_canvas_once(tmp_path, iiif_server, demo_scans):
    """A real ``python -m app ingest`` killed (SIGKILL) while the third image is on its way, then
    run again: four canvases, four cards, no stray file in the store."""
    h, w = demo_scans[0].shape[:2]
    services = [iiif_server.add_image(f"s{i}", demo_scans[i]) for i in range(4)]
    url = iiif_server.add_document(
        "s.json", iiif_server.manifest_v3("s.json", "Four cards", [(f"c{i}", w, h, services[i]) for i in range(4)])
    )
    third = "/image/s2/full/max/0/default.jpg"
    iiif_server.delays[third] = 30.0  # the kill comes while it waits
    (tmp_path / "instance").mkdir()
    env = {
        **os.environ,
        "KEYSTONE_INSTANCE_PATH": str(tmp_path / "instance"),
        "KEYSTONE_DATA_DIR": str(tmp_path / "data"),
        "KEYSTONE_DATABASE_URL": f"sqlite:///{tmp_path / 'instance' / 'keystone.sqlite3'}",
        "KEYSTONE_SECRET_KEY": "test-secret",
        "PYTHONPATH": str(REPO),
    }
    command = [sys.executable, "-m", "app", "ingest", url, "--json", "--timeout", "60"]
    with subprocess.Popen(command, env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as process:
        for _ in range(1200):  # bounded: 120 s at most
            if third in iiif_server.requests or process.poll() is not None:
                break
            time.sleep(0.1)
        assert third in iiif_server.requests, f"the first run ended early with {process.returncode}"
        process.send_signal(signal.SIGKILL)
    iiif_server.delays.clear()
    done = subprocess.run(command, env=env, cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout)
    assert (report["ingested"], report["duplicates"], report["rejected"]) == (2, 2, [])
    import sqlite3

    with sqlite3.connect(tmp_path / "instance" / "keystone.sqlite3") as connection:
        rows = connection.execute("SELECT iiif_canvas_id, count(*) FROM cards GROUP BY iiif_canvas_id ORDER BY 1").fetchall()
    assert rows == [(f"{url}/canvas/c{i}", 1) for i in range(4)]
    stored = [p for p in (tmp_path / "data" / "originals").rglob("*") if p.is_file()]
    assert len(stored) == 4  # the killed download left nothing behind that a card does not own... or was removed
    assert not any(p.name.startswith(".") for p in stored)


def test_each_broken_canvas_and_manifest_gets_a_reason_and_the_rest_goes_on(app, runner, iiif_server, demo_scans, tmp_path):
    h, w = demo_scans[0].shape[:2]
    good = iiif_server.add_image("good", demo_scans[0])
    big = iiif_server.add_image("big", np.zeros((900, 1800, 3), np.uint8) + 128)
    app.config["KEYSTONE_MAX_PIXELS"] = 1_500_000  # the demo card (about 0.95 MP) fits, 1800 x 900 does not
    manifest = iiif_server.manifest_v3(
        "bad/m.json",
        "Mixed",
        [
            ("good", w, h, good),
            ("missing", w, h, f"{iiif_server.url}/image/nowhere"),  # 404 on info.json
            ("noservice", w, h, None),
            ("big", 1800, 900, big),
        ],
    )
    url = iiif_server.add_document("bad/m.json", manifest)
    not_json = iiif_server.add_document("bad/notjson.json", {})
    (iiif_server.root / "bad" / "notjson.json").write_text("<html>not a manifest</html>")
    no_type = iiif_server.add_document(
        "bad/invalid.json", {"@context": "http://iiif.io/api/presentation/3/context.json", "id": "x", "type": "Manifest"}
    )
    local = tmp_path / "local.json"
    local.write_text(json.dumps(iiif_server.manifest_v3("local.json", "Local", [("l", w, h, "file:///etc")])))
    result = runner.invoke(
        args=["ingest", url, not_json, no_type, f"{iiif_server.url}/bad/gone.json", "file:///etc/passwd", str(local), "--json"]
    )
    assert result.exit_code == 1, result.output
    report = json.loads(result.output)
    reasons = {entry["path"]: entry["reason"] for entry in report["rejected"]}
    assert report["ingested"] == 1
    assert "HTTP 404" in reasons[f"{url}/canvas/missing"]
    assert "no IIIF Image API service" in reasons[f"{url}/canvas/noservice"]
    assert "over the pixel cap of 1,500,000" in reasons[f"{url}/canvas/big"]
    assert "not JSON" in reasons[not_json]
    assert "not a valid IIIF Presentation 3 manifest" in reasons[no_type]
    assert "HTTP 404" in reasons[f"{iiif_server.url}/bad/gone.json"]
    assert "only http and https" in reasons["file:///etc/passwd"]
    assert "only http and https" in reasons[f"{iiif_server.url}/local.json/canvas/l"]
    assert len(reasons) == 8
    assert not any(path.startswith("/etc") for path in iiif_server.requests)


def test_a_slow_server_hits_the_timeout_with_a_reason(app, runner, iiif_server, demo_scans):
    h, w = demo_scans[0].shape[:2]
    slow = iiif_server.add_image("slow", demo_scans[0])
    fast = iiif_server.add_image("fast", demo_scans[1])
    iiif_server.delays["/image/slow/info.json"] = 3.0
    url = iiif_server.add_document(
        "slow.json", iiif_server.manifest_v3("slow.json", "Slow", [("slow", w, h, slow), ("fast", w, h, fast)])
    )
    result = runner.invoke(args=["ingest", url, "--timeout", "0.3", "--json"])
    assert result.exit_code == 1, result.output
    report = json.loads(result.output)
    assert report["ingested"] == 1
    [rejected] = report["rejected"]
    assert rejected["path"] == f"{url}/canvas/slow"
    assert "within the 0.3 s timeout (3 tries)" in rejected["reason"]
    assert iiif_server.requests.count("/image/slow/info.json") == 3


def test_the_largest_size_within_the_service_limits_and_the_cap_is_requested():
    from catalogue.iiif import IiifError, ImageService, choose_image_request

    v3, v2 = ImageService("http://h/i", 3), ImageService("http://h/i", 2)
    info = {"width": 4000, "height": 2000, "profile": "level2", "maxWidth": 3000}
    request = choose_image_request(v3, info, max_pixels=10**8)
    assert (request.url, request.width, request.height) == ("http://h/i/full/3000,1500/0/default.jpg", 3000, 1500)
    request = choose_image_request(v2, {"width": 4000, "height": 2000, "profile": ["level2", {"maxArea": 2_000_000}]}, 10**8)
    assert (request.url, request.width, request.height) == ("http://h/i/full/2000,/0/default.jpg", 2000, 1000)
    request = choose_image_request(v3, {"width": 4000, "height": 2000, "profile": "level2"}, max_pixels=2_000_000)
    assert (request.width, request.height) == (2000, 1000)
    sizes = {
        "width": 4000,
        "height": 2000,
        "profile": "level0",
        "sizes": [{"width": 1000, "height": 500}, {"width": 2000, "height": 1000}],
    }
    assert choose_image_request(v3, sizes, max_pixels=3_000_000).url == "http://h/i/full/2000,1000/0/default.jpg"
    with pytest.raises(IiifError, match="over the pixel cap"):
        choose_image_request(v3, {"width": 4000, "height": 2000, "profile": "level0"}, max_pixels=1_000_000)


def test_real_cards_served_as_iiif_become_cards(app, runner, iiif_server, shared_data):
    """Three of the real NYPL cards, served as a level-0 tree, ingest with their records."""
    from PIL import Image

    folder = shared_data / "stereocards" / "full_cards"
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))[:3]
    canvases = []
    for path in files:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB"))
        service = iiif_server.add_image(path.stem, array)
        canvases.append((path.stem, array.shape[1], array.shape[0], service))
    url = iiif_server.add_document("real.json", iiif_server.manifest_v3("real.json", "NYPL stereographs", canvases))
    result = runner.invoke(args=["ingest", url, "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["ingested"] == len(files)
    assert {card.iiif_canvas_id for card in _cards(app)} == {f"{url}/canvas/{p.stem}" for p in files}


def test_a_download_killed_halfway_is_a_temporary_file_the_next_run_clears(tmp_path):
    """Downloads go to a hidden ``.tmp`` file in the store; the one a killed ingest leaves is
    removed by ``keystone run``'s leftovers sweep once untouched for ten minutes."""
    from runs.leftovers import remove_leftovers

    staging = tmp_path / "originals" / ".iiif-downloads"
    staging.mkdir(parents=True)
    left = staging / ".iiif-k1ll3d.tmp"
    left.write_bytes(b"\xff\xd8 half a jpeg")
    os.utime(left, (time.time() - 3600, time.time() - 3600))
    fresh = staging / ".iiif-running.tmp"
    fresh.write_bytes(b"\xff\xd8 being written")
    report = remove_leftovers(tmp_path)
    assert report.paths == [str(left)] and not left.exists() and fresh.exists()

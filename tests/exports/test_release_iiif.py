"""A release gives back to the museum: cards ingested from IIIF (a level-0 tree on loopback) go
through the real pipeline and come out as ``iiif/manifest.json``, whose annotations put each
crop box on the right pixels of the museum's own canvas."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

SCALE = 2  # the museum's canvas is twice the size its image service sends
RIGHTS = "http://rightsstatements.org/vocab/NoC-US/1.0/"


def _xywh(annotation: dict) -> tuple[int, int, int, int]:
    value = annotation["target"]["selector"]["value"]
    x, y, w, h = (int(v) for v in value.removeprefix("xywh=").split(","))
    return x, y, w, h


@pytest.fixture
def released_from_iiif(app, runner, iiif_server, add_stage_result, decide_orientation, review_card, tmp_path):
    """Two demo cards served as IIIF (the second scanned upside down), ingested, rectified,
    accepted and released with the default formats and with ``iiif`` alone."""
    from sqlalchemy import select

    from core.db import db
    from core.models import Card
    from simulation.cards import make_stereo_card

    upright = make_stereo_card(seed=11, index=0).image
    turned = np.ascontiguousarray(make_stereo_card(seed=11, index=1).image[::-1, ::-1])
    canvases = []
    for name, image in (("upright", upright), ("turned", turned)):
        service = iiif_server.add_image(name, image)
        canvases.append((name, image.shape[1] * SCALE, image.shape[0] * SCALE, service))
    url = iiif_server.add_document(
        "release.json",
        iiif_server.manifest_v3(
            "release.json",
            "Stereo views",
            canvases,
            rights=RIGHTS,
            requiredStatement={"label": {"en": ["Attribution"]}, "value": {"en": ["The Example Museum"]}},
        ),
    )
    result = runner.invoke(args=["ingest", url, "--json"])
    assert result.exit_code == 0, result.output
    with app.app_context():
        cards = {card.iiif_canvas_id.rsplit("/", 1)[-1]: card.id for card in db.session.scalars(select(Card))}
    for card_id in cards.values():
        add_stage_result(card_id, "filter")  # the split down the middle, in the scan's pixels
    decide_orientation([cards["upright"]])
    decide_orientation([cards["turned"]], upside_down=True)
    ran = runner.invoke(args=["run", "--stages", "rectify,disparity", "--json"])
    assert ran.exit_code == 0, ran.output
    for card_id in cards.values():
        review_card(card_id, "few")
    from exports.release import publish_release

    with app.app_context():
        report = publish_release(tmp_path / "out")
        alone = publish_release(tmp_path / "alone", formats=("iiif",))
    return {"url": url, "cards": cards, "root": Path(report.path), "alone": Path(alone.path), "images": (upright, turned)}


def test_release_manifest_puts_each_crop_box_on_the_right_pixels_of_the_museums_canvas(released_from_iiif, iiif_server):
    from iiif_prezi3 import Manifest

    root, url = released_from_iiif["root"], released_from_iiif["url"]
    document = json.loads((root / "iiif" / "manifest.json").read_text())
    Manifest(**document)  # the Presentation 3 model loads it
    canvases = {canvas["id"]: canvas for canvas in document["items"]}
    assert set(canvases) == {f"{url}/canvas/upright", f"{url}/canvas/turned"}
    served = {
        name: np.asarray(Image.open(iiif_server.root / "image" / name / "full" / "max" / "0" / "default.jpg").convert("RGB"))
        for name in ("upright", "turned")
    }
    for name, card_id in released_from_iiif["cards"].items():
        canvas = canvases[f"{url}/canvas/{name}"]
        image = served[name]
        assert (canvas["width"], canvas["height"]) == (image.shape[1] * SCALE, image.shape[0] * SCALE)
        painting = canvas["items"][0]["items"][0]["body"]
        assert painting["service"][0]["id"] == f"{iiif_server.url}/image/{name}"
        assert canvas["rights"] == RIGHTS and canvas["partOf"] == [{"id": url, "type": "Manifest"}]
        items = {a["id"].rsplit("#", 1)[-1]: a for a in canvas["annotations"][0]["items"]}
        key = f"{card_id:05d}"
        for eye, suffix in (("left_eye", "L"), ("right_eye", "R")):
            x, y, w, h = _xywh(items[eye])
            assert x % SCALE == y % SCALE == w % SCALE == h % SCALE == 0
            region = image[y // SCALE : (y + h) // SCALE, x // SCALE : (x + w) // SCALE]
            cropped = np.asarray(Image.open(root / "cropped" / "cropped_full_LR" / f"{key}{suffix}.png").convert("RGB"))
            if name == "turned":
                region = region[::-1, ::-1]  # the pipeline cut from the card turned upright
            assert region.shape == cropped.shape and np.array_equal(region, cropped), (name, eye)
        # the left eye's photo is on the left of an upright card, and on the right of one scanned upside down
        left_x, right_x = _xywh(items["left_eye"])[0], _xywh(items["right_eye"])[0]
        assert (left_x < right_x) == (name == "upright")
        assert "Grade: few artifacts (accepted by a curator)" in items["grade"]["body"]["value"]
        orientation = items["orientation"]["body"]["value"]
        if name == "turned":
            assert "upside down" in orientation and "curator override" in orientation and "rotated 180 deg" in orientation
        else:
            assert "upright, positive, eyes in order" in orientation
        supplements = {k: v["body"]["id"] for k, v in items.items() if v["motivation"] == "supplementing"}
        assert supplements["rectified-left"].endswith(f"processed/rectified/rectified_LR/{key}L.png")
        assert supplements["depth"].endswith(f"processed/depth_512/{key}.exr")


def test_release_carries_the_rights_into_croissant_and_the_dataset_card_and_verifies(app, runner, released_from_iiif):
    root = released_from_iiif["root"]
    croissant = json.loads((root / "croissant.json").read_text())
    assert croissant["license"] == RIGHTS
    readme = (root / "README.md").read_text()
    assert f"license_link: {RIGHTS}" in readme and f"- {RIGHTS}: 2 card(s)" in readme
    records = [json.loads(line) for line in (root / "cards.jsonl").read_text().splitlines()]
    assert {r["metadata"]["rights"] for r in records} == {RIGHTS}
    assert {r["iiif"]["canvas"].rsplit("/", 1)[-1] for r in records} == {"upright", "turned"}
    checked = runner.invoke(args=["verify", str(root), "--json"])
    assert checked.exit_code == 0, checked.output
    # iiif alone: the scan, rectified views and depth are written beside the manifest
    alone = released_from_iiif["alone"]
    document = json.loads((alone / "iiif" / "manifest.json").read_text())
    bodies = [a["body"]["id"] for c in document["items"] for a in c["annotations"][0]["items"] if "id" in a["body"]]
    assert bodies and all(
        b.removeprefix("https://keystone.invalid/release/") and (alone / b.split("release/", 1)[1]).is_file() for b in bodies
    )
    assert runner.invoke(args=["verify", str(alone), "--json"]).exit_code == 0


def test_verify_refuses_a_manifest_whose_box_leaves_its_canvas(runner, released_from_iiif):
    import hashlib

    root = released_from_iiif["root"]
    path = root / "iiif" / "manifest.json"
    document = json.loads(path.read_text())
    canvas = document["items"][0]
    box = canvas["annotations"][0]["items"][0]
    box["target"]["selector"]["value"] = f"xywh={canvas['width'] - 10},0,50,50"
    path.chmod(0o644)
    path.write_text(json.dumps(document))
    sums = root / "SHA256SUMS"
    sums.chmod(0o644)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    sums.write_text(
        "".join(
            f"{digest}  iiif/manifest.json\n" if line.endswith("  iiif/manifest.json") else line + "\n"
            for line in sums.read_text().splitlines()
        )
    )
    checked = runner.invoke(args=["verify", str(root), "--json"])
    assert checked.exit_code != 0
    assert "is not inside the" in checked.output


def test_card_fragment_maps_image_pixels_onto_the_canvas():
    from exports.formats.iiif import canvas_fragment, scanned_box

    assert canvas_fragment([10, 20, 110, 220], (2.0, 2.0), (1000, 1000)) == (20, 40, 200, 400)
    assert canvas_fragment([10, 20, 600, 220], (2.0, 1.5), (1000, 1000)) == (20, 30, 980, 300)
    # a card turned 180 deg: the oriented box turned back into the scan's pixels
    assert scanned_box({}, [0, 0, 40, 30], "left_eye", ["rotated 180 deg"], (100, 50)) == [60, 20, 100, 50]
    assert scanned_box({"scanned_boxes": {"left_eye": [1, 2, 3, 4]}}, [0, 0, 40, 30], "left_eye", [], (100, 50)) == [1, 2, 3, 4]


def test_a_card_from_a_file_gets_a_canvas_of_its_own(app, processed_cards, review_card, tmp_path):
    from iiif_prezi3 import Manifest

    from exports.release import publish_release

    [card_id] = processed_cards(1)
    review_card(card_id, "few")
    with app.app_context():
        report = publish_release(tmp_path / "out")
    root = Path(report.path)
    document = json.loads((root / "iiif" / "manifest.json").read_text())
    Manifest(**document)
    [canvas] = document["items"]
    key = f"{card_id:05d}"
    assert canvas["id"] == f"https://keystone.invalid/release/iiif/canvas/{key}"
    painting = canvas["items"][0]["items"][0]["body"]
    assert painting["id"].endswith(f"original/{key}.png")
    scan = np.asarray(Image.open(io.BytesIO((root / "original" / f"{key}.png").read_bytes())).convert("RGB"))
    assert (canvas["width"], canvas["height"]) == (scan.shape[1], scan.shape[0])
    left = next(a for a in canvas["annotations"][0]["items"] if a["id"].endswith("#left_eye"))
    x, y, w, h = _xywh(left)
    cropped = np.asarray(Image.open(root / "cropped" / "cropped_full_LR" / f"{key}L.png").convert("RGB"))
    assert np.array_equal(scan[y : y + h, x : x + w], cropped)
    assert json.loads((root / "croissant.json").read_text())["license"] == "https://creativecommons.org/publicdomain/mark/1.0/"

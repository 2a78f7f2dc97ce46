"""The viewer's routes: login required, 404 without views, files served with an ETag."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture
def card_with_views(make_card_with_views):  # type: ignore[no-untyped-def]
    return make_card_with_views(160, "few")


def test_the_viewer_needs_a_login(client, card_with_views):
    card_id, _ = card_with_views
    for url in (f"/viewer/cards/{card_id}", f"/viewer/cards/{card_id}/files/v0"):
        response = client.get(url, headers={"Accept": "text/html"})
        assert response.status_code == 302 and "/auth/login" in response.headers["Location"]


def test_a_person_without_a_role_is_refused(client, login, card_with_views):
    card_id, _ = card_with_views
    login()
    assert client.get(f"/viewer/cards/{card_id}").status_code == 403


@pytest.mark.parametrize("role", ["annotator", "curator", "exporter", "admin"])
def test_any_role_sees_the_viewer_page_with_five_views(client, login, card_with_views, role):
    card_id, record = card_with_views
    login(role)
    response = client.get(f"/viewer/cards/{card_id}")
    assert response.status_code == 200
    page = response.get_data(as_text=True)
    config = json.loads(re.search(r'<script id="viewer-config" type="application/json">(.*?)</script>', page, re.DOTALL).group(1))
    assert [v["name"] for v in config["views"]] == ["v0", "v1", "v2", "v3", "v4"]
    assert (config["width"], config["height"]) == tuple(record.metrics["size"])
    assert config["quadRadius"] == pytest.approx(record.metrics["quad_radius"])
    assert config["views"][2]["image"].startswith(f"/viewer/cards/{card_id}/files/v2_web?v=")
    assert config["views"][2]["mesh"].startswith(f"/viewer/cards/{card_id}/files/v2_mesh?v=")
    assert config["mesh"]["step"] >= 1 and config["maxStretchPx"] == record.metrics["max_stretch_px"]
    assert "_depth" not in page  # the float32 maps are for releases; the page never fetches them
    assert "viewer.js" in page and 'id="viewer-canvas"' in page


def test_a_card_without_views_is_404(client, login, make_card, add_stage_result):
    login("curator")
    bare = make_card(state="pass")
    response = client.get(f"/viewer/cards/{bare}")
    text = response.get_data(as_text=True)
    assert response.status_code == 404 and "no 3D views yet: the views stage has not run on it" in text
    assert "keystone run" not in text
    assert client.get(f"/viewer/cards/{bare}/files/v0").status_code == 404
    add_stage_result(bare, "views", status="skipped", outcome=None, reason="not needed: graded failure")
    response = client.get(f"/viewer/cards/{bare}")
    assert response.status_code == 404 and "graded failure" in response.get_data(as_text=True)
    assert client.get("/viewer/cards/999999").status_code == 404


def test_gd_files_are_served_with_an_etag_and_revalidate(client, login, data_dir, card_with_views):
    card_id, record = card_with_views
    login("annotator")
    response = client.get(f"/viewer/cards/{card_id}/files/v3")
    assert response.status_code == 200 and response.mimetype == "image/png"
    assert response.data == (Path(data_dir) / record.artifacts["v3"]).read_bytes()
    etag = response.headers["ETag"]
    assert etag and response.headers["Cache-Control"] == "private, no-cache"
    again = client.get(f"/viewer/cards/{card_id}/files/v3", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.headers["ETag"] == etag
    depth = client.get(f"/viewer/cards/{card_id}/files/v3_depth")
    assert depth.status_code == 200 and depth.headers["ETag"] != etag
    values = np.load(io.BytesIO(depth.data), allow_pickle=False)
    assert values.dtype == np.float32 and values.shape == tuple(record.metrics["size"][::-1])
    assert np.isfinite(values).all() and (values > 0).all()
    preview = client.get(f"/viewer/cards/{card_id}/files/preview")
    assert preview.status_code == 200 and preview.mimetype == "image/webp" and preview.data[8:12] == b"WEBP"
    assert client.get(f"/viewer/cards/{card_id}/files/secrets").status_code == 404
    assert client.get(f"/viewer/cards/{card_id}/files/..%2Fkeystone.sqlite3").status_code == 404


def test_a_versioned_url_is_cacheable_for_a_year(client, login, card_with_views):
    card_id, _ = card_with_views
    login("curator")
    page = client.get(f"/viewer/cards/{card_id}").get_data(as_text=True)
    url = re.search(rf'"(/viewer/cards/{card_id}/files/v0_web\?v=[0-9a-f]+)"', page).group(1)
    response = client.get(url)
    assert response.status_code == 200 and "immutable" in response.headers["Cache-Control"]


def test_the_viewer_files_are_a_jpeg_and_a_mesh_png_that_decodes_to_the_depth(client, login, data_dir, card_with_views):
    from PIL import Image

    card_id, record = card_with_views
    login("annotator")
    page = client.get(f"/viewer/cards/{card_id}").get_data(as_text=True)
    config = json.loads(re.search(r'<script id="viewer-config" type="application/json">(.*?)</script>', page, re.DOTALL).group(1))
    picture = client.get(f"/viewer/cards/{card_id}/files/v1_web")
    assert picture.status_code == 200 and picture.mimetype == "image/jpeg" and picture.data[:2] == b"\xff\xd8"
    mesh = client.get(f"/viewer/cards/{card_id}/files/v1_mesh")
    assert mesh.status_code == 200 and mesh.mimetype == "image/png"
    rgb = np.asarray(Image.open(io.BytesIO(mesh.data)))
    assert rgb.shape == (config["mesh"]["rows"], config["mesh"]["columns"], 3) and rgb.dtype == np.uint8
    lo, hi = config["mesh"]["inverseDepthRange"]
    inverse = lo + (rgb[..., 0].astype(float) * 256 + rgb[..., 1]) / 65535 * (hi - lo)
    depth = np.load(Path(data_dir) / record.artifacts["v1_depth"])
    step = config["mesh"]["step"]
    w, h = record.metrics["size"]
    xs = sorted({*range(0, w - 1, step), w - 1})
    ys = sorted({*range(0, h - 1, step), h - 1})
    truth = 1.0 / depth[np.ix_(ys, xs)].astype(float)
    assert np.abs(inverse - truth).max() <= (hi - lo) / 65535  # 16-bit quantisation, nothing worse


def test_views_made_before_the_compact_files_ask_for_a_rerun(client, login, data_dir, card_with_views, add_stage_result):
    card_id, record = card_with_views
    login("curator")
    old = {k: v for k, v in record.artifacts.items() if not k.endswith(("_web", "_mesh"))}
    add_stage_result(card_id, "views", status="done", outcome=None, param_hash="old", metrics=record.metrics, artifacts=old)
    response = client.get(f"/viewer/cards/{card_id}")
    assert response.status_code == 404 and "keystone run --stages views" in response.get_data(as_text=True)

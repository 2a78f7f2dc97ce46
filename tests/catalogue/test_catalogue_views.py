"""The catalogue and card pages on real stored cards, and the image routes with their caching."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
from PIL import Image

STAFF_MATRIX = [(None, 302), ("annotator", 403), ("curator", 200), ("exporter", 200), ("admin", 200)]


@pytest.fixture
def filtered_card(make_card, add_stage_result) -> int:
    card_id = make_card(
        accession="1996.0009.17827",
        metadata={
            "title": "Niagara Falls from below",
            "Subjects": "Falls\nRivers",
            "odd column from the museum": "kept <b>as text</b>",
            "url": "https://example.org/objects/1",
        },
    )
    add_stage_result(card_id, outcome="pass")
    return card_id


def image_of(response) -> Image.Image:  # type: ignore[no-untyped-def]
    return Image.open(io.BytesIO(response.get_data()))


def tile_titles(html: str) -> set[str]:
    return set(re.findall(r'<span class="tile-title">([^<]+)</span>', html))


def image_urls(html: str) -> list[str]:
    return [url.replace("&amp;", "&") for url in re.findall(r'<img src="([^"]+)"', html)]


# --------------------------------------------------------------------------- roles x routes


def test_root_sends_anonymous_people_to_log_in(client):
    assert client.get("/").headers["Location"] == "/auth/login"


@pytest.mark.parametrize(
    ("role", "home"), [("curator", "/review/"), ("exporter", "/releases/"), ("admin", "/cards"), ("annotator", "/crowd/mine")]
)
def test_root_sends_each_role_where_its_work_starts(client, login, role, home):
    login(role)
    assert client.get("/").headers["Location"] == home


def test_root_greets_someone_with_no_role_without_the_catalogue(client, login):
    login()
    response = client.get("/")
    assert response.status_code == 200 and "invite" in response.get_data(as_text=True)


@pytest.mark.parametrize("role, expected", STAFF_MATRIX)
def test_catalogue_access(client, as_role, filtered_card, role, expected):
    as_role(role)
    response = client.get("/cards")
    assert response.status_code == expected
    if expected == 302:
        assert response.headers["Location"].startswith("/auth/login")


@pytest.mark.parametrize("role, expected", STAFF_MATRIX)
def test_card_page_access(client, as_role, filtered_card, role, expected):
    as_role(role)
    assert client.get(f"/cards/{filtered_card}").status_code == expected


@pytest.mark.parametrize("role, expected", STAFF_MATRIX)
@pytest.mark.parametrize("route", ["image/original", "image/thumb", "image/filter/left", "image/filter/right"])
def test_image_access(client, as_role, filtered_card, role, expected, route):
    as_role(role)
    response = client.get(f"/cards/{filtered_card}/{route}")
    assert response.status_code == expected
    if expected == 200:
        assert response.mimetype in ("image/jpeg", "image/png")


# --------------------------------------------------------------------------- the catalogue


def test_catalogue_shows_real_cards_with_thumbnails_and_state_counts(client, login, make_card, add_stage_result):
    login("curator")
    passed = make_card(metadata={"title": "Yosemite Valley"})
    add_stage_result(passed, outcome="pass")
    culled = make_card(image=np.zeros((20, 40, 3), np.uint8))
    add_stage_result(culled, outcome="culled", reason="too_few_matches: 3 < 10")
    make_card(image=np.full((30, 60, 3), 90, np.uint8))
    html = client.get("/cards").get_data(as_text=True)
    assert "Yosemite Valley" in html and "3 cards" in html
    assert re.search(r'all <span class="count">3</span>', html)
    assert re.search(r'pass <span class="count">1</span>', html)
    assert re.search(r'culled <span class="count">1</span>', html)
    assert re.search(r'ingested <span class="count">1</span>', html)
    assert re.search(r'review <span class="count">0</span>', html)
    thumbs = [url for url in image_urls(html) if "/image/thumb" in url]
    assert len(thumbs) == 3
    response = client.get(thumbs[0])
    assert response.status_code == 200 and max(image_of(response).size) <= 320


def test_catalogue_filters_by_state(client, login, make_card, add_stage_result):
    login("curator")
    ids = [make_card(image=np.full((20, 40 + i, 3), 10 * i, np.uint8), metadata={"title": f"Card number {i}"}) for i in range(3)]
    add_stage_result(ids[0], outcome="review")
    html = client.get("/cards?state=review").get_data(as_text=True)
    assert "Card number 0" in html and "Card number 1" not in html and "1 card" in html


def test_catalogue_filters_by_collection(client, login, make_card):
    login("exporter")
    make_card(image=np.zeros((20, 40, 3), np.uint8), collection="nypl", metadata={"title": "From NYPL"})
    make_card(image=np.ones((20, 40, 3), np.uint8), collection="ucr", metadata={"title": "From UCR"})
    from core.db import db
    from core.models import Collection

    with client.application.app_context():
        nypl = db.session.query(Collection).filter_by(name="nypl").one().id
    html = client.get(f"/cards?collection={nypl}").get_data(as_text=True)
    assert "From NYPL" in html and "From UCR" not in html
    assert client.get("/cards?collection=987654").status_code == 404


@pytest.mark.both_databases
def test_catalogue_filters_by_stage_status(client, login, make_card, add_stage_result):
    login("admin")
    done = make_card(image=np.full((20, 40, 3), 1, np.uint8), metadata={"title": "Done card"})
    add_stage_result(done, outcome="pass")
    failed = make_card(image=np.full((20, 40, 3), 2, np.uint8), metadata={"title": "Failed card"})
    add_stage_result(failed, status="failed", outcome=None, reason="unreadable_image: truncated", artifacts={})
    culled = make_card(image=np.full((20, 40, 3), 3, np.uint8), metadata={"title": "Culled card"})
    add_stage_result(culled, outcome="culled")
    make_card(image=np.full((20, 40, 3), 4, np.uint8), metadata={"title": "Pending card"})

    def titles(query: str) -> set[str]:
        return tile_titles(client.get(f"/cards?{query}").get_data(as_text=True))

    assert titles("stage=filter&status=done") == {"Done card", "Culled card"}
    assert titles("stage=filter&status=failed") == {"Failed card"}
    assert titles("stage=filter&status=pending") == {"Pending card"}
    assert titles("stage=filter&status=skipped") == set()
    # Stages after the filter are skipped for culled cards, as `keystone cards` reports them.
    assert titles("stage=rectify&status=skipped") == {"Culled card"}
    assert titles("stage=rectify&status=pending") == {"Done card", "Failed card", "Pending card"}
    assert titles("stage=filter") == {"Done card", "Failed card", "Culled card", "Pending card"}


@pytest.mark.parametrize(
    "query, message",
    [
        ("state=lost", "Unknown state"),
        ("stage=paint&status=done", "Unknown stage"),
        ("stage=filter&status=maybe", "Unknown status"),
        ("status=done", "needs a stage"),
        ("page=0", "positive whole number"),
        ("page=abc", "positive whole number"),
        ("collection=x", "positive whole number"),
    ],
)
def test_catalogue_rejects_filters_that_name_nothing(client, login, query, message):
    login("curator")
    response = client.get(f"/cards?{query}")
    assert response.status_code == 400 and message in response.get_data(as_text=True)


def test_catalogue_pages(app, client, login, make_card):
    app.config["CATALOG_PAGE_SIZE"] = 2
    login("curator")
    for i in range(5):
        make_card(image=np.full((20, 40, 3), 20 * i, np.uint8), metadata={"title": f"Title {i}"})
    first = client.get("/cards").get_data(as_text=True)
    assert tile_titles(first) == {"Title 0", "Title 1"} and "Page 1 of 3" in first
    assert 'href="/cards?page=2"' in first
    third = client.get("/cards?page=3").get_data(as_text=True)
    assert tile_titles(third) == {"Title 4"}
    assert client.get("/cards?page=4").status_code == 404
    assert 'href="/cards?state=ingested&amp;page=2"' in client.get("/cards?state=ingested").get_data(as_text=True)


def test_empty_catalogue_says_so(client, login):
    login("curator")
    response = client.get("/cards")
    assert response.status_code == 200 and "No cards match" in response.get_data(as_text=True)


# --------------------------------------------------------------------------- the card page


@pytest.mark.both_databases
def test_card_page_shows_the_card_its_split_metrics_metadata_and_history(client, login, filtered_card, add_stage_result):
    login("curator")
    add_stage_result(filtered_card, "judge", outcome="valid", update_state=False)
    html = client.get(f"/cards/{filtered_card}").get_data(as_text=True)
    assert "Niagara Falls from below" in html and "1996.0009.17827" in html
    # The original with the split boxes drawn over it, in card pixels.
    assert f'src="/cards/{filtered_card}/image/original?v=' in html
    assert '<svg class="overlay" viewBox="0 0 604 200"' in html
    assert re.search(r'<rect class="box box-left" x="0\.0" y="0\.0" width="296\.0" height="200\.0"', html)
    assert re.search(r'<rect class="box box-right" x="308\.0" y="0\.0" width="296\.0" height="200\.0"', html)
    # The two halves, by artifact name.
    assert f"/cards/{filtered_card}/image/filter/left?v=" in html and f"/cards/{filtered_card}/image/filter/right?v=" in html
    # Metrics: the fraction with its denominator, matches, keypoints, timings.
    assert "23.41 % = 512 good matches / keypoints_left = 2,187" in html
    assert "2,204" in html and "81 ms" in html and "34 ms" in html and "210 ms" in html
    assert "similarity" in html  # other metrics are shown too
    # Source metadata, every column, escaped.
    assert "odd column from the museum" in html and "kept &lt;b&gt;as text&lt;/b&gt;" in html
    assert "Falls\nRivers" in html
    assert '<a href="https://example.org/objects/1" rel="noopener noreferrer">' in html
    # Stage statuses and the results history.
    assert re.search(r"<td>rectify</td><td><span class=\"badge status-pending\">pending</span>", html)
    assert html.count("<code>0123456789abcdef</code>") == 2
    assert "valid" in html


def test_card_page_shows_thresholds_when_recorded(client, login, make_card, add_stage_result):
    login("curator")
    card_id = make_card()
    add_stage_result(card_id, outcome="review", metrics={"thresholds": {"cull_below_fraction": 0.005, "min_matches": 10}})
    html = client.get(f"/cards/{card_id}").get_data(as_text=True)
    assert "cull_below_fraction" in html and "0.005" in html and "min_matches" in html


def test_card_page_shows_the_current_thresholds_when_the_result_used_them(app, client, login, make_card, add_stage_result):
    from dataclasses import asdict

    from pipeline.records import param_hash
    from runs.specs import available_stages

    with app.app_context():  # the grade stage's thresholds come from the database
        params = available_stages()["filter"].params
    login("curator")
    current = make_card()
    add_stage_result(current, param_hash=param_hash(params))
    html = client.get(f"/cards/{current}").get_data(as_text=True)
    for name in asdict(params):
        assert f'<th scope="row">{name}</th>' in html
    older = make_card(image=np.full((20, 40, 3), 5, np.uint8))
    add_stage_result(older, param_hash="0000000000000000")
    assert "other than the current ones" in client.get(f"/cards/{older}").get_data(as_text=True)
    # Parameter fields the stage copied into its metrics are its thresholds, shown once.
    name = next(iter(asdict(params)))
    copied = make_card(image=np.full((20, 40, 3), 6, np.uint8))
    add_stage_result(copied, param_hash="1111111111111111", metrics={name: 0.123})
    html = client.get(f"/cards/{copied}").get_data(as_text=True)
    assert "other than the current ones" not in html
    assert html.count(f'<th scope="row">{name}</th>') == 1 and "0.123" in html


def test_card_page_for_a_card_the_filter_has_not_seen(client, login, make_card):
    login("curator")
    card_id = make_card()
    html = client.get(f"/cards/{card_id}").get_data(as_text=True)
    assert "has not run on this card yet" in html and "<svg" not in html


def test_card_page_of_a_missing_card_is_404(client, login):
    login("curator")
    assert client.get("/cards/424242").status_code == 404


# --------------------------------------------------------------------------- images


def test_original_is_a_cached_display_jpeg(client, login, filtered_card, data_dir):
    login("curator")
    response = client.get(f"/cards/{filtered_card}/image/original")
    assert response.status_code == 200 and response.mimetype == "image/jpeg"
    assert image_of(response).size == (604, 200)
    previews = list((data_dir / "previews").glob("*.jpg"))
    assert {p.name.split(".")[0] for p in previews} == {previews[0].name.split(".")[0]}
    assert len(previews[0].name.split(".")[0]) == 64  # named by content hash


def test_a_16_bit_tiff_is_shown_as_a_jpeg_no_larger_than_1600(client, login, make_card, card_image):
    login("curator")
    grey = card_image()[..., 1].astype(np.uint16) * 257
    big = np.tile(grey, (2, 3))  # 1812 x 400, 16-bit
    card_id = make_card(big, suffix=".tif")
    response = client.get(f"/cards/{card_id}/image/original")
    assert response.status_code == 200 and response.mimetype == "image/jpeg"
    shown = image_of(response)
    assert max(shown.size) == 1600 and shown.mode == "L"
    thumb = image_of(client.get(f"/cards/{card_id}/image/thumb"))
    assert max(thumb.size) == 320


def test_versioned_image_urls_are_cached_forever_with_a_strong_etag(client, login, filtered_card):
    login("curator")
    html = client.get(f"/cards/{filtered_card}").get_data(as_text=True)
    for url in image_urls(html):
        response = client.get(url)
        assert response.status_code == 200, url
        etag = response.headers["ETag"]
        assert etag.startswith('"') and not etag.startswith("W/")
        assert response.headers["Cache-Control"] == "private, max-age=31536000, immutable"
        again = client.get(url, headers={"If-None-Match": etag})
        assert again.status_code == 304 and again.get_data() == b""
        assert again.headers["ETag"] == etag
        assert again.headers["Cache-Control"] == "private, max-age=31536000, immutable"


def test_unversioned_image_urls_revalidate(client, login, filtered_card):
    login("curator")
    response = client.get(f"/cards/{filtered_card}/image/filter/left")
    assert response.status_code == 200 and response.headers["Cache-Control"] == "private, no-cache"
    assert (
        client.get(f"/cards/{filtered_card}/image/filter/left", headers={"If-None-Match": response.headers["ETag"]}).status_code
        == 304
    )


def test_a_rerun_changes_the_artifact_etag(client, login, filtered_card, add_stage_result):
    login("curator")
    before = client.get(f"/cards/{filtered_card}/image/filter/left").headers["ETag"]
    add_stage_result(filtered_card, param_hash="fedcba9876543210", outcome="review")
    after = client.get(f"/cards/{filtered_card}/image/filter/left", headers={"If-None-Match": before})
    assert after.status_code == 200 and after.headers["ETag"] != before


def test_304_does_not_need_the_preview_to_exist(client, login, filtered_card, data_dir):
    login("curator")
    etag = client.get(f"/cards/{filtered_card}/image/thumb").headers["ETag"]
    for preview in (data_dir / "previews").glob("*"):
        preview.unlink()
    assert client.get(f"/cards/{filtered_card}/image/thumb", headers={"If-None-Match": etag}).status_code == 304
    assert not list((data_dir / "previews").glob("*"))


def test_artifact_images_match_the_recorded_halves(client, login, filtered_card, card_image):
    login("curator")
    left = np.asarray(image_of(client.get(f"/cards/{filtered_card}/image/filter/left")))
    right = np.asarray(image_of(client.get(f"/cards/{filtered_card}/image/filter/right")))
    card = card_image()
    assert np.array_equal(left, card[:, :296]) and np.array_equal(right, card[:, 308:])


@pytest.mark.parametrize(
    "route",
    [
        "image/filter/disparity",  # a name the result did not record
        "image/rectify/left",  # a stage with no result
        "image/filter/left.png",
        "image/filter/..%2F..%2F..%2Fetc%2Fpasswd",
        "image/filter/%2E%2E",
        "image/../../../etc/passwd",
        "image/original/../../secret",
    ],
)
def test_unrecorded_artifacts_and_traversal_attempts_are_404(client, login, filtered_card, route):
    login("curator")
    response = client.get(f"/cards/{filtered_card}/{route}")
    assert response.status_code == 404
    assert response.mimetype == "text/html"


def test_a_recorded_path_outside_the_data_dir_is_404(client, login, make_card, add_stage_result, data_dir):
    login("curator")
    secret = data_dir.parent / "secret.png"
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(secret)
    card_id = make_card()
    add_stage_result(card_id, metrics={}, artifacts={"left": "../secret.png", "right": str(secret)})
    assert client.get(f"/cards/{card_id}/image/filter/left").status_code == 404
    assert client.get(f"/cards/{card_id}/image/filter/right").status_code == 404


def test_a_non_image_artifact_is_not_served(client, login, make_card, add_stage_result, data_dir):
    login("curator")
    (data_dir / "derived").mkdir(parents=True, exist_ok=True)
    (data_dir / "derived" / "flow.npy").write_bytes(b"\x93NUMPY")
    card_id = make_card()
    add_stage_result(card_id, "disparity", outcome=None, artifacts={"flow": "derived/flow.npy"})
    assert client.get(f"/cards/{card_id}/image/disparity/flow").status_code == 404


def test_a_missing_artifact_file_is_404(client, login, filtered_card, data_dir):
    login("curator")
    for half in (data_dir / "derived").rglob("left.png"):
        half.unlink()
    response = client.get(f"/cards/{filtered_card}/image/filter/left")
    assert response.status_code == 404 and "rerun the filter stage" in response.get_data(as_text=True)


def test_an_undecodable_original_is_404_with_the_reason(client, login, make_card):
    login("curator")
    good = io.BytesIO()
    Image.fromarray(np.zeros((50, 80, 3), np.uint8) + 7).save(good, format="PNG")
    card_id = make_card(payload=good.getvalue()[:-40], suffix=".png")
    response = client.get(f"/cards/{card_id}/image/original")
    assert response.status_code == 404
    assert "cannot be shown" in response.get_data(as_text=True)


def test_card_page_shows_the_grade_with_its_reasons(client, login, make_card, add_stage_result) -> None:  # type: ignore[no-untyped-def]
    login("curator")
    card_id = make_card()
    add_stage_result(
        card_id,
        "grade",
        outcome="failure",
        metrics={"reasons": ["failure: rows of the two views are misaligned by 6.0 px (> 4 px)"], "uncertainty": 0.25},
    )
    html = client.get(f"/cards/{card_id}").get_data(as_text=True)
    assert '<span class="grade grade-failure">failure</span>' in html and "uncertainty 0.25" in html
    assert "<li>failure: rows of the two views are misaligned by 6.0 px (&gt; 4 px)</li>" in html
    assert "Open the 3D viewer" not in html  # no views result yet


def test_every_image_on_a_processed_card_page_loads(app, client, login, runner, make_card, decide_orientation) -> None:  # type: ignore[no-untyped-def]
    """The card page lists only the artifacts that are images (issue 33.4: the filter's matches,
    a .npy, was shown as an image and answered 404 on every card) and every one of them loads."""
    import re

    card = make_card()
    decide_orientation([card])
    result = runner.invoke(args=["run", "--stages", "filter,rectify,disparity,grade", "--json"])
    assert result.exit_code == 0, result.output
    login("curator")
    page = client.get(f"/cards/{card}").get_data(as_text=True)
    sources = re.findall(r'<img[^>]+src="([^"]+)"', page)
    assert any("/image/filter/" in source for source in sources) and not any("/image/filter/matches" in s for s in sources)
    for source in sources:
        answer = client.get(source.replace("&amp;", "&"))
        assert answer.status_code == 200 and answer.mimetype.startswith("image/"), (source, answer.status_code)

"""The card page's stereo downloads: each format made from the card's rectified pair and disparity."""

from __future__ import annotations

import io
import re

import pytest
from PIL import Image

FORMATS = {
    "anaglyph": "image/jpeg",
    "wiggle_gif": "image/gif",
    "wiggle_webp": "image/webp",
    "sbs_full": "image/jpeg",
    "sbs_half": "image/jpeg",
    "jps": "image/x-jps",
    "mpo": "image/mpo",
}


@pytest.fixture
def rectified_card(runner, make_card, add_stage_result, decide_orientation) -> int:
    card_id = make_card(accession="1996.0009.17827", metadata={"title": "Motorcycle in the lab", "date": "2014"})
    add_stage_result(card_id, "filter")
    decide_orientation([card_id])
    result = runner.invoke(args=["run", "--stages", "rectify,disparity", "--json"])
    assert result.exit_code == 0, result.output
    return card_id


def test_card_page_offers_every_stereo_format_and_each_downloads(client, login, rectified_card, data_dir) -> None:
    login("curator")
    page = client.get(f"/cards/{rectified_card}").get_data(as_text=True)
    assert "Stereo downloads" in page
    urls = [url.replace("&amp;", "&") for url in re.findall(r'href="(/cards/\d+/stereo/[^"]+)"', page)]
    shown = [url.split("/stereo/")[1].split("?")[0] for url in re.findall(r'<img src="(/cards/\d+/stereo/[^"]+)"', page)]
    assert shown == ["anaglyph", "wiggle_webp"]  # previews on the page, beside the download links
    assert [url.split("/stereo/")[1].split("?")[0] for url in urls] == list(FORMATS)
    sizes = {}
    for url in urls:
        fmt = url.split("/stereo/")[1].split("?")[0]
        response = client.get(url)
        assert response.status_code == 200, (fmt, response.get_data(as_text=True)[:200])
        assert response.mimetype == FORMATS[fmt]
        assert response.headers["Content-Disposition"].startswith(f'attachment; filename="card-{rectified_card:05d}-')
        assert "immutable" in response.headers["Cache-Control"]
        with Image.open(io.BytesIO(response.get_data())) as image:
            sizes[fmt] = image.size
            if fmt == "mpo":
                assert image.format == "MPO" and image.n_frames == 2
                assert image.getexif()[0x010E] == "Motorcycle in the lab; 2014; accession 1996.0009.17827"
            if fmt.startswith("wiggle"):
                assert image.n_frames == 12
    assert sizes["jps"] == sizes["sbs_full"] == (2 * sizes["anaglyph"][0], sizes["anaglyph"][1])
    # Made once, then served from the cache.
    assert len(list((data_dir / "stereo_downloads").iterdir())) == len(FORMATS)
    again = client.get(urls[0], headers={"If-None-Match": client.get(urls[0]).headers["ETag"].strip('"')})
    assert again.status_code == 304


def test_annotators_cannot_download_stereo_files(client, login, rectified_card) -> None:
    login("annotator")
    assert client.get(f"/cards/{rectified_card}/stereo/anaglyph").status_code == 403


def test_stereo_downloads_need_a_rectified_pair_and_a_known_format(
    client, login, make_card, add_stage_result, card_image, rectified_card
) -> None:
    only_filtered = make_card(image=card_image((200, 150)))
    add_stage_result(only_filtered, "filter")
    login("curator")
    assert "Stereo downloads" not in client.get(f"/cards/{only_filtered}").get_data(as_text=True)
    response = client.get(f"/cards/{only_filtered}/stereo/anaglyph")
    assert response.status_code == 404 and "no rectified pair" in response.get_data(as_text=True)
    unknown = client.get(f"/cards/{rectified_card}/stereo/gif")
    assert unknown.status_code == 404 and "anaglyph, wiggle_gif" in unknown.get_data(as_text=True)
    assert client.get("/cards/999/stereo/anaglyph").status_code == 404

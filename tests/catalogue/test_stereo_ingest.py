"""Stereo inputs at ingest: MPO files, left/right pairs (by name and by CSV), JPS eye order.

Real inputs where ../shared/data is present (an MPO made from a Keystone-Mast scan's two halves,
the depthy 7995 left/right pair, a JPS), Motorcycle (scikit-image) everywhere else.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cards(app) -> list:  # type: ignore[no-untyped-def]
    from sqlalchemy import select

    from core.db import db
    from core.models import Card

    with app.app_context():
        cards = list(db.session.scalars(select(Card).order_by(Card.id)))
        db.session.expunge_all()
        return cards


def _motorcycle_views() -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    return left[:, :720], right[:, :720]


def _save_mpo(path: Path, left: np.ndarray, right: np.ndarray | None) -> Path:
    extra = [] if right is None else [Image.fromarray(right)]
    Image.fromarray(left).save(path, format="MPO", save_all=True, append_images=extra, quality=95)
    return path


# ---- grouping by name (pure) -------------------------------------------------------------------


def test_pairs_are_matched_by_name_in_every_documented_pattern(tmp_path) -> None:
    from catalogue.stereo_ingest import StereoOptions, plan_stereo

    names = [
        "7995l-image.jpg",
        "7995r-image.jpg",
        "card_L.png",
        "card_r.png",
        "cardL.jpg",
        "cardR.jpg",
        "Niagara-left.tif",
        "Niagara-Right.tif",
        "scan 12 left.jpg",
        "scan 12 right.jpg",
        "Hall.jpg",
        "Parlor.jpg",
        "lonely_L.jpg",
        "Views of the R. River.jpg",
        "plain.jpg",
        "photo.jps",
        "camera.mpo",
    ]
    files = [tmp_path / name for name in names]
    plan = plan_stereo(files, StereoOptions())
    pairs = {(left.name, right.name) for left, right, _how in plan.pairs}
    assert pairs == {
        ("7995l-image.jpg", "7995r-image.jpg"),
        ("card_L.png", "card_r.png"),
        ("cardL.jpg", "cardR.jpg"),
        ("Niagara-left.tif", "Niagara-Right.tif"),
        ("scan 12 left.jpg", "scan 12 right.jpg"),
    }
    assert [p.name for p in plan.singles] == ["Hall.jpg", "Parlor.jpg", "Views of the R. River.jpg", "plain.jpg"]
    assert [p.name for p in plan.mpos] == ["camera.mpo"]
    assert [(p.name, order) for p, order, _why in plan.side_by_side] == [("photo.jps", "cross")]
    assert len(plan.rejected) == 1 and plan.rejected[0]["path"].endswith("lonely_L.jpg")
    assert "no right view" in plan.rejected[0]["reason"]
    # --sbs-order makes every plain file side by side with that order, JPS included.
    ordered = plan_stereo([tmp_path / "plain.jpg", tmp_path / "photo.jps"], StereoOptions(sbs_order="parallel"))
    assert [(p.name, order) for p, order, _why in ordered.side_by_side] == [("plain.jpg", "parallel"), ("photo.jps", "parallel")]
    with pytest.raises(ValueError, match="eye order"):
        StereoOptions(sbs_order="sideways")


# ---- ingest (database, files) -------------------------------------------------------------------


@pytest.mark.both_databases
def test_an_mpo_becomes_one_card_with_its_original_kept_as_it_came(app, runner, client, login, tmp_path, data_dir) -> None:
    left, right = _motorcycle_views()
    mpo = _save_mpo(tmp_path / "camera.mpo", left, right)
    result = runner.invoke(args=["ingest", str(mpo), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["ingested"] == 1 and report["cards"][0]["stereo"]["kind"] == "mpo"
    [card] = _cards(app)
    source = card.stereo_source
    assert source["frames"] == 2 and source["eye_order"] == "parallel"
    [original] = source["originals"]
    assert original["sha256"] == _sha(mpo) and (data_dir / original["stored_path"]).read_bytes() == mpo.read_bytes()
    # The card image is derived: the two frames side by side, left first, decoded as stored.
    with Image.open(mpo) as image:
        frames = [np.asarray(image.convert("RGB"))]
        image.seek(1)
        frames.append(np.asarray(image.convert("RGB")))
    stored = np.asarray(Image.open(data_dir / card.stored_path))
    assert card.stored_path.startswith("derived/stereo_inputs/") and card.content_hash == _sha(data_dir / card.stored_path)
    assert (card.width, card.height) == (2 * left.shape[1], left.shape[0])
    assert np.array_equal(stored, np.concatenate(frames, axis=1))
    # The card page names the original and its hash.
    login("curator")
    page = client.get(f"/cards/{card.id}").get_data(as_text=True)
    assert "MPO (frames 1 and 2: left, right)" in page and original["sha256"] in page and "camera.mpo" in page
    # Ingesting it again is a duplicate, not a second card.
    again = json.loads(runner.invoke(args=["ingest", str(mpo), "--json"]).output)
    assert again["ingested"] == 0 and again["duplicates"] == 1


def test_a_jps_is_cross_eyed_by_default_and_parallel_on_request(app, runner, tmp_path, data_dir) -> None:
    left, right = _motorcycle_views()
    cross = tmp_path / "cross.jps"
    Image.fromarray(np.concatenate([right, left], axis=1)).save(cross, format="JPEG", quality=95)
    parallel = tmp_path / "parallel" / "stored-parallel.jps"
    parallel.parent.mkdir()
    Image.fromarray(np.concatenate([left, right], axis=1)).save(parallel, format="JPEG", quality=95)

    first = runner.invoke(args=["ingest", str(cross), "--json"])
    assert first.exit_code == 0, first.output
    second = runner.invoke(args=["ingest", str(parallel), "--sbs-order", "parallel", "--json"])
    assert second.exit_code == 0, second.output
    cross_card, parallel_card = _cards(app)
    width = left.shape[1]
    jps_pixels = np.asarray(Image.open(cross)).astype(int)
    card_pixels = np.asarray(Image.open(data_dir / cross_card.stored_path)).astype(int)
    # Cross-eyed: the card image the pipeline reads has the JPS's right half (the left eye's view) first.
    assert np.array_equal(card_pixels[:, :width], jps_pixels[:, width:])
    assert cross_card.stereo_source["eye_order"] == "cross"
    assert cross_card.stereo_source["eye_order_from"] == "JPS convention (default)"
    assert cross_card.stereo_source["originals"][0]["sha256"] == _sha(cross)
    # Parallel: no derived copy, the JPS itself is the card image.
    assert parallel_card.stereo_source["eye_order"] == "parallel"
    assert parallel_card.content_hash == _sha(parallel) and parallel_card.stored_path.startswith("originals/")
    assert (parallel_card.width, parallel_card.height) == (2 * width, left.shape[0])
    # The automatic check agrees with both declared orders here (the pair is in the right order each time).
    assert cross_card.stereo_source["eye_order_check"]["agrees"] is True
    assert parallel_card.stereo_source["eye_order_check"]["agrees"] is True


@pytest.mark.both_databases
def test_bad_pairs_get_a_reason_each_while_the_rest_goes_on(app, runner, tmp_path) -> None:
    left, right = _motorcycle_views()
    good_left, good_right = tmp_path / "good_L.png", tmp_path / "good_R.png"
    Image.fromarray(left).save(good_left)
    Image.fromarray(right).save(good_right)
    one_frame = _save_mpo(tmp_path / "one-frame.mpo", left, None)
    lonely = tmp_path / "lonely-left.png"
    Image.fromarray(left[:, :400]).save(lonely)
    big, small = tmp_path / "csv" / "big.png", tmp_path / "csv" / "small.png"
    big.parent.mkdir()
    Image.fromarray(left).save(big)
    Image.fromarray(right[:200, :300]).save(small)
    pairs = tmp_path / "csv" / "pairs.csv"
    pairs.write_text("left,right\nbig.png,small.png\nbig.png,gone.png\n")
    result = runner.invoke(
        args=["ingest", str(good_left), str(good_right), str(one_frame), str(lonely), "--pairs", str(pairs), "--json"]
    )
    assert result.exit_code == 1
    report = json.loads(result.output)
    assert report["ingested"] == 1 and report["cards"][0]["stereo"]["kind"] == "pair"
    reasons = {entry["path"]: entry["reason"] for entry in report["rejected"]}
    assert "1 frame" in reasons[str(one_frame)]
    assert "no right view" in reasons[str(lonely)]
    assert "differ too much" in reasons[f"{big} + {small}"]
    assert "one view of the pair is missing" in reasons[f"{pairs}:3"] and "gone.png" in reasons[f"{pairs}:3"]
    assert len(report["rejected"]) == 4
    [card] = _cards(app)
    assert [o["sha256"] for o in card.stereo_source["originals"]] == [_sha(good_left), _sha(good_right)]
    assert card.stereo_source["matched_by"] == "file names (good_<eye>.png)"


def test_real_stereo_inputs_become_one_card_each_and_run_through_the_pipeline(
    app, runner, client, login, tmp_path, data_dir, shared_data, decide_orientation
) -> None:
    """An MPO made from a real Keystone-Mast scan's halves, the depthy 7995 left/right pair (two
    files that used to be two culled cards) and a real JPS (stored parallel: the check says so)."""
    from pipeline.io import read_image

    scan = read_image(shared_data / "stereocards/keystone_mast_raw_scans/09995.jpg")
    half = scan.shape[1] // 2
    mpo = _save_mpo(tmp_path / "09995.mpo", np.ascontiguousarray(scan[:, :half]), np.ascontiguousarray(scan[:, half : 2 * half]))
    depthy = shared_data / "stereocards/cropped_pairs/depthy_7995"
    jps = shared_data / "stereocards/cropped_pairs/jps/8618s.jps"
    result = runner.invoke(args=["ingest", str(mpo), str(depthy), str(jps), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    # 7995l-depth.jpg has no right-eye twin: it is a plain image of its own, not part of the pair.
    kinds = sorted(entry.get("stereo", {}).get("kind", "plain") for entry in report["cards"])
    assert kinds == ["mpo", "pair", "plain", "side_by_side"]
    cards = {card.source_name: card for card in _cards(app)}
    pair = cards["7995l-image.jpg"]
    assert [o["source_name"] for o in pair.stereo_source["originals"]] == ["7995l-image.jpg", "7995r-image.jpg"]
    assert [o["sha256"] for o in pair.stereo_source["originals"]] == [
        _sha(depthy / "7995l-image.jpg"),
        _sha(depthy / "7995r-image.jpg"),
    ]
    assert (pair.width, pair.height) == (2 * 1121, 1119)
    # The JPS is stored parallel whatever its convention says; the check notices.
    check = cards["8618s.jps"].stereo_source["eye_order_check"]
    assert check["suggests"] == "cross" and check["agrees"] is False  # the card image was swapped by the default
    login("curator")
    page = client.get(f"/cards/{cards['8618s.jps'].id}").get_data(as_text=True)
    assert "<strong>disagrees</strong>: the halves look cross-eyed as stored" in page

    decide_orientation()  # made from known eyes: a curator says so (undecided cards are not rectified)
    run = runner.invoke(args=["run", "--stages", "filter,rectify,disparity,grade", "--json"])
    assert run.exit_code in (0, 1), run.output
    listed = {c["source"]: c["stages"] for c in json.loads(runner.invoke(args=["cards", "--json"]).output)["cards"]}
    assert listed["7995l-image.jpg"]["filter"]["outcome"] == "pass"  # as two cards, both were culled
    assert listed["09995.mpo"]["filter"]["outcome"] == "pass"
    assert listed["09995.mpo"]["grade"]["status"] == "done"
    assert listed["8618s.jps"]["filter"]["outcome"] == "pass"
    assert listed["8618s.jps"]["grade"]["status"] == "done"
    # Every stage of the pair recorded an outcome (rectification may refuse it with a typed reason).
    for stage in ("rectify", "disparity", "grade"):
        assert listed["7995l-image.jpg"][stage]["status"] in ("done", "failed", "skipped"), stage


def test_a_pairs_csv_alone_is_enough_and_a_bad_csv_is_one_rejection(app, runner, tmp_path) -> None:
    left, right = _motorcycle_views()
    Image.fromarray(left).save(tmp_path / "first view.png")
    Image.fromarray(right).save(tmp_path / "second view.png")
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("Left,Right\nfirst view.png,second view.png\n")
    result = runner.invoke(args=["ingest", "--pairs", str(pairs), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["ingested"] == 1 and report["cards"][0]["stereo"]["kind"] == "pair"
    [card] = _cards(app)
    assert card.stereo_source["matched_by"] == "pairs CSV row 2" and card.source_name == "first view.png"
    no_header = tmp_path / "no-header.csv"
    no_header.write_text("a.png,b.png\n")
    bad = json.loads(runner.invoke(args=["ingest", "--pairs", str(no_header), "--json"]).output)
    assert bad["rejected"] == [
        {
            "path": str(no_header),
            "reason": "cannot read the pairs CSV: expected a header with 'left' and 'right' columns, got ['a.png', 'b.png']",
        }
    ]

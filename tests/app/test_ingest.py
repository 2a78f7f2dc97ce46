"""``keystone ingest``: content-addressed store, duplicates, resume, metadata, and every bad input."""

from __future__ import annotations

import json
import os
import stat
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import func, select

from app import ingest as ingest_module
from app.cli import cli
from app.db import db
from app.models import Card, MetadataRecord

pytestmark = pytest.mark.both_databases


def stereo_card(scale: float = 0.4, shift: int = 0) -> np.ndarray:
    """A small real stereo card: Motorcycle's two views side by side on a grey gutter."""
    from skimage import data, transform

    left, right, _ = data.stereo_motorcycle()
    if shift:
        right = np.roll(right, shift, axis=1)
    left = (transform.rescale(left, scale, channel_axis=2) * 255).astype(np.uint8)
    right = (transform.rescale(right, scale, channel_axis=2) * 255).astype(np.uint8)
    gutter = np.full((left.shape[0], 12, 3), 200, np.uint8)
    return np.concatenate([left, gutter, right], axis=1)


def png_bomb(path: Path, width: int = 60_000, height: int = 60_000) -> None:
    """A 1 KB PNG whose header claims width x height pixels (a decompression bomb)."""

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + chunk(b"IEND", b""))


@pytest.fixture
def scans(tmp_path: Path) -> Path:
    folder = tmp_path / "scans"
    (folder / "box 1").mkdir(parents=True)
    Image.fromarray(stereo_card()).save(folder / "1996.0009.17827.jpg", quality=92)
    Image.fromarray(stereo_card(shift=3)).save(folder / "box 1" / "card_b.png")
    grey16 = (stereo_card()[..., 0].astype(np.uint16) * 257)
    Image.fromarray(grey16).save(folder / "box 1" / "card_c.tif")
    Image.fromarray(stereo_card(shift=6)).save(folder / "card_d.jps", format="JPEG")
    (folder / "notes.txt").write_text("not an image, ignored inside folders")
    return folder


def invoke(runner, *args: str):  # type: ignore[no-untyped-def]
    result = runner.invoke(cli, list(args))
    return result, (json.loads(result.stdout) if "--json" in args and result.stdout.strip() else None)


def test_ingest_folder_recursively_into_content_addressed_store(app, runner, scans):
    result, report = invoke(runner, "ingest", str(scans), "--collection", "nypl", "--json")
    assert result.exit_code == 0, result.output
    assert report["ingested"] == 4 and report["duplicates"] == 0 and report["rejected"] == []
    data_dir = Path(app.config["KEYSTONE_DATA_DIR"])
    with app.app_context():
        cards = db.session.scalars(select(Card).order_by(Card.source_name)).all()
        assert [c.source_name for c in cards] == ["1996.0009.17827.jpg", "card_b.png", "card_c.tif", "card_d.jps"]
        for card in cards:
            # A JPS is cross-eyed by default: its card image is derived (halves swapped, see
            # app.stereo_ingest) and its original is kept, as it came, in stereo_source.
            original = card.stereo_source["originals"][0] if card.stereo_source else None
            content_hash = original["sha256"] if original else card.content_hash
            stored = data_dir / (original["stored_path"] if original else card.stored_path)
            assert stored.name.startswith(content_hash)
            assert str(stored.relative_to(data_dir)).startswith(f"originals/{content_hash[:2]}/")
            assert stored.read_bytes() == Path(card.source_path).read_bytes()
            assert not stored.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
            assert (card.width, card.height) == (604, 200)
            assert card.collection.name == "nypl"
        assert {c.image_format for c in cards} == {"JPEG", "PNG", "TIFF"}


def test_duplicates_by_hash_are_a_no_op_that_says_so(app, runner, scans, tmp_path):
    invoke(runner, "ingest", str(scans), "--json")
    copy = tmp_path / "copy_of_b.png"
    copy.write_bytes((scans / "box 1" / "card_b.png").read_bytes())
    result, report = invoke(runner, "ingest", str(scans), str(copy), "--json")
    assert result.exit_code == 0
    assert report["ingested"] == 0 and report["duplicates"] == 5
    reasons = {Path(d["path"]).name: d["reason"] for d in report["duplicate_files"]}
    assert "same content as card" in reasons["copy_of_b.png"] and "card_b.png" in reasons["copy_of_b.png"]
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Card)) == 4


def test_interrupted_ingest_resumes(app, runner, scans, monkeypatch):
    real_ingest_one = ingest_module._ingest_one
    calls = {"n": 0}

    def crash_on_third(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # the operator's Ctrl+C, or a killed process
        return real_ingest_one(*args, **kwargs)

    monkeypatch.setattr(ingest_module, "_ingest_one", crash_on_third)
    result, _ = invoke(runner, "ingest", str(scans), "--json")
    assert result.exit_code != 0
    with app.app_context():
        # The JPS went through the stereo hook before the ordinary files: it and two of those are in.
        assert db.session.scalar(select(func.count()).select_from(Card)) == 3
    monkeypatch.setattr(ingest_module, "_ingest_one", real_ingest_one)
    result, report = invoke(runner, "ingest", str(scans), "--json")
    assert result.exit_code == 0
    assert report["ingested"] == 1 and report["duplicates"] == 3
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Card)) == 4
    leftovers = [p for p in Path(app.config["KEYSTONE_DATA_DIR"]).rglob("*.tmp")]
    assert leftovers == []


def test_store_file_without_row_is_completed_on_rerun(app, runner, scans):
    """A crash between copying the original and committing its row leaves a stored file; rerun adopts it."""
    from app.ingest import sha256_file, store_original

    source = scans / "1996.0009.17827.jpg"
    store_original(source, sha256_file(source), Path(app.config["KEYSTONE_DATA_DIR"]))
    result, report = invoke(runner, "ingest", str(source), "--json")
    assert result.exit_code == 0 and report["ingested"] == 1


def test_every_bad_input_is_rejected_with_a_reason_and_the_rest_goes_on(app, runner, scans, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    good = scans / "1996.0009.17827.jpg"
    jpeg = good.read_bytes()
    (bad / "truncated.jpg").write_bytes(jpeg[: len(jpeg) // 2])
    (bad / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(2000))
    (bad / "empty.jpg").write_bytes(b"")
    (bad / "text.tif").write_text("this is not a TIFF")
    png_bomb(bad / "bomb.png")
    (bad / "dangling.jpg").symlink_to(tmp_path / "nowhere.jpg")
    missing = tmp_path / "missing-folder"
    unsupported = tmp_path / "scan.gif"
    unsupported.write_bytes(b"GIF89a")

    result, report = invoke(runner, "ingest", str(bad), str(missing), str(unsupported), str(good), "--json")
    assert result.exit_code == 1
    assert report["ingested"] == 1
    reasons = {Path(r["path"]).name: r["reason"] for r in report["rejected"]}
    assert "truncated" in reasons["truncated.jpg"]
    assert "not an image" in reasons["corrupt.png"] or "corrupt" in reasons["corrupt.png"]
    assert "empty file" in reasons["empty.jpg"]
    assert "not an image" in reasons["text.tif"]
    assert "decompression bomb" in reasons["bomb.png"] and "3,600,000,000" in reasons["bomb.png"]
    assert "symbolic link" in reasons["dangling.jpg"] or "no such file" in reasons["dangling.jpg"]
    assert "no such file or folder" in reasons["missing-folder"]
    assert "unsupported file type '.gif'" in reasons["scan.gif"]
    stored = list((Path(app.config["KEYSTONE_DATA_DIR"]) / "originals").rglob("*.*"))
    assert len(stored) == 1  # nothing of the rejected files reached the store


def test_pixel_cap_is_configurable(app, runner, scans):
    app.config["KEYSTONE_MAX_PIXELS"] = 100_000
    result, report = invoke(runner, "ingest", str(scans / "1996.0009.17827.jpg"), "--json")
    assert result.exit_code == 1
    assert "exceeds the cap of 100,000" in report["rejected"][0]["reason"]


def test_human_output_and_exit_code(app, runner, scans, tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    result = runner.invoke(cli, ["ingest", str(scans), str(tmp_path / "empty.png")])
    assert result.exit_code == 1
    assert "ingested 4, duplicates 0, rejected 1" in result.output
    assert "empty.png: empty file (0 bytes)" in result.output


def test_metadata_tidy_emuseum_attaches_by_accession_and_keeps_unknown_columns(app, runner, scans, tmp_path):
    csv_path = tmp_path / "records.csv"
    csv_path.write_text(
        "emuseum_key,Accession Number,Title,Date,Subjects,Shelf\n"
        '26348,1996.0009.17827,"""End of the Trail""",1915,"Sculpture\nExhibition buildings",B-12\n'
        "86636,1996.0009.28024,Men looking at stereo cards,[Date not indicated],Stereoscopes,B-13\n"
        "86637,1996.0009.28025,Too many,fields,here,x,y\n"
    )
    result, report = invoke(runner, "ingest", str(scans), "--metadata", str(csv_path), "--json")
    assert result.exit_code == 1  # one malformed row and one row with no image
    assert report["ingested"] == 4
    assert report["metadata"] == {"rows": 2, "matched": 1, "unmatched": 1}
    reasons = {r["path"].rsplit(":", 1)[1]: r["reason"] for r in report["rejected"]}
    assert "has 7 fields, the header has 6" in reasons["3"]
    assert "1996.0009.28024" in reasons["2"] and "matches no ingested image" in reasons["2"]
    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "1996.0009.17827.jpg"))
        assert card.accession == "1996.0009.17827"
        assert card.source_metadata["title"] == '"End of the Trail"'
        assert card.source_metadata["Shelf"] == "B-12"
        assert card.source_metadata["Subjects"] == "Sculpture\nExhibition buildings"


def test_metadata_row_kept_until_its_image_arrives(app, runner, scans, tmp_path):
    csv_path = tmp_path / "plain.csv"
    csv_path.write_text("file_name,title,photographer\ncard_b.png,Falls,Kilburn\nlater.jpg,Later card,Unknown\n")
    result, report = invoke(runner, "ingest", str(scans / "box 1" / "card_b.png"), "--metadata", str(csv_path), "--json")
    assert report["metadata"]["matched"] == 1 and report["metadata"]["unmatched"] == 1
    later = tmp_path / "later.jpg"
    Image.fromarray(stereo_card(shift=9)).save(later)
    result, report = invoke(runner, "ingest", str(later), "--json")
    assert result.exit_code == 0
    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "later.jpg"))
        assert card.source_metadata["title"] == "Later card" and card.source_metadata["creator"] == "Unknown"
        assert db.session.scalar(select(func.count()).select_from(MetadataRecord)) == 2


def test_metadata_file_without_key_column_is_rejected_whole(app, runner, scans, tmp_path):
    csv_path = tmp_path / "nokey.csv"
    csv_path.write_text("title,date\nA,1900\n")
    result, report = invoke(runner, "ingest", str(scans), "--metadata", str(csv_path), "--json")
    assert result.exit_code == 1 and report["ingested"] == 4
    assert "no key column" in report["rejected"][0]["reason"]


def test_real_emuseum_exports(app, runner, shared_data, tmp_path):
    """Both real exports (tidy and transposed) load all 1,371 records and attach by accession."""
    card_path = tmp_path / "1996.0009.17827.png"
    Image.fromarray(stereo_card()).save(card_path)
    for name in ("keystone_mast_records.csv", "photo_infos_1370.csv"):
        result, report = invoke(runner, "ingest", str(card_path), "--metadata",
                                str(shared_data / "keystone_mast_metadata" / name), "--json")
        assert report["metadata"]["rows"] == 1371
        assert report["metadata"]["matched"] == 1
        assert result.exit_code == 1  # 1,370 rows have no image here, each listed
        assert len(report["rejected"]) == 1370
    with app.app_context():
        card = db.session.scalar(select(Card))
        assert card.accession == "1996.0009.17827"
        assert card.source_metadata["title"] == '"End of the Trail"'
        assert card.source_metadata["publisher"] == "Keystone View Company"
        assert card.source_metadata["emuseum_key"] == "26348"


def test_ingest_needs_something_to_do(runner):
    result = runner.invoke(cli, ["ingest"])
    assert result.exit_code == 2 and "at least one PATH" in result.output

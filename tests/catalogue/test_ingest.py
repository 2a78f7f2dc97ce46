"""``keystone ingest``: content-addressed store, duplicates, resume, metadata, and every bad input."""

from __future__ import annotations

import io
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

from app.cli import cli
from catalogue import ingest as ingest_module
from core.db import db
from core.models import Card, MetadataRecord

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
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + chunk(b"IEND", b"")
    )


@pytest.fixture
def scans(tmp_path: Path) -> Path:
    folder = tmp_path / "scans"
    (folder / "box 1").mkdir(parents=True)
    Image.fromarray(stereo_card()).save(folder / "1996.0009.17827.jpg", quality=92)
    Image.fromarray(stereo_card(shift=3)).save(folder / "box 1" / "card_b.png")
    grey16 = stereo_card()[..., 0].astype(np.uint16) * 257
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
            # catalogue.stereo_ingest) and its original is kept, as it came, in stereo_source.
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
    from catalogue.originals import sha256_file, store_original

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
    text_bomb = io.BytesIO()
    Image.new("RGB", (64, 32)).save(text_bomb, "PNG")
    chunk = b"k\0\0" + zlib.compress(b"A" * (2 << 20))  # a 2 KB PNG whose zTXt inflates to 2 MiB
    packed = struct.pack(">I", len(chunk)) + b"zTXt" + chunk + struct.pack(">I", zlib.crc32(b"zTXt" + chunk))
    (bad / "ztxt.png").write_bytes(text_bomb.getvalue()[:33] + packed + text_bomb.getvalue()[33:])
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
    assert reasons["ztxt.png"] == "cannot open: ValueError: Decompressed data too large for PngImagePlugin.MAX_TEXT_CHUNK"
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
        result, report = invoke(
            runner, "ingest", str(card_path), "--metadata", str(shared_data / "keystone_mast_metadata" / name), "--json"
        )
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


# ---- a database that refuses writes, unreadable paths, files that are not files ----


def _refuse_card_commits(monkeypatch):  # type: ignore[no-untyped-def]
    """Make every commit after the collection's raise what SQLite says on a full disk."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    real_commit = db.session.commit
    calls = {"n": 0}

    def commit() -> None:
        calls["n"] += 1
        if calls["n"] > 1:  # the first commit creates the collection
            raise OperationalError("INSERT INTO cards ...", {}, sqlite3.OperationalError("database or disk is full"))
        real_commit()

    monkeypatch.setattr(db.session, "commit", commit)


def test_failed_database_write_removes_the_stored_original_and_says_why(app, runner, scans, monkeypatch):
    _refuse_card_commits(monkeypatch)
    result, report = invoke(runner, "ingest", str(scans), "--json")
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit)  # exit 1, not a traceback
    assert report["ingested"] == 0 and len(report["rejected"]) == 4
    for entry in report["rejected"]:
        assert "database refused the write (OperationalError: database or disk is full)" in entry["reason"]
        assert "the stored copy was removed" in entry["reason"]
    data_dir = Path(app.config["KEYSTONE_DATA_DIR"])
    assert [p for p in (data_dir / "originals").rglob("*") if p.is_file()] == []  # no orphan original
    monkeypatch.undo()
    with app.app_context():
        assert db.session.scalar(select(func.count()).select_from(Card)) == 0
    result, report = invoke(runner, "ingest", str(scans), "--json")  # space freed: the same command works
    assert result.exit_code == 0 and report["ingested"] == 4


def test_named_pipes_are_rejected_without_blocking(app, runner, scans, tmp_path):
    os.mkfifo(scans / "box 1" / "pipe.jpg")
    named = tmp_path / "named-pipe.png"
    os.mkfifo(named)
    result, report = invoke(runner, "ingest", str(scans), str(named), "--json")
    assert result.exit_code == 1 and report["ingested"] == 4
    reasons = {Path(r["path"]).name: r["reason"] for r in report["rejected"]}
    assert reasons == {
        "pipe.jpg": "a named pipe (FIFO), not an image file",
        "named-pipe.png": "a named pipe (FIFO), not an image file",
    }


def test_linked_folder_inside_a_folder_is_reported_not_skipped(app, runner, scans, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    Image.fromarray(stereo_card(shift=12)).save(elsewhere / "linked.png")
    (scans / "box 2").symlink_to(elsewhere, target_is_directory=True)
    result, report = invoke(runner, "ingest", str(scans), "--json")
    assert result.exit_code == 1 and report["ingested"] == 4
    assert [Path(r["path"]).name for r in report["rejected"]] == ["box 2"]
    assert "not followed inside folders" in report["rejected"][0]["reason"]
    result, report = invoke(runner, "ingest", str(scans / "box 2"), "--json")  # named: followed
    assert result.exit_code == 0 and report["ingested"] == 1


UNPRIVILEGED_INGEST = r"""
import json, os, shutil, sys
from pathlib import Path

from PIL import Image

from app import create_app

Image.init()  # the image plugins load lazily: load them while the interpreter's files are readable
app = create_app()
runner = app.test_cli_runner()
from app.cli import cli

root, uid, gid = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
warm = runner.invoke(cli, ["ingest", str(root / "warm-up.png"), "--json"])  # imports every module on the path
assert warm.exit_code == 0, warm.output
for folder in (root / "instance", root / "data"):
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in [dirpath, *(os.path.join(dirpath, f) for f in dirnames + filenames)]:
            os.chown(name, uid, gid)
os.setgroups([])
os.setgid(gid)
os.setuid(uid)
result = runner.invoke(cli, ["ingest", *sys.argv[4:], "--json"])
print(json.dumps({"exit_code": result.exit_code, "stdout": result.stdout, "exception": repr(result.exception)}))
"""


def test_unreadable_folders_and_files_are_rejected_items_for_an_unprivileged_user(scans):
    """Run as ``nobody`` (root reads through chmod 000): an unreadable subfolder, an unreadable
    file and an unreadable folder named on the command line are each a rejected item, the rest
    is ingested, and the command exits 1 (click's own check used to end it with exit 2); an
    unreadable metadata CSV is one rejected item too."""
    import pwd
    import shutil
    import subprocess
    import sys
    import tempfile

    if os.geteuid() != 0:
        pytest.skip("needs root to switch to an unprivileged user")
    account = pwd.getpwnam("nobody")
    root = Path(tempfile.mkdtemp(prefix="keystone-unreadable-"))
    try:
        root.chmod(0o755)
        work = root / "scans"
        shutil.copytree(scans, work)
        Image.fromarray(stereo_card(shift=15)).save(root / "warm-up.png")
        (work / "locked box").mkdir()
        Image.fromarray(stereo_card(shift=18)).save(work / "locked box" / "hidden.png")
        (work / "locked box").chmod(0)
        locked_file = root / "locked.png"
        Image.fromarray(stereo_card(shift=21)).save(locked_file)
        locked_file.chmod(0)
        locked_folder = root / "locked-folder"
        locked_folder.mkdir(mode=0)
        locked_csv = root / "locked.csv"
        locked_csv.write_text("file_name,title\ncard_b.png,Falls\n")
        locked_csv.chmod(0)
        (root / "instance").mkdir()
        env = {
            **os.environ,
            "KEYSTONE_INSTANCE_PATH": str(root / "instance"),
            "KEYSTONE_DATA_DIR": str(root / "data"),
            "KEYSTONE_DATABASE_URL": f"sqlite:///{root / 'instance' / 'keystone.sqlite3'}",
            "KEYSTONE_SECRET_KEY": "test-secret",
            "PYTHONPATH": str(Path(__file__).resolve().parents[2]),
        }
        done = subprocess.run(
            [
                sys.executable,
                "-c",
                UNPRIVILEGED_INGEST,
                str(root),
                str(account.pw_uid),
                str(account.pw_gid),
                str(work),
                str(locked_file),
                str(locked_folder),
                "--metadata",
                str(locked_csv),
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        outcome = json.loads(done.stdout.strip().splitlines()[-1])
        assert outcome["exit_code"] == 1, outcome
        report = json.loads(outcome["stdout"])
        assert report["ingested"] == 4
        reasons = {r["path"]: r["reason"] for r in report["rejected"]}
        assert reasons == {
            str(work / "locked box"): "cannot list folder: Permission denied; nothing under it was ingested",
            str(locked_file): "unreadable: Permission denied",
            str(locked_folder): "cannot list folder: Permission denied; nothing under it was ingested",
            str(locked_csv): "cannot read metadata: Permission denied",
        }
    finally:
        for locked in root.rglob("locked*"):
            locked.chmod(0o700)
        shutil.rmtree(root, ignore_errors=True)


# ---- metadata CSVs: one bad row or column costs only itself ----


def _metadata_report(runner, scans, csv_path):  # type: ignore[no-untyped-def]
    result, report = invoke(runner, "ingest", str(scans), "--metadata", str(csv_path), "--json")
    reasons = {r["path"].rsplit(":", 1)[-1] if r["path"] != str(csv_path) else "file": r["reason"] for r in report["rejected"]}
    return result, report, reasons


def test_unterminated_quote_rejects_its_row_alone(app, runner, scans, tmp_path):
    csv_path = tmp_path / "quote.csv"
    csv_path.write_text(
        "file_name,title,photographer\n"
        "card_b.png,Falls,Kilburn\n"
        'card_c.tif,"Bridge at night,Kilburn\n'  # the quote never closes: it used to eat the file
        'card_d.jps,"Quoted, fine",Underwood\n'
        "1996.0009.17827.jpg,End of the Trail,Keystone\n"
    )
    result, report, reasons = _metadata_report(runner, scans, csv_path)
    assert result.exit_code == 1
    assert report["metadata"] == {"rows": 3, "matched": 3, "unmatched": 0}
    assert set(reasons) == {"2"}
    assert "line 3" in reasons["2"] and "unterminated quote" in reasons["2"]
    with app.app_context():
        titles = dict(db.session.execute(select(Card.source_name, Card.source_metadata["title"].as_string())).all())
    assert titles == {
        "card_b.png": "Falls",
        "card_c.tif": None,
        "card_d.jps": "Quoted, fine",
        "1996.0009.17827.jpg": "End of the Trail",
    }


def test_stray_quote_that_would_merge_rows_is_undone_line_by_line(app, runner, scans, tmp_path):
    csv_path = tmp_path / "stray.csv"
    csv_path.write_text(
        "file_name,title,photographer\n"
        'card_b.png,"Falls,Kilburn\n'  # opens a quote that the stray one two lines down closes
        "card_c.tif,Bridge,Kilburn\n"
        'card_d.jps,Quarry,Underwood"\n'
    )
    _, report, reasons = _metadata_report(runner, scans, csv_path)
    assert report["metadata"]["rows"] == 2 and set(reasons) == {"1"}
    assert "runs over 3 lines" in reasons["1"]


def test_oversize_field_rejects_its_row_alone(app, runner, scans, tmp_path):
    import csv

    csv_path = tmp_path / "big.csv"
    huge = "x" * 200_000
    csv_path.write_text(f"file_name,title\ncard_b.png,Falls\ncard_c.tif,{huge}\ncard_d.jps,Quarry\n")
    _, report, reasons = _metadata_report(runner, scans, csv_path)
    assert report["metadata"] == {"rows": 2, "matched": 2, "unmatched": 0}
    assert set(reasons) == {"2"}
    assert f"longer than {csv.field_size_limit():,} characters" in reasons["2"]


def test_conflicting_rows_for_one_key_are_all_rejected_and_repeats_load_once(app, runner, scans, tmp_path):
    csv_path = tmp_path / "dupes.csv"
    csv_path.write_text(
        "file_name,accession,title\n"
        "card_b.png,,Falls\n"
        "card_b.png,,Falls at dawn\n"  # conflicts with row 1: neither loads
        "card_d.jps,,Quarry\n"
        "card_d.jps,,Quarry\n"  # repeats row 3 exactly: row 3 loads
        ",1996.0009.17827,End of the Trail\n"
        "CARD_C.TIF,1996.0009.17827,Other\n"  # shares row 5's accession with other values
    )
    result, report, reasons = _metadata_report(runner, scans, csv_path)
    assert result.exit_code == 1
    assert report["metadata"]["rows"] == 1
    assert set(reasons) == {"1", "2", "4", "5", "6"}
    assert "rows 1, 2 all describe file card_b.png with different values" in reasons["1"]
    assert reasons["2"] == reasons["1"]
    assert "repeats row 3" in reasons["4"] and "the first is loaded" in reasons["4"]
    assert "rows 5, 6 all describe accession 1996.0009.17827" in reasons["5"]
    with app.app_context():
        cards = {c.source_name: c for c in db.session.scalars(select(Card))}
        assert cards["card_d.jps"].source_metadata["title"] == "Quarry"
        assert "title" not in cards["card_b.png"].source_metadata
        assert cards["1996.0009.17827.jpg"].accession is None


def test_duplicated_column_is_an_error_for_that_column_and_the_rest_loads(app, runner, scans, tmp_path):
    csv_path = tmp_path / "columns.csv"
    csv_path.write_text("file_name,Title,photographer,title \ncard_b.png,Falls,Kilburn,Cascade\n")
    result, report, reasons = _metadata_report(runner, scans, csv_path)
    assert result.exit_code == 1 and report["metadata"]["matched"] == 1
    assert reasons == {
        "file": "metadata: column 'Title / title' appears 2 times (columns 2 and 4): none of its "
        "values is loaded; rename or remove the copies and ingest the file again"
    }
    with app.app_context():
        card = db.session.scalar(select(Card).where(Card.source_name == "card_b.png"))
        assert card.source_metadata == {"file_name": "card_b.png", "photographer": "Kilburn", "creator": "Kilburn"}


def test_duplicated_key_column_rejects_the_file_with_a_clear_reason(app, runner, scans, tmp_path):
    csv_path = tmp_path / "keys.csv"
    csv_path.write_text("file_name,title,file_name\ncard_b.png,Falls,card_c.tif\n")
    _, report, reasons = _metadata_report(runner, scans, csv_path)
    assert report["ingested"] == 4
    assert "key column 'file_name' appears 2 times (columns 1 and 3)" in reasons["file"]

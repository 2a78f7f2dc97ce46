"""keystone verify / verify_release: a sound release passes; each kind of damage is named."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.fixture
def release(app, tmp_path, processed_cards, review_card) -> Path:  # type: ignore[no-untyped-def]
    from exports.release import publish_release

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    with app.app_context():
        report = publish_release(tmp_path / "out", formats=("keystonedepth", "parquet", "webdataset"))
    return Path(report.path)


def _verify(root: Path):  # type: ignore[no-untyped-def]
    from exports.verify import verify_release

    return verify_release(root)


def test_a_sound_release_passes_and_mlcroissant_validates_it_offline(release: Path) -> None:
    report = _verify(release)
    assert report.ok, report.problems
    assert report.checked == len((release / "SHA256SUMS").read_text().splitlines()) > 20
    mlcroissant = pytest.importorskip("mlcroissant", reason="mlcroissant is not installed (pip install mlcroissant)")
    done = subprocess.run(
        [sys.executable, "-m", "mlcroissant.scripts.validate", "--jsonld", str(release / "croissant.json")],
        capture_output=True,
        text=True,
        timeout=300,
        env={"PATH": "/usr/bin:/bin", "NO_PROXY": "*", "HOME": str(release.parent)},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    # mlcroissant checks the sha256 of the file it reads: the card records load offline.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # rdflib's own deprecations inside mlcroissant
        records = list(mlcroissant.Dataset(str(release / "croissant.json")).records("cards"))
    assert sorted(r["cards/grade"] for r in records) == [b"few", b"few"]


def test_a_flipped_byte_is_caught(release: Path) -> None:
    target = next(release.glob("processed/rectified/disp_info_LR/*L.exr"))
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x01
    target.write_bytes(bytes(data))
    report = _verify(release)
    relative = target.relative_to(release).as_posix()
    assert report.problems == [{"path": relative, "problem": "sha256 does not match SHA256SUMS (file changed or corrupted)"}]


def test_a_missing_file_is_caught(release: Path) -> None:
    target = next(release.glob("cropped/cropped_full_LR/*R.png"))
    target.unlink()
    report = _verify(release)
    assert {"path": target.relative_to(release).as_posix(), "problem": "listed in SHA256SUMS but missing"} in report.problems
    assert len(report.problems) == 1


def test_an_extra_file_is_caught(release: Path) -> None:
    (release / "cropped/cropped_full_LR/99999L.png").write_bytes(b"\x89PNG extra")
    report = _verify(release)
    assert report.problems == [{"path": "cropped/cropped_full_LR/99999L.png", "problem": "present but not listed in SHA256SUMS"}]


def test_a_corrupted_croissant_is_caught(release: Path) -> None:
    import hashlib

    document = json.loads((release / "croissant.json").read_text())
    document["distribution"][0]["sha256"] = "0" * 64
    text = json.dumps(document).encode()
    (release / "croissant.json").write_bytes(text)
    # Even with SHA256SUMS updated to match, the file's own content is checked.
    sums = (release / "SHA256SUMS").read_text().splitlines()
    sums = [f"{hashlib.sha256(text).hexdigest()}  croissant.json" if line.endswith("  croissant.json") else line for line in sums]
    (release / "SHA256SUMS").write_text("\n".join(sums) + "\n")
    report = _verify(release)
    first = document["distribution"][0]["contentUrl"]
    assert report.problems == [{"path": "croissant.json", "problem": f"sha256 of {first!r} differs from SHA256SUMS"}]

    (release / "croissant.json").write_text("{not json")
    problems = _verify(release).problems
    assert {"path": "croissant.json", "problem": "sha256 does not match SHA256SUMS (file changed or corrupted)"} in problems
    assert any(p["path"] == "croissant.json" and p["problem"].startswith("not valid JSON") for p in problems)


def test_a_parquet_shard_with_another_schema_is_caught(release: Path) -> None:
    import hashlib

    import pyarrow as pa
    import pyarrow.parquet as pq

    shard = release / "data/train-00000-of-00001.parquet"
    table = pq.read_table(shard).drop_columns(["depth_512"])
    pq.write_table(table, shard)
    digest = hashlib.sha256(shard.read_bytes()).hexdigest()
    sums = [
        f"{digest}  data/train-00000-of-00001.parquet" if line.endswith(".parquet") else line
        for line in (release / "SHA256SUMS").read_text().splitlines()
    ]
    (release / "SHA256SUMS").write_text("\n".join(sums) + "\n")
    problems = _verify(release).problems
    assert {"path": "data/train-00000-of-00001.parquet", "problem": "Parquet schema differs from the release schema"} in problems
    assert pa is not None


def test_the_streamed_croissant_equals_the_document_dumped_whole() -> None:
    import io

    from exports.croissant import croissant_document, write_croissant

    options = dict(
        version="1.2.0",
        date="2026-03-01T10:00:00+00:00",
        card_count=2,
        grade_counts={"few": 1, "some": 1},
        crowd={"answers_per_card": 3.5},
        notes="n",
    )
    for files in ({}, {"cards.jsonl": ("a" * 64, 10), "data/train-00000-of-00001.parquet": ("b" * 64, 2048)}):
        buffer = io.BytesIO()
        write_croissant(buffer, files, **options)
        whole = json.dumps(croissant_document(files=files, **options), indent=2, sort_keys=True, ensure_ascii=False)
        assert buffer.getvalue().decode() == whole + "\n"
    assert json.loads(buffer.getvalue())["distribution"][1]["contentSize"] == "2048 B"

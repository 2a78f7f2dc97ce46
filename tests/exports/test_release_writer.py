"""publish_release on real pipeline outputs: layouts, versions, reproducibility, crash safety."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest


def _files(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _publish(app, out: Path, **options):  # type: ignore[no-untyped-def]
    from exports.release import publish_release

    with app.app_context():
        return publish_release(out, **options)


@pytest.mark.both_databases
def test_release_layouts_hold_the_pipeline_outputs(app, tmp_path, processed_cards, review_card, data_dir) -> None:
    from exports.formats.parquet import parquet_schema
    from exports.writers import read_exr

    ids = processed_cards(3)
    review_card(ids[0], "few")
    review_card(ids[1], "some", decision="changed", auto_grade="few")
    review_card(ids[2], "failure")  # never released
    report = _publish(app, tmp_path / "out", formats=("keystonedepth", "parquet", "webdataset"))
    root = Path(report.path)
    assert report.version == "1.0.0" and root == (tmp_path / "out" / "1.0.0").resolve()
    assert report.cards == 2 and report.grades == {"few": 1, "some": 1}
    key = f"{ids[0]:05d}"
    for relative in (
        f"cropped/cropped_full_LR/{key}L.png",
        f"cropped/cropped_full_LR/{key}R.png",
        f"processed/rectified/disp_info_LR/{key}L.exr",
        f"processed/rectified/disp_info_LR/{key}R.exr",
        f"processed/depth_512/{key}.exr",
        "README.md",
        "CHANGELOG.md",
        "croissant.json",
        "SHA256SUMS",
        "cards.jsonl",
        "data/train-00000-of-00001.parquet",
        "webdataset/keystone-000000.tar",
    ):
        assert (root / relative).is_file(), relative
    assert not (root / f"cropped/cropped_full_LR/{ids[2]:05d}L.png").exists()
    assert not list((tmp_path / "out").glob(".*partial*"))

    # The EXR holds the pipeline's disparity exactly (float32, NaN where unknown).
    with app.app_context():
        from sqlalchemy import select

        from core.db import db
        from core.models import StageResult

        row = db.session.scalar(select(StageResult).where(StageResult.card_id == ids[0], StageResult.stage == "disparity"))
        expected = np.load(data_dir / row.artifacts["disparity_left"])
        depth = np.load(data_dir / row.artifacts["depth_512"])
    stored = read_exr(root / f"processed/rectified/disp_info_LR/{key}L.exr")
    assert stored.shape == expected.shape and np.array_equal(stored, expected, equal_nan=True)
    assert read_exr(root / f"processed/depth_512/{key}.exr").shape == (512, 512)
    assert np.array_equal(read_exr(root / f"processed/depth_512/{key}.exr"), depth, equal_nan=True)

    # Parquet: the release schema with Hugging Face image columns, typed metadata, real maps.
    import pyarrow.parquet as pq

    table = pq.read_table(root / "data/train-00000-of-00001.parquet")
    assert table.schema.equals(parquet_schema(), check_metadata=False)
    features = json.loads(table.schema.metadata[b"huggingface"])["info"]["features"]
    assert features["rectified_left"] == {"_type": "Image"} and features["card_id"]["dtype"] == "int64"
    rows = table.to_pylist()
    assert [r["card_id"] for r in rows] == ids[:2]
    assert rows[0]["accession"] == "1996.0009.17827" and rows[0]["museum_url"].endswith("/17827")
    assert rows[1]["grade"] == "some" and rows[1]["review_decision"] == "changed" and rows[1]["automatic_grade"] == "few"
    assert rows[0]["rectified_left"]["bytes"][:8] == b"\x89PNG\r\n\x1a\n" and rows[0]["rectified_left"]["path"] == f"{key}L.png"
    disparity = np.asarray(rows[0]["disparity_left"], np.float32)
    assert np.array_equal(disparity, expected, equal_nan=True)
    assert len(rows[0]["H_l"]) == 3 and len(rows[0]["K"][0]) == 3

    # WebDataset: dot-free keys, although accession numbers have dots.
    import tarfile

    with tarfile.open(root / "webdataset/keystone-000000.tar") as tar:
        names = tar.getnames()
        assert {name.split(".", 1)[0] for name in names} == {f"{i:05d}" for i in ids[:2]}
        record = json.loads(tar.extractfile(f"{key}.json").read())
        assert record["accession"] == "1996.0009.17827" and record["grade"] == "few"
        assert {m.mtime for m in tar.getmembers()} == {int(_date(report.date))}

    # No absolute path of this machine inside any text file.
    for path in root.rglob("*"):
        if path.suffix in (".json", ".jsonl", ".md") or path.name == "SHA256SUMS":
            assert str(tmp_path) not in path.read_text()
    with app.app_context():
        from sqlalchemy import select

        from core.audit import AuditEvent
        from core.db import db
        from exports.models import Release

        row = db.session.scalar(select(Release))
        assert row.version == "1.0.0" and row.card_count == 2
        assert row.manifest_sha256 == hashlib.sha256((root / "SHA256SUMS").read_bytes()).hexdigest()
        event = db.session.scalar(select(AuditEvent).where(AuditEvent.entity == "release"))
        assert event.entity_id == row.id and event.after["version"] == "1.0.0"


def _date(text: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(text).timestamp()


def test_versions_follow_the_changes_and_data_files_stay_byte_identical(app, tmp_path, processed_cards, review_card) -> None:
    ids = processed_cards(3)
    review_card(ids[0], "few")
    review_card(ids[1], "some")
    first = _publish(app, tmp_path / "a", notes="first")
    assert first.version == "1.0.0"

    # Same cards, same data: a patch release whose data files are byte for byte the same.
    second = _publish(app, tmp_path / "b", notes="first")
    assert second.version == "1.0.1" and second.changes["kind"] == "patch"
    a, b = _files(Path(first.path)), _files(Path(second.path))
    data = [p for p in a if p not in ("README.md", "CHANGELOG.md", "croissant.json", "SHA256SUMS")]
    assert len(data) > 10 and all(a[p] == b[p] for p in data)

    # A card added: minor.
    review_card(ids[2], "some")
    third = _publish(app, tmp_path / "c")
    assert third.version == "1.1.0" and third.changes["added"] == [ids[2]]

    # A grade changed: major, and the CHANGELOG says which card and why.
    review_card(ids[0], "some", decision="changed", auto_grade="few")
    fourth = _publish(app, tmp_path / "d")
    assert fourth.version == "2.0.0"
    assert fourth.changes["changed"] == [
        {"card_id": ids[0], "why": ["grade changed (few -> some)", "review decision changed (accepted -> changed)"]}
    ]
    changelog = (Path(fourth.path) / "CHANGELOG.md").read_text()
    assert f"card {ids[0]:05d}: grade changed (few -> some)" in changelog and "Against 1.1.0: a major release" in changelog

    # A card rejected after release: removed, a major release.
    review_card(ids[1], "some", decision="rejected")
    fifth = _publish(app, tmp_path / "e")
    assert fifth.version == "3.0.0" and fifth.changes["removed"] == [ids[1]]


def test_same_inputs_give_byte_identical_releases(app, tmp_path, processed_cards, review_card) -> None:
    from core.db import db
    from exports.models import Release

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    first = _publish(app, tmp_path / "one", formats=("keystonedepth", "parquet", "webdataset"), notes="n")
    with app.app_context():  # forget it, so the second run is again 1.0.0 from the same inputs
        db.session.query(Release).delete()
        db.session.commit()
    second = _publish(app, tmp_path / "two", formats=("keystonedepth", "parquet", "webdataset"), notes="n")
    assert first.version == second.version == "1.0.0"
    assert _files(Path(first.path)) == _files(Path(second.path))


def test_a_crash_mid_release_leaves_no_release_and_no_row(app, tmp_path, processed_cards, review_card, monkeypatch) -> None:
    from core.db import db
    from exports.formats import parquet
    from exports.models import Release

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    calls = []

    def exploding_add(self, payload):  # type: ignore[no-untyped-def]
        calls.append(payload.card.card_id)
        if len(calls) == 2:
            raise OSError("disk full (simulated)")
        original_add(self, payload)

    original_add = parquet.ParquetWriter.add
    monkeypatch.setattr(parquet.ParquetWriter, "add", exploding_add)
    with pytest.raises(OSError, match="disk full"):
        _publish(app, tmp_path / "out")
    assert calls == ids
    assert not (tmp_path / "out").exists()  # the publish made the folder to lock it, and leaves none behind
    with app.app_context():
        assert db.session.query(Release).count() == 0


def test_nothing_accepted_is_a_clear_error(app, tmp_path, processed_cards, review_card) -> None:
    from exports.release import ReleaseError

    ids = processed_cards(1)
    review_card(ids[0], "some", decision="pending")
    with pytest.raises(ReleaseError, match="no curator-accepted cards"):
        _publish(app, tmp_path / "out")
    review_card(ids[0], "some")
    with pytest.raises(ReleaseError, match="no curator-accepted cards at grade few"):
        _publish(app, tmp_path / "out", min_grade="few")
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []


def test_a_card_with_a_missing_artifact_is_left_out_with_the_reason(
    app, tmp_path, processed_cards, review_card, data_dir
) -> None:
    from sqlalchemy import select

    from core.db import db
    from core.models import StageResult

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    with app.app_context():
        row = db.session.scalar(select(StageResult).where(StageResult.card_id == ids[1], StageResult.stage == "disparity"))
        (data_dir / row.artifacts["depth_512"]).unlink()
    report = _publish(app, tmp_path / "out")
    assert report.cards == 1
    assert report.excluded == [
        {"card_id": ids[1], "reason": f"disparity artifact 'depth_512' is missing on disk ({row.artifacts['depth_512']})"}
    ]
    assert f"card {ids[1]:05d}: disparity artifact 'depth_512' is missing" in (Path(report.path) / "CHANGELOG.md").read_text()


def test_hugging_face_datasets_loads_the_parquet_shards(app, tmp_path, processed_cards, review_card, monkeypatch) -> None:
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")  # a local folder: nothing to fetch from a hub
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    datasets = pytest.importorskip("datasets", reason="Hugging Face datasets is not installed (pip install datasets)")
    ids = processed_cards(1)
    review_card(ids[0], "few")
    report = _publish(app, tmp_path / "out", formats=("parquet",))
    loaded = datasets.load_dataset(
        "parquet", data_files=str(Path(report.path) / "data" / "*.parquet"), split="train", cache_dir=str(tmp_path / "hf-cache")
    )
    assert isinstance(loaded.features["rectified_left"], datasets.Image)
    row = loaded[0]
    assert row["card_id"] == ids[0] and row["grade"] == "few"
    assert row["rectified_left"].size[0] > 100 and row["cropped_right"].mode == "RGB"
    assert np.asarray(row["depth_512"], np.float32).shape == (512, 512)

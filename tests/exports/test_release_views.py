"""The optional ``views`` release component: the five GD images per card (docs/RELEASES.md).

The views are made by the real views stage (:func:`pipeline.stages.views.views_task`) on the
real rectified Motorcycle pairs that ``keystone run`` produced, at a reduced size to stay fast.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

VIEWS_PARAMS: dict[str, Any] = {"max_side": 160, "preview_side": 64, "preview_frames": 4}


@pytest.fixture
def make_views(app, data_dir, add_stage_result):  # type: ignore[no-untyped-def]
    """Run the views stage on a card's rectified left view and disparity; record the result."""

    def run(card_id: int, **params: Any) -> dict[str, str]:
        from sqlalchemy import select

        from core.db import db
        from core.hooks import approved_decisions
        from core.models import Card
        from pipeline.records import CardTask, card_work_dir, inputs_digest, param_hash
        from pipeline.stages.views import views_task
        from pipeline.view_synthesis import ViewsStageParams
        from runs.specs import available_stages

        settings = ViewsStageParams(**{**VIEWS_PARAMS, **params})
        with app.app_context():
            card = db.session.scalar(select(Card).where(Card.id == card_id))
            latest = card.latest_results()
            rectify, disparity = latest["rectify"], latest["disparity"]
            # the digest keystone run records: of the inputs the views stage builds for the card now
            recorded = inputs_digest(
                dict(available_stages()["views"].inputs(card, approved_decisions([card_id]).get(card_id, {})))
            )
            task = CardTask(
                card_id=card_id,
                content_hash=card.content_hash,
                image_path=str(data_dir / card.stored_path),
                work_dir=str(card_work_dir(data_dir, card.content_hash, "views", param_hash(settings))),
                data_dir=str(data_dir),
                inputs={
                    "left": rectify.artifacts["left"],
                    "disparity_left": disparity.artifacts["disparity_left"],
                    "focal_px": disparity.metrics.get("focal_px"),
                    "grade": "few",
                },
            )
        record = views_task(task, settings)
        assert record.status == "done", record.reason
        add_stage_result(
            card_id,
            "views",
            outcome=None,
            param_hash=record.param_hash,
            metrics={**record.metrics, "inputs_digest": recorded},
            artifacts=record.artifacts,
        )
        return record.artifacts

    return run


def _publish(app, out: Path, formats: tuple[str, ...] = ("keystonedepth", "views")):  # type: ignore[no-untyped-def]
    from exports.release import publish_release

    with app.app_context():
        return publish_release(out, formats=formats)


@pytest.fixture
def three_cards(processed_cards, review_card, make_views, add_stage_result):  # type: ignore[no-untyped-def]
    """Card 0 with real views; card 1 never ran views; card 2 skipped them (graded failure by the
    grader, then changed to ``some`` by a curator, so it is released without views)."""
    ids = processed_cards(3)
    artifacts = make_views(ids[0])
    add_stage_result(ids[2], "views", status="skipped", outcome=None, reason="not needed: graded failure")
    review_card(ids[0], "few")
    review_card(ids[1], "some")
    review_card(ids[2], "some", decision="changed", auto_grade="failure")
    return ids, artifacts


def test_views_are_released_for_cards_that_have_them(app, tmp_path, three_cards, data_dir) -> None:
    from exports.formats.views import view_files
    from exports.writers import read_exr

    ids, artifacts = three_cards
    report = _publish(app, tmp_path / "out")
    root = Path(report.path)
    assert report.cards == 3
    assert report.summaries["views"] == {
        "cards_with_views": 1,
        "cards_without_views": 2,
        "without": {"views not run": 1, "views skipped: not needed: graded failure": 1},
    }
    key = f"{ids[0]:05d}"
    for relative in view_files(key):
        assert (root / relative).is_file(), relative
    assert not (root / "views" / f"{ids[1]:05d}").exists() and not (root / "views" / f"{ids[2]:05d}").exists()
    # The images (grey or RGB, as the card) and the preview byte for byte; depth exactly, as float EXR; cameras name the EXRs.
    for name in ("v0", "v3"):
        assert (root / f"views/{key}/{name}.png").read_bytes() == (data_dir / artifacts[name]).read_bytes()
        depth = np.load(data_dir / artifacts[f"{name}_depth"])
        stored = read_exr(root / f"views/{key}/{name}_depth.exr")
        assert stored.dtype == np.float32 and np.array_equal(stored, depth)
        assert np.isfinite(stored).all() and stored.min() > 0
    assert (root / f"views/{key}/preview.webp").read_bytes()[8:12] == b"WEBP"
    scene = json.loads((root / f"views/{key}/views.json").read_text())
    original = json.loads((data_dir / artifacts["scene"]).read_text())
    assert [v["depth"] for v in scene["views"]] == [f"v{i}_depth.exr" for i in range(5)]
    assert [v["focal_px"] for v in scene["views"]] == [v["focal_px"] for v in original["views"]]
    # The viewer's JPEGs and mesh PNGs are not released, so the released document names none of them.
    assert "mesh" in original and all("web_image" in v for v in original["views"])
    assert "mesh" not in scene and not any("web_image" in v or "mesh" in v for v in scene["views"])
    assert not list((root / f"views/{key}").glob("*.jpg")) and not list((root / f"views/{key}").glob("*_mesh.png"))
    assert scene["width"] == stored.shape[1] and scene["height"] == stored.shape[0] and max(stored.shape) <= 160

    # Every card is listed; cards.jsonl says where the views are or why there are none.
    records = {r["card_id"]: r for r in map(json.loads, (root / "cards.jsonl").read_text().splitlines())}
    assert records[ids[0]]["views"] == {"folder": f"views/{key}", "why_not": None}
    assert records[ids[1]]["views"] == {"folder": None, "why_not": "views not run"}
    assert records[ids[2]]["views"] == {"folder": None, "why_not": "views skipped: not needed: graded failure"}
    assert records[ids[0]]["pipeline"]["views"]["status"] == "done"
    index = [json.loads(line) for line in (root / "views/views.jsonl").read_text().splitlines()]
    assert [(r["key"], r["folder"], r["width"]) for r in index] == [(key, f"views/{key}", scene["width"])]

    # SHA256SUMS and croissant.json cover the views; the dataset card and CHANGELOG count them.
    sums = dict(reversed(line.split("  ", 1)) for line in (root / "SHA256SUMS").read_text().splitlines())
    exr = f"views/{key}/v2_depth.exr"
    assert sums[exr] == hashlib.sha256((root / exr).read_bytes()).hexdigest()
    croissant = json.loads((root / "croissant.json").read_text())
    described = {entry["contentUrl"] for entry in croissant["distribution"]}
    assert set(view_files(key)) | {"views/views.jsonl"} <= described
    assert [rs["@id"] for rs in croissant["recordSet"]] == ["cards", "views"]
    assert "for 1 of 3 cards" in (root / "README.md").read_text()
    changelog = (root / "CHANGELOG.md").read_text()
    assert "### Views (1 of 3 cards)" in changelog and "- 1 card(s) without views: views not run" in changelog


def test_verify_passes_and_catches_a_flipped_byte_in_a_views_file(app, tmp_path, three_cards) -> None:
    from exports.verify import verify_release

    ids, _ = three_cards
    root = Path(_publish(app, tmp_path / "out").path)
    sound = verify_release(root)  # with mlcroissant's own validation, when installed
    assert sound.ok, sound.problems
    mlcroissant = pytest.importorskip("mlcroissant", reason="mlcroissant is not installed (pip install mlcroissant)")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # rdflib's own deprecations inside mlcroissant
        records = list(mlcroissant.Dataset(str(root / "croissant.json")).records("views"))
    # (mlcroissant reads JSON Lines with pandas, which turns the key "00001" into a number: compare the folder.)
    assert [(r["views/folder"], r["views/card_id"]) for r in records] == [(f"views/{ids[0]:05d}".encode(), ids[0])]
    target = root / f"views/{ids[0]:05d}/v1_depth.exr"
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x01
    target.write_bytes(bytes(data))
    report = verify_release(root, validate_croissant=False)
    assert report.problems == [
        {"path": f"views/{ids[0]:05d}/v1_depth.exr", "problem": "sha256 does not match SHA256SUMS (file changed or corrupted)"}
    ]


def test_verify_names_an_incomplete_views_folder(app, tmp_path, three_cards) -> None:
    from exports.verify import verify_release

    ids, _ = three_cards
    root = Path(_publish(app, tmp_path / "out").path)
    key = f"{ids[0]:05d}"
    # Drop a file and its SHA256SUMS line, as a careless re-packer would: the checksums agree, the views do not.
    (root / f"views/{key}/v4.png").unlink()
    sums = root / "SHA256SUMS"
    sums.write_text("".join(line + "\n" for line in sums.read_text().splitlines() if not line.endswith(f"{key}/v4.png")))
    problems = verify_release(root, validate_croissant=False).problems
    assert {"path": f"views/{key}/", "problem": "incomplete views: v4.png not listed"} in problems


def test_views_releases_are_byte_identical_and_a_changed_views_result_is_a_changed_card(
    app, tmp_path, three_cards, make_views
) -> None:
    ids, _ = three_cards
    first = _publish(app, tmp_path / "a")
    second = _publish(app, tmp_path / "b")
    assert (first.version, second.version) == ("1.0.0", "1.0.1") and second.changes["changed"] == []
    files_a = {p.relative_to(first.path).as_posix(): p.read_bytes() for p in Path(first.path).rglob("*") if p.is_file()}
    files_b = {p.relative_to(second.path).as_posix(): p.read_bytes() for p in Path(second.path).rglob("*") if p.is_file()}
    same = [path for path in files_a if path.startswith("views/") or path == "cards.jsonl"]
    assert len(same) == 14 and all(files_a[path] == files_b[path] for path in same)

    # New views (other parameters) for card 0 and first views for card 1: both are changed cards, in words.
    make_views(ids[0], shift_px=64.0)
    make_views(ids[1])
    third = _publish(app, tmp_path / "c")
    changed = {entry["card_id"]: entry["why"] for entry in third.changes["changed"]}
    assert third.version == "2.0.0" and sorted(changed) == ids[:2]
    assert changed[ids[0]][0].startswith("views re-synthesised (views parameter hash, inputs or code version changed) (")
    assert changed[ids[1]][0].startswith("views added (views ")
    assert third.summaries["views"]["cards_with_views"] == 2
    changelog = (Path(third.path) / "CHANGELOG.md").read_text()
    assert f"- card {ids[1]:05d}: views added" in changelog

    # A release without the views component: the same manifest digests as before views existed.
    plain = _publish(app, tmp_path / "d", formats=("keystonedepth",))
    assert "views" not in plain.summaries and not (Path(plain.path) / "views").exists()
    assert {entry["card_id"] for entry in plain.changes["changed"]} == set(ids[:2])
    assert all(why[0].startswith("views removed") for why in (entry["why"] for entry in plain.changes["changed"]))


def test_views_is_an_optional_format(runner) -> None:
    from exports.formats import default_format_names, parse_formats

    assert "views" not in default_format_names()
    assert parse_formats("views,keystonedepth") == ("keystonedepth", "views")


def test_stale_views_are_left_out_of_a_release_with_the_reason(app, tmp_path, three_cards) -> None:  # type: ignore[no-untyped-def]
    from sqlalchemy import select

    from core.db import db
    from core.models import StageResult
    from exports.verify import verify_release

    ids, _ = three_cards
    with app.app_context():
        views = db.session.scalar(select(StageResult).where(StageResult.card_id == ids[0], StageResult.stage == "views"))
        views.metrics = {**views.metrics, "inputs_digest": "computed-from-an-older-grade"}
        db.session.commit()
    report = _publish(app, tmp_path / "out")
    root = Path(report.path)
    assert report.cards == 3 and report.summaries["views"]["cards_with_views"] == 0
    assert not (root / "views" / f"{ids[0]:05d}").exists()
    record = next(r for r in map(json.loads, (root / "cards.jsonl").read_text().splitlines()) if r["card_id"] == ids[0])
    assert record["views"]["why_not"].startswith("views out of date (its inputs changed since the views stage ran)")
    assert verify_release(root, validate_croissant=False).ok

"""The optional ``stereo`` release component: anaglyph, wiggles, side-by-side, JPS and MPO per card,
made from the rectified pairs and disparities that ``keystone run`` produced on real photographs."""

from __future__ import annotations

import json
from pathlib import Path

from PIL import Image

STEREO_NAMES = ("anaglyph.jpg", "wiggle.gif", "wiggle.webp", "sbs_full.jpg", "sbs_half.jpg", "cross.jps", "pair.mpo")


def test_a_release_with_the_stereo_format_verifies(app, runner, tmp_path, processed_cards, review_card) -> None:
    from core.db import db
    from core.models import Card
    from exports.verify import verify_release

    ids = processed_cards(2)
    review_card(ids[0], "few")
    review_card(ids[1], "some")
    with app.app_context():  # as catalogue.stereo_ingest records an MPO's card
        db.session.get(Card, ids[0]).stereo_source = {
            "kind": "mpo",
            "frames": 2,
            "eye_order": "parallel",
            "originals": [
                {
                    "role": "mpo",
                    "source_name": "camera.mpo",
                    "source_path": "/home/someone/camera.mpo",
                    "sha256": "ab" * 32,
                    "stored_path": "originals/ab/x.mpo",
                    "bytes": 1234,
                }
            ],
        }
        db.session.commit()
    result = runner.invoke(args=["export", "--out", str(tmp_path / "out"), "--format", "keystonedepth,stereo", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["formats"] == ["keystonedepth", "stereo"]
    assert report["stereo"]["cards"] == 2 and report["stereo"]["cards_without"] == 0
    assert set(report["stereo"]["per_card"]) == {"anaglyph", "wiggle_gif", "wiggle_webp", "sbs_full", "sbs_half", "jps", "mpo"}
    root = Path(report["path"])
    sums = {line.split("  ", 1)[1] for line in (root / "SHA256SUMS").read_text().splitlines()}
    croissant = json.loads((root / "croissant.json").read_text())
    described = {entry["contentUrl"] for entry in croissant["distribution"]}
    index = [json.loads(line) for line in (root / "stereo" / "stereo.jsonl").read_text().splitlines()]
    assert [line["card_id"] for line in index] == ids
    assert index[0]["title"] == "Motorcycle 0" and index[0]["accession"] == "1996.0009.17827"
    for card_id in ids:
        key = f"{card_id:05d}"
        for name in STEREO_NAMES:
            relative = f"stereo/{key}/{name}"
            assert (root / relative).is_file() and relative in sums and relative in described
        with Image.open(root / "stereo" / key / "pair.mpo") as mpo:
            assert mpo.n_frames == 2
        with (
            Image.open(root / "processed/rectified/rectified_LR" / f"{key}L.png") as left,
            Image.open(root / "stereo" / key / "cross.jps") as jps,
        ):
            assert jps.size == (2 * left.width, left.height)
    records = [json.loads(line) for line in (root / "cards.jsonl").read_text().splitlines()]
    assert records[0]["stereo_source"] == {
        "kind": "mpo",
        "frames": 2,
        "eye_order": "parallel",
        "originals": [{"role": "mpo", "source_name": "camera.mpo", "sha256": "ab" * 32, "bytes": 1234}],
    }
    assert "stereo_source" not in records[1]
    assert "stereo" in {record["@id"] for record in croissant["recordSet"]}
    assert "stereo/stereo.jsonl" in described and "`stereo/<id>/`" in (root / "README.md").read_text()
    assert "### Stereo files (2 of 2 cards)" in (root / "CHANGELOG.md").read_text()

    verified = verify_release(root, validate_croissant=True)
    assert verified.ok, verified.problems
    verify = runner.invoke(args=["verify", str(root), "--json"])
    assert verify.exit_code == 0, verify.output


def test_verify_names_a_one_frame_mpo_and_a_missing_stereo_file(app, tmp_path, processed_cards, review_card) -> None:
    import hashlib

    from exports.release import publish_release
    from exports.verify import verify_release

    ids = processed_cards(1)
    review_card(ids[0], "few")
    with app.app_context():
        report = publish_release(tmp_path / "out", formats=("keystonedepth", "stereo"))
    root = Path(report.path)
    key = f"{ids[0]:05d}"
    mpo = root / "stereo" / key / "pair.mpo"
    with Image.open(mpo) as image:
        image.convert("RGB").save(mpo, format="JPEG")  # one frame left
    sums = root / "SHA256SUMS"
    new_sha = hashlib.sha256(mpo.read_bytes()).hexdigest()
    sums.write_text(
        "\n".join(
            f"{new_sha}  {line.split('  ', 1)[1]}" if line.endswith(f"stereo/{key}/pair.mpo") else line
            for line in sums.read_text().splitlines()
        )
        + "\n"
    )
    (root / "stereo" / key / "wiggle.gif").unlink()
    sums.write_text("".join(line + "\n" for line in sums.read_text().splitlines() if not line.endswith("wiggle.gif")))
    problems = verify_release(root, validate_croissant=False).problems
    assert {"path": f"stereo/{key}/pair.mpo", "problem": "expected an MPO with 2 frames, got JPEG with 1"} in problems
    assert {"path": f"stereo/{key}/", "problem": "incomplete: wiggle.gif not listed"} in problems

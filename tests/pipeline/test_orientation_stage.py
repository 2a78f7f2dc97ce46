"""The orientation stage task on awkward cards: each gives a typed result, never a silent guess."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.records import CardTask
from pipeline.split import split_card
from pipeline.stages.orientation import OrientationStageParams, orientation_task

PARAMS = OrientationStageParams()
MOUNT = (214, 200, 170)


@pytest.fixture(scope="module")
def moto() -> tuple[np.ndarray, np.ndarray]:
    from skimage import data

    left, right, _ = data.stereo_motorcycle()
    return left, right


def _mounted(*photos: np.ndarray, margin: int = 30, gap: int = 24) -> np.ndarray:
    height = max(p.shape[0] for p in photos)
    width = sum(p.shape[1] for p in photos) + gap * (len(photos) - 1) + 2 * margin
    card = np.empty((height + 2 * margin, width, 3), np.uint8)
    card[:] = MOUNT
    x = margin
    for photo in photos:
        card[margin : margin + photo.shape[0], x : x + photo.shape[1]] = photo if photo.ndim == 3 else photo[..., None]
        x += photo.shape[1] + gap
    return card


def _run(tmp_path: Path, image: Image.Image, boxes: tuple | None = None) -> object:
    path = tmp_path / "card.png"
    image.save(path)
    if boxes is None:
        array = np.asarray(Image.open(path).convert("RGB"))
        split = split_card(array)
        boxes = (list(split.left_box), list(split.right_box))
    task = CardTask(
        card_id=1,
        content_hash="ab" * 32,
        image_path=str(path),
        work_dir=str(tmp_path / "work"),
        data_dir=str(tmp_path),
        inputs={"left_box": list(boxes[0]), "right_box": list(boxes[1])},
    )
    return orientation_task(task, PARAMS)


def test_an_ordinary_card_records_flags_evidence_decision_and_photo_area(tmp_path, moto):
    left, right = moto
    record = _run(tmp_path, Image.fromarray(_mounted(left, right)))
    assert record.status == "done" and record.outcome in ("auto", "ask")
    metrics = record.metrics
    assert metrics["decision"] == record.outcome
    assert set(metrics["flags"]) == {"upside_down", "inverted", "swapped"}
    for info in metrics["flags"].values():
        assert 0.0 <= info["p"] <= 1.0 and info["evidence"] and all(isinstance(w, str) for w in info["evidence"])
    # A positive in warm mount colours: the negative flag is decided, and said why.
    assert metrics["flags"]["inverted"]["value"] is False and metrics["flags"]["inverted"]["p"] < 0.1
    width, height = metrics["card_size"]
    for name, x_range in (("photo_left_box", (0, width // 2)), ("photo_right_box", (width // 2, width))):
        x0, y0, x1, y1 = metrics[name]
        assert x_range[0] <= x0 < x1 <= x_range[1] + 12 and 0 <= y0 < y1 <= height
    assert metrics["photo_area_source"]
    assert metrics["seconds_orientation"] > 0 and metrics["seconds_photo_area"] > 0


def test_blank_halves_ask_people_with_the_reason(tmp_path):
    card = np.empty((300, 620, 3), np.uint8)
    card[:] = MOUNT
    record = _run(tmp_path, Image.fromarray(card), ([10, 10, 300, 290], [320, 10, 610, 290]))
    assert record.status == "done" and record.outcome == "ask"
    assert "blank photo" in record.metrics["undecidable"]
    assert all(info["value"] is None and not info["decided"] for info in record.metrics["flags"].values())


def test_identical_halves_ask_people(tmp_path, moto):
    left, _ = moto
    record = _run(tmp_path, Image.fromarray(_mounted(left, left)))
    assert record.status == "done" and record.outcome == "ask"
    # Split a few px apart, the copies are not pixel-identical; aligned, they show no parallax.
    assert "no parallax" in record.metrics["undecidable"] or "identical photos" in record.metrics["undecidable"]
    exact = _run(tmp_path, Image.fromarray(_mounted(left, left)), ([30, 30, 771, 530], [795, 30, 1536, 530]))
    assert exact.outcome == "ask" and exact.metrics["undecidable"]
    assert all(info["value"] is None for info in exact.metrics["flags"].values())


def test_three_photos_ask_people(tmp_path, moto):
    left, right = moto
    small = [np.asarray(Image.fromarray(v).resize((370, 250))) for v in (left, right, left)]
    card = _mounted(*small)
    record = _run(tmp_path, Image.fromarray(card), ([30, 30, 400, 280], [424, 30, 794, 280]))
    assert record.status == "done" and record.outcome == "ask"
    assert "third copy" in record.metrics["undecidable"]


def test_a_tiny_card_is_a_typed_failure(tmp_path):
    card = np.random.default_rng(0).integers(0, 255, (20, 40, 3), dtype=np.uint8)
    record = _run(tmp_path, Image.fromarray(card), ([0, 0, 18, 20], [22, 0, 40, 20]))
    assert record.status == "failed"
    assert record.reason.split(":")[0] in ("orientation_input", "invalid_input")


def test_sixteen_bit_and_greyscale_scans_give_a_result_with_reasons(tmp_path, moto):
    left, right = moto
    grey = np.asarray(Image.fromarray(_mounted(left, right)).convert("L"))
    eight = _run(tmp_path, Image.fromarray(grey))
    assert eight.status == "done" and eight.outcome in ("auto", "ask")
    # No colour: the warm-tone cue says it has no evidence instead of voting.
    assert any("greyscale" in words for words in eight.metrics["flags"]["inverted"]["evidence"])
    sixteen = (grey.astype(np.uint16) * 257).astype(np.uint16)
    deep = _run(tmp_path, Image.fromarray(sixteen))
    assert deep.status == "done" and deep.outcome == eight.outcome
    # The 16-bit scan is stretched to its used range first, so its grey levels differ from the
    # 8-bit scan's by up to one level: the occlusion bands move a little, the answer does not.
    for flag in ("upside_down", "inverted", "swapped"):
        assert abs(deep.metrics["flags"][flag]["p"] - eight.metrics["flags"][flag]["p"]) < 0.1


def test_a_large_jpeg_is_read_at_a_reduced_size_and_answers_in_scan_pixels(tmp_path, moto):
    """A ~3000 px JPEG card is decoded at 1/2 (every cue works on a smaller copy); the photo
    areas come back in the scan's pixels, where a full decode puts them, and the flags agree."""
    left, right = moto
    card = np.asarray(Image.fromarray(_mounted(left, right)).resize((3000, 1140), Image.Resampling.LANCZOS))
    path = tmp_path / "large.jpg"
    Image.fromarray(card).save(path, quality=92)
    split = split_card(np.asarray(Image.open(path)))
    records = {}
    for name, params in (("reduced", PARAMS), ("full", OrientationStageParams(decode_min_width=0))):
        task = CardTask(
            card_id=1,
            content_hash="cd" * 32,
            image_path=str(path),
            work_dir=str(tmp_path / name),
            data_dir=str(tmp_path),
            inputs={"left_box": list(split.left_box), "right_box": list(split.right_box)},
        )
        records[name] = orientation_task(task, params)
    reduced, full = records["reduced"].metrics, records["full"].metrics
    assert reduced["decode_factor"] == 2 and full["decode_factor"] == 1
    assert reduced["card_size"] == full["card_size"] == [3000, 1140]
    for key in ("photo_left_box", "photo_right_box"):
        x0, y0, x1, y1 = reduced[key]
        assert 0 <= x0 < x1 <= 3000 and 0 <= y0 < y1 <= 1140
        assert np.abs(np.subtract(reduced[key], full[key])).max() <= 16, (reduced[key], full[key])
    for flag in ("upside_down", "inverted", "swapped"):
        assert reduced["flags"][flag]["value"] == full["flags"][flag]["value"]
        assert abs(reduced["flags"][flag]["p"] - full["flags"][flag]["p"]) < 0.15

"""pipeline.text_orientation: which way up a card's print reads (the ``text_upright`` cue)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import InvalidInputError
from pipeline.orientation import OrientationParams, estimate_orientation
from pipeline.split import split_card
from pipeline.text_orientation import (
    MODELS_ENV,
    TextModelMissingError,
    TextParams,
    models_folder,
    read_text_orientation,
)


@pytest.fixture(autouse=True, scope="module")
def text_models() -> None:
    folder = models_folder()
    if folder is None or not (folder / "ch_PP-OCRv4_det_infer.onnx").is_file():
        if os.environ.get("CI"):
            pytest.fail("CI must install the text models: pip install --no-deps rapidocr-onnxruntime==1.4.4")
        pytest.skip("text models absent: pip install --no-deps rapidocr-onnxruntime==1.4.4")


def printed_card(lines: list[str], vertical: bool = False) -> np.ndarray:
    """A buff card (760 x 400 px, like an NYPL web scan) with dark print: caption lines under a
    photo-like textured block, or (``vertical``) the same print running up the left side."""
    rng = np.random.default_rng(0)
    card = np.empty((400, 760, 3), np.uint8)
    card[:] = (214, 201, 170)
    photo = cv2.resize(rng.random((20, 60)).astype(np.float32), (640, 280), interpolation=cv2.INTER_CUBIC)
    card[30:310, 60:700] = (np.clip(photo, 0, 1)[..., None] * np.array([150, 120, 90]) + 40).astype(np.uint8)
    if vertical:
        strip = np.full((40, 300, 3), (214, 201, 170), np.uint8)
        cv2.putText(strip, lines[0], (8, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (40, 30, 20), 2, cv2.LINE_AA)
        card[40:340, 10:50] = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
    else:
        for k, text in enumerate(lines):
            cv2.putText(card, text, (90, 340 + 30 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (40, 30, 20), 2, cv2.LINE_AA)
    return card


def test_a_printed_caption_reads_upright_and_its_turn_reads_upside_down() -> None:
    card = printed_card(["1894. The Grand Canyon, Arizona", "Copyright by Underwood"])
    upright = read_text_orientation(card)
    turned = read_text_orientation(np.ascontiguousarray(card[::-1, ::-1]))
    assert len(upright.lines) >= 1 and upright.value > 0.3, upright.as_dict()
    assert len(turned.lines) >= 1 and turned.value < -0.3, turned.as_dict()
    best = max(upright.lines, key=lambda line: line.upright_confidence)
    assert best.upright_confidence > 0.8 and best.turned_confidence < 0.5
    assert "Canyon" in best.text or "Underwood" in best.text
    # every line box lies on the card, in its pixels
    for line in upright.lines:
        x0, y0, x1, y1 = line.as_dict()["box"]
        assert -5 <= x0 < x1 <= 765 and 300 <= y0 < y1 <= 405


def test_a_greyscale_scan_reads_the_same() -> None:
    card = cv2.cvtColor(printed_card(["The Pyramids of Gizeh, Egypt"]), cv2.COLOR_RGB2GRAY)
    assert read_text_orientation(card).value > 0.3
    assert read_text_orientation(np.ascontiguousarray(card[::-1, ::-1])).value < -0.3


def test_print_up_the_side_is_no_evidence() -> None:
    """A title printed up the side reads the same way on a card turned 180 deg (it moves to the
    other side), so vertical lines are left out."""
    reading = read_text_orientation(printed_card(["NORTHERN PACIFIC VIEWS"], vertical=True))
    assert reading.value == 0.0 and reading.lines == ()
    assert "no readable horizontal print" in reading.note


@pytest.mark.parametrize(
    "image",
    [np.full((300, 600, 3), 200, np.uint8), np.zeros((40, 40), np.uint8), np.full((2, 900), 255, np.uint8)],
    ids=["blank", "tiny-black", "one-row-high"],
)
def test_no_print_gives_no_evidence(image: np.ndarray) -> None:
    reading = read_text_orientation(image)
    assert reading.value == 0.0 and reading.lines == () and np.isfinite(reading.seconds)


@pytest.mark.parametrize(
    "image",
    [np.zeros((50, 50), np.float32), np.zeros((50, 50, 4), np.uint8), [[0, 1], [1, 0]]],
    ids=["float", "rgba", "list"],
)
def test_bad_input_raises_a_typed_error(image: object) -> None:
    with pytest.raises(InvalidInputError):
        read_text_orientation(image)  # type: ignore[arg-type]


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(InvalidInputError):
        TextParams(detect_side=64)
    with pytest.raises(InvalidInputError):
        TextParams(min_reading=1.5)
    with pytest.raises(InvalidInputError):
        OrientationParams(text_detect_side=50)


def test_missing_models_are_a_typed_error_and_no_evidence_in_the_step(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(MODELS_ENV, str(tmp_path))
    card = printed_card(["1894. The Grand Canyon, Arizona"])
    with pytest.raises(TextModelMissingError, match="text models not found"):
        read_text_orientation(card)
    split = split_card(card)
    estimate = estimate_orientation(card, split.left_box, split.right_box, OrientationParams(text_only_when_undecided=False))
    cue = next(c for c in estimate.cues if c.name == "text_upright")
    assert cue.value == 0.0 and "not read" in str(estimate.details["text"])


# The step without its learned cues and faces: what the print does where nothing else decides.
WITHOUT_NETWORK = OrientationParams(w_learned_upright=0.0, w_learned_tone=0.0, face_max_side=0)


def test_real_caption_decides_the_turned_card(load_card) -> None:
    """The Pima card's caption ("387-The Pima Indians of Arizona") reads upright as scanned and
    upside down turned; the step then decides the turned card upside down by itself."""
    card = load_card("full_cards/nypl_000206_pima_indians_of_arizona.jpg")
    assert read_text_orientation(card).value > 0.3
    turned = np.ascontiguousarray(card[::-1, ::-1])
    assert read_text_orientation(turned).value < -0.2
    split = split_card(turned)
    # The network's "which way up" decides the turned card before the print is needed...
    default = estimate_orientation(turned, split.left_box, split.right_box)
    assert default.upside_down.value is True and default.details["text"] == "not read: the card is decided without it"
    # ...and without the network (and faces), the caption decides it.
    estimate = estimate_orientation(turned, split.left_box, split.right_box, WITHOUT_NETWORK)
    cue = next(c for c in estimate.cues if c.name == "text_upright")
    assert cue.value < -0.2 and "upside down" in cue.meaning and "Pima" in cue.meaning  # what was read, in words
    assert estimate.upside_down.decided and estimate.upside_down.value is True


def test_the_text_cue_is_skipped_when_the_card_is_decided_without_it(load_card) -> None:
    card = load_card("full_cards/nypl_stereogranimator_demo1.jpg")  # arched tops, warm, clear ground
    split = split_card(card)
    estimate = estimate_orientation(card, split.left_box, split.right_box)
    assert estimate.decided
    assert estimate.details["text"] == "not read: the card is decided without it"
    off = estimate_orientation(card, split.left_box, split.right_box, OrientationParams(text_detect_side=0))
    assert off.details["text"] == "text cue off"


def test_the_text_cue_is_skipped_when_no_reading_could_decide_the_card(load_card) -> None:
    """A greyscale Keystone-Mast scan: its tones do not settle whether it is a negative, so print
    read either way up could not decide it (without the network's tone head); the step says so
    instead of spending the reading."""
    card = load_card("keystone_mast_raw_scans/09995.jpg")
    split = split_card(card)
    estimate = estimate_orientation(card, split.left_box, split.right_box, WITHOUT_NETWORK)
    assert not estimate.decided
    assert estimate.details["text"] == "not read: print either way up could not decide the card"
    assert next(c.value for c in estimate.cues if c.name == "text_upright") == 0.0


def test_an_unreadable_model_file_is_no_evidence_said(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "ch_PP-OCRv4_det_infer.onnx").write_bytes(b"not a model")
    (tmp_path / "ch_PP-OCRv4_rec_infer.onnx").write_bytes(b"\x08\x07")
    monkeypatch.setenv(MODELS_ENV, str(tmp_path))
    card = printed_card(["1894. The Grand Canyon, Arizona"])
    with pytest.raises(TextModelMissingError, match="unreadable"):
        read_text_orientation(card)
    split = split_card(card)
    estimate = estimate_orientation(card, split.left_box, split.right_box, OrientationParams(text_only_when_undecided=False))
    assert "not read: text models unreadable" in str(estimate.details["text"])

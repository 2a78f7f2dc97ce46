"""Which way up the printed text on a card reads: the ``text_upright`` orientation cue.

Stereo cards carry print: the publisher's name and the title on the mount, captions under the
photos, signs inside them. Text tells which way is up far more reliably than the scene does (a
person turning a card reads its caption first). Two networks do the reading: PaddleOCR's
PP-OCRv4 text detector (DB, Liao et al. AAAI 2020) and its PP-OCRv4 line recogniser (CTC), as
ONNX models shipped inside the ``rapidocr-onnxruntime`` wheel and run with ``onnxruntime``.

Steps (:func:`read_text_orientation`): the card is scaled so its longer side is
``TextParams.detect_side`` px (text on a 760 px NYPL card is 6-10 px high: scaling it up is
what lets the detector see it), the detector's probability map is thresholded into line boxes
(minimum-area rectangles grown by DB's "unclip" distance ``area * 1.6 / perimeter``), and each
line that lies horizontal (longer side along x, at least ``min_aspect`` long, at least
``min_line_px`` high) is cut out level and read twice, as seen and turned 180 deg. Print read
the right way up gives confident characters (0.83-0.96 mean top probability over the 12 lines
found on the shared cards, both ways up); upside down, the recogniser finds few characters or
none (0.0-0.64, the highest on a stamp in small capitals, where the right way read 0.87). A line counts
when one of its two readings reaches ``min_reading``; its evidence is the difference of the two
confidences. Vertical lines are left out on purpose: the titles printed up the sides of a mount
read bottom-to-top on the left and top-to-bottom on the right, and a card turned 180 deg shows
the same two, so they carry no evidence. (Measured and left out: PaddleOCR's 0/180 line
classifier, which was unsure or wrong on 4 of 12 lines the recogniser read both ways right.)

The cue's value, in -1..1, positive = the text reads upright: ``sum_i (c_i - c180_i) / (n +
1)`` over the ``n`` lines that count (the ``+ 1`` is one pseudo-line of no opinion, so one line
is never taken as certain). 0, with a note, when there is no such line.

Conventions: ``image`` is ``uint8`` ``(H, W, 3)`` RGB or ``(H, W)`` grey, a positive (the
caller inverts a negative first: the models were trained on dark print on light paper). Line
corners are in the image's pixels, ``(4, 2)`` float.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import InvalidInputError, PipelineError

MODELS_ENV = "KEYSTONE_TEXT_MODELS"
DETECTOR_FILE = "ch_PP-OCRv4_det_infer.onnx"
RECOGNISER_FILE = "ch_PP-OCRv4_rec_infer.onnx"
RECOGNISER_HEIGHT = 48  # px: a line's height as the recogniser takes it
MAX_LINE_ASPECT = 12.0  # a longer line is read on its middle 12:1 (both ways: the middle stays the middle)


class TextModelMissingError(PipelineError):
    """The ONNX models (or onnxruntime) are not installed or cannot be loaded: no evidence."""

    code = "text_model_missing"


class TextReadFailedError(PipelineError):
    """onnxruntime refused to run a model on this input: the cue gives no evidence for the card."""

    code = "text_read_failed"


def _run(session: Any, tensor: np.ndarray) -> np.ndarray:
    """One model run; onnxruntime's own exceptions (they derive from Exception alone) as a typed error."""
    try:
        return np.asarray(session.run(None, {session.get_inputs()[0].name: tensor})[0])
    except Exception as exc:  # onnxruntime's Fail, InvalidArgument, RuntimeException, ...
        raise TextReadFailedError(f"onnxruntime: {type(exc).__name__}: {str(exc).strip()[:160]}") from exc


@dataclass(frozen=True)
class TextParams:
    """Parameters of :func:`read_text_orientation`."""

    detect_side: int = 1024
    """px: the card's longer side as the detector sees it (scaled up or down, multiple of 32)."""
    line_threshold: float = 0.3
    """Detector probability above which a pixel is text."""
    min_line_score: float = 0.6
    """Mean detector probability inside a line's box for it to count."""
    min_aspect: float = 2.5
    """A line's length over its height: shorter blobs are single letters, ornaments or noise."""
    min_line_px: float = 8.0
    """px (detector scale): lines lower than this are too small to read."""
    min_reading: float = 0.6
    """Mean character confidence that one of a line's two readings must reach for it to count."""
    max_lines: int = 4
    """The longest lines read (a cost bound on a card covered in print)."""

    def __post_init__(self) -> None:
        if self.detect_side < 128:
            raise InvalidInputError(f"Expected detect_side >= 128 px, got {self.detect_side}")
        if not all(0 < v < 1 for v in (self.line_threshold, self.min_line_score, self.min_reading)):
            raise InvalidInputError("Expected line_threshold, min_line_score and min_reading in (0, 1)")
        if self.min_aspect < 1 or self.min_line_px <= 0 or self.max_lines < 1:
            raise InvalidInputError("Expected min_aspect >= 1, min_line_px > 0 and max_lines >= 1")


@dataclass(frozen=True)
class TextLine:
    """One horizontal line of print: its corners in image px and its two readings."""

    corners: np.ndarray  # (4, 2) float32: top-left, top-right, bottom-right, bottom-left as seen
    height_px: float
    length_px: float
    upright_confidence: float  # mean character confidence read as seen, 0..1
    turned_confidence: float  # the same, read turned 180 deg
    text: str  # the better of the two readings

    @property
    def evidence(self) -> float:
        """> 0: reads upright; in -1..1."""
        return self.upright_confidence - self.turned_confidence

    def as_dict(self) -> dict[str, Any]:
        x0, y0 = self.corners.min(axis=0)
        x1, y1 = self.corners.max(axis=0)
        return {
            "box": [round(float(v), 1) for v in (x0, y0, x1, y1)],
            "height_px": round(self.height_px, 1),
            "upright_confidence": round(self.upright_confidence, 3),
            "turned_confidence": round(self.turned_confidence, 3),
            "text": self.text,
        }


@dataclass(frozen=True)
class TextReading:
    """The lines read and the cue's value (> 0: the text reads upright)."""

    value: float
    lines: tuple[TextLine, ...]
    seconds: float
    note: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "value": round(self.value, 4),
            "lines": [line.as_dict() for line in self.lines],
            "note": self.note,
            "seconds": round(self.seconds, 4),
        }


def models_folder() -> Path | None:
    """Where the two ONNX files are: ``$KEYSTONE_TEXT_MODELS``, else the ``models`` folder of
    the installed ``rapidocr_onnxruntime`` package (found without importing it), else None."""
    override = os.environ.get(MODELS_ENV)
    if override:
        return Path(override)
    spec = importlib.util.find_spec("rapidocr_onnxruntime")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "models"


@functools.lru_cache(maxsize=2)
def _sessions(folder: str) -> tuple[Any, Any]:
    """(detector, recogniser) onnxruntime sessions, one thread each: the pipeline runs one card
    per worker process, and more threads would only oversubscribe the cores."""
    try:
        import onnxruntime  # lazy: heavy, and only this cue needs it
    except ImportError as exc:
        raise TextModelMissingError("onnxruntime is not installed") from exc
    paths = [Path(folder) / DETECTOR_FILE, Path(folder) / RECOGNISER_FILE]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise TextModelMissingError(f"text models not found: {', '.join(missing)}")
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    try:
        detector, recogniser = (
            onnxruntime.InferenceSession(str(p), sess_options=options, providers=["CPUExecutionProvider"]) for p in paths
        )
    except Exception as exc:  # a truncated or foreign file: onnxruntime's InvalidGraph, Fail, ...
        raise TextModelMissingError(f"text models unreadable ({type(exc).__name__}): {str(exc).strip()[:160]}") from exc
    return detector, recogniser


def _rgb(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise InvalidInputError(f"Expected a uint8 image, got {getattr(image, 'dtype', type(image).__name__)}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    raise InvalidInputError(f"Expected an image (H, W) or (H, W, 3), got {image.shape}")


def _detect_lines(detector: Any, rgb: np.ndarray, params: TextParams) -> tuple[list[np.ndarray], float]:
    """Line rectangles (``(4, 2)`` corners in the image's px) and the detector's scale."""
    h, w = rgb.shape[:2]
    scale = params.detect_side / max(h, w)
    dw, dh = max(32, round(w * scale / 32) * 32), max(32, round(h * scale / 32) * 32)
    small = cv2.resize(rgb, (dw, dh), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    # PP-OCR's detector takes BGR in (v / 255 - 0.5) / 0.5, NCHW.
    tensor = (small[..., ::-1].astype(np.float32) / 127.5 - 1.0).transpose(2, 0, 1)[None]
    probability = _run(detector, tensor)[0, 0]
    mask = cv2.dilate((probability > params.line_threshold).astype(np.uint8), np.ones((2, 2), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    sx, sy = w / dw, h / dh
    lines = []
    for contour in contours:
        (cx, cy), (rw, rh), angle = cv2.minAreaRect(contour)
        if min(rw, rh) < 2:
            continue
        x, y, bw, bh = cv2.boundingRect(contour)
        inside = np.zeros((bh, bw), np.uint8)
        cv2.drawContours(inside, [contour - np.array([x, y])], -1, 1, -1)
        score = float(probability[y : y + bh, x : x + bw][inside > 0].mean())
        if score < params.min_line_score:
            continue
        grow = rw * rh * 1.6 / (2 * (rw + rh))  # DB's unclip distance, per side
        corners = cv2.boxPoints(((cx, cy), (rw + 2 * grow, rh + 2 * grow), angle))
        lines.append(corners * np.array([sx, sy], np.float32))
    return lines, scale


def _level(corners: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """Corners ordered top-left, top-right, bottom-right, bottom-left as seen, with length and
    height; None for a line whose longer side is not the horizontal one (vertical print)."""
    s, d = corners.sum(axis=1), corners[:, 1] - corners[:, 0]
    ordered = np.array([corners[s.argmin()], corners[d.argmin()], corners[s.argmax()], corners[d.argmax()]], np.float32)
    if len({tuple(p) for p in ordered.tolist()}) < 4:  # a square at 45 deg: no level reading
        return None
    length = float(np.linalg.norm(ordered[1] - ordered[0]))
    height = float(np.linalg.norm(ordered[3] - ordered[0]))
    if length <= height:
        return None
    return ordered, length, height


def _line_crops(rgb: np.ndarray, lines: list[tuple[np.ndarray, float, float]]) -> list[np.ndarray]:
    """Each line cut out level (corners mapped onto an upright rectangle), as seen, at most its
    middle ``MAX_LINE_ASPECT`` heights long (the recogniser's cost grows with the length)."""
    crops = []
    for corners, full_length, height in lines:
        length = min(full_length, MAX_LINE_ASPECT * height)
        margin = (full_length - length) / 2
        target = np.array([[-margin, 0], [length + margin, 0], [length + margin, height], [-margin, height]], np.float32)
        crops.append(
            cv2.warpPerspective(
                rgb,
                cv2.getPerspectiveTransform(corners, target),
                (max(1, round(length)), max(1, round(height))),
                flags=cv2.INTER_AREA,
                borderMode=cv2.BORDER_REPLICATE,
            )
        )
    return crops


def _recognise(recogniser: Any, crops: list[np.ndarray]) -> list[tuple[float, str]]:
    """(confidence, text) per crop: the recogniser's mean top probability over the characters it
    emits (CTC steps whose best class is not the blank), 0 when it emits none. Crops are scaled
    to 48 px high (aspect kept), right-padded to the batch's widest, BGR in (v / 255 - 0.5) / 0.5."""
    widths = [max(8, int(np.ceil(RECOGNISER_HEIGHT * c.shape[1] / c.shape[0]))) for c in crops]
    batch = np.zeros((len(crops), 3, RECOGNISER_HEIGHT, max(widths)), np.float32)
    for k, (crop, width) in enumerate(zip(crops, widths, strict=True)):
        resized = cv2.resize(crop, (width, RECOGNISER_HEIGHT), interpolation=cv2.INTER_LINEAR)
        batch[k, :, :, :width] = (resized[..., ::-1].astype(np.float32) / 127.5 - 1.0).transpose(2, 0, 1)
    probabilities = _run(recogniser, batch)  # (N, T, classes)
    alphabet = _alphabet(recogniser)
    out = []
    for steps in probabilities:
        best, top = steps.argmax(axis=1), steps.max(axis=1)
        emitted = best != 0
        if not emitted.any():
            out.append((0.0, ""))
            continue
        # CTC: repeats of one class in a row are one character
        chars = [alphabet[c] for i, c in enumerate(best) if c != 0 and (i == 0 or best[i - 1] != c) and c < len(alphabet)]
        out.append((float(top[emitted].mean()), "".join(chars)))
    return out


def _alphabet(recogniser: Any) -> list[str]:
    """The recogniser's classes: the CTC blank, the characters stored in the model, a space."""
    characters = recogniser.get_modelmeta().custom_metadata_map.get("character", "")
    return ["", *characters.splitlines(), " "]


def read_text_orientation(image: np.ndarray, params: TextParams = TextParams()) -> TextReading:
    """Read which way up the card's horizontal print is (module docstring).

    Raises :class:`InvalidInputError` for a bad array, :class:`TextModelMissingError` when the
    models cannot be loaded and :class:`TextReadFailedError` when a model refuses the input (the
    caller turns the last two into "no evidence", said).
    """
    clock = time.perf_counter()
    rgb = _rgb(image)
    folder = models_folder()
    if folder is None:
        raise TextModelMissingError("the rapidocr-onnxruntime package (its ONNX text models) is not installed")
    detector, recogniser = _sessions(str(folder))
    boxes, scale = _detect_lines(detector, rgb, params)
    level = [line for line in map(_level, boxes) if line is not None]
    candidates = [line for line in level if line[1] >= params.min_aspect * line[2] and line[2] * scale >= params.min_line_px]
    candidates = sorted(candidates, key=lambda line: -line[1])[: params.max_lines]
    lines: tuple[TextLine, ...] = ()
    if candidates:
        crops = _line_crops(rgb, candidates)
        readings = _recognise(recogniser, crops + [np.ascontiguousarray(c[::-1, ::-1]) for c in crops])
        seen, turned = readings[: len(crops)], readings[len(crops) :]
        lines = tuple(
            TextLine(
                corners=corners,
                height_px=height,
                length_px=length,
                upright_confidence=up[0],
                turned_confidence=down[0],
                text=up[1] if up[0] >= down[0] else down[1],
            )
            for (corners, length, height), up, down in zip(candidates, seen, turned, strict=True)
            if max(up[0], down[0]) >= params.min_reading
        )
    if not lines:
        note = (
            f"no readable horizontal print ({len(boxes)} text blobs, {len(boxes) - len(level)} vertical, "
            f"{len(candidates)} line(s) tried)"
        )
        return TextReading(0.0, (), time.perf_counter() - clock, note)
    value = float(sum(line.evidence for line in lines) / (len(lines) + 1.0))
    upright = sum(line.evidence > 0 for line in lines)
    note = f"{len(lines)} line(s) of print read: {upright} upright, {len(lines) - upright} upside down"
    return TextReading(value, lines, time.perf_counter() - clock, note)

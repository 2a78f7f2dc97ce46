"""Stereo viewing formats made from a rectified pair: anaglyph, wiggle frames, side-by-side layouts.

Pure array code (numpy + OpenCV); encoding to files lives in :mod:`pipeline.stereo_files`.

Conventions (as everywhere in the pipeline): images are ``uint8`` ``(H, W)`` grey or
``(H, W, 3)`` RGB, row 0 at the top; the disparity is the disparity stage's ``disparity_left``,
``(H, W)`` float32 pixels on the left rectified view, ``x_right = x_left - d``, NaN = unknown.

* **Anaglyph**: Dubois's least-squares red-cyan projection (E. Dubois, "A projection method to
  generate anaglyph stereo images", ICASSP 2001; the red-cyan matrices are the ones published
  on his page, "Conversion of a stereo pair to anaglyph with the least-squares projection
  method", March 2009, http://www.site.uottawa.ca/~edubois/anaglyph/). The projection is
  defined on linear RGB, so sRGB values are linearised first and re-encoded after.
* **Wiggle**: intermediate views synthesised by backward-warping the left view by a fraction
  ``t`` of the disparity: ``I_t(x, y) = I_left(x + t d(x, y), y)``, so ``t = 0`` is the left view
  and ``t = 1`` approximates the right one (a point at ``x_left`` appears at ``x_left - t d``).
  The sweep goes 0 -> 1 -> 0 with a cosine ease so the motion slows at both ends.
* **Side by side**: parallel (left view on the left, for headsets and parallel viewing) at full
  or half width; cross-eyed (right view on the left) is the JPS convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import PipelineError

# Dubois red-cyan, least squares (source above). Rows give the anaglyph's R, G, B; columns the
# input's R, G, B. The output is  A = DUBOIS_LEFT @ L + DUBOIS_RIGHT @ R  on linear RGB in [0, 1].
DUBOIS_LEFT = np.array([[0.437, 0.449, 0.164], [-0.062, -0.062, -0.024], [-0.048, -0.050, -0.017]], np.float64)
DUBOIS_RIGHT = np.array([[-0.011, -0.032, -0.007], [0.377, 0.761, 0.009], [-0.026, -0.093, 1.234]], np.float64)

ENCODE_LEVELS = 65536  # entries of the linear -> sRGB table used by the anaglyph
WIGGLE_STEPS = 7  # views from left to right inclusive (odd, so t = 0.5 is one of them)


class StereoFormatError(PipelineError):
    """The pair cannot be turned into a stereo format (sizes differ, no disparity at all, ...)."""

    code = "stereo_format"


@dataclass(frozen=True)
class StereoPair:
    """A rectified pair as RGB arrays of the same size, with the left view's disparity."""

    left: np.ndarray  # (H, W, 3) uint8
    right: np.ndarray  # (H, W, 3) uint8
    disparity: np.ndarray  # (H, W) float32 px, x_right = x_left - d, NaN unknown


def as_rgb(image: np.ndarray) -> np.ndarray:
    """``(H, W)`` grey or ``(H, W, 3)`` RGB ``uint8`` -> ``(H, W, 3)`` RGB ``uint8``."""
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise StereoFormatError(f"Expected a uint8 (H, W) or (H, W, 3) image, got {image.dtype} {image.shape}")
    return np.ascontiguousarray(np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image)


def make_pair(left: np.ndarray, right: np.ndarray, disparity: np.ndarray) -> StereoPair:
    """Check sizes and convert to RGB. Raises :class:`StereoFormatError` on mismatched shapes."""
    left, right = as_rgb(left), as_rgb(right)
    if left.shape != right.shape:
        raise StereoFormatError(f"Expected left and right views of one size, got {left.shape[:2]} and {right.shape[:2]}")
    if disparity.shape != left.shape[:2]:
        raise StereoFormatError(f"Expected a disparity of the views' size {left.shape[:2]}, got {disparity.shape}")
    return StereoPair(left, right, np.asarray(disparity, np.float32))


# ---- anaglyph -------------------------------------------------------------------------------


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] -> linear light in [0, 1] (IEC 61966-2-1)."""
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    values = np.clip(values, 0.0, 1.0)
    return np.where(values <= 0.0031308, values * 12.92, 1.055 * values ** (1 / 2.4) - 0.055)


def dubois_anaglyph(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Red-cyan anaglyph of two views of one size, ``(H, W, 3)`` uint8 (red = left eye).

    Linearise, project with :data:`DUBOIS_LEFT` / :data:`DUBOIS_RIGHT`, clip to [0, 1], re-encode sRGB."""
    left, right = as_rgb(left), as_rgb(right)
    if left.shape != right.shape:
        raise StereoFormatError(f"Expected views of one size, got {left.shape[:2]} and {right.shape[:2]}")
    # Both transfer functions go through tables (256 and 65,536 entries): a power per pixel and
    # channel took 0.8 s on a 1800 x 1900 pair; the encode table's step is far below one grey level.
    import cv2

    decode = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)
    # cv2.transform applies a 3 x 3 matrix per pixel (out = M @ px), several times faster than numpy's matmul.
    projected = cv2.transform(decode[left], DUBOIS_LEFT.astype(np.float32)) + cv2.transform(
        decode[right], DUBOIS_RIGHT.astype(np.float32)
    )
    encode = np.round(linear_to_srgb(np.arange(ENCODE_LEVELS) / (ENCODE_LEVELS - 1)) * 255.0).astype(np.uint8)
    index = np.clip(projected, 0.0, 1.0) * np.float32(ENCODE_LEVELS - 1) + np.float32(0.5)
    return encode[index.astype(np.int32)]


# ---- wiggle ---------------------------------------------------------------------------------


def wiggle_fractions(steps: int = WIGGLE_STEPS) -> list[float]:
    """The fractions ``t`` of the disparity, one per frame: 0 -> 1 with a cosine ease, then back
    without repeating the ends (``2 * steps - 2`` frames; ``steps`` odd puts t = 0.5 at frame
    ``(steps - 1) // 2``)."""
    if steps < 2:
        raise StereoFormatError(f"Expected at least 2 wiggle steps, got {steps}")
    forward = [float(0.5 - 0.5 * np.cos(np.pi * k / (steps - 1))) for k in range(steps)]
    forward[0], forward[-1] = 0.0, 1.0
    return forward + forward[-2:0:-1]


def fill_disparity(disparity: np.ndarray) -> np.ndarray:
    """Unknown (non-finite) disparities filled by normalised convolution (the mean of known
    neighbours at growing radii), then the median of the known ones. Raises when none is known."""
    import cv2

    known = np.isfinite(disparity)
    if not known.any():
        raise StereoFormatError("the disparity map has no known value: cannot synthesise views")
    filled = np.where(known, disparity, 0.0).astype(np.float32)
    weight = known.astype(np.float32)
    result = filled.copy()
    missing = ~known
    for radius in (4, 16, 64):
        if not missing.any():
            break
        size = (2 * radius + 1, 2 * radius + 1)
        total = cv2.boxFilter(filled, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
        count = cv2.boxFilter(weight, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
        reached = missing & (count > 0.5)
        result[reached] = total[reached] / count[reached]
        missing &= ~reached
    result[missing] = float(np.median(disparity[known]))
    return result


def warp_left(left: np.ndarray, disparity: np.ndarray, t: float) -> np.ndarray:
    """The left view moved a fraction ``t`` of the way to the right view:
    ``I_t(x, y) = I_left(x + t d(x, y), y)`` (bilinear, edges replicated). ``disparity`` must be
    finite (see :func:`fill_disparity`)."""
    import cv2

    height, width = disparity.shape
    xs = np.arange(width, dtype=np.float32)[None, :] + np.float32(t) * disparity.astype(np.float32)
    ys = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], (height, width))
    return cv2.remap(left, xs, np.ascontiguousarray(ys), interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def wiggle_frames(pair: StereoPair, steps: int = WIGGLE_STEPS, max_side: int | None = None) -> list[np.ndarray]:
    """Frames of the wiggle, ``(H', W', 3)`` uint8 each, one per :func:`wiggle_fractions` entry;
    ``max_side`` shrinks the views (and scales the disparity with them) first."""
    import cv2

    left, disparity = pair.left, fill_disparity(pair.disparity)
    height, width = disparity.shape
    scale = 1.0 if max_side is None else min(1.0, max_side / max(height, width))
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        disparity = cv2.resize(disparity, size, interpolation=cv2.INTER_LINEAR) * np.float32(size[0] / width)
    return [warp_left(left, disparity, t) for t in wiggle_fractions(steps)]


# ---- side by side ---------------------------------------------------------------------------


def side_by_side(first: np.ndarray, second: np.ndarray, half: bool = False) -> np.ndarray:
    """``first`` on the left, ``second`` on the right; ``half`` squeezes each to half its width
    (the "half side-by-side" frame of 3D TVs and headsets: the pair in one view's width)."""
    import cv2

    first, second = as_rgb(first), as_rgb(second)
    if first.shape != second.shape:
        raise StereoFormatError(f"Expected views of one size, got {first.shape[:2]} and {second.shape[:2]}")
    if half:
        height, width = first.shape[:2]
        size = (max(1, width // 2), height)
        first, second = (cv2.resize(view, size, interpolation=cv2.INTER_AREA) for view in (first, second))
    return np.ascontiguousarray(np.concatenate([first, second], axis=1))


def split_side_by_side(image: np.ndarray, order: str) -> tuple[np.ndarray, np.ndarray]:
    """(left view, right view) of a side-by-side image whose halves are in ``order``:
    ``parallel`` (left eye's view on the left) or ``cross`` (right eye's view on the left, JPS).
    An odd width drops the middle column."""
    if order not in ("parallel", "cross"):
        raise StereoFormatError(f"Expected an eye order of 'parallel' or 'cross', got {order!r}")
    half = image.shape[1] // 2
    if half < 1:
        raise StereoFormatError(f"Expected a side-by-side image at least 2 px wide, got width {image.shape[1]}")
    first, second = image[:, :half], image[:, image.shape[1] - half :]
    return (first, second) if order == "parallel" else (second, first)


# ---- eye order check ------------------------------------------------------------------------

EYE_ORDER_STRIPS = 8
EYE_ORDER_MIN_SLOPE = 0.004  # |shift change| per image width, top to bottom, below which the check abstains


@dataclass(frozen=True)
class EyeOrderEvidence:
    """Which eye order the halves of a side-by-side image suggest, and why.

    ``shifts``: horizontal shift (px, at the analysed width) of the second half against the first,
    per horizontal strip from top to bottom; ``slope``: the fitted change of that shift from the
    top strip to the bottom one, as a fraction of one half's width. Scenes are nearer at the bottom
    (ground) than at the top (sky, far buildings), so with the left view first the right half's
    content moves further left (more negative) towards the bottom: a negative slope suggests
    ``parallel``, a positive one ``cross``. A heuristic (a ceiling, a tilted card, a flat scene can
    fool it): it informs a person, it never reorders a card by itself."""

    suggests: str  # "parallel", "cross" or "unknown"
    slope: float
    shifts: tuple[float, ...]
    width: int

    def as_json(self) -> dict[str, object]:
        return {
            "suggests": self.suggests,
            "slope": round(self.slope, 5),
            "shifts_px": [round(s, 2) for s in self.shifts],
            "analysed_width": self.width,
        }


def eye_order_evidence(first: np.ndarray, second: np.ndarray, analysed_width: int = 512) -> EyeOrderEvidence:
    """Strip-wise phase correlation between the two halves of a side-by-side image (as stored:
    ``first`` = left half). See :class:`EyeOrderEvidence`."""
    import cv2

    first, second = as_rgb(first), as_rgb(second)
    height = min(first.shape[0], second.shape[0])
    width = min(first.shape[1], second.shape[1])
    if height < 4 * EYE_ORDER_STRIPS or width < 32:
        raise StereoFormatError(f"Expected halves of at least 32 x {4 * EYE_ORDER_STRIPS} px, got {width} x {height}")
    scale = min(1.0, analysed_width / width)
    size = (max(32, round(width * scale)), max(4 * EYE_ORDER_STRIPS, round(height * scale)))
    grey = [
        cv2.resize(
            cv2.cvtColor(np.ascontiguousarray(view[:height, :width]), cv2.COLOR_RGB2GRAY), size, interpolation=cv2.INTER_AREA
        ).astype(np.float64)
        for view in (first, second)
    ]
    window_rows = size[1] // EYE_ORDER_STRIPS
    margin = size[0] // 10  # mount edges and arch corners sit at the sides
    shifts: list[float] = []
    for strip in range(EYE_ORDER_STRIPS):
        rows = slice(strip * window_rows, (strip + 1) * window_rows)
        a, b = (image[rows, margin : size[0] - margin] for image in grey)
        window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_64F)
        (dx, _dy), _response = cv2.phaseCorrelate(a, b, window)
        shifts.append(float(dx))
    centres = (np.arange(EYE_ORDER_STRIPS) + 0.5) / EYE_ORDER_STRIPS
    slope = float(np.polyfit(centres, np.asarray(shifts), 1)[0]) / size[0]
    suggests = "unknown" if abs(slope) < EYE_ORDER_MIN_SLOPE else ("parallel" if slope < 0 else "cross")
    return EyeOrderEvidence(suggests=suggests, slope=slope, shifts=tuple(shifts), width=size[0])

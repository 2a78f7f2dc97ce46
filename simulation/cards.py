"""The demo collection: antique-looking stereo cards made from photographs every install has.

``keystone demo`` must run on a fresh machine with no data, so the cards are built from images
that ship inside the scikit-image wheel (all load offline, no pooch/network):

* ``skimage.data.stereo_motorcycle()``: a real, rectified Middlebury 2014 stereo pair (741 x 500)
  with ground-truth disparity (Scharstein et al., GCPR 2014). Every stereo card crops both views
  with the *same* window, so each card holds a true stereo pair.
* ``coffee``, ``rocket``, ``astronaut``, ``chelsea``, ``camera``: single photographs for the
  broken cards (not a stereo pair).

A card is mounted, toned and damaged like a 1900s card: sepia-toned prints, cardboard with paper
texture and darker edges, arched or square print tops, a 10-30 px gutter, printed captions and
side imprints (``cv2.putText``), vignetting, grain, scratches, dust, foxing, and a dark scanner
bed around rounded card corners. The right print is imperfect the way real ones are: a small
rotation (0.2-1.0 deg) and vertical offset (1-4 px) relative to the left. Everything done is
recorded in :attr:`DemoCard.truth` (JSON-serialisable), so tests and the demo can check stages.

Broken cards: ``mono`` (one wide photo, or two unrelated photos), ``back`` (a card back: text
and a seal, no photos), ``upside_down`` (a stereo card rotated 180 deg, which also swaps the
halves) and ``inverted`` (``255 - card``, as scanned from a negative).

Deterministic: every card draws from its own ``numpy`` Generator seeded by ``(seed, index)``, so
the same seed gives byte-identical images. Sizes: scans about 1400 x 700 px, prints about
600 x 550 px.
"""

from __future__ import annotations

import csv
import functools
import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.io import write_jpeg

KINDS = ("stereo", "mono", "back", "upside_down", "inverted")
METADATA_COLUMNS = ("file_name", "accession", "title", "date", "creator", "publisher", "place", "subjects")
# eMuseum exports (the Keystone-Mast records) separate subjects with newlines inside one cell.
SUBJECT_SEPARATOR = "\n"

# Index offsets of the (seed, index) streams: stereo cards use 0..n_stereo-1 and the stereo cards
# that the upside-down and inverted cards are made from use their own, disjoint indices (which are
# 6 and 7 modulo the 8 titles, so the default collection repeats no title).
_UPSIDE_DOWN_BASE = 1006
_INVERTED_BASE = 2007
_MONO_STREAM = 3000
_BACK_STREAM = 4000


@dataclass(frozen=True, eq=False)  # eq would compare arrays elementwise
class DemoCard:
    """One demo scan and what is known about it.

    ``truth`` (JSON-serialisable) holds, where they apply:

    * boxes ``[x0, y0, x1, y1]`` in scan pixels, x1/y1 exclusive: ``card_box`` (the mount inside
      the scan), ``photo_boxes`` (prints, left to right as scanned), ``left_box`` / ``right_box``
      (the *left-eye* / *right-eye* print as scanned: swapped for an upside-down card; ``None``
      when the card holds no stereo pair). Both eyes' boxes have the same size.
    * ``crop_window`` (the Motorcycle window, source pixels), ``scale`` (print px per source px),
      ``left_affine`` / ``right_affine`` (2x3, source view pixels -> scan pixels; map ground-truth
      disparity with them).
    * ``right_rotation_deg`` (OpenCV sign: positive turns the content counter-clockwise as seen)
      about the right print's centre and ``right_vertical_offset_px`` (positive: right content lower),
      both applied to the right print only.
    * ``gutter_px``, ``photo_shape`` ("arched" | "square"), ``corner_radius_px``, ``caption``,
      ``scratches``, ``dust_specks``, ``sources`` (mono cards).
    * flags ``upside_down``, ``inverted``, ``halves_swapped``; derived cards add ``derived_from``
      (``{"seed", "index"}`` for :func:`make_stereo_card`). An upside-down card's boxes and affines
      are as scanned; its rotation and offset are its base card's (true once turned upright).
    """

    name: str  # file-name stem, e.g. "demo_motorcycle_01"
    image: np.ndarray  # (H, W, 3) uint8 RGB, the whole card scan
    kind: str  # "stereo" | "mono" | "back" | "upside_down" | "inverted"
    expected_filter: tuple[str, ...]  # filter outcomes that are right for this card
    truth: dict[str, Any]
    metadata: dict[str, Any]  # accession, title, date, creator, publisher, place, subjects (tuple)


# ----------------------------------------------------------------------------------- sources


@functools.lru_cache(maxsize=1)
def _motorcycle() -> tuple[np.ndarray, np.ndarray]:
    """Left and right Motorcycle views as read-only float32 luminance (0..255)."""
    from skimage import data

    left, right, _disparity = data.stereo_motorcycle()
    views = tuple(cv2.cvtColor(view, cv2.COLOR_RGB2GRAY).astype(np.float32) for view in (left, right))
    for view in views:
        view.setflags(write=False)
    return views  # type: ignore[return-value]


@functools.lru_cache(maxsize=8)
def _single_photo(name: str) -> np.ndarray:
    """A scikit-image sample photograph (one shipped in the wheel) as read-only float32 grey."""
    from skimage import data

    image = getattr(data, name)()
    grey = image if image.ndim == 2 else cv2.cvtColor(image[..., :3], cv2.COLOR_RGB2GRAY)
    grey = grey.astype(np.float32)
    grey.setflags(write=False)
    return grey


# Single photographs for the mono cards: (title, subjects) for their catalogue records.
_WIDE_SOURCES = {
    "coffee": ("Breakfast table with coffee", ("Coffee", "Tableware")),
    "rocket": ("Rocket on the launching stand", ("Rockets", "Launch sites")),
}
_SINGLE_SOURCES = {
    "astronaut": ("Portrait of an aviator", ("Portraits", "Aviators")),
    "chelsea": ("The family cat", ("Cats", "Pets")),
    "camera": ("The photographer in the field", ("Photographers", "Cameras")),
    "coffee": ("Breakfast table with coffee", ("Coffee", "Tableware")),
}


# ---------------------------------------------------------------------------------- catalogue

_PUBLISHERS = (
    # (publisher on the record, name printed on the mount, side imprints left/right)
    (
        "Keystone View Company",
        "KEYSTONE VIEW COMPANY",
        ("KEYSTONE VIEW COMPANY", "MANUFACTURERS AND PUBLISHERS"),
        ("MEADVILLE, PA.  NEW YORK, N.Y.", "CHICAGO, ILL.  LONDON, ENG."),
    ),
    (
        "Underwood & Underwood",
        "UNDERWOOD & UNDERWOOD",
        ("UNDERWOOD & UNDERWOOD, PUBLISHERS", "NEW YORK, LONDON, TORONTO-CANADA"),
        ("WORKS AND STUDIOS", "ARLINGTON, N.J.  WESTWOOD, N.J."),
    ),
    (
        "H. C. White Co.",
        "H. C. WHITE CO.",
        ("H. C. WHITE CO., PUBLISHERS", "NORTH BENNINGTON, VT., U.S.A."),
        ("PERFEC STEREOGRAPH", "CHICAGO, ILL.  LONDON, ENG."),
    ),
)

_MOTORCYCLE_TITLES = (
    (
        "The new motor cycle in the repair shop",
        "North and Central America, United States, Pennsylvania, Meadville",
        ("Motorcycles", "Repair shops"),
    ),
    (
        "A motor bicycle ready for the road",
        "North and Central America, United States, Massachusetts, Springfield",
        ("Motorcycles", "Transportation"),
    ),
    (
        "Latest model of the motor cycle, showing engine and tank",
        "North and Central America, United States, Wisconsin, Milwaukee",
        ("Motorcycles", "Engines", "Industry"),
    ),
    (
        "Mechanic's garage with motor cycle",
        "North and Central America, United States, Illinois, Chicago",
        ("Motorcycles", "Garages", "Tools"),
    ),
    (
        "Police motor cycle at the station house",
        "North and Central America, United States, New York, New York",
        ("Motorcycles", "Police"),
    ),
    (
        "Racing motor cycle at the factory",
        "North and Central America, United States, Ohio, Toledo",
        ("Motorcycles", "Racing", "Factories"),
    ),
    ("The machine that conquered distance", "Europe, England, London", ("Motorcycles", "Inventions")),
    (
        "Motor cycle on exhibition at the automobile show",
        "North and Central America, United States, New York, New York",
        ("Motorcycles", "Exhibitions"),
    ),
)

_CREATORS = ("Not Known", "B. L. Singley", "James M. Reid", "Not Known", "B. W. Kilburn")

_BACK_SENTENCES = (
    "The motor cycle has in a few short years become one of the most familiar sights upon our roads.",
    "Its engine, of a single cylinder, drives the rear wheel by a leather belt running over a pulley.",
    "The gasoline is carried in the tank above the frame, enough for a journey of a hundred miles.",
    "Notice the spring fork, which takes up the shocks of the road before they reach the rider.",
    "Mechanics of the shop keep such machines in repair, and many tools lie ready upon the bench.",
    "A skilled rider may reach a speed of forty miles an hour upon a good level road.",
    "The postman, the physician and the policeman have each found it a useful servant.",
    "From the factories of this country thousands of machines are shipped every year to distant lands.",
    "Look closely at the carburetor, where air and gasoline are mixed before they enter the cylinder.",
    "Within a generation the horse may be a rare sight upon the streets of our great cities.",
)


# ------------------------------------------------------------------------------- rendering


@dataclass(frozen=True)
class _Layout:
    """Geometry of a two-print card inside its scan (all integers, pixels)."""

    scan_w: int
    scan_h: int
    card_box: tuple[int, int, int, int]
    photo_w: int
    photo_h: int
    left_box: tuple[int, int, int, int]
    right_box: tuple[int, int, int, int]
    gutter: int


def _layout(rng: np.random.Generator) -> _Layout:
    photo_w = int(rng.integers(575, 611))
    photo_h = int(rng.integers(530, 566))
    gutter = int(rng.integers(10, 31))
    side = int(rng.integers(72, 96))
    top = int(rng.integers(26, 44))
    caption = int(rng.integers(88, 114))
    card_w, card_h = 2 * side + 2 * photo_w + gutter, top + photo_h + caption
    bed = [int(v) for v in rng.integers(0, 15, size=4)]  # scanner bed visible left, top, right, bottom
    cx0, cy0 = bed[0], bed[1]
    y0 = cy0 + top
    left_box = (cx0 + side, y0, cx0 + side + photo_w, y0 + photo_h)
    rx0 = left_box[2] + gutter
    right_box = (rx0, y0, rx0 + photo_w, y0 + photo_h)
    return _Layout(
        scan_w=card_w + bed[0] + bed[2],
        scan_h=card_h + bed[1] + bed[3],
        card_box=(cx0, cy0, cx0 + card_w, cy0 + card_h),
        photo_w=photo_w,
        photo_h=photo_h,
        left_box=left_box,
        right_box=right_box,
        gutter=gutter,
    )


def _noise(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Zero-mean, unit-variance float32 noise (uniform: several times cheaper than normal)."""
    u = rng.random(shape, dtype=np.float32)
    u -= 0.5
    u *= math.sqrt(12.0)
    return u


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """Zero-mean smooth noise with features about ``cell`` px wide (float32)."""
    small = rng.standard_normal((max(2, h // cell + 2), max(2, w // cell + 2)), dtype=np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


_MOUNT_COLOURS = np.array(
    [
        (206, 190, 152),  # buff
        (221, 206, 168),  # cream
        (158, 156, 136),  # grey-green
        (176, 168, 152),  # grey
        (214, 172, 104),  # orange-yellow
        (196, 176, 140),  # tan
    ],
    dtype=np.float32,
)


def _edge_profile(n: int, depth: float, width: float) -> np.ndarray:
    """Brightness factor against the distance to the nearer end, for one card axis."""
    d = np.minimum(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32)[::-1])
    return (1.0 - depth * np.exp(-d / width)) * (1.0 - 0.06 * np.exp(-d / 40.0))


def _blend_patch(scan: np.ndarray, alpha: np.ndarray, colour: np.ndarray, x: int, y: int) -> None:
    """scan <- scan * (1 - alpha) + colour * alpha for an alpha patch at (x, y), clipped to the scan."""
    h, w = scan.shape[:2]
    x0, y0, x1, y1 = max(0, x), max(0, y), min(w, x + alpha.shape[1]), min(h, y + alpha.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    a = alpha[y0 - y : y1 - y, x0 - x : x1 - x, None]
    region = scan[y0:y1, x0:x1]
    region += (colour - region) * a


def _mount(rng: np.random.Generator, layout: _Layout, colour: np.ndarray | None = None) -> np.ndarray:
    """Scan canvas: dark scanner bed, aged cardboard with texture, darker edges, foxing (float32 RGB)."""
    h, w = layout.scan_h, layout.scan_w
    x0, y0, x1, y1 = layout.card_box
    ch, cw = y1 - y0, x1 - x0
    if colour is None:
        colour = _MOUNT_COLOURS[int(rng.integers(len(_MOUNT_COLOURS)))]
    colour = colour * rng.uniform(0.94, 1.04, size=3).astype(np.float32)
    fibre = _noise(rng, (h, w))  # one draw: the bed's sensor noise and the card's paper fibre
    shade = 0.03 * _smooth_noise(rng, ch, cw, 90)
    shade += 0.012 * _smooth_noise(rng, ch, cw, 14)
    shade += 0.012 * fibre[y0:y1, x0:x1]
    shade += 1.0
    # Edges handled for a century are darker; the factor is monotone in the edge distance, so
    # the 2-D factor is the smaller of the two 1-D ones.
    depth, width = float(rng.uniform(0.18, 0.32)), float(rng.uniform(4.0, 9.0))
    shade *= np.minimum(_edge_profile(ch, depth, width)[:, None], _edge_profile(cw, depth, width)[None, :])

    scan = np.empty((h, w, 3), np.float32)
    bed = float(rng.uniform(22, 42))
    for sl in (
        (slice(None), slice(0, x0)),
        (slice(None), slice(x1, w)),
        (slice(0, y0), slice(x0, x1)),
        (slice(y1, h), slice(x0, x1)),
    ):
        scan[sl] = (bed + 3.0 * fibre[sl])[..., None]
    np.multiply(shade[..., None], colour, out=scan[y0:y1, x0:x1])

    # Foxing: small soft brown spots.
    fox = np.array([0.25, 0.4, 0.6], np.float32)
    for _ in range(int(rng.integers(4, 14))):
        radius = int(rng.integers(2, 9))
        size = 2 * radius + 15
        spot = np.zeros((size, size), np.float32)
        cv2.circle(spot, (size // 2, size // 2), radius, float(rng.uniform(0.15, 0.45)), -1, cv2.LINE_AA)
        spot = cv2.GaussianBlur(spot, (0, 0), 2.5)
        sx, sy = x0 + int(rng.integers(0, cw)) - size // 2, y0 + int(rng.integers(0, ch)) - size // 2
        region = scan[max(0, sy) : sy + size, max(0, sx) : sx + size]
        patch = spot[max(0, sy) - sy :, max(0, sx) - sx :][: region.shape[0], : region.shape[1]]
        region *= 1.0 - patch[..., None] * fox

    # Rounded card corners over the scanner bed.
    radius = int(rng.integers(10, 24))
    corner = np.zeros((radius + 1, radius + 1), np.float32)
    cv2.circle(corner, (radius, radius), radius, 1.0, -1, cv2.LINE_AA)
    outside = 1.0 - corner  # alpha of the bed in the top-left corner
    for flip_y, flip_x in ((False, False), (False, True), (True, False), (True, True)):
        a = outside[:: -1 if flip_y else 1, :: -1 if flip_x else 1]
        cx = x1 - radius - 1 if flip_x else x0
        cy = y1 - radius - 1 if flip_y else y0
        _blend_patch(scan, a, np.float32(bed), cx, cy)
    return scan


def _photo_mask(rng: np.random.Generator, w: int, h: int) -> tuple[np.ndarray, str, int]:
    """Alpha of a print: arched (big rounded top corners, as on 1900s cards) or square.

    Returns (alpha (h, w) float32, style, top corner radius in px).
    """
    style = "arched" if rng.random() < 0.5 else "square"
    top = int(rng.integers(90, 170)) if style == "arched" else int(rng.integers(2, 7))
    bottom = int(rng.integers(2, 7))
    k = 4  # drawn 4x supersampled, then area-reduced: smooth edges
    mask = np.zeros((h * k, w * k), np.uint8)
    right, low, t, b = w * k - 1, h * k - 1, top * k, bottom * k
    cv2.rectangle(mask, (0, t), (right, low - b), 255, -1)
    cv2.rectangle(mask, (t, 0), (right - t, t), 255, -1)
    cv2.rectangle(mask, (b, low - b), (right - b, low), 255, -1)
    for centre, r in (((t, t), t), ((right - t, t), t), ((b, low - b), b), ((right - b, low - b), b)):
        cv2.circle(mask, centre, r, 255, -1)
    alpha = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    alpha *= 1.0 / 255.0
    return alpha, style, top


def _window_affine(x0: float, y0: float, scale: float) -> np.ndarray:
    """2x3 affine taking source pixels to print pixels for the window at (x0, y0)."""
    return np.array([[scale, 0.0, -scale * x0], [0.0, scale, -scale * y0]], np.float64)


def _misalign(affine: np.ndarray, w: int, h: int, angle_deg: float, dy: float) -> np.ndarray:
    """Compose ``affine`` with a rotation about the print centre and a vertical shift (+dy = down)."""
    rotation = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), angle_deg, 1.0)
    rotation[1, 2] += dy
    return (np.vstack([rotation, [0, 0, 1]]) @ np.vstack([affine, [0, 0, 1]]))[:2]


def _render_source(source: np.ndarray, affine: np.ndarray, w: int, h: int) -> np.ndarray:
    return cv2.warpAffine(source, affine, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)


@dataclass(frozen=True)
class _Tone:
    """How prints on one card were made and have aged (shared by both prints of a pair)."""

    blur: float
    low: float
    high: float
    gamma: float
    vignette: float
    grain: float
    lut: np.ndarray  # (256, 3) float32 grey -> toned RGB


_TONE_PALETTES = np.array(
    [
        # shadows, mid-tones, highlights (RGB)
        [(40, 25, 16), (142, 104, 68), (238, 219, 180)],  # warm sepia (albumen)
        [(31, 28, 25), (124, 116, 102), (226, 220, 204)],  # near-neutral gelatin silver
        [(52, 31, 18), (160, 114, 64), (241, 214, 160)],  # strong yellow-brown, faded albumen
    ],
    dtype=np.float32,
)


def _tone(rng: np.random.Generator) -> _Tone:
    weights = rng.dirichlet(np.ones(len(_TONE_PALETTES)))
    palette = np.tensordot(weights, _TONE_PALETTES, axes=1)  # (3 stops, 3 channels)
    g = np.linspace(0.0, 1.0, 256, dtype=np.float32)
    lut = np.stack([np.interp(g, [0.0, 0.5, 1.0], palette[:, c]) for c in range(3)], axis=1).astype(np.float32)
    return _Tone(
        blur=float(rng.uniform(0.6, 1.1)),
        low=float(rng.uniform(0.03, 0.12)),
        high=float(rng.uniform(0.86, 0.97)),
        gamma=float(rng.uniform(0.85, 1.15)),
        vignette=float(rng.uniform(0.15, 0.35)),
        grain=float(rng.uniform(0.012, 0.028)),
        lut=lut,
    )


def _age_print(rng: np.random.Generator, grey: np.ndarray, tone: _Tone) -> np.ndarray:
    """Soften, fade, vignette, add grain, then sepia-tone a float grey print (0..255) -> RGB float32."""
    h, w = grey.shape
    g = cv2.GaussianBlur(grey, (0, 0), tone.blur)
    g *= 1.0 / 255.0
    np.clip(g, 0.0, 1.0, out=g)
    g = tone.low + (tone.high - tone.low) * np.power(g, np.float32(tone.gamma))
    x = ((np.arange(w, dtype=np.float32) - (w - 1) / 2) / (w / 2)) ** 2
    y = ((np.arange(h, dtype=np.float32) - (h - 1) / 2) / (h / 2)) ** 2
    r2 = (y[:, None] + x[None, :]) * 0.5  # squared radius, 1 in the corners
    g *= 1.0 - tone.vignette * np.power(r2, np.float32(1.25))
    grain = cv2.GaussianBlur(_noise(rng, (h, w)), (0, 0), 0.7)
    g += (tone.grain * 2.0) * grain  # the blur divides the noise's std by about 2
    g *= 255.0
    return tone.lut[cv2.convertScaleAbs(g)]  # saturating float -> uint8 (g >= 0 up to grain)


def _paste(scan: np.ndarray, photo: np.ndarray, alpha: np.ndarray, box: tuple[int, int, int, int]) -> None:
    x0, y0, x1, y1 = box
    region = scan[y0:y1, x0:x1]
    region[...] = cv2.blendLinear(photo, region, alpha, 1.0 - alpha)


def _text_block(text: str, font: int, scale: float, thickness: int) -> np.ndarray:
    """Text rendered white on black into a tight uint8 patch.

    Drawn at 3x and area-reduced: glyphs get soft, sub-pixel-placed edges, so repeated letters are
    not pixel-identical copies (as in print, and unlike a plain raster font).
    """
    k = 3
    (tw, th), base = cv2.getTextSize(text, font, scale * k, thickness * k)
    pad = (thickness + 2) * k
    height, width = th + base + 2 * pad, tw + 2 * pad
    patch = np.zeros((height + (-height) % k, width + (-width) % k), np.uint8)
    cv2.putText(patch, text, (pad, pad + th), font, scale * k, 255, thickness * k, cv2.LINE_AA)
    return cv2.resize(patch, (patch.shape[1] // k, patch.shape[0] // k), interpolation=cv2.INTER_AREA)


def _stamp(ink: np.ndarray, patch: np.ndarray, x: int, y: int) -> None:
    """Max-composite ``patch`` into the ink layer with its top-left at (x, y), clipped to the layer."""
    h, w = ink.shape
    px0, py0 = max(0, -x), max(0, -y)
    x0, y0 = max(0, x), max(0, y)
    x1, y1 = min(w, x + patch.shape[1]), min(h, y + patch.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    sub = patch[py0 : py0 + (y1 - y0), px0 : px0 + (x1 - x0)]
    np.maximum(ink[y0:y1, x0:x1], sub, out=ink[y0:y1, x0:x1])


def _text_centred(
    ink: np.ndarray, text: str, cx: int, cy: int, font: int, scale: float, thickness: int, max_width: int | None = None
) -> None:
    patch = _text_block(text, font, scale, thickness)
    if max_width is not None and patch.shape[1] > max_width:
        patch = _text_block(text, font, scale * max_width / patch.shape[1], thickness)
    _stamp(ink, patch, cx - patch.shape[1] // 2, cy - patch.shape[0] // 2)


def _apply_ink(
    rng: np.random.Generator,
    scan: np.ndarray,
    ink: np.ndarray,
    colour: np.ndarray,
    strength: float,
    zones: list[tuple[int, int, int, int]] | None = None,
) -> None:
    """Print the ink layer inside ``zones`` (x0, y0, x1, y1; default: where there is ink): slightly
    spread, uneven coverage (letterpress on cardboard)."""
    if zones is None:
        x, y, w, h = cv2.boundingRect(ink)
        zones = [(x, y, x + w, y + h)] if w and h else []
    for x0, y0, x1, y1 in zones:
        x0, y0 = max(0, x0 - 3), max(0, y0 - 3)
        x1, y1 = min(ink.shape[1], x1 + 3), min(ink.shape[0], y1 + 3)
        if x1 <= x0 or y1 <= y0:
            continue
        coverage = cv2.GaussianBlur(ink[y0:y1, x0:x1].astype(np.float32), (0, 0), 0.6)
        uneven = _smooth_noise(rng, y1 - y0, x1 - x0, 5)
        np.clip(uneven, -1.5, 1.5, out=uneven)
        coverage *= (1.0 - 0.12 * uneven * uneven) * (strength / 255.0)
        np.clip(coverage, 0.0, 1.0, out=coverage)
        _blend_patch(scan, coverage, colour, x0, y0)


def _damage(rng: np.random.Generator, scan: np.ndarray, areas: list[tuple[int, int, int, int]]) -> dict[str, int]:
    """Scratches (thin bright or dark lines) and dust specks, over the prints where there are any."""
    h, w = scan.shape[:2]
    bright, dark = np.float32(238.0), np.float32(28.0)

    def mark(draw, points: np.ndarray, pad: int, colour: np.float32) -> None:
        lo = np.floor(points.min(axis=0)).astype(int) - pad
        hi = np.ceil(points.max(axis=0)).astype(int) + pad
        layer = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.float32)
        draw(layer, lo)
        _blend_patch(scan, layer, colour, int(lo[0]), int(lo[1]))

    n_scratches = int(rng.integers(2, 7))
    for _ in range(n_scratches):
        x0, y0, x1, y1 = areas[int(rng.integers(len(areas)))] if areas else (0, 0, w, h)
        start = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        # Print scratches run mostly up-down (handling, sliding in and out of boxes).
        angle = rng.normal(math.pi / 2, 0.35) if rng.random() < 0.7 else rng.uniform(0, math.pi)
        end = start + rng.uniform(40, 380) * np.array([math.cos(angle), math.sin(angle)])
        end = np.clip(end, (x0, y0), (x1 - 1, y1 - 1))  # a print's scratch stays on the print
        level = float(rng.uniform(0.35, 0.85))
        colour = bright if rng.random() < 0.6 else dark
        mark(
            lambda layer, lo, a=start, b=end, v=level: cv2.line(
                layer, tuple(int(t) for t in a - lo), tuple(int(t) for t in b - lo), v, 1, cv2.LINE_AA
            ),
            np.stack([start, end]),
            2,
            colour,
        )
    n_dust = int(rng.integers(15, 45))
    for _ in range(n_dust):
        x0, y0, x1, y1 = areas[int(rng.integers(len(areas)))] if areas and rng.random() < 0.8 else (0, 0, w, h)
        centre = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        radius, level = int(rng.integers(1, 4)), float(rng.uniform(0.4, 0.95))
        colour = bright if rng.random() < 0.5 else dark
        mark(
            lambda layer, lo, c=centre, r=radius, v=level: cv2.circle(
                layer, tuple(int(t) for t in c - lo), r, v, -1, cv2.LINE_AA
            ),
            centre[None, :],
            radius + 2,
            colour,
        )
    return {"scratches": n_scratches, "dust_specks": n_dust}


def _to_uint8(scan: np.ndarray) -> np.ndarray:
    return cv2.convertScaleAbs(scan)  # rounds and saturates; every value is >= 0 here


_INK = np.array([(38, 30, 26), (60, 38, 28), (30, 34, 40)], np.float32)


def _print_mount_text(
    rng: np.random.Generator, scan: np.ndarray, layout: _Layout, publisher: tuple, caption: str, copyright_line: str
) -> None:
    """Caption strip under the prints and vertical imprints on the side margins."""
    ink = np.zeros(scan.shape[:2], np.uint8)
    cx0, cy0, cx1, cy1 = layout.card_box
    serif = cv2.FONT_HERSHEY_COMPLEX if rng.random() < 0.6 else cv2.FONT_HERSHEY_TRIPLEX
    strip_top = layout.left_box[3]
    strip_h = cy1 - strip_top
    mid = (cx0 + cx1) // 2
    _text_centred(ink, caption, mid, strip_top + int(strip_h * 0.36), serif, 0.95, 2, max_width=cx1 - cx0 - 260)
    _text_centred(ink, copyright_line, mid, strip_top + int(strip_h * 0.68), cv2.FONT_HERSHEY_COMPLEX_SMALL, 0.85, 1)
    # Side imprints: the left reads bottom-to-top, the right top-to-bottom (as on real cards).
    side_w = layout.left_box[0] - cx0
    for lines, rotate, centre_x in (
        (publisher[2], 1, cx0 + side_w // 2),
        (publisher[3], 3, cx1 - side_w // 2),
    ):
        patches = [
            _text_block(line, cv2.FONT_HERSHEY_COMPLEX, 0.78 if i == 0 else 0.62, 2 if i == 0 else 1)
            for i, line in enumerate(lines)
        ]
        width = max(p.shape[1] for p in patches)
        block = np.zeros((sum(p.shape[0] for p in patches) + 6, width), np.uint8)
        y = 0
        for p in patches:
            x = (width - p.shape[1]) // 2
            block[y : y + p.shape[0], x : x + p.shape[1]] = p
            y += p.shape[0] + 6
        limit = layout.photo_h - 40
        if block.shape[1] > limit:
            block = cv2.resize(block, (limit, max(1, block.shape[0] * limit // block.shape[1])), interpolation=cv2.INTER_AREA)
        block = np.rot90(block, rotate)
        top = layout.left_box[1] + (layout.photo_h - block.shape[0]) // 2
        _stamp(ink, np.ascontiguousarray(block), centre_x - block.shape[1] // 2, top)
    zones = [
        (cx0, layout.left_box[1], layout.left_box[0], layout.left_box[3]),
        (layout.right_box[2], layout.right_box[1], cx1, layout.right_box[3]),
        (cx0, strip_top, cx1, cy1),
    ]
    _apply_ink(rng, scan, ink, _INK[int(rng.integers(len(_INK)))], float(rng.uniform(0.75, 0.92)), zones)


def _catalogue_number(rng: np.random.Generator) -> int:
    return int(rng.integers(1000, 30000))


def make_stereo_card(seed: int, index: int, name: str | None = None) -> DemoCard:
    """One realistic stereo card from the Motorcycle pair; stream ``(seed, index)`` fixes every choice."""
    rng = np.random.default_rng([seed, index])
    left_src, right_src = _motorcycle()
    src_h, src_w = left_src.shape
    layout = _layout(rng)
    pw, ph = layout.photo_w, layout.photo_h

    # Same window on both views: the prints stay a true (rectified) stereo pair before misalignment.
    margin = 16  # room for the right print's rotation and shift without running off the source
    win_h = float(rng.uniform(250, src_h - 2 * margin))
    win_w = win_h * pw / ph
    wx0 = float(rng.uniform(margin, src_w - margin - win_w))
    wy0 = float(rng.uniform(margin, src_h - margin - win_h))
    scale = pw / win_w
    angle = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 1.0))
    dy = float(rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 4.0))
    angle, dy = round(angle, 3), round(dy, 2)
    left_affine = _window_affine(wx0, wy0, scale)
    right_affine = _misalign(left_affine, pw, ph, angle, dy)

    tone = _tone(rng)
    left_print = _age_print(rng, _render_source(left_src, left_affine, pw, ph), tone)
    right_print = _age_print(rng, _render_source(right_src, right_affine, pw, ph), tone)
    alpha, style, radius = _photo_mask(rng, pw, ph)

    scan = _mount(rng, layout)
    _paste(scan, left_print, alpha, layout.left_box)
    _paste(scan, right_print, alpha, layout.right_box)

    # Consecutive cards of one collection get different titles.
    first_title = int(np.random.default_rng(seed).integers(len(_MOTORCYCLE_TITLES)))
    title, place, subjects = _MOTORCYCLE_TITLES[(first_title + index) % len(_MOTORCYCLE_TITLES)]
    publisher = _PUBLISHERS[int(rng.choice(len(_PUBLISHERS), p=[0.6, 0.25, 0.15]))]
    year = int(rng.integers(1903, 1926))
    number = _catalogue_number(rng)
    caption = f"{number}-{title}."
    copyright_line = f"Copyright {year} by {publisher[0].rstrip('.')}."
    _print_mount_text(rng, scan, layout, publisher, caption, copyright_line)
    damage = _damage(rng, scan, [layout.left_box, layout.right_box])
    image = _to_uint8(scan)

    def shifted(affine: np.ndarray, box: tuple[int, int, int, int]) -> list[list[float]]:
        out = affine.copy()
        out[:, 2] += box[:2]
        return out.round(6).tolist()

    truth = {
        "source": "skimage.data.stereo_motorcycle",
        "crop_window": [round(wx0, 3), round(wy0, 3), round(wx0 + win_w, 3), round(wy0 + win_h, 3)],
        "scale": round(scale, 6),
        "right_rotation_deg": angle,
        "right_vertical_offset_px": dy,
        # Source view pixels -> scan pixels (2x3), for ground-truth disparity in scan coordinates.
        "left_affine": shifted(left_affine, layout.left_box),
        "right_affine": shifted(right_affine, layout.right_box),
        "left_box": list(layout.left_box),
        "right_box": list(layout.right_box),
        "photo_boxes": [list(layout.left_box), list(layout.right_box)],
        "card_box": list(layout.card_box),
        "gutter_px": layout.gutter,
        "photo_shape": style,
        "corner_radius_px": radius,
        "caption": caption,
        "upside_down": False,
        "inverted": False,
        "halves_swapped": False,
        **damage,
    }
    metadata = _record(title, year, rng, publisher[0], place, subjects)
    return DemoCard(
        name=name or f"demo_stereo_{index:04d}",
        image=image,
        kind="stereo",
        expected_filter=("pass",),
        truth=truth,
        metadata=metadata,
    )


def _record(title: str, year: int, rng: np.random.Generator, publisher: str, place: str, subjects: tuple) -> dict:
    date = str(year) if rng.random() < 0.7 else f"ca. {year}"
    return {
        "title": title,
        "date": date,
        "creator": _CREATORS[int(rng.integers(len(_CREATORS)))],
        "publisher": publisher,
        "place": place,
        "subjects": tuple(subjects),
    }


def _fit_window(rng: np.random.Generator, shape: tuple[int, int], aspect: float) -> tuple[float, float, float]:
    """A random window of width/height ``aspect`` covering most of an image: (x0, y0, scale-free width)."""
    h, w = shape
    win_w = min(w, h * aspect) * float(rng.uniform(0.82, 1.0))
    win_h = win_w / aspect
    return float(rng.uniform(0, w - win_w)), float(rng.uniform(0, h - win_h)), win_w


def _make_mono(seed: int, variant: int, name: str) -> DemoCard:
    """Not a stereo pair: one wide photo across the card (variant 0) or two unrelated photos (1)."""
    rng = np.random.default_rng([seed, _MONO_STREAM + variant])
    layout = _layout(rng)
    pw, ph = layout.photo_w, layout.photo_h
    tone = _tone(rng)
    scan = _mount(rng, layout)
    if variant == 0:
        source_name = sorted(_WIDE_SOURCES)[int(rng.integers(len(_WIDE_SOURCES)))]
        source = _single_photo(source_name)
        wide_w = 2 * pw + layout.gutter
        x0, y0, win_w = _fit_window(rng, source.shape, wide_w / ph)
        affine = _window_affine(x0, y0, wide_w / win_w)
        alpha, style, radius = _photo_mask(rng, wide_w, ph)
        box = (layout.left_box[0], layout.left_box[1], layout.right_box[2], layout.right_box[3])
        _paste(scan, _age_print(rng, _render_source(source, affine, wide_w, ph), tone), alpha, box)
        boxes, sources = [list(box)], [source_name]
        title, subjects = _WIDE_SOURCES[source_name]
    else:
        sources = [str(n) for n in rng.choice(sorted(_SINGLE_SOURCES), size=2, replace=False)]
        alpha, style, radius = _photo_mask(rng, pw, ph)
        for source_name, box in zip(sources, (layout.left_box, layout.right_box)):
            source = _single_photo(source_name)
            x0, y0, win_w = _fit_window(rng, source.shape, pw / ph)
            affine = _window_affine(x0, y0, pw / win_w)
            _paste(scan, _age_print(rng, _render_source(source, affine, pw, ph), tone), alpha, box)
        boxes = [list(layout.left_box), list(layout.right_box)]
        (first, first_subjects), (second, second_subjects) = (_SINGLE_SOURCES[n] for n in sources)
        title, subjects = f"{first}; {second.lower()}", first_subjects + second_subjects
    publisher = _PUBLISHERS[int(rng.integers(len(_PUBLISHERS)))]
    year = int(rng.integers(1900, 1926))
    caption = f"{_catalogue_number(rng)}-{title}."
    _print_mount_text(rng, scan, layout, publisher, caption, f"Copyright {year} by {publisher[0].rstrip('.')}.")
    damage = _damage(rng, scan, [tuple(b) for b in boxes])
    truth = {
        "sources": sources,
        "photo_boxes": boxes,
        "left_box": None,
        "right_box": None,
        "card_box": list(layout.card_box),
        "photo_shape": style,
        "corner_radius_px": radius,
        "caption": caption,
        "upside_down": False,
        "inverted": False,
        "halves_swapped": False,
        **damage,
    }
    metadata = _record(title, year, rng, publisher[0], "North and Central America, United States", subjects)
    return DemoCard(
        name=name, image=_to_uint8(scan), kind="mono", expected_filter=("culled", "review"), truth=truth, metadata=metadata
    )


def _make_back(seed: int, name: str) -> DemoCard:
    """A card back: cardboard, descriptive paragraphs, a publisher's seal, a pencilled number."""
    rng = np.random.default_rng([seed, _BACK_STREAM])
    layout = _layout(rng)
    scan = _mount(rng, layout, colour=_MOUNT_COLOURS[int(rng.integers(2))])  # backs: buff or cream
    cx0, cy0, cx1, cy1 = layout.card_box
    ink = np.zeros(scan.shape[:2], np.uint8)
    publisher = _PUBLISHERS[int(rng.integers(len(_PUBLISHERS)))]
    title, place, subjects = _MOTORCYCLE_TITLES[int(rng.integers(len(_MOTORCYCLE_TITLES)))]
    year = int(rng.integers(1903, 1926))

    # Two text columns either side of a central seal.
    column_w = (cx1 - cx0) // 2 - 230
    font, scale = cv2.FONT_HERSHEY_COMPLEX_SMALL, 0.9
    char_w = cv2.getTextSize("abcdefghijklmnopqrstuvwxyz", font, scale, 1)[0][0] / 26
    chars_per_line = max(20, int(column_w / char_w))
    sentences = list(rng.permutation(_BACK_SENTENCES))
    for column, x in enumerate((cx0 + 70, (cx0 + cx1) // 2 + 160)):
        y = cy0 + 90
        heading = title.upper() if column == 0 else "THE MOTOR CYCLE"
        _stamp(ink, _text_block(heading, cv2.FONT_HERSHEY_TRIPLEX, 0.75, 1), x, y - 40)
        paragraph = " ".join(str(s) for s in sentences[column * 5 : (column + 1) * 5])
        for line in textwrap.wrap(paragraph, chars_per_line):
            patch = _text_block(line, font, scale, 1)
            _stamp(ink, patch, x, y)
            y += patch.shape[0] + 6
    # The seal: double ring, a keystone, the publisher's name.
    centre = ((cx0 + cx1) // 2, cy0 + int((cy1 - cy0) * 0.45))
    cv2.circle(ink, centre, 118, 255, 3, cv2.LINE_AA)
    cv2.circle(ink, centre, 104, 255, 1, cv2.LINE_AA)
    keystone = np.array([[-46, -58], [46, -58], [30, 52], [-30, 52]], np.int32) + np.array(centre, np.int32)
    cv2.polylines(ink, [keystone], True, 255, 3, cv2.LINE_AA)
    _text_centred(ink, publisher[1].split()[0][:1], centre[0], centre[1] - 4, cv2.FONT_HERSHEY_TRIPLEX, 2.2, 3)
    _text_centred(ink, "TRADE MARK", centre[0], centre[1] + 80, cv2.FONT_HERSHEY_COMPLEX_SMALL, 0.7, 1)
    _text_centred(ink, publisher[1], centre[0], centre[1] - 150, cv2.FONT_HERSHEY_TRIPLEX, 0.9, 1)
    _text_centred(ink, f"Copyright {year}", centre[0], centre[1] + 150, cv2.FONT_HERSHEY_COMPLEX_SMALL, 0.8, 1)
    _apply_ink(rng, scan, ink, _INK[int(rng.integers(len(_INK)))], float(rng.uniform(0.7, 0.9)))
    # A curator's pencilled inventory number, grey and script-like.
    pencil = np.zeros(scan.shape[:2], np.uint8)
    number = f"KV{int(rng.integers(100, 999))}-{int(rng.integers(1000, 9999))}"
    _stamp(pencil, _text_block(number, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX, 1.1, 1), cx0 + 120, cy1 - 70)
    _apply_ink(rng, scan, pencil, np.array([95, 95, 100], np.float32), 0.55)
    damage = _damage(rng, scan, [])
    truth = {
        "photo_boxes": [],
        "left_box": None,
        "right_box": None,
        "card_box": list(layout.card_box),
        "upside_down": False,
        "inverted": False,
        "halves_swapped": False,
        **damage,
    }
    metadata = _record(f"{title} (card verso)", year, rng, publisher[0], place, subjects)
    return DemoCard(
        name=name, image=_to_uint8(scan), kind="back", expected_filter=("culled", "review"), truth=truth, metadata=metadata
    )


def _rotate_box_180(box: list[int], width: int, height: int) -> list[int]:
    x0, y0, x1, y1 = box
    return [width - x1, height - y1, width - x0, height - y0]


def _make_upside_down(seed: int, name: str) -> DemoCard:
    base = make_stereo_card(seed, _UPSIDE_DOWN_BASE)
    h, w = base.image.shape[:2]
    truth = dict(base.truth)
    for key in ("left_box", "right_box", "card_box"):
        truth[key] = _rotate_box_180(base.truth[key], w, h)
    # The left-eye print now lies on the right of the scan: the halves are swapped.
    truth["photo_boxes"] = [truth["right_box"], truth["left_box"]]
    truth.update(upside_down=True, halves_swapped=True, rotation_deg=180, derived_from={"seed": seed, "index": _UPSIDE_DOWN_BASE})
    for key in ("left_affine", "right_affine"):
        # Rotation by 180 deg: x' = (w - 1) - x, y' = (h - 1) - y.
        rotated = -np.array(base.truth[key])
        rotated[:, 2] += (w - 1, h - 1)
        truth[key] = rotated.round(6).tolist()
    image = np.ascontiguousarray(base.image[::-1, ::-1])
    return DemoCard(name=name, image=image, kind="upside_down", expected_filter=("pass",), truth=truth, metadata=base.metadata)


def _make_inverted(seed: int, name: str) -> DemoCard:
    base = make_stereo_card(seed, _INVERTED_BASE)
    truth = {**base.truth, "inverted": True, "derived_from": {"seed": seed, "index": _INVERTED_BASE}}
    return DemoCard(
        name=name, image=255 - base.image, kind="inverted", expected_filter=("pass",), truth=truth, metadata=base.metadata
    )


def make_demo_cards(seed: int = 0, n_stereo: int = 6) -> list[DemoCard]:
    """The demo collection: ``n_stereo`` stereo cards, then two mono cards, a back, an upside-down
    and an inverted card. Same ``seed`` -> byte-identical images. Accessions ``DEMO.0001``...
    """
    if n_stereo < 0:
        raise ValueError(f"Expected n_stereo >= 0, got {n_stereo}")
    cards = [make_stereo_card(seed, i, name=f"demo_motorcycle_{i + 1:02d}") for i in range(n_stereo)]
    cards += [
        _make_mono(seed, 0, "demo_mono_01"),
        _make_mono(seed, 1, "demo_mono_02"),
        _make_back(seed, "demo_back_01"),
        _make_upside_down(seed, "demo_upside_down_01"),
        _make_inverted(seed, "demo_inverted_01"),
    ]
    out = []
    for number, card in enumerate(cards, start=1):
        metadata = {"accession": f"DEMO.{number:04d}", **card.metadata}
        out.append(
            DemoCard(
                name=card.name,
                image=card.image,
                kind=card.kind,
                expected_filter=card.expected_filter,
                truth=card.truth,
                metadata=metadata,
            )
        )
    return out


def write_demo_cards(cards: list[DemoCard], folder: Path) -> list[Path]:
    """Write ``<name>.jpg`` (quality 90) per card and ``metadata.csv``; returns the paths written.

    Subjects are joined with newlines inside one cell, as in eMuseum exports.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for card in cards:
        path = folder / f"{card.name}.jpg"
        write_jpeg(path, card.image, quality=90)
        paths.append(path)
    csv_path = folder / "metadata.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(METADATA_COLUMNS)
        for card in cards:
            meta = card.metadata
            writer.writerow(
                [
                    f"{card.name}.jpg",
                    *(str(meta.get(c, "")) for c in METADATA_COLUMNS[1:-1]),
                    SUBJECT_SEPARATOR.join(meta.get("subjects", ())),
                ]
            )
    paths.append(csv_path)
    return paths


# ------------------------------------------------------------------ cards from any stereo scene


@dataclass(frozen=True)
class Degradation:
    """How a card made by :func:`make_card_from_pair` is spoiled (all off by default).

    ``fade`` 0..1: the prints' tonal range shrinks (1 = a quarter of it left) and lifts to a pale
    grey; ``scratches``: extra rounds of damage on each print (each 2-6 scratches and 15-45 specks,
    independent per print); ``blur_px``:
    extra Gaussian blur (sigma, print px) of both prints; ``jpeg_quality``: the scan is saved at
    this JPEG quality (``None`` = 92); ``dy_px``: right print moved down (print px);
    ``rotation_deg``: right print turned (OpenCV sign) about its centre; ``low_texture`` 0..1: the
    source's fine texture blended away (1 = only structure over ~8 source px is left);
    ``swap``: the right eye's print is mounted on the left and vice versa.
    """

    fade: float = 0.0
    scratches: int = 0
    blur_px: float = 0.0
    jpeg_quality: int | None = None
    dy_px: float = 0.0
    rotation_deg: float = 0.0
    low_texture: float = 0.0
    swap: bool = False


def _luminance(view: np.ndarray) -> np.ndarray:
    grey = view if view.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(view[..., :3]), cv2.COLOR_RGB2GRAY)
    return grey.astype(np.float32)


def _flatten_texture(grey: np.ndarray, amount: float) -> np.ndarray:
    if amount <= 0:
        return grey
    smooth = cv2.bilateralFilter(grey, 9, 40, 8)  # keeps object outlines, loses surface texture
    smooth = cv2.GaussianBlur(smooth, (0, 0), 3.0)
    return (1.0 - amount) * grey + amount * smooth


def make_card_from_pair(
    left: np.ndarray, right: np.ndarray, seed: int, degradation: Degradation = Degradation(), name: str = "scene_card"
) -> DemoCard:
    """An antique card made from any rectified stereo pair (``left``/``right``: uint8 RGB or grey,
    the same shape, e.g. a Middlebury scene), spoiled by ``degradation``.

    The prints show the same window of both views (the largest of the print's aspect that leaves
    16 source px for the right print's rotation and shift), so a ground-truth disparity ``d`` of
    the left view maps to the scan as: left-eye point ``left_affine @ (x, y, 1)``, right-eye point
    ``right_affine @ (x - d, y, 1)``. ``truth["left_box"]``/``["right_box"]`` are the left-eye and
    right-eye prints' boxes wherever they are mounted (exchanged on the card when ``swap``,
    flagged ``halves_swapped``). Deterministic in ``seed``.
    """
    if left.shape[:2] != right.shape[:2]:
        raise ValueError(f"left {left.shape[:2]} and right {right.shape[:2]} differ in size")
    rng = np.random.default_rng([seed, 5000])
    left_src = _flatten_texture(_luminance(left), degradation.low_texture)
    right_src = _flatten_texture(_luminance(right), degradation.low_texture)
    src_h, src_w = left_src.shape
    layout = _layout(rng)
    pw, ph = layout.photo_w, layout.photo_h
    margin = min(16, src_w // 20, src_h // 20)
    win_h = float(src_h - 2 * margin)
    win_w = win_h * pw / ph
    if win_w > src_w - 2 * margin:
        win_w = float(src_w - 2 * margin)
        win_h = win_w * ph / pw
    wx0, wy0 = (src_w - win_w) / 2, (src_h - win_h) / 2
    scale = pw / win_w
    left_affine = _window_affine(wx0, wy0, scale)
    right_affine = _misalign(left_affine, pw, ph, degradation.rotation_deg, degradation.dy_px)

    tone = _tone(rng)
    if degradation.fade > 0:
        keep = 1.0 - 0.75 * min(1.0, degradation.fade)
        centre = 0.62 + 0.1 * degradation.fade  # faded prints go pale
        tone = _Tone(
            blur=tone.blur,
            low=centre - keep * (centre - tone.low),
            high=centre + keep * (tone.high - centre),
            gamma=tone.gamma,
            vignette=tone.vignette,
            grain=tone.grain,
            lut=tone.lut,
        )
    if degradation.blur_px > 0:
        tone = _Tone(
            blur=float(np.hypot(tone.blur, degradation.blur_px)),
            low=tone.low,
            high=tone.high,
            gamma=tone.gamma,
            vignette=tone.vignette,
            grain=tone.grain,
            lut=tone.lut,
        )
    left_print = _age_print(rng, _render_source(left_src, left_affine, pw, ph), tone)
    right_print = _age_print(rng, _render_source(right_src, right_affine, pw, ph), tone)
    alpha, style, radius = _photo_mask(rng, pw, ph)

    scan = _mount(rng, layout)
    left_eye_box, right_eye_box = (layout.right_box, layout.left_box) if degradation.swap else (layout.left_box, layout.right_box)
    _paste(scan, left_print, alpha, left_eye_box)
    _paste(scan, right_print, alpha, right_eye_box)
    _print_mount_text(rng, scan, layout, _PUBLISHERS[0], "1234-A scene with known depth.", "Copyright 1905.")
    damage = _damage(rng, scan, [layout.left_box, layout.right_box])
    extra = 0
    for box in (layout.left_box, layout.right_box):  # independent damage on each print
        for rounds in range(degradation.scratches):
            extra += _damage(np.random.default_rng([seed, 5001 + rounds, box[0]]), scan, [box])["scratches"]
    image = _to_uint8(scan)

    def placed(affine: np.ndarray, box: tuple[int, int, int, int]) -> list[list[float]]:
        out = affine.copy()
        out[:, 2] += box[:2]
        return out.round(6).tolist()

    truth = {
        "source": name,
        "crop_window": [round(wx0, 3), round(wy0, 3), round(wx0 + win_w, 3), round(wy0 + win_h, 3)],
        "scale": round(scale, 6),
        "right_rotation_deg": degradation.rotation_deg,
        "right_vertical_offset_px": degradation.dy_px,
        "left_affine": placed(left_affine, left_eye_box),
        "right_affine": placed(right_affine, right_eye_box),
        "left_box": list(left_eye_box),
        "right_box": list(right_eye_box),
        "photo_boxes": [list(layout.left_box), list(layout.right_box)],
        "card_box": list(layout.card_box),
        "gutter_px": layout.gutter,
        "photo_shape": style,
        "corner_radius_px": radius,
        "upside_down": False,
        "inverted": False,
        "halves_swapped": bool(degradation.swap),
        "degradation": {k: v for k, v in degradation.__dict__.items()},
        "extra_scratches": extra,
        **damage,
    }
    return DemoCard(name=name, image=image, kind="stereo", expected_filter=("pass",), truth=truth, metadata={})

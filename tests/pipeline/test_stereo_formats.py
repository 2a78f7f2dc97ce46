"""Stereo viewing formats: the Dubois anaglyph, the synthesised wiggle, side-by-side, JPS and MPO.

The pair is Middlebury 2014 Motorcycle (shipped with scikit-image) with its ground-truth left
disparity (x_right = x_left - d, +inf unknown), so the in-between views can be checked against
an independent warp of the *right* view.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image


@pytest.fixture(scope="module")
def motorcycle() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from skimage import data

    left, right, disparity = data.stereo_motorcycle()
    small = (370, 250)  # half size: keeps the test fast; disparities scale with the width
    scale = small[0] / left.shape[1]
    import cv2

    left, right = (cv2.resize(view, small, interpolation=cv2.INTER_AREA) for view in (left, right))
    disparity = np.where(np.isfinite(disparity), disparity, np.nan).astype(np.float32)
    disparity = cv2.resize(disparity, small, interpolation=cv2.INTER_NEAREST) * np.float32(scale)
    return left, right, disparity


def _srgb_decode(value: float) -> float:
    value /= 255.0
    return value / 12.92 if value <= 0.04045 else ((value + 0.055) / 1.055) ** 2.4


def _srgb_encode(value: float) -> int:
    value = min(max(value, 0.0), 1.0)
    return round(255 * (value * 12.92 if value <= 0.0031308 else 1.055 * value ** (1 / 2.4) - 0.055))


def test_anaglyph_matches_the_dubois_red_cyan_matrices_on_known_pixels() -> None:
    from pipeline.stereo_formats import dubois_anaglyph

    # Published red-cyan least-squares matrices (Dubois 2009), typed here from the source again.
    left_matrix = [[0.437, 0.449, 0.164], [-0.062, -0.062, -0.024], [-0.048, -0.050, -0.017]]
    right_matrix = [[-0.011, -0.032, -0.007], [0.377, 0.761, 0.009], [-0.026, -0.093, 1.234]]
    pixels = [
        ((255, 255, 255), (0, 0, 0)),
        ((0, 0, 0), (255, 255, 255)),
        ((128, 128, 128), (128, 128, 128)),
        ((200, 100, 50), (30, 180, 220)),
        ((12, 250, 90), (240, 10, 160)),
    ]
    left = np.array([[p[0] for p in pixels]], np.uint8)
    right = np.array([[p[1] for p in pixels]], np.uint8)
    got = dubois_anaglyph(left, right)[0]
    for index, (lp, rp) in enumerate(pixels):
        lin_l, lin_r = [_srgb_decode(v) for v in lp], [_srgb_decode(v) for v in rp]
        expected = [
            _srgb_encode(sum(left_matrix[c][k] * lin_l[k] + right_matrix[c][k] * lin_r[k] for k in range(3))) for c in range(3)
        ]
        assert np.abs(got[index].astype(int) - expected).max() <= 1, (index, got[index], expected)
    # The left eye's white shows only through the red filter, the right eye's through the cyan one.
    assert got[0].tolist() == [255, 0, 0]
    assert got[1].tolist() == [0, 255, 255]


def test_anaglyph_refuses_views_of_different_sizes() -> None:
    from pipeline.stereo_formats import StereoFormatError, dubois_anaglyph

    with pytest.raises(StereoFormatError, match="one size"):
        dubois_anaglyph(np.zeros((4, 5, 3), np.uint8), np.zeros((4, 6, 3), np.uint8))


def test_wiggle_sweeps_from_left_to_right_and_back() -> None:
    from pipeline.stereo_formats import wiggle_fractions

    fractions = wiggle_fractions(7)
    assert len(fractions) == 12
    assert fractions[0] == 0.0 and fractions[6] == 1.0 and fractions[3] == pytest.approx(0.5)
    assert fractions[1:7] == sorted(fractions[1:7]) and fractions[7:] == fractions[5:0:-1]
    steps = np.diff(fractions[:7])
    assert steps[0] < steps[3] and steps[-1] < steps[3]  # eased: slow at the ends, fast in the middle


def test_middle_wiggle_frame_lies_between_the_views(motorcycle) -> None:
    import cv2

    from pipeline.stereo_formats import make_pair, wiggle_frames

    left, right, disparity = motorcycle
    frames = wiggle_frames(make_pair(left, right, disparity))
    assert len(frames) == 12 and frames[0].shape == left.shape
    middle = frames[3].astype(np.float32)  # t = 0.5
    # Independent reference: the right view moved half way back, I_right(x - d/2).
    height, width = disparity.shape
    known = np.isfinite(disparity)
    xs = np.arange(width, dtype=np.float32)[None, :] - 0.5 * np.nan_to_num(disparity)
    ys = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    reference = cv2.remap(right, xs.astype(np.float32), ys, cv2.INTER_LINEAR).astype(np.float32)
    inside = known & (xs > 0) & (xs < width - 1)
    inside[:, : int(np.nanmax(disparity)) + 2] = False  # the left border has no match in the right view

    def error(image: np.ndarray) -> float:
        return float(np.abs(middle - image.astype(np.float32))[inside].mean())

    to_reference, to_left, to_right = error(reference), error(left), error(right)
    assert to_reference < 0.75 * min(to_left, to_right), (to_reference, to_left, to_right)
    # The ends are the views themselves: t = 0 is the left view, t = 1 close to the right one.
    assert np.array_equal(frames[0], left)
    assert float(np.abs(frames[6].astype(np.float32) - right)[inside].mean()) < error(right)


def test_wiggle_needs_some_disparity() -> None:
    from pipeline.stereo_formats import StereoFormatError, make_pair, wiggle_frames

    view = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(StereoFormatError, match="no known value"):
        wiggle_frames(make_pair(view, view, np.full((8, 8), np.nan, np.float32)))


def _mean_difference(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float32) - b.astype(np.float32)).mean())


def test_encoded_files_keep_eye_order_sizes_and_the_cards_facts(motorcycle) -> None:
    from pipeline.stereo_files import STEREO_FORMATS, CardCaption, StereoCosts, encode_stereo

    left, right, disparity = motorcycle
    height, width = left.shape[:2]
    caption = CardCaption.of(
        {"title": "Palais des Beaux-Arts, Exposition é", "date": "1893", "creator": "B. W. Kilburn"},
        "1996.0009.17827",
        "scan.jpg",
    )
    costs = StereoCosts()
    files = encode_stereo(left, right, disparity, caption, costs=costs)
    assert set(files) == set(STEREO_FORMATS) and costs.cards == 1

    # MPO: two frames, left first, both the views' size.
    with Image.open(io.BytesIO(files["mpo"])) as mpo:
        assert mpo.format == "MPO" and mpo.n_frames == 2
        entries = mpo.mpinfo[0xB002]  # CIPA DC-007 MP index: a stereo pair, the left frame representative
        assert [e["Attribute"]["MPType"] for e in entries] == ["Multi-Frame Image: (Disparity)"] * 2
        assert [e["Attribute"]["RepresentativeImageFlag"] for e in entries] == [True, False]
        first = np.asarray(mpo.convert("RGB"))
        description = mpo.getexif().get(0x010E)
        xmp = mpo.info.get("xmp", b"")
        mpo.seek(1)
        second = np.asarray(mpo.convert("RGB"))
    assert first.shape == second.shape == left.shape
    assert _mean_difference(first, left) < 0.3 * _mean_difference(first, right)
    assert _mean_difference(second, right) < 0.3 * _mean_difference(second, left)
    assert description == "Palais des Beaux-Arts, Exposition e; 1893; accession 1996.0009.17827"
    assert "Exposition é".encode() in xmp and b"1996.0009.17827" in xmp and b"publicdomain/mark" in xmp

    # JPS: cross-eyed, right view on the left half, full width.
    with Image.open(io.BytesIO(files["jps"])) as jps:
        jps_pixels = np.asarray(jps.convert("RGB"))
        assert jps.getexif().get(0x8298, "").startswith("Public Domain Mark")
        assert jps.getexif().get(0x013B) == "B. W. Kilburn"
    assert jps_pixels.shape == (height, 2 * width, 3)
    on_left = jps_pixels[:, :width]
    assert _mean_difference(on_left, right) < 0.3 * _mean_difference(on_left, left)

    # Side by side: parallel, full and half width.
    with Image.open(io.BytesIO(files["sbs_full"])) as full:
        full_pixels = np.asarray(full.convert("RGB"))
    assert full_pixels.shape == (height, 2 * width, 3)
    assert _mean_difference(full_pixels[:, :width], left) < 0.3 * _mean_difference(full_pixels[:, :width], right)
    with Image.open(io.BytesIO(files["sbs_half"])) as half:
        assert half.size == (2 * (width // 2), height)

    # Wiggles: 12 frames each; the GIF's comment names the card.
    for name, fmt in (("wiggle_gif", "GIF"), ("wiggle_webp", "WEBP")):
        with Image.open(io.BytesIO(files[name])) as wiggle:
            assert wiggle.format == fmt and wiggle.n_frames == 12
            if fmt == "GIF":
                assert b"1996.0009.17827" in wiggle.info["comment"]
            else:
                assert wiggle.getexif().get(0x010E).endswith("accession 1996.0009.17827")
    with Image.open(io.BytesIO(files["anaglyph"])) as anaglyph:
        assert anaglyph.size == (width, height)


def test_eye_order_check_flips_with_the_halves(motorcycle) -> None:
    from pipeline.stereo_formats import eye_order_evidence

    left, right, _ = motorcycle
    parallel, crossed = eye_order_evidence(left, right), eye_order_evidence(right, left)
    assert parallel.suggests == "parallel" and crossed.suggests == "cross"
    assert parallel.slope == pytest.approx(-crossed.slope, rel=0.2)
    assert len(parallel.shifts) == 8


def test_eye_order_check_on_the_real_jps_files_says_they_are_stored_parallel(shared_data) -> None:
    """PROVENANCE.md: the three JPS files hold the left eye's view on the left, against the JPS convention."""
    from pipeline.io import read_image
    from pipeline.stereo_formats import eye_order_evidence, split_side_by_side

    for name in ("8618s.jps", "Daibutsu.jps", "sports.jps"):
        image = read_image(shared_data / "stereocards/cropped_pairs/jps" / name)
        as_parallel = eye_order_evidence(*split_side_by_side(image, "parallel"))
        as_cross = eye_order_evidence(*split_side_by_side(image, "cross"))
        assert as_parallel.suggests == "parallel" and as_cross.suggests == "cross", (name, as_parallel.slope)


def test_stereo_files_are_byte_reproducible(motorcycle) -> None:
    """A release must be byte-identical when written again from the same inputs."""
    from pipeline.stereo_files import CardCaption, encode_stereo

    left, right, disparity = motorcycle
    caption = CardCaption.of({"title": "Motorcycle"}, None, "scan.png")
    first = encode_stereo(left, right, disparity, caption)
    second = encode_stereo(left.copy(), right.copy(), disparity.copy(), caption)
    assert {name: len(data) for name, data in first.items()} == {name: len(data) for name, data in second.items()}
    assert first == second

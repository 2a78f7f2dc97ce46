"""Decoding originals: every format we ingest, 16-bit scans, and typed errors for bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.errors import ImageReadError, ImageTooLargeError, InvalidInputError
from pipeline.io import probe_image, read_image, read_image_reduced, shared_decodes, to_grey, write_jpeg, write_png


def test_rgb_grey_and_16_bit(tmp_path: Path):
    rgb = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "a.png")
    assert np.array_equal(read_image(tmp_path / "a.png"), rgb)

    ramp16 = np.arange(600, dtype=np.uint16).reshape(20, 30) * 100 + 1000
    Image.fromarray(ramp16).save(tmp_path / "b.tif")
    grey = read_image(tmp_path / "b.tif")
    assert grey.dtype == np.uint8 and grey.shape == (20, 30)
    assert (grey.min(), grey.max()) == (0, 255)  # stretched over the used range, not truncated
    assert np.all(np.diff(grey.ravel().astype(int)) >= 0)

    info = probe_image(tmp_path / "b.tif")
    assert (info.width, info.height, info.format) == (30, 20, "TIFF")


def test_jps_is_a_jpeg(tmp_path: Path):
    Image.fromarray(np.full((16, 32, 3), 128, np.uint8)).save(tmp_path / "pair.jps", format="JPEG")
    assert read_image(tmp_path / "pair.jps").shape == (16, 32, 3)


@pytest.mark.parametrize(
    "content,match",
    [(b"", "empty file"), (b"hello", "not an image"), (b"\xff\xd8\xff\xe0" + b"\0" * 50, "not an image|corrupt|cannot open")],
)
def test_bad_files_raise_typed_errors(tmp_path: Path, content: bytes, match: str):
    path = tmp_path / "bad.jpg"
    path.write_bytes(content)
    with pytest.raises(ImageReadError, match=match):
        read_image(path)


def _png_with_chunk(kind: bytes, data: bytes) -> bytes:
    """A 64 x 32 PNG with one more ancillary chunk right after its header."""
    import io
    import struct
    import zlib

    buffer = io.BytesIO()
    Image.new("RGB", (64, 32)).save(buffer, "PNG")
    png = buffer.getvalue()
    chunk = struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return png[:33] + chunk + png[33:]


@pytest.mark.parametrize("kind", [b"zTXt", b"iCCP"])
def test_a_chunk_that_inflates_past_pillows_limit_is_a_typed_refusal(tmp_path: Path, kind: bytes):
    """A 2 KB PNG whose compressed text or colour profile inflates past 1 MiB: Pillow raises
    ValueError while opening it; the reader refuses the file with the reason instead."""
    import zlib

    path = tmp_path / "bomb.png"
    path.write_bytes(_png_with_chunk(kind, b"k\0\0" + zlib.compress(b"A" * (2 << 20))))
    assert path.stat().st_size < 4096
    for reader in (probe_image, read_image):
        with pytest.raises(ImageReadError, match="cannot open: ValueError: Decompressed data too large"):
            reader(path)


def test_truncated_file(tmp_path: Path):
    rng = np.random.default_rng(1)
    Image.fromarray(rng.integers(0, 256, (200, 200, 3), dtype=np.uint8)).save(tmp_path / "full.jpg")
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 3])
    with pytest.raises(ImageReadError, match="truncated"):
        probe_image(tmp_path / "cut.jpg")


def test_pixel_cap(tmp_path: Path):
    Image.fromarray(np.zeros((100, 100), np.uint8)).save(tmp_path / "x.png")
    with pytest.raises(ImageTooLargeError, match="10,000 pixels exceeds the cap of 9,999"):
        read_image(tmp_path / "x.png", max_pixels=9_999)


def test_missing_file(tmp_path: Path):
    with pytest.raises(ImageReadError, match="no such file"):
        probe_image(tmp_path / "nope.png")


def test_writers_are_atomic_and_round_trip(tmp_path: Path):
    image = np.random.default_rng(2).integers(0, 256, (40, 60, 3), dtype=np.uint8)
    write_png(tmp_path / "deep" / "x.png", image)
    assert np.array_equal(read_image(tmp_path / "deep" / "x.png"), image)
    # The fast encoder (OpenCV) writes the same pixels, in RGB order, for colour and grey.
    for pixels in (image, image[..., 1]):
        write_png(tmp_path / "fast.png", pixels, fast=True)
        with Image.open(tmp_path / "fast.png") as written:
            assert written.format == "PNG" and written.mode == ("RGB" if pixels.ndim == 3 else "L")
        assert np.array_equal(read_image(tmp_path / "fast.png"), pixels)
    write_jpeg(tmp_path / "y.jpg", image, max_side=30)
    assert read_image(tmp_path / "y.jpg").shape == (20, 30, 3)
    assert list(tmp_path.rglob("*.tmp")) == []
    assert to_grey(image).shape == (40, 60)


def test_stale_temporary_files_are_removed_and_nothing_else(tmp_path: Path):
    import os
    import time

    from pipeline.io import remove_stale_temp_files

    now = time.time()
    work = tmp_path / "derived" / "ab" / "views"
    work.mkdir(parents=True)
    stale = work / ".v0.png.k2j3.tmp"
    fresh = work / ".v1.png.x9y8.tmp"
    visible = work / "notes.tmp"  # not one of ours: atomic_write's names start with a dot
    finished = work / "v0.png"
    for path in (stale, fresh, visible, finished):
        path.write_bytes(b"x" * 1000)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / ".outside.tmp").write_bytes(b"y")
    (work / "link").symlink_to(elsewhere, target_is_directory=True)
    for path in (stale, visible, finished, elsewhere / ".outside.tmp"):
        os.utime(path, (now - 3600, now - 3600))
    os.utime(fresh, (now - 60, now - 60))

    removed = remove_stale_temp_files(tmp_path / "derived", older_than_s=600, now=now)
    assert removed == [(stale, 1000)]
    assert not stale.exists() and fresh.exists() and visible.exists() and finished.exists()
    assert (elsewhere / ".outside.tmp").exists()  # links are not followed
    assert remove_stale_temp_files(tmp_path / "missing", older_than_s=600) == []


def test_reduced_decode_picks_the_largest_jpeg_reduction_that_keeps_the_size(tmp_path: Path):
    from pipeline.io import jpeg_reduction, read_image_reduced

    ramp = np.tile(np.linspace(0, 255, 410), (203, 1)).astype(np.uint8)
    picture = np.dstack([ramp, ramp[:, ::-1], np.full_like(ramp, 90)])
    Image.fromarray(picture).save(tmp_path / "a.jpg", quality=95)
    Image.fromarray(picture).save(tmp_path / "a.png")
    assert jpeg_reduction((410, 203), (100, 1)) == 4  # ceil(410 / 4) = 103 >= 100, 52 is not
    assert jpeg_reduction((410, 203), (100, 60)) == 2  # the height decides: ceil(203 / 4) = 51 < 60
    assert jpeg_reduction((410, 203), (400, 1)) == 1

    reduced = read_image_reduced(tmp_path / "a.jpg", (100, 1))
    assert (reduced.factor, reduced.full_size, reduced.pixels.shape) == (4, (410, 203), (51, 103, 3))
    # Each decoded pixel is the mean of its 4 x 4 block of the original (up to JPEG's rounding).
    full = read_image(tmp_path / "a.jpg").astype(np.float64)
    blocks = full[:200, :408].reshape(50, 4, 102, 4, 3).mean(axis=(1, 3))
    assert np.abs(reduced.pixels[:50, :102] - blocks).mean() < 2.0
    np.testing.assert_allclose(reduced.to_full(np.array([[0.0, 0.0], [10.0, 2.0]])), [[1.5, 1.5], [41.5, 9.5]])
    # Not a JPEG, or asked for the full size: decoded as read_image does.
    for path, size in ((tmp_path / "a.png", (100, 1)), (tmp_path / "a.jpg", (410, 203))):
        same = read_image_reduced(path, size)
        assert same.factor == 1 and np.array_equal(same.pixels, read_image(path))


def _count_decodes(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    import pipeline.io

    calls: list[str] = []
    real = pipeline.io._decode

    def counted(image: Image.Image) -> None:
        calls.append(str(image.size))
        real(image)

    monkeypatch.setattr(pipeline.io, "_decode", counted)
    return calls


def test_shared_decodes_decode_a_file_once_and_give_each_reader_its_own_copy(tmp_path: Path, monkeypatch):
    rng = np.random.default_rng(3)
    scan = rng.integers(0, 256, (600, 1000, 3), np.uint8)
    Image.fromarray(scan).save(tmp_path / "scan.jpg", quality=95)
    alone = read_image_reduced(tmp_path / "scan.jpg", (400, 1))
    calls = _count_decodes(monkeypatch)
    with shared_decodes():
        first = read_image_reduced(tmp_path / "scan.jpg", (400, 1))  # 1/2: 500 px wide
        second = read_image_reduced(tmp_path / "scan.jpg", (450, 0))  # also 1/2
        # Read-only, as a decode is: no reader can change what another reads.
        assert not first.pixels.flags.writeable and not second.pixels.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            second.pixels[:] = 0
        full = read_image(tmp_path / "scan.jpg")  # another reduction: decoded
        view = rng.integers(0, 256, (300, 200, 3), np.uint8)
        write_png(tmp_path / "view.png", view, fast=True)
        back = read_image(tmp_path / "view.png")  # what was written, not decoded
        view[:] = 0  # the writer changing its array afterwards changes nothing kept
        assert not back.flags.writeable and back.any()
    assert calls == ["(500, 300)", "(1000, 600)"]
    assert second.factor == 2 and second.full_size == (1000, 600)
    assert np.array_equal(second.pixels, alone.pixels)
    assert full.shape == (600, 1000, 3) and np.array_equal(back, read_image(tmp_path / "view.png"))
    # Outside the block nothing is kept.
    read_image_reduced(tmp_path / "scan.jpg", (400, 1))
    assert len(calls) == 4


def test_a_shared_decode_is_not_served_for_a_changed_file_or_past_a_tighter_cap(tmp_path: Path, monkeypatch):
    path = tmp_path / "view.png"
    with shared_decodes(max_entries=1):
        write_png(path, np.zeros((40, 50), np.uint8))
        write_png(path, np.full((40, 50), 7, np.uint8))  # rewritten: a new file under the name
        assert int(read_image(path).max()) == 7
        with pytest.raises(ImageTooLargeError):
            read_image(path, max_pixels=1000)
        Image.fromarray(np.full((40, 60), 9, np.uint8)).save(path)  # changed in place, behind its back
        assert int(read_image(path).max()) == 9
        calls = _count_decodes(monkeypatch)
        write_png(tmp_path / "other.png", np.zeros((8, 8), np.uint8))  # the one entry is now this
        read_image(path)
        assert calls == ["(60, 40)"]
    with pytest.raises(InvalidInputError, match="max_entries"):
        with shared_decodes(max_entries=0):
            pass


def test_a_writable_decode_is_shared_as_a_copy_for_each_reader(tmp_path: Path):
    Image.fromarray(np.arange(1200, dtype=np.uint16).reshape(30, 40) * 50).save(tmp_path / "scan16.png")
    with shared_decodes():
        first = read_image(tmp_path / "scan16.png")  # 16-bit: stretched, a new writable array
        second = read_image(tmp_path / "scan16.png")
        second[:] = 0
        third = read_image(tmp_path / "scan16.png")
    assert first.flags.writeable and np.array_equal(first, third) and first.max() == 255

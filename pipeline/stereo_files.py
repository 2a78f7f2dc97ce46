"""The stereo viewing files of a rectified pair, encoded: anaglyph, wiggles, side-by-side, JPS, MPO.

Shared by the ``stereo`` release format (:mod:`exports.formats.stereo`) and the card page's
downloads (:mod:`catalogue.views`). The pixels come from :mod:`pipeline.stereo_formats`; this
module encodes them to bytes (no disk, no clock) and writes the card's title, date, accession and
licence into each file where the format has a place for them: EXIF ``ImageDescription`` /
``Artist`` / ``Copyright`` (ASCII, accents folded) plus an XMP packet in Dublin Core (UTF-8) for
JPEG, JPS, MPO and WebP; the comment extension for GIF. Encoding is deterministic (fixed
settings), so a release stays byte-reproducible.
"""

from __future__ import annotations

import io
import time
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from .stereo_formats import as_rgb, dubois_anaglyph, make_pair, side_by_side, wiggle_frames

# name -> (file name, MIME type, what it is for); the release and the downloads use these names.
STEREO_FORMATS: dict[str, tuple[str, str, str]] = {
    "anaglyph": ("anaglyph.jpg", "image/jpeg", "red-cyan anaglyph (Dubois least squares), red filter on the left eye"),
    "wiggle_gif": ("wiggle.gif", "image/gif", "animated wiggle, views synthesised from the disparity (GIF)"),
    "wiggle_webp": ("wiggle.webp", "image/webp", "animated wiggle, views synthesised from the disparity (WebP)"),
    "sbs_full": ("sbs_full.jpg", "image/jpeg", "full side-by-side, parallel (left view on the left)"),
    "sbs_half": ("sbs_half.jpg", "image/jpeg", "half side-by-side, parallel, each view squeezed to half width"),
    "jps": ("cross.jps", "image/x-jps", "JPS, cross-eyed (right view on the left half), as the format defines"),
    "mpo": ("pair.mpo", "image/mpo", "MPO (CIPA DC-007, type disparity) with the left view first, for 3D displays"),
}
JPEG_QUALITY = 92
WIGGLE_MAX_SIDE = 800  # px: GIF frames at full size of a 3000 px scan made ~10 MB files
WIGGLE_FRAME_MS = 70
DEFAULT_LICENCE = "Public Domain Mark 1.0 where applicable: https://creativecommons.org/publicdomain/mark/1.0/"


@dataclass(frozen=True)
class CardCaption:
    """What a file says about its card."""

    title: str
    date: str | None
    accession: str | None
    creator: str | None
    licence: str

    @classmethod
    def of(cls, metadata: dict[str, Any], accession: str | None, fallback_title: str) -> CardCaption:
        def text(*names: str) -> str | None:
            for name in names:
                value = metadata.get(name) or metadata.get(name.title())
                if value not in (None, ""):
                    return str(value)
            return None

        return cls(
            title=text("title") or fallback_title,
            date=text("date", "dated"),
            accession=accession,
            creator=text("creator", "photographer", "publisher", "artist"),
            licence=text("license", "licence", "rights", "credit_line") or DEFAULT_LICENCE,
        )

    @property
    def description(self) -> str:
        parts = [self.title]
        if self.date:
            parts.append(self.date)
        if self.accession:
            parts.append(f"accession {self.accession}")
        return "; ".join(parts)

    def exif(self) -> bytes:
        from PIL import Image

        exif = Image.Exif()
        exif[0x010E] = _ascii(self.description)  # ImageDescription
        if self.creator:
            exif[0x013B] = _ascii(self.creator)  # Artist
        exif[0x8298] = _ascii(self.licence)  # Copyright
        return exif.tobytes()

    def xmp(self) -> bytes:
        """A minimal XMP packet: dc:title, dc:date, dc:identifier (accession), dc:creator, dc:rights."""

        def alt(tag: str, value: str) -> str:
            return f'<dc:{tag}><rdf:Alt><rdf:li xml:lang="x-default">{escape(value)}</rdf:li></rdf:Alt></dc:{tag}>'

        body = [alt("title", self.title), alt("rights", self.licence), alt("description", self.description)]
        if self.date:
            body.append(f"<dc:date><rdf:Seq><rdf:li>{escape(self.date)}</rdf:li></rdf:Seq></dc:date>")
        if self.accession:
            body.append(f"<dc:identifier>{escape(self.accession)}</dc:identifier>")
        if self.creator:
            body.append(f"<dc:creator><rdf:Seq><rdf:li>{escape(self.creator)}</rdf:li></rdf:Seq></dc:creator>")
        return (
            '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
            '<rdf:Description rdf:about="" xmlns:dc="http://purl.org/dc/elements/1.1/">'
            + "".join(body)
            + "</rdf:Description></rdf:RDF></x:xmpmeta>"
        ).encode()

    def comment(self) -> bytes:
        return f"{self.description}. {self.licence}".encode()


def _ascii(text: str) -> str:
    """EXIF ASCII fields cannot hold accents: fold them (``é`` -> ``e``), drop what remains."""
    folded = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    return folded.replace("\0", "")


def _jpeg(image: np.ndarray, caption: CardCaption, **extra: Any) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(
        buffer, format="JPEG", quality=JPEG_QUALITY, subsampling=0, exif=caption.exif(), xmp=caption.xmp(), **extra
    )
    return buffer.getvalue()


def encode_anaglyph(left: np.ndarray, right: np.ndarray, caption: CardCaption) -> bytes:
    """JPEG at 4:4:4: chroma subsampling would smear the red and cyan fringes that carry the depth."""
    return _jpeg(dubois_anaglyph(left, right), caption)


def encode_wiggle(frames: list[np.ndarray], caption: CardCaption, fmt: str) -> bytes:
    """Animated GIF (one palette for all frames, so colours do not flicker) or WebP, looping."""
    from PIL import Image

    images = [Image.fromarray(frame) for frame in frames]
    buffer = io.BytesIO()
    if fmt == "gif":
        palette = images[0].quantize(colors=256, method=Image.Quantize.MEDIANCUT)
        paletted = [image.quantize(palette=palette, dither=Image.Dither.NONE) for image in images]
        paletted[0].save(
            buffer,
            format="GIF",
            save_all=True,
            append_images=paletted[1:],
            duration=WIGGLE_FRAME_MS,
            loop=0,
            comment=caption.comment(),
            optimize=False,
        )
    elif fmt == "webp":
        images[0].save(
            buffer,
            format="WEBP",
            save_all=True,
            append_images=images[1:],
            duration=WIGGLE_FRAME_MS,
            loop=0,
            quality=80,
            method=4,
            exif=caption.exif(),
            xmp=caption.xmp(),
        )
    else:
        raise ValueError(f"Expected a wiggle format of gif or webp, got {fmt!r}")
    return buffer.getvalue()


def encode_mpo(left: np.ndarray, right: np.ndarray, caption: CardCaption) -> bytes:
    """Two JPEG frames in one MPO file, left view first (the order 3D cameras and displays use)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(as_rgb(left)).save(
        buffer,
        format="MPO",
        save_all=True,
        append_images=[Image.fromarray(as_rgb(right))],
        quality=JPEG_QUALITY,
        exif=caption.exif(),
        xmp=caption.xmp(),
    )
    return mark_disparity_pair(buffer.getvalue())


# CIPA DC-007 MP entry attributes: bit 29 = representative image, low 24 bits = MP type;
# 0x020002 = "multi-frame image, disparity" (a stereo pair), what stereo cameras write and 3D
# displays look for. Pillow writes "baseline primary" and "undefined" instead.
MP_DISPARITY = 0x020002
MP_REPRESENTATIVE = 1 << 29


def mark_disparity_pair(data: bytes) -> bytes:
    """Set the MP index entries of a two-frame MPO written by Pillow to "disparity" (the first
    frame representative). Raises ``ValueError`` if the file has no MP index of two entries."""
    import struct

    start = data.find(b"MPF\0")
    if start < 0 or data[start + 4 : start + 8] not in (b"II*\0", b"MM\0*"):
        raise ValueError("no MP index (APP2 'MPF') in the MPO")
    tiff = start + 4
    order = "<" if data[tiff : tiff + 2] == b"II" else ">"
    ifd = tiff + struct.unpack_from(order + "L", data, tiff + 4)[0]
    (count,) = struct.unpack_from(order + "H", data, ifd)
    patched = bytearray(data)
    for number in range(count):
        tag, _kind, length, value = struct.unpack_from(order + "HHLL", data, ifd + 2 + 12 * number)
        if tag != 0xB002:
            continue
        if length != 32:
            raise ValueError(f"expected an MP index of 2 entries (32 bytes), got {length} bytes")
        for entry in range(2):
            attribute = MP_DISPARITY | (MP_REPRESENTATIVE if entry == 0 else 0)
            struct.pack_into(order + "L", patched, tiff + value + 16 * entry, attribute)
        return bytes(patched)
    raise ValueError("the MPO's MP index has no entry list (tag 0xB002)")


@dataclass
class StereoCosts:
    """Seconds and bytes spent per format (summed over cards)."""

    cards: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: {name: 0.0 for name in STEREO_FORMATS})
    bytes: dict[str, int] = field(default_factory=lambda: {name: 0 for name in STEREO_FORMATS})

    def as_json(self) -> dict[str, Any]:
        per = max(self.cards, 1)
        return {
            "cards": self.cards,
            "per_card": {
                name: {"seconds": round(self.seconds[name] / per, 4), "bytes": round(self.bytes[name] / per)}
                for name in STEREO_FORMATS
            },
        }


def encode_stereo(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    caption: CardCaption,
    only: tuple[str, ...] | None = None,
    costs: StereoCosts | None = None,
) -> dict[str, bytes]:
    """Every stereo file of a rectified pair (or the ``only`` ones): format name -> bytes.

    Raises :class:`pipeline.stereo_formats.StereoFormatError` on mismatched sizes or a disparity
    with no known value."""
    pair = make_pair(left, right, disparity)
    frames: list[np.ndarray] = []

    def wiggle(fmt: str) -> bytes:
        # The frames are shared by both wiggles; their synthesis is timed with the first one made.
        if not frames:
            frames.extend(wiggle_frames(pair, max_side=WIGGLE_MAX_SIDE))
        return encode_wiggle(frames, caption, fmt)

    makers: dict[str, Callable[[], bytes]] = {
        "anaglyph": lambda: encode_anaglyph(pair.left, pair.right, caption),
        "wiggle_gif": lambda: wiggle("gif"),
        "wiggle_webp": lambda: wiggle("webp"),
        "sbs_full": lambda: _jpeg(side_by_side(pair.left, pair.right), caption),
        "sbs_half": lambda: _jpeg(side_by_side(pair.left, pair.right, half=True), caption),
        "jps": lambda: _jpeg(side_by_side(pair.right, pair.left), caption),
        "mpo": lambda: encode_mpo(pair.left, pair.right, caption),
    }
    out: dict[str, bytes] = {}
    for name in STEREO_FORMATS:
        if only is not None and name not in only:
            continue
        clock = time.perf_counter()
        out[name] = makers[name]()
        if costs is not None:
            costs.seconds[name] += time.perf_counter() - clock
            costs.bytes[name] += len(out[name])
    if costs is not None:
        costs.cards += 1
    return out


def decode_png(data: bytes) -> np.ndarray:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as image:
        image.load()
        return np.asarray(image.convert("RGB") if image.mode not in ("L", "RGB") else image)

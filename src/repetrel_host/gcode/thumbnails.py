"""The preview images slicers embed in G-code, read back as images a browser shows.

PrusaSlicer, OrcaSlicer and SuperSlicer write each thumbnail as a comment block::

    ; thumbnail begin 220x124 5404        (or thumbnail_JPG, thumbnail_QOI)
    ; iVBORw0KGgoAAAANSUhEUgAAANwAAAB8CAYAAAA...
    ; thumbnail end

and Cura's "Create Thumbnail" script writes the PNG form. The analysis pass
(:mod:`repetrel_host.gcode.analysis`) notes where each block lies; :func:`read` takes the
block's bytes back out of the file and decodes them. PNG and JPEG are served as they are;
QOI, which no browser shows, becomes a PNG here (QOI's whole specification is a page:
https://qoiformat.org/qoi-specification.pdf; a dependency would be larger than this).
"""

from __future__ import annotations

import base64
import binascii
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

MAX_BYTES = 16 << 20  # a block's base64 text read at most: a thumbnail, not a film
MEDIA_TYPES = {"PNG": "image/png", "JPG": "image/jpeg"}  # served as they are


@dataclass(frozen=True)
class Thumbnail:
    """One embedded image: its format (``PNG``, ``JPG``, ``QOI``), its size in pixels, and
    where its base64 lines lie in the file (``start`` to ``end``, in bytes)."""

    format: str
    width: int
    height: int
    start: int
    end: int


class ThumbnailError(ValueError):
    """The block does not hold the image its first line announced."""


def read(path: Path, thumbnail: Thumbnail) -> tuple[bytes, str]:
    """The image and its media type (``OSError`` when the file cannot be read,
    :class:`ThumbnailError` when the block is not an image of its format)."""
    size = thumbnail.end - thumbnail.start
    if size <= 0 or size > MAX_BYTES:
        raise ThumbnailError(f"a thumbnail block of {size} bytes")
    with path.open("rb") as handle:
        handle.seek(thumbnail.start)
        text = handle.read(size)
    encoded = b"".join(line.strip().lstrip(b";").strip() for line in text.splitlines())
    try:
        image = base64.b64decode(encoded, validate=True)
    except binascii.Error as exc:
        raise ThumbnailError(f"the thumbnail is not base64: {exc}") from None
    if thumbnail.format == "QOI":
        width, height, pixels = decode_qoi(image)
        return encode_png(width, height, pixels), "image/png"
    magic = b"\x89PNG" if thumbnail.format == "PNG" else b"\xff\xd8"
    if not image.startswith(magic):
        raise ThumbnailError(f"the thumbnail is not a {thumbnail.format} image")
    return image, MEDIA_TYPES[thumbnail.format]


def decode_qoi(data: bytes) -> tuple[int, int, bytes]:
    """A QOI image's width, height and RGBA pixels."""
    if len(data) < 22 or data[:4] != b"qoif":
        raise ThumbnailError("the thumbnail is not a QOI image")
    width, height = struct.unpack(">II", data[4:12])
    count = width * height
    if not count or count > 16 << 20:
        raise ThumbnailError(f"a QOI image of {width}x{height} pixels")
    out = bytearray(count * 4)
    seen = [(0, 0, 0, 0)] * 64
    r, g, b, a = 0, 0, 0, 255
    position, end, pixel, run = 14, len(data) - 8, 0, 0
    while pixel < count:
        if run:
            run -= 1
        elif position < end:
            op = data[position]
            position += 1
            if op == 0xFE:  # QOI_OP_RGB
                r, g, b = data[position : position + 3]
                position += 3
            elif op == 0xFF:  # QOI_OP_RGBA
                r, g, b, a = data[position : position + 4]
                position += 4
            elif op >> 6 == 0:  # QOI_OP_INDEX
                r, g, b, a = seen[op]
            elif op >> 6 == 1:  # QOI_OP_DIFF
                r = (r + (op >> 4 & 3) - 2) & 255
                g = (g + (op >> 2 & 3) - 2) & 255
                b = (b + (op & 3) - 2) & 255
            elif op >> 6 == 2:  # QOI_OP_LUMA
                green = (op & 63) - 32
                second = data[position]
                position += 1
                r = (r + green - 8 + (second >> 4)) & 255
                g = (g + green) & 255
                b = (b + green - 8 + (second & 15)) & 255
            else:  # QOI_OP_RUN: this pixel and ``run`` more
                run = op & 63
        else:
            raise ThumbnailError("the QOI image ends before its last pixel")
        seen[(r * 3 + g * 5 + b * 7 + a * 11) % 64] = (r, g, b, a)
        out[pixel * 4 : pixel * 4 + 4] = bytes((r, g, b, a))
        pixel += 1
    return width, height, bytes(out)


def encode_png(width: int, height: int, rgba: bytes) -> bytes:
    """RGBA pixels as a PNG (8 bits a channel, no filter)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    stride = width * 4
    rows = b"".join(b"\0" + rgba[y * stride : (y + 1) * stride] for y in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows, 6))
        + chunk(b"IEND", b"")
    )

"""Reading one photo for ingestion: grey pixels as the sensor stored them, and the EXIF orientation.

The EXIF orientation is reported, never applied: K belongs to the sensor's pixel grid, so every
photo of one camera keeps one image size and one pixel frame however the phone was held (a
turned or upside-down photo is told apart by the board identification instead).

The image size is read from the file's header **before** decoding (``header_size``: JPEG, PNG,
TIFF, WebP, BMP, PNM) and checked against the caps (``check_size``): at most ``max_megapixels``
(MAX_MEGAPIXELS by default), every side at least MIN_SIDE_PX, the longer side at most MAX_ASPECT
times the shorter. A file that claims 30000x30000 px is refused without allocating its pixels;
a format whose size cannot be read first is refused. Specified in models_spec/ingest.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime.errors import PhotoError

EXIF_ORIENTATION_TAG = 0x0112
MAX_MEGAPIXELS = 50.0  # default cap: 12 MP phone photos and 48 MP (8000x6000) sensors pass; --max-megapixels
MIN_SIDE_PX = 64  # shorter image side: a board needs tens of px to be found at all
MAX_ASPECT = 4.0  # longer / shorter side: 4:3 ... 32:9 pass; a strip or a panorama is no single pinhole view
MAX_FILE_BYTES_PER_PIXEL = 8  # the file may hold at most this many bytes per pixel of the cap (16-bit RGBA, raw)
FORMATS = "JPEG, PNG, TIFF, WebP, BMP, PNM"  # the formats whose size header_size reads before decoding
JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # start-of-frame markers (DHT, JPG, DAC are not)
PNM_MAGIC = (b"P1", b"P2", b"P3", b"P4", b"P5", b"P6")  # PBM, PGM, PPM, plain and raw
TIFF_TYPE_BYTES = {3: 2, 4: 4, 16: 8}  # SHORT, LONG, LONG8: the types a TIFF ImageWidth/ImageLength may have


@dataclass(frozen=True)
class Photo:
    """A decoded photo: ``gray`` (h, w) uint8 in the stored pixel frame; ``exif_orientation`` the EXIF
    Orientation tag (1 upright, 3 turned 180°, 6 and 8 turned 90°, 2/4/5/7 mirrored), 1 when absent."""

    gray: np.ndarray
    exif_orientation: int


def tiff_orientation(tiff: bytes) -> int:
    """The Orientation tag of a TIFF block's first IFD (the EXIF payload); 1 when absent or malformed."""
    order = {b"II": "little", b"MM": "big"}.get(tiff[:2])
    if order is None or len(tiff) < 8:
        return 1
    ifd = int.from_bytes(tiff[4:8], order)
    count = int.from_bytes(tiff[ifd : ifd + 2], order) if ifd + 2 <= len(tiff) else 0
    for entry in range(ifd + 2, min(ifd + 2 + 12 * count, len(tiff) - 11), 12):
        if int.from_bytes(tiff[entry : entry + 2], order) == EXIF_ORIENTATION_TAG:
            value = int.from_bytes(tiff[entry + 8 : entry + 10], order)
            return value if 1 <= value <= 8 else 1
    return 1


def exif_orientation(data: bytes) -> int:
    """The EXIF Orientation of a JPEG file's bytes (APP1 ``Exif`` segment); 1 for other formats or none."""
    if data[:2] != b"\xff\xd8":
        return 1
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF and data[pos + 1] not in (0xD9, 0xDA):
        length = int.from_bytes(data[pos + 2 : pos + 4], "big")
        if data[pos + 1] == 0xE1 and data[pos + 4 : pos + 10] == b"Exif\x00\x00":
            return tiff_orientation(data[pos + 10 : pos + 2 + length])
        pos += 2 + length
    return 1


def _u(data: bytes, pos: int, n: int, order: str = "big") -> int:
    """The unsigned ``n``-byte integer at ``pos``; ValueError past the end."""
    if pos < 0 or pos + n > len(data):
        raise ValueError("header ends early")
    return int.from_bytes(data[pos : pos + n], order)


def _jpeg_size(data: bytes) -> tuple[int, int]:
    pos = 2
    while True:
        if _u(data, pos, 1) != 0xFF:
            raise ValueError("no marker where one belongs")
        while _u(data, pos + 1, 1) == 0xFF:  # fill bytes
            pos += 1
        marker = _u(data, pos + 1, 1)
        if marker in JPEG_SOF:
            return _u(data, pos + 7, 2), _u(data, pos + 5, 2)
        if marker in (0xD9, 0xDA):
            raise ValueError("no frame header before the image data")
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # standalone markers
            pos += 2
            continue
        length = _u(data, pos + 2, 2)
        if length < 2:
            raise ValueError("a segment of negative length")
        pos += 2 + length


def _tiff_size(data: bytes) -> tuple[int, int]:
    order = "little" if data[:2] == b"II" else "big"
    big = _u(data, 2, 2, order) == 43  # BigTIFF: 8-byte offsets and counts
    ifd = _u(data, 8, 8, order) if big else _u(data, 4, 4, order)
    count = _u(data, ifd, 8 if big else 2, order)
    first, step, value_at = (ifd + 8, 20, 12) if big else (ifd + 2, 12, 8)
    size: dict[int, int] = {}
    for entry in range(first, first + step * min(count, 4096), step):
        tag, kind = _u(data, entry, 2, order), _u(data, entry + 2, 2, order)
        if tag in (256, 257) and kind in TIFF_TYPE_BYTES:
            size[tag] = _u(data, entry + value_at, TIFF_TYPE_BYTES[kind], order)
    if len(size) < 2:
        raise ValueError("no ImageWidth and ImageLength in the first directory")
    return size[256], size[257]


def _webp_size(data: bytes) -> tuple[int, int]:
    chunk = data[12:16]
    if chunk == b"VP8 " and data[23:26] == b"\x9d\x01\x2a":
        return _u(data, 26, 2, "little") & 0x3FFF, _u(data, 28, 2, "little") & 0x3FFF
    if chunk == b"VP8L" and data[20:21] == b"\x2f":
        bits = _u(data, 21, 4, "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":
        return _u(data, 24, 3, "little") + 1, _u(data, 27, 3, "little") + 1
    raise ValueError(f"unknown WebP chunk {chunk!r}")


def _bmp_size(data: bytes) -> tuple[int, int]:
    if _u(data, 14, 4, "little") == 12:  # OS/2 BITMAPCOREHEADER
        return _u(data, 18, 2, "little"), _u(data, 20, 2, "little")
    w, h = (_u(data, at, 4, "little") for at in (18, 22))
    return w if w < 2**31 else 2**32 - w, h if h < 2**31 else 2**32 - h  # signed; a negative height is top-down


def _pnm_size(data: bytes) -> tuple[int, int]:
    tokens: list[int] = []
    pos = 2
    while len(tokens) < 2:
        while pos < len(data) and (data[pos : pos + 1].isspace() or data[pos] == ord("#")):
            if data[pos] == ord("#"):  # a comment runs to the end of the line
                end = data.find(b"\n", pos)
                pos = len(data) if end < 0 else end
            pos += 1
        start = pos
        while pos < len(data) and data[pos : pos + 1].isdigit():
            pos += 1
        if pos == start or pos - start > 12:
            raise ValueError("no width and height after the magic number")
        tokens.append(int(data[start:pos]))
    return tokens[0], tokens[1]


def header_size(data: bytes) -> Optional[tuple[int, int]]:
    """(width, height) px that a file's header declares, read without decoding a pixel; None when the
    format is none of FORMATS. ValueError when the header is one of them but malformed or cut short."""
    if data[:3] == b"\xff\xd8\xff":
        return _jpeg_size(data)
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if data[12:16] != b"IHDR":
            raise ValueError("no IHDR chunk first")
        return _u(data, 16, 4), _u(data, 20, 4)
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _tiff_size(data)
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return _webp_size(data)
    if data[:2] == b"BM":
        return _bmp_size(data)
    if data[:2] in PNM_MAGIC:
        return _pnm_size(data)
    return None


def check_size(name: str, size: tuple[int, int], max_megapixels: float = MAX_MEGAPIXELS) -> None:
    """PhotoError naming the file and its size when a (width, height) px image is beyond the caps: more than
    ``max_megapixels``, a side under MIN_SIDE_PX, or the longer side over MAX_ASPECT times the shorter."""
    w, h = size
    if w * h > max_megapixels * 1e6:
        raise PhotoError(
            f"{name}: {w}x{h} px is {w * h / 1e6:.1f} MP, over the {max_megapixels:g} MP cap "
            "(dimenet ingest --max-megapixels raises it)"
        )
    if min(w, h) < MIN_SIDE_PX:
        raise PhotoError(f"{name}: {w}x{h} px is too small (every side needs >= {MIN_SIDE_PX} px)")
    if max(w, h) > MAX_ASPECT * min(w, h):
        raise PhotoError(
            f"{name}: {w}x{h} px has an aspect ratio of {max(w, h) / min(w, h):.1f}:1, over {MAX_ASPECT:g}:1"
        )


def read_photo(path: str | Path, max_megapixels: float = MAX_MEGAPIXELS) -> Photo:
    """Decode a photo (JPEG, PNG, TIFF, WebP, BMP, PNM) to grey, EXIF orientation not applied, after checking
    the size its header declares against the caps (``check_size``). Raises PhotoError naming the file:
    unreadable, empty, unsupported format, a size beyond the caps, corrupt or truncated."""
    path = Path(path)
    max_bytes = MAX_FILE_BYTES_PER_PIXEL * max_megapixels * 1e6
    try:
        n_bytes = path.stat().st_size
        if n_bytes > max_bytes:
            raise PhotoError(
                f"{path.name}: the file has {n_bytes / 1e6:.0f} MB, more than {MAX_FILE_BYTES_PER_PIXEL} bytes per "
                f"pixel of the {max_megapixels:g} MP cap (dimenet ingest --max-megapixels raises it)"
            )
        data = path.read_bytes()
    except OSError as exc:
        raise PhotoError(f"{path.name}: cannot read the file ({exc.strerror or exc})") from None
    if not data:
        raise PhotoError(f"{path.name}: empty file")
    try:
        size = header_size(data)
    except ValueError as exc:
        raise PhotoError(f"{path.name}: cannot decode the image (corrupt or truncated header: {exc})") from None
    if size is None:
        if cv2.haveImageReader(str(path)):
            raise PhotoError(
                f"{path.name}: unsupported image format for ingest (its size cannot be checked before decoding; "
                f"convert it to one of {FORMATS})"
            )
        raise PhotoError(f"{path.name}: unsupported image format (ingest reads {FORMATS})")
    check_size(path.name, size, max_megapixels)
    try:
        gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as exc:
        raise PhotoError(f"{path.name}: cannot decode the image (OpenCV: {exc.err})") from None
    if gray is None:
        raise PhotoError(f"{path.name}: cannot decode the image (corrupt or truncated file)")
    if gray.shape != (size[1], size[0]):
        raise PhotoError(
            f"{path.name}: cannot decode the image (its header declares {size[0]}x{size[1]} px, "
            f"it decodes to {gray.shape[1]}x{gray.shape[0]} px)"
        )
    return Photo(gray=gray, exif_orientation=exif_orientation(data))

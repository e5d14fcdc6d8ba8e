"""Reading one photo for ingestion: grey pixels as the sensor stored them, and the EXIF orientation.

The EXIF orientation is reported, never applied: K belongs to the sensor's pixel grid, so every
photo of one camera keeps one image size and one pixel frame however the phone was held (a
turned or upside-down photo is told apart by the board identification instead).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dimenet.runtime.errors import PhotoError

EXIF_ORIENTATION_TAG = 0x0112


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


def read_photo(path: str | Path) -> Photo:
    """Decode a photo (any format OpenCV reads: JPEG, PNG, TIFF, WebP, ...) to grey, EXIF orientation
    not applied. Raises PhotoError naming the file: unreadable, unsupported format or undecodable."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PhotoError(f"{path.name}: cannot read the file ({exc.strerror or exc})") from None
    if not data:
        raise PhotoError(f"{path.name}: empty file")
    if not cv2.haveImageReader(str(path)):
        raise PhotoError(f"{path.name}: unsupported image format (OpenCV reads JPEG, PNG, TIFF, WebP, BMP, ...)")
    gray = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if gray is None:
        raise PhotoError(f"{path.name}: cannot decode the image (corrupt or truncated file)")
    return Photo(gray=gray, exif_orientation=exif_orientation(data))

"""Natural-object points for ingestion: ``OBJECT.csv`` (3D in {W}) and ``LABELS.csv`` (2D per photo).

``OBJECT.csv``: header ``point_id,X_mm,Y_mm,Z_mm``, one row per point of the object (e.g. LEGO
window corners), coordinates in mm in the rig frame {W}. ``LABELS.csv``: header
``image,point_id,x_px,y_px``, one row per point hand-labelled in a photo (``image`` is the photo's
file name), pixels x right, y down in the photo's stored pixel frame (EXIF orientation not applied).
Specified in models_spec/ingest.md.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import LabelsError
from dimenet.runtime.formats.text import decimal, read_text

OBJECT_HEADER = ("point_id", "X_mm", "Y_mm", "Z_mm")
LABELS_HEADER = ("image", "point_id", "x_px", "y_px")
MAX_CSV_BYTES = 16 << 20  # 16 MiB: ~500 k label rows (~15 s to read); a LEGO test has ~10^3
MAX_OBJECT_POINTS = 100_000  # rows of OBJECT.csv: a rig's limit too (formats.rig.MAX_RIG_POINTS)
MAX_LABEL_ROWS = 1_000_000  # rows of LABELS.csv (the byte limit allows ~500 k anyway)
MAX_OBJECT_MM = 1e6  # |X_mm|, |Y_mm|, |Z_mm|: 1 km, the rig's limit too (formats.rig.MAX_LENGTH_MM)
MAX_LABEL_PX = 1e6  # |x_px|, |y_px|: the dataset's largest image side (formats.dataset.MAX_IMAGE_SIDE_PX)


@dataclass(frozen=True)
class NaturalObject:
    """The object's points: ids (M,) and positions (M, 3) mm in {W}, in OBJECT.csv order."""

    point_ids: tuple[str, ...]
    points_mm: np.ndarray


@dataclass(frozen=True)
class ImageLabels:
    """The points labelled in one photo: ``index`` (k,) into the object's points, ``points_px`` (k, 2)."""

    index: np.ndarray
    points_px: np.ndarray


def _rows(path: Path, header: tuple[str, ...], max_rows: int) -> Iterator[tuple[int, list[str]]]:
    """(line number, stripped fields) of every non-empty data row, read as they are needed.

    LabelsError unless the header is ``header``, for a row of another field count and for more than
    ``max_rows`` rows.
    """
    reader = csv.reader(io.StringIO(read_text(path, MAX_CSV_BYTES, "CSV file of points", LabelsError), newline=""))
    start, n_rows, seen_header = 1, 0, False
    try:
        for row in reader:
            if "".join(row).strip():
                fields = [c.strip() for c in row]
                if not seen_header:
                    if tuple(fields) != header:
                        break
                    seen_header = True
                elif len(fields) != len(header):
                    raise LabelsError(
                        f"{path}:{start}: expected {len(header)} fields ({','.join(header)}), got {len(fields)}"
                    )
                elif n_rows == max_rows:
                    raise LabelsError(f"{path}:{start}: more than {max_rows} rows")
                else:
                    n_rows += 1
                    yield start, fields
            start = reader.line_num + 1  # a quoted field may span lines: a row is named by its first line
    except csv.Error as exc:
        raise LabelsError(f"{path}:{start}: not a readable CSV row ({exc})") from None
    if not seen_header:
        raise LabelsError(f"{path}:1: the header must be {','.join(header)}")
    if not n_rows:
        raise LabelsError(f"{path}: no rows after the header")


def _number(text: str, path: Path, line: int, field: str, limit: float) -> float:
    """A plain decimal number (``-12.5``, ``3e2``; ``formats.text.decimal``) of magnitude at most ``limit``."""
    value = decimal(text)
    if value is None or not math.isfinite(value):  # 1e400 is inf
        raise LabelsError(f"{path}:{line}: {field} must be a finite number, got {_shown(text)}")
    if abs(value) > limit:
        raise LabelsError(f"{path}:{line}: {field} must be at most {limit:g} in magnitude, got {_shown(text)}")
    return value


def _shown(text: str) -> str:
    return repr(text) if len(text) <= 40 else f"{text[:30]!r}... ({len(text)} characters)"


def read_object(path: str | Path) -> NaturalObject:
    """Read OBJECT.csv. Raises LabelsError naming the file and line (header, fields, numbers, duplicate ids)."""
    path = Path(path)
    ids: dict[str, None] = {}  # insertion-ordered; a set's lookup (a list's made 10^5 points quadratic)
    points = []
    for line, (point_id, *xyz) in _rows(path, OBJECT_HEADER, MAX_OBJECT_POINTS):
        if not point_id:
            raise LabelsError(f"{path}:{line}: empty point_id")
        if point_id in ids:
            raise LabelsError(f"{path}:{line}: duplicate point_id {_shown(point_id)}")
        ids[point_id] = None
        points.append([_number(v, path, line, f, MAX_OBJECT_MM) for v, f in zip(xyz, OBJECT_HEADER[1:])])
    return NaturalObject(point_ids=tuple(ids), points_mm=np.array(points, dtype=np.float64))


def read_labels(path: str | Path, obj: NaturalObject) -> dict[str, ImageLabels]:
    """Read LABELS.csv against the object: the labels of each photo, by photo file name.

    Raises LabelsError naming the file and line (header, fields, numbers, unknown or repeated points).
    """
    path = Path(path)
    index_of = {pid: k for k, pid in enumerate(obj.point_ids)}
    per_image: dict[str, dict[int, list[float]]] = {}
    for line, (image, point_id, x, y) in _rows(path, LABELS_HEADER, MAX_LABEL_ROWS):
        if not image:
            raise LabelsError(f"{path}:{line}: empty image name")
        if point_id not in index_of:
            raise LabelsError(f"{path}:{line}: point_id {_shown(point_id)} is not in the object file")
        labelled = per_image.setdefault(image, {})
        if index_of[point_id] in labelled:
            raise LabelsError(f"{path}:{line}: point {point_id!r} labelled twice in {image}")
        labelled[index_of[point_id]] = [
            _number(x, path, line, "x_px", MAX_LABEL_PX),
            _number(y, path, line, "y_px", MAX_LABEL_PX),
        ]
    return {
        image: ImageLabels(index=np.array(list(points), dtype=np.int64), points_px=np.array(list(points.values())))
        for image, points in per_image.items()
    }

"""Natural-object points for ingestion: ``OBJECT.csv`` (3D in {W}) and ``LABELS.csv`` (2D per photo).

``OBJECT.csv``: header ``point_id,X_mm,Y_mm,Z_mm``, one row per point of the object (e.g. LEGO
window corners), coordinates in mm in the rig frame {W}. ``LABELS.csv``: header
``image,point_id,x_px,y_px``, one row per point hand-labelled in a photo (``image`` is the photo's
file name), pixels x right, y down in the photo's stored pixel frame (EXIF orientation not applied).
Specified in models_spec/ingest.md.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import LabelsError

OBJECT_HEADER = ("point_id", "X_mm", "Y_mm", "Z_mm")
LABELS_HEADER = ("image", "point_id", "x_px", "y_px")


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


def _rows(path: Path, header: tuple[str, ...]) -> list[tuple[int, list[str]]]:
    """(line number, fields) of every non-empty data row; LabelsError unless the header is ``header``."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            lines = [(n, row) for n, row in enumerate(csv.reader(f), start=1) if any(c.strip() for c in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise LabelsError(f"{path}: cannot read the CSV file ({exc})") from None
    if not lines or tuple(c.strip() for c in lines[0][1]) != header:
        raise LabelsError(f"{path}:1: the header must be {','.join(header)}")
    rows = []
    for n, row in lines[1:]:
        if len(row) != len(header):
            raise LabelsError(f"{path}:{n}: expected {len(header)} fields ({','.join(header)}), got {len(row)}")
        rows.append((n, [c.strip() for c in row]))
    if not rows:
        raise LabelsError(f"{path}: no rows after the header")
    return rows


def _number(text: str, path: Path, line: int, field: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise LabelsError(f"{path}:{line}: {field} must be a finite number, got {text!r}")
    return value


def read_object(path: str | Path) -> NaturalObject:
    """Read OBJECT.csv. Raises LabelsError naming the file and line (header, fields, numbers, duplicate ids)."""
    path = Path(path)
    ids: list[str] = []
    points = []
    for line, (point_id, *xyz) in _rows(path, OBJECT_HEADER):
        if not point_id:
            raise LabelsError(f"{path}:{line}: empty point_id")
        if point_id in ids:
            raise LabelsError(f"{path}:{line}: duplicate point_id {point_id!r}")
        ids.append(point_id)
        points.append([_number(v, path, line, f) for v, f in zip(xyz, OBJECT_HEADER[1:])])
    return NaturalObject(point_ids=tuple(ids), points_mm=np.array(points, dtype=np.float64))


def read_labels(path: str | Path, obj: NaturalObject) -> dict[str, ImageLabels]:
    """Read LABELS.csv against the object: the labels of each photo, by photo file name.

    Raises LabelsError naming the file and line (header, fields, numbers, unknown or repeated points).
    """
    path = Path(path)
    index_of = {pid: k for k, pid in enumerate(obj.point_ids)}
    per_image: dict[str, dict[int, list[float]]] = {}
    for line, (image, point_id, x, y) in _rows(path, LABELS_HEADER):
        if not image:
            raise LabelsError(f"{path}:{line}: empty image name")
        if point_id not in index_of:
            raise LabelsError(f"{path}:{line}: point_id {point_id!r} is not in the object file")
        labelled = per_image.setdefault(image, {})
        if index_of[point_id] in labelled:
            raise LabelsError(f"{path}:{line}: point {point_id!r} labelled twice in {image}")
        labelled[index_of[point_id]] = [_number(x, path, line, "x_px"), _number(y, path, line, "y_px")]
    return {
        image: ImageLabels(index=np.array(list(points), dtype=np.int64), points_px=np.array(list(points.values())))
        for image, points in per_image.items()
    }

"""The motion samples beside a points file (`dimenet rectify --points FILE --temporal --motion FILE`;
models_spec/points-csv.md, "Motion"), one sample a row in time order, on the points' clock (ns), either kind:

- the gyroscope: a CSV ``t_ns,gx_rad_s,gy_rad_s,gz_rad_s``, the angular rate (rad/s) in the camera's axes (OpenCV
  {C}: x right, y down, z forward);
- the lens shift: a CSV ``t_ns,x_shift_px,y_shift_px``, the platform's samples of the optical centre's shift (px of
  the sensor's active array, +x to the right, +y down: Android's STATISTICS_OIS_SAMPLES, ``OisSample``).

``write_gyro`` and ``write_lens_shift`` write one atomically; ``read_motion`` reads either whole (a sample is ~30
bytes: 10 minutes at 500 Hz is 9 MB), telling them apart by the header. Every problem is a PointsError naming the
file and line."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import PointsError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.text import decimal, t_ns_integer
from dimenet.runtime.json_text import shown
from dimenet.runtime.rectify.gyro_ois import MAX_RATE_RAD_S, MAX_SHIFT_PX

GYRO_COLUMNS = ("t_ns", "gx_rad_s", "gy_rad_s", "gz_rad_s")
LENS_SHIFT_COLUMNS = ("t_ns", "x_shift_px", "y_shift_px")
GYRO, LENS_SHIFT = "gyro", "lens_shift"
_KINDS = {
    GYRO: (GYRO_COLUMNS, MAX_RATE_RAD_S, "finite rad/s of magnitude <= {:g} (deg/s?)"),
    LENS_SHIFT: (LENS_SHIFT_COLUMNS, MAX_SHIFT_PX, "finite px of magnitude <= {:g}"),
}


@dataclass(frozen=True)
class Motion:
    """A motion file's samples: ``kind`` GYRO ((G, 4) rows t_ns, gx, gy, gz rad/s) or LENS_SHIFT ((G, 3) rows t_ns,
    x_shift_px, y_shift_px), float64."""

    kind: str
    samples: np.ndarray


def _write(path: str | Path, columns: tuple, samples: np.ndarray) -> Path:
    text = io.StringIO()
    text.write(",".join(columns) + "\n")
    for t, *values in np.asarray(samples, dtype=np.float64):
        text.write(",".join([str(int(t)), *(repr(float(v)) for v in values)]) + "\n")
    return atomic_write(path, lambda f: f.write(text.getvalue().encode("utf-8")))


def write_gyro(path: str | Path, samples: np.ndarray) -> Path:
    """Write (G, 4) rows (t_ns, gx, gy, gz rad/s) as the gyroscope CSV, atomically."""
    return _write(path, GYRO_COLUMNS, samples)


def write_lens_shift(path: str | Path, samples: np.ndarray) -> Path:
    """Write (G, 3) rows (t_ns, x_shift_px, y_shift_px) as the lens-shift CSV, atomically."""
    return _write(path, LENS_SHIFT_COLUMNS, samples)


def read_motion(path: str | Path) -> Motion:
    """The samples of a motion CSV: its header names GYRO_COLUMNS or LENS_SHIFT_COLUMNS (in any order, other
    columns ignored), t_ns integers strictly increasing, the values finite and within the kind's bound."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise PointsError(f"{path}: cannot read the motion file ({exc})") from None
    try:
        rows = [r for r in csv.reader(io.StringIO(text)) if "".join(r).strip()]
    except csv.Error as exc:  # a NUL byte on Python < 3.11, for one
        raise PointsError(f"{path}: not a readable CSV ({exc})") from None
    if not rows:
        raise PointsError(f"{path}:1: no header: the motion file is empty")
    names = [c.strip() for c in rows[0]]
    kind = next((k for k, (columns, _, _) in _KINDS.items() if all(c in names for c in columns)), None)
    if kind is None:
        raise PointsError(
            f"{path}:1: the header must name {', '.join(GYRO_COLUMNS)} (the gyroscope) or "
            f"{', '.join(LENS_SHIFT_COLUMNS)} (the lens shift); it has {', '.join(names)}"
        )
    columns, bound, unit = _KINDS[kind]
    index = [names.index(c) for c in columns]
    out = np.empty((len(rows) - 1, len(columns)))
    previous = None  # the last row's t_ns
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != len(names):
            raise PointsError(f"{path}:{line}: expected {len(names)} fields as the header has, got {len(row)}")
        t = t_ns_integer(row[index[0]])
        if t is None:
            shown_t = shown(row[index[0]])
            raise PointsError(
                f"{path}:{line}: t_ns must be an integer of nanoseconds (|t_ns| <= 2**63 - 1), got {shown_t}"
            )
        values = [decimal(row[j]) for j in index[1:]]
        if any(v is None or not abs(v) <= bound for v in values):
            raise PointsError(
                f"{path}:{line}: {', '.join(columns[1:])} must be {unit.format(bound)}, got "
                f"{', '.join(row[j] for j in index[1:])}"
            )
        out[i] = (t, *values)
        if previous is not None and t <= previous:
            raise PointsError(f"{path}:{line}: t_ns must increase strictly, got {t} after {previous}")
        if previous is not None and out[i, 0] <= out[i - 1, 0]:  # beyond 2**53 ns float64 steps by more than 1 ns
            raise PointsError(
                f"{path}:{line}: t_ns {t} and {previous} are one float64 at this magnitude: count the clock from a "
                "nearer start"
            )
        previous = t
    if len(out) < 2:
        raise PointsError(f"{path}:{len(rows) + 1}: the motion file needs at least 2 samples, it has {len(out)}")
    return Motion(kind, out)

"""The gyroscope's samples beside a points file (`dimenet rectify --points FILE --motion GYRO.csv`;
models_spec/points-csv.md, "Motion"): a CSV ``t_ns,gx_rad_s,gy_rad_s,gz_rad_s``, one sample a row in time
order, on the points' clock (ns), the angular rate (rad/s) in the camera's axes (OpenCV {C}: x right, y down,
z forward). ``write_gyro`` writes one atomically; ``read_gyro`` reads one whole (a gyroscope's samples are
~30 bytes each: 10 minutes at 500 Hz is 9 MB) into a (G, 4) float64 array. Every problem is a PointsError naming
the file and line."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import PointsError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.text import decimal

GYRO_COLUMNS = ("t_ns", "gx_rad_s", "gy_rad_s", "gz_rad_s")
MAX_RATE_RAD_S = 100.0  # |rate| above this is no hand-held phone's (a unit error: deg/s)


def write_gyro(path: str | Path, samples: np.ndarray) -> Path:
    """Write (G, 4) rows (t_ns, gx, gy, gz rad/s) as the gyroscope CSV, atomically."""
    text = io.StringIO()
    text.write(",".join(GYRO_COLUMNS) + "\n")
    for t, gx, gy, gz in np.asarray(samples, dtype=np.float64):
        text.write(f"{int(t)},{float(gx)!r},{float(gy)!r},{float(gz)!r}\n")
    return atomic_write(path, lambda f: f.write(text.getvalue().encode("utf-8")))


def read_gyro(path: str | Path) -> np.ndarray:
    """(G, 4) float64 rows (t_ns, gx, gy, gz rad/s) of a gyroscope CSV: header GYRO_COLUMNS (in any order, other
    columns ignored), t_ns integers strictly increasing, rates finite and |rate| <= MAX_RATE_RAD_S."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise PointsError(f"{path}: cannot read the gyroscope file ({exc})") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if "".join(r).strip()]
    if not rows:
        raise PointsError(f"{path}:1: no header: the gyroscope file is empty")
    names = [c.strip() for c in rows[0]]
    missing = [c for c in GYRO_COLUMNS if c not in names]
    if missing:
        raise PointsError(f"{path}:1: the header must name {', '.join(GYRO_COLUMNS)}; it has no {', '.join(missing)}")
    index = [names.index(c) for c in GYRO_COLUMNS]
    out = np.empty((len(rows) - 1, 4))
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != len(names):
            raise PointsError(f"{path}:{line}: expected {len(names)} fields as the header has, got {len(row)}")
        t = row[index[0]].strip()
        if not t.lstrip("+-").isdigit():
            raise PointsError(f"{path}:{line}: t_ns must be an integer of nanoseconds, got {t!r}")
        values = [decimal(row[j]) for j in index[1:]]
        if any(v is None or not abs(v) <= MAX_RATE_RAD_S for v in values):
            raise PointsError(
                f"{path}:{line}: gx_rad_s, gy_rad_s, gz_rad_s must be finite rad/s of magnitude <= "
                f"{MAX_RATE_RAD_S:g} (deg/s?), got {', '.join(row[j] for j in index[1:])}"
            )
        out[i] = (int(t), *values)
        if i and out[i, 0] <= out[i - 1, 0]:
            raise PointsError(f"{path}:{line}: t_ns must increase strictly, got {t} after {int(out[i - 1, 0])}")
    if len(out) == 0:
        raise PointsError(f"{path}:2: no samples in the gyroscope file")
    return out

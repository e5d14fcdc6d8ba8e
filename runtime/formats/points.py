"""Correspondences recorded by an app, frame by frame: a points CSV or JSON Lines file (`dimenet rectify
--points`).

Specified in ``models_spec/points-csv.md``. Input: one row (CSV) or one JSON object (JSON
Lines) per point, with ``frame_id``, optional ``t_ns``, ``x_px``, ``y_px`` (px, OpenCV's pixel
convention) and ``X_mm``, ``Y_mm``, ``Z_mm`` (or ``X_m``, ``Y_m``, ``Z_m``) in the frame's world
frame {W}; other columns and keys are ignored. The rows of a frame are consecutive. A file of format 2 declares
it on its first non-blank line (CSV: ``#dimenet-points/2``; JSON Lines: ``{"format": "dimenet-points/2"}``) and may give
each frame its own K_c in ``fx_px``, ``fy_px``, ``cx_px``, ``cy_px`` (all four or none, the same on every row of
a frame); a file without the line is format 1, whose such columns are ignored as any other.
``read_points`` reads the file lazily, one frame at a time (memory: one frame and 8 bytes per
frame id seen), and yields each frame's points with the 3D points in mm. Every problem of the
file is a PointsError naming the file and line. The output, the JSON lines of their rectification, is
``formats.rectified_points``.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from math import isfinite
from operator import itemgetter
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dimenet.runtime.errors import PointsError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.text import decimal, t_ns_integer
from dimenet.runtime.json_text import JsonProblem, is_number, parse_json, shown
from dimenet.runtime.rectify.clock import MAX_T_NS

MAX_LINE_BYTES = 64 << 10  # one row or object, its line end included (a point's row is ~80 bytes)
MAX_FRAME_POINTS = 100_000  # rows of one frame: bounds the memory of a frame (~16 MB while read)
UNITS = {"mm": 1.0, "m": 1000.0}  # 3D columns X_<unit>, Y_<unit>, Z_<unit> -> mm
_SEEN_BUFFER = 4096  # frame-id hashes held in a set before they join the sorted arrays
FORMAT_NAME = "dimenet-points"
FORMATS = (1, 2)  # format 2: the declaration line and a frame's own K_c
K_COLUMNS = ("fx_px", "fy_px", "cx_px", "cy_px")  # format 2: the frame's K_c (px)


@dataclass(frozen=True)
class PointsFrame:
    """One frame of a points file: ``points_2d`` (N, 2) float64 px and ``points_3d`` (N, 3)
    float64 mm in the frame's {W}, row by row; ``t_ns`` int ns or None; ``line``: the line of
    its first row; ``bytes_read``: the bytes of the file read when the frame was complete; ``K_c`` (3, 3)
    float64 px the frame's own prior (format 2's fx_px..cy_px) or None."""

    frame_id: str
    t_ns: Optional[int]
    points_2d: np.ndarray
    points_3d: np.ndarray
    line: int
    bytes_read: int
    K_c: Optional[np.ndarray] = None


def _unreadable(path: Path, exc: OSError) -> PointsError:
    return PointsError(f"{path}: cannot read the points file ({exc.strerror or exc})")


class _Lines:
    """The lines of a binary file as text, numbered from 1; ``bytes_read`` so far. PointsError
    for a line over MAX_LINE_BYTES or not UTF-8 (a BOM on line 1 is dropped)."""

    def __init__(self, f: io.BufferedReader, path: Path) -> None:
        self._f, self.path = f, path
        self.number = self.bytes_read = 0

    def __iter__(self) -> _Lines:
        return self

    def is_json(self) -> bool:
        """Whether the file (not read yet) is JSON Lines: its first non-blank byte is ``{``."""
        try:
            start = self._f.peek(MAX_LINE_BYTES)[:MAX_LINE_BYTES]
        except OSError as exc:
            raise _unreadable(self.path, exc) from None
        return start.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"{")

    def __next__(self) -> str:
        try:
            raw = self._f.readline(MAX_LINE_BYTES + 1)
        except OSError as exc:
            raise _unreadable(self.path, exc) from None
        if not raw:
            raise StopIteration
        self.number += 1
        self.bytes_read += len(raw)
        if len(raw) > MAX_LINE_BYTES:
            raise self.error(f"longer than {MAX_LINE_BYTES} bytes")
        try:
            return raw.decode("utf-8-sig" if self.number == 1 else "utf-8")
        except UnicodeDecodeError as exc:
            raise self.error(f"not UTF-8 text ({exc.reason} at byte {exc.start} of the line)") from None

    def error(self, problem: str, line: Optional[int] = None) -> PointsError:
        return PointsError(f"{self.path}:{self.number if line is None else line}: {problem}")


class _SeenIds:
    """Frame ids seen so far, as 64-bit hashes: a set of up to _SEEN_BUFFER, then sorted arrays of
    _SEEN_BUFFER * 2**i hashes, at most one of each size (the bits of a binary counter). Memory
    ~8 bytes per id; a look-up is one binary search per array, log2(ids / _SEEN_BUFFER) at most."""

    def __init__(self) -> None:
        self._levels: list[Optional[np.ndarray]] = []
        self._recent: set[int] = set()

    def add(self, frame_id: str) -> bool:
        """Record ``frame_id``; False when it was seen before."""
        h = hash(frame_id)
        if h in self._recent or any(_holds(a, h) for a in self._levels if a is not None):
            return False
        self._recent.add(h)
        if len(self._recent) == _SEEN_BUFFER:
            carry = np.sort(np.fromiter(self._recent, np.int64, _SEEN_BUFFER))
            self._recent.clear()
            for i, level in enumerate(self._levels):
                if level is None:
                    self._levels[i] = carry
                    break
                carry = np.sort(np.concatenate([level, carry]), kind="stable")  # two sorted runs: a linear merge
                self._levels[i] = None
            else:
                self._levels.append(carry)
        return True


def _holds(a: np.ndarray, h: int) -> bool:
    """Whether the sorted array ``a`` holds ``h``."""
    i = int(a.searchsorted(h))
    return i < len(a) and bool(a[i] == h)


def _point_names(has, lines: _Lines, what: str) -> tuple[list[str], float]:
    """The names of x_px, y_px, X, Y, Z among a header's names or an object's keys (``has(name)``)
    and the 3D unit's scale to mm; PointsError when frame_id, x_px, y_px or one whole unit is missing."""
    units = [u for u in UNITS if any(has(f"{axis}_{u}") for axis in "XYZ")]
    names = ["x_px", "y_px", *(f"{axis}_{units[0]}" for axis in "XYZ" if len(units) == 1)]
    missing = [n for n in ("frame_id", *names) if not has(n)]
    if missing or len(units) != 1:
        found = "both X_mm.. and X_m.." if len(units) > 1 else f"no {', '.join(missing) or 'X_mm, Y_mm, Z_mm'}"
        raise lines.error(
            f"{what} must name frame_id, x_px, y_px and X_mm, Y_mm, Z_mm (or X_m, Y_m, Z_m), t_ns optional; "
            f"it has {found}"
        )
    return names, UNITS[units[0]]


def _columns(names: list[str], lines: _Lines) -> tuple[int, Optional[int], list[int], float]:
    """The CSV header's indices of frame_id, t_ns (or None) and x_px, y_px, X, Y, Z, and the
    3D unit's scale to mm."""
    doubled = sorted({n for n in names if names.count(n) > 1 and n})
    if doubled:
        raise lines.error(f"the header names {', '.join(doubled)} twice")
    coords, scale = _point_names(names.__contains__, lines, "the header")
    t_ns = names.index("t_ns") if "t_ns" in names else None
    return names.index("frame_id"), t_ns, [names.index(n) for n in coords], scale


def _k_names(has, lines: _Lines, what: str) -> bool:
    """Whether a format-2 header or object (``has(name)``) gives the frame's K_c: all of K_COLUMNS, or none."""
    given = [n for n in K_COLUMNS if has(n)]
    if given and len(given) != len(K_COLUMNS):
        missing = ", ".join(n for n in K_COLUMNS if n not in given)
        raise lines.error(f"{what} gives {', '.join(given)} but not {missing}: a frame's K_c needs all four or none")
    return bool(given)


def _declared_format(text: str, lines: _Lines) -> int:
    """The format a declaration names (``dimenet-points/N``), or PointsError for another name or version."""
    name, _, version = text.strip().partition("/")
    version = version.strip()
    if name.strip() != FORMAT_NAME or not (version.isascii() and version.isdigit() and len(version) <= 9):
        raise lines.error(f"the first line declares {shown(text.strip())}; expected {FORMAT_NAME}/N")
    if int(version) not in FORMATS:
        raise lines.error(
            f"{FORMAT_NAME}/{int(version)} is not a format this release reads "
            f"({', '.join(f'{FORMAT_NAME}/{v}' for v in FORMATS)}): update dimenet-runtime"
        )
    return int(version)


def _t_ns(text: str, lines: _Lines, line: int) -> int:
    """t_ns: an integer (ns) of magnitude at most MAX_T_NS (``text.t_ns_integer``)."""
    t_ns = t_ns_integer(text)
    if t_ns is None:
        raise lines.error(f"t_ns must be an integer of nanoseconds (|t_ns| <= 2**63 - 1), got {shown(text)}", line)
    return t_ns


def _csv_points(lines: _Lines) -> Iterator[tuple]:
    """(line, frame_id, t_ns text or None, [x, y, X, Y, Z] px and mm, [fx, fy, cx, cy] px or None) of every
    non-blank CSV row after the header (and the format's declaration before it)."""
    reader = csv.reader(lines)
    names: Optional[list[str]] = None
    start, version, k_of, declared = 1, 1, None, False
    try:
        for row in reader:
            line, start = start, lines.number + 1  # a quoted field may span lines: a row is named by its first line
            if not "".join(row).strip():
                continue
            if names is None and not declared and row[0].lstrip().startswith("#"):
                version, declared = _declared_format(",".join(row).lstrip()[1:], lines), True
                continue
            if names is None:
                names = [c.strip() for c in row]
                i_id, i_t, coords, scale = _columns(names, lines)
                coordinates = itemgetter(*coords)
                if version >= 2 and _k_names(names.__contains__, lines, "the header"):
                    k_of = itemgetter(*(names.index(n) for n in K_COLUMNS))
                continue
            if len(row) != len(names):
                raise lines.error(f"expected {len(names)} fields as the header has, got {len(row)}", line)
            values = _decimals(coordinates(row))
            if values is None:
                bad = next(i for i in coords if decimal(row[i]) is None)
                raise lines.error(f"{names[bad]} must be a number, got {shown(row[bad])}", line)
            if scale != 1.0:
                values[2:] = [v * scale for v in values[2:]]
            k = None
            if k_of is not None:
                k = _decimals(k_of(row))
                if k is None:
                    bad = next(n for n in K_COLUMNS if decimal(row[names.index(n)]) is None)
                    raise lines.error(f"{bad} must be a number, got {shown(row[names.index(bad)])}", line)
            yield line, row[i_id].strip(), None if i_t is None else row[i_t], values, k
    except csv.Error as exc:
        raise lines.error(f"not a readable CSV row ({exc})", start) from None
    if names is None:
        raise lines.error("no header: the file is empty", 1)


def _decimals(texts: tuple[str, ...]) -> Optional[list[float]]:
    """The floats of ``texts`` when each is a ``formats.text.decimal`` (else None): the same test,
    once over the fields joined, so a row reads as fast as with float() alone."""
    joined = "".join(texts)
    if not joined.isascii() or "_" in joined:
        return None
    try:
        return list(map(float, texts))
    except ValueError:
        return None


def _json_number(d: dict, key: str, lines: _Lines) -> float:
    value = d[key]
    if not is_number(value):
        raise lines.error(f"{key} must be a finite number, got {shown(value)}")
    return float(value)


def _json_point(d: Any, lines: _Lines, version: int) -> tuple:
    """One JSON Lines object -> (frame_id, t_ns, [x, y, X, Y, Z] px and mm, [fx, fy, cx, cy] px or None)."""
    if not isinstance(d, dict):
        raise lines.error(f"expected a JSON object (one point), got {shown(d)}")
    names, scale = _point_names(d.__contains__, lines, "a point")
    frame_id = d["frame_id"]
    if isinstance(frame_id, bool) or not isinstance(frame_id, (str, int)):
        raise lines.error(f"frame_id must be a string or an integer, got {shown(frame_id)}")
    t_ns = d.get("t_ns")
    if t_ns is not None and (isinstance(t_ns, bool) or not isinstance(t_ns, int) or abs(t_ns) > MAX_T_NS):
        raise lines.error(f"t_ns must be an integer of nanoseconds (|t_ns| <= 2**63 - 1) or null, got {shown(t_ns)}")
    values = [_json_number(d, n, lines) for n in names]
    values[2:] = [v * scale for v in values[2:]]
    k = (
        [_json_number(d, n, lines) for n in K_COLUMNS]
        if version >= 2 and _k_names(d.__contains__, lines, "a point")
        else None
    )
    return str(frame_id).strip(), t_ns, values, k


def _jsonl_points(lines: _Lines) -> Iterator[tuple]:
    """(line, frame_id, t_ns, [x, y, X, Y, Z] px and mm, [fx, fy, cx, cy] px or None) of every non-blank JSON
    line (after the format's declaration, an object with ``format`` and no ``frame_id``, when it is first)."""
    version, first = 1, True
    for text in lines:
        if text.strip():
            try:
                d = parse_json(text, max_chars=MAX_LINE_BYTES)
            except JsonProblem as exc:
                raise lines.error(f"not valid JSON ({exc.problem})") from None
            if first and isinstance(d, dict) and "format" in d and "frame_id" not in d:
                if not isinstance(d["format"], str):
                    raise lines.error(f"format must be a string, got {shown(d['format'])}")
                version, first = _declared_format(d["format"], lines), False
                continue
            first = False
            yield (lines.number, *_json_point(d, lines, version))


def _frame(frame_id: str, t_ns, values: list, line: int, bytes_read: int, k: Optional[list]) -> PointsFrame:
    a = np.array(values, dtype=np.float64).reshape(-1, 5)
    K_c = None if k is None else np.array([[k[0], 0.0, k[2]], [0.0, k[1], k[3]], [0.0, 0.0, 1.0]])
    return PointsFrame(frame_id, t_ns, a[:, :2].copy(), a[:, 2:].copy(), line, bytes_read, K_c)


def _frames(points: Iterable[tuple], lines: _Lines, t_as_text: bool) -> Iterator[PointsFrame]:
    """Group consecutive points of one frame_id into frames (checks: ids, t_ns, finiteness, size)."""
    seen = _SeenIds()
    frame_id, t_ns, values, first, t_text, k_first = None, None, [], 0, None, None
    for line, fid, t, xyz, k in points:
        if fid != frame_id:
            if frame_id is not None:
                yield _frame(frame_id, t_ns, values, first, lines.bytes_read, k_first)
            if not fid:
                raise lines.error("empty frame_id", line)
            if not seen.add(fid):
                raise lines.error(
                    f"frame_id {shown(fid)} reappears after other frames (the rows of a frame must be consecutive)",
                    line,
                )
            frame_id, values, first, t_text, k_first = fid, [], line, t, k
            t_ns = _t_ns(t, lines, line) if t_as_text and t is not None else t
            if k is not None and not all(map(isfinite, k)):
                raise lines.error(
                    f"fx_px, fy_px, cx_px, cy_px must be finite numbers, got {', '.join(map(repr, k))}", line
                )
        elif t != t_text and (not t_as_text or _t_ns(t, lines, line) != t_ns):
            raise lines.error(f"t_ns {shown(t)} differs from the frame's first row ({t_ns}, line {first})", line)
        elif k != k_first:
            raise lines.error(
                f"fx_px, fy_px, cx_px, cy_px ({'none' if k is None else ', '.join(map(repr, k))}) differ from the "
                f"frame's first row (line {first}): a frame has one K_c",
                line,
            )
        if len(values) == 5 * MAX_FRAME_POINTS:
            raise lines.error(f"frame {shown(fid)} has more than {MAX_FRAME_POINTS} points", line)
        if not isfinite(sum(xyz)) and not all(map(isfinite, xyz)):  # the sum: one test for most rows
            raise lines.error(f"coordinates must be finite numbers, got {', '.join(map(repr, xyz))}", line)
        values += xyz
    if frame_id is None:
        raise lines.error("no points in the file", lines.number or 1)
    yield _frame(frame_id, t_ns, values, first, lines.bytes_read, k_first)


def read_points(path: str | Path) -> Iterator[PointsFrame]:
    """The frames of a points file, one at a time, read as they are asked for (the file stays open
    until the generator ends or is closed). CSV or JSON Lines, told by the content: a first
    non-blank line starting with ``{`` is JSON Lines. Raises PointsError naming the file (and
    the line), also when it cannot be read."""
    path = Path(path)
    try:
        f = path.open("rb")
    except OSError as exc:
        raise _unreadable(path, exc) from None
    with f:
        lines = _Lines(f, path)
        if lines.is_json():
            yield from _frames(_jsonl_points(lines), lines, t_as_text=False)
        else:
            yield from _frames(_csv_points(lines), lines, t_as_text=True)


POINTS_COLUMNS = ("frame_id", "t_ns", "x_px", "y_px", "X_mm", "Y_mm", "Z_mm")


def write_points(path: str | Path, rows: Iterable[tuple], *, frame_k_c: bool = False) -> Path:
    """Write a points CSV of ``rows`` (frame_id, t_ns or None, x, y px, X, Y, Z mm), the rows of a frame
    consecutive, atomically (``formats.atomic``): format 1 (POINTS_COLUMNS), or with ``frame_k_c`` format 2, each
    row ending in its frame's K_c (fx, fy, cx, cy px: K_COLUMNS)."""
    text = io.StringIO()
    if frame_k_c:
        text.write(f"#{FORMAT_NAME}/2\n")
    text.write(",".join(POINTS_COLUMNS + (K_COLUMNS if frame_k_c else ())) + "\n")
    for fid, t, *values in rows:
        text.write(",".join([str(fid), "" if t is None else str(int(t)), *(repr(float(v)) for v in values)]) + "\n")
    return atomic_write(path, lambda f: f.write(text.getvalue().encode("utf-8")))

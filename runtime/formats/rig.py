"""Rig format ``dimenet-rig/1``: checkerboards placed in the rig frame {W} (mm).

Specified in ``models_spec/rig-v1.md``. A board's frame has its origin at the first inner
corner, x along ``inner_corners[0]``, y along ``inner_corners[1]`` and z = x × y; inner
corner (i, j) sits at (i·square_mm, j·square_mm, 0) and corners are ordered row by row
(j outer, i inner), as ``cv2.findChessboardCorners(img, (nx, ny))`` returns them. In {W}
a corner is R(rvec)·p + tvec_mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from dimenet.runtime.assets import asset
from dimenet.runtime.errors import RigError
from dimenet.runtime.formats.text import read_text
from dimenet.runtime.geometry import rvec_to_matrix
from dimenet.runtime.json_text import JsonProblem, is_number, parse_json, shown

FORMAT = "dimenet-rig/1"
UNITS = "mm"
_TOP_KEYS = ("format", "units", "boards")
_BOARD_KEYS = ("name", "inner_corners", "square_mm", "rvec", "tvec_mm")
_ARUCO_KEYS = ("dictionary", "first_id", "marker_mm")
PAPER_RIG_NAME = "paper"  # names the bundled paper rig on the command line (``--rig paper``)
MAX_RIG_BYTES = 1 << 20  # a rig file: 1 MiB of JSON (the paper rig is 735 bytes; ~200 bytes a board)
MAX_LENGTH_MM = 1e6  # square_mm, marker_mm, |tvec_mm| components: 1 km (more is a unit mistake, and safe to square)
MAX_ROTATION_RAD = 2 * math.pi  # |rvec|: every rotation has an axis-angle of at most pi
MAX_INNER_CORNERS = 1000  # per board side
MAX_RIG_POINTS = 100_000  # corners over all boards (P of every dataset ingested with the rig)


def _read_only(array: np.ndarray) -> np.ndarray:
    """``array``, made read-only: a rig's corners are computed once and shared."""
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class Aruco:
    """ArUco markers in the board's white squares (ChArUco style): ids from ``first_id``."""

    dictionary: str  # an OpenCV predefined dictionary name, e.g. "DICT_4X4_50"
    first_id: int
    marker_mm: float  # marker side, mm (< square_mm)


@dataclass(frozen=True)
class Board:
    """One planar checkerboard: its pattern and its pose board -> {W} (rvec rad, tvec mm)."""

    name: str
    inner_corners: tuple[int, int]  # (nx, ny) inner corners along board x and y
    square_mm: float
    rvec: tuple[float, float, float]
    tvec_mm: tuple[float, float, float]
    aruco: Optional[Aruco] = None

    @property
    def n_points(self) -> int:
        return self.inner_corners[0] * self.inner_corners[1]

    def local_points(self) -> np.ndarray:
        """(nx·ny, 3) inner corners in the board frame (mm), j outer, i inner."""
        nx, ny = self.inner_corners
        j, i = np.mgrid[0:ny, 0:nx]
        return np.stack([i.ravel() * self.square_mm, j.ravel() * self.square_mm, np.zeros(nx * ny)], axis=1)

    def rotation(self) -> np.ndarray:
        """(3, 3) rotation board -> {W} (read-only)."""
        return self._rotation

    def points(self) -> np.ndarray:
        """(nx·ny, 3) inner corners in {W} (mm; read-only)."""
        return self._points

    def normal(self) -> np.ndarray:
        """(3,) unit board z axis (x × y) in {W}; the printed side faces -normal."""
        return self._rotation[:, 2]

    @cached_property
    def _rotation(self) -> np.ndarray:  # computed once: detection asks for a board's corners tens of times a photo
        return _read_only(rvec_to_matrix(np.asarray(self.rvec, dtype=np.float64)))

    @cached_property
    def _points(self) -> np.ndarray:
        return _read_only(self.local_points() @ self._rotation.T + np.asarray(self.tvec_mm))


def charuco_board(board: Board) -> cv2.aruco.CharucoBoard:
    """OpenCV's ChArUco board for a rig board with ``aruco`` (corner ids = the rig's corner order)."""
    a = board.aruco
    nx, ny = board.inner_corners
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, a.dictionary))
    n_markers = (nx + 1) * (ny + 1) // 2
    return cv2.aruco.CharucoBoard(
        (nx + 1, ny + 1), board.square_mm, a.marker_mm, dictionary, np.arange(a.first_id, a.first_id + n_markers)
    )


@dataclass(frozen=True)
class Rig:
    """A set of boards in one rig frame {W} (mm)."""

    boards: tuple[Board, ...]

    @property
    def n_points(self) -> int:
        return sum(b.n_points for b in self.boards)

    def points(self) -> np.ndarray:
        """(P, 3) every board's inner corners in {W} (mm), board by board in rig order (read-only)."""
        return self._points

    @cached_property
    def _points(self) -> np.ndarray:
        return _read_only(np.concatenate([b.points() for b in self.boards]))

    @property
    def board_of_point(self) -> np.ndarray:
        """(P,) index into ``boards`` of each row of ``points()``."""
        return np.repeat(np.arange(len(self.boards)), [b.n_points for b in self.boards])


def _fail(field: str, problem: str) -> RigError:
    return RigError(f"{field}: {problem}")


def _check_keys(d: Any, required: tuple[str, ...], where: str, optional: tuple[str, ...] = ()) -> None:
    if not isinstance(d, dict):
        raise _fail(where.rstrip(".") or "rig", f"must be a JSON object, got {type(d).__name__}")
    missing = [k for k in required if k not in d]
    if missing:
        raise _fail(f"{where}{missing[0]}", "missing required field")
    unknown = sorted(set(d) - set(required) - set(optional))
    if unknown:
        raise _fail(f"{where}{unknown[0]}", f"unknown field (format {FORMAT} does not define it)")


def _number(value: Any, field: str, limit: float = MAX_LENGTH_MM) -> float:
    if not (is_number(value) or (type(value) is int)):  # an int too big for a float is still finite: range
        raise _fail(field, f"must be a finite number, got {shown(value)}")
    if abs(value) > limit:
        raise _fail(field, f"must be at most {limit:g} in magnitude, got {shown(value)}")
    return float(value)


def _vector3(value: Any, field: str) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise _fail(field, f"must be a list of 3 numbers, got {shown(value)}")
    x, y, z = (_number(v, f"{field}[{k}]") for k, v in enumerate(value))
    return x, y, z


def _rotation(value: Any, field: str) -> tuple[float, float, float]:
    rvec = _vector3(value, field)
    if math.hypot(*rvec) > MAX_ROTATION_RAD:
        raise _fail(field, f"must be an axis-angle of at most 2 pi rad, got |rvec| = {math.hypot(*rvec):g} rad")
    return rvec


def _aruco_from_dict(d: Any, where: str) -> Optional[Aruco]:
    if d is None:
        return None
    _check_keys(d, _ARUCO_KEYS, where)
    name = d["dictionary"]
    if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
        raise _fail(f"{where}dictionary", f"must name an OpenCV predefined ArUco dictionary, got {shown(name)}")
    first_id = d["first_id"]
    if isinstance(first_id, bool) or not isinstance(first_id, int) or first_id < 0:
        raise _fail(f"{where}first_id", f"must be an integer >= 0, got {shown(first_id)}")
    marker = _number(d["marker_mm"], f"{where}marker_mm")
    if marker <= 0:
        raise _fail(f"{where}marker_mm", f"must be > 0 mm, got {marker}")
    return Aruco(dictionary=name, first_id=first_id, marker_mm=marker)


def _board_from_dict(d: Any, where: str) -> Board:
    _check_keys(d, _BOARD_KEYS, where, optional=("aruco",))
    name = d["name"]
    if not isinstance(name, str) or not name.strip():
        raise _fail(f"{where}name", f"must be a non-empty string, got {shown(name)}")
    corners = d["inner_corners"]
    if (
        not isinstance(corners, (list, tuple))
        or len(corners) != 2
        or any(isinstance(c, bool) or not isinstance(c, int) or not 2 <= c <= MAX_INNER_CORNERS for c in corners)
    ):
        raise _fail(
            f"{where}inner_corners", f"must be 2 integers in [2, {MAX_INNER_CORNERS}] (nx, ny), got {shown(corners)}"
        )
    square = _number(d["square_mm"], f"{where}square_mm")
    if square <= 0:
        raise _fail(f"{where}square_mm", f"must be > 0 mm, got {square}")
    aruco = _aruco_from_dict(d.get("aruco"), f"{where}aruco.")
    if aruco is not None and aruco.marker_mm >= square:
        raise _fail(f"{where}aruco.marker_mm", f"must be smaller than square_mm ({square}), got {aruco.marker_mm}")
    if aruco is not None:
        n_markers = (corners[0] + 1) * (corners[1] + 1) // 2  # one per white square
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, aruco.dictionary)).bytesList.shape[0]
        if aruco.first_id + n_markers > size:
            raise _fail(
                f"{where}aruco.first_id",
                f"the board's {n_markers} markers from id {aruco.first_id} exceed {aruco.dictionary} "
                f"(ids 0-{size - 1})",
            )
    return Board(
        name=name,
        inner_corners=(int(corners[0]), int(corners[1])),
        square_mm=square,
        rvec=_rotation(d["rvec"], f"{where}rvec"),
        tvec_mm=_vector3(d["tvec_mm"], f"{where}tvec_mm"),
        aruco=aruco,
    )


def rig_from_dict(d: Any) -> Rig:
    """Validate a ``dimenet-rig/1`` mapping and build the Rig. Raises RigError naming the field."""
    _check_keys(d, _TOP_KEYS, "")
    if d["format"] != FORMAT:
        raise _fail("format", f"must be exactly {FORMAT!r}, got {shown(d['format'])}")
    if d["units"] != UNITS:
        raise _fail("units", f"must be {UNITS!r}, got {shown(d['units'])}")
    boards = d["boards"]
    if not isinstance(boards, list) or not boards:
        raise _fail("boards", "must be a non-empty list of boards")
    built = tuple(_board_from_dict(b, f"boards[{k}].") for k, b in enumerate(boards))
    if sum(b.n_points for b in built) > MAX_RIG_POINTS:
        raise _fail("boards", f"{sum(b.n_points for b in built)} corners in all; a rig has at most {MAX_RIG_POINTS}")
    names = [b.name for b in built]
    for k, name in enumerate(names):
        if name in names[:k]:
            raise _fail(f"boards[{k}].name", f"duplicate board name {name!r}")
    return Rig(boards=built)


def rig_to_dict(rig: Rig) -> dict:
    """The ``dimenet-rig/1`` mapping of a Rig (JSON-serialisable)."""

    def aruco(a: Optional[Aruco]) -> Optional[dict]:
        return None if a is None else {"dictionary": a.dictionary, "first_id": a.first_id, "marker_mm": a.marker_mm}

    return {
        "format": FORMAT,
        "units": UNITS,
        "boards": [
            {
                "name": b.name,
                "inner_corners": list(b.inner_corners),
                "square_mm": b.square_mm,
                "rvec": list(b.rvec),
                "tvec_mm": list(b.tvec_mm),
                "aruco": aruco(b.aruco),
            }
            for b in rig.boards
        ],
    }


def _parse_json(text: str, source: str) -> Rig:
    try:
        d = parse_json(text, max_chars=MAX_RIG_BYTES)
    except JsonProblem as exc:
        raise RigError(f"{source}: not valid JSON ({exc})" if exc.line else f"{source}: {exc.problem}") from None
    return rig_from_dict(d)


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig JSON file (UTF-8, a BOM ignored, at most ``MAX_RIG_BYTES``).

    Raises RigError (the message starts with the path).
    """
    path = Path(path)
    text = read_text(path, MAX_RIG_BYTES, "rig file", RigError)
    try:
        return _parse_json(text, str(path))
    except RigError as exc:
        message = str(exc)
        raise RigError(message if message.startswith(str(path)) else f"{path}: {message}") from None


def paper_rig() -> Rig:
    """The paper's rig (Sec. IV-D): four 10x8-inner-corner, 22 mm boards on four planes."""
    text = asset("paper_rig.json").read_text(encoding="utf-8")
    return _parse_json(text, "paper_rig.json")


def rig_from_argument(text: str) -> Rig:
    """A command line's ``--rig``: ``paper`` for the bundled paper rig, else a rig file's path."""
    return paper_rig() if text == PAPER_RIG_NAME else load_rig(text)

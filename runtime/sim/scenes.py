"""Random rigs, framed at random distances: the scene half of a family, so that a network trained across cameras
does not learn the paper's one rig and framing (models_spec/simulator.md, "Scene family").

``random_rig`` draws a calibration rig from a seeded generator: 2 to 6 plain boards of one square size
(10-40 mm) and 5-15 squares per side each, laid out side by side with gaps, each tilted 0-60 degrees
about a random in-plane axis and set forward or back, so the rig spans 3D (its first two boards at
least MIN_PLANE_ANGLE_DEG apart, its corners spanning 3D: K* observable from a rig photo). ``framed`` sets a camera's
distances so the rig fills between FILL[0] and FILL[1] of the image's width (from a fifth of the frame to
most of it), and aims within a tenth of the rig's extent of its centre. ``build_errors_mm`` is how the rig
as built departs from its file: sheets that sag and boards placed slightly off, which a camera sees and the
rig's 3D points do not hold (the real rig's 1.9 px residual).

Frames: {W} the rig frame (mm); the camera looks along +z of {W}, so a board's printed side faces -z
(its normal +z before its tilt).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from dimenet.runtime.errors import InputError, RigError
from dimenet.runtime.formats.rig import Board, Rig
from dimenet.runtime.geometry import RIG_VIEW_RATIO, matrix_to_rvec, rvec_to_matrix, spans_3d
from dimenet.runtime.sim.profiles import DeviceProfile

BOARDS = (2, 6)  # boards per rig, uniform
SQUARES = (5, 15)  # squares per board side, uniform (inner corners: one fewer)
SQUARE_MM = (10.0, 40.0)  # square size of the rig's boards, uniform
TILT_DEG = (0.0, 60.0)  # each board's tilt off facing the camera, uniform, about a random in-plane axis
MIN_PLANE_ANGLE_DEG = 20.0  # the first two boards' normals at least this far apart (the rig spans 3D)
GAP_SQUARES = (1.0, 3.0)  # white gap between neighbouring boards' patterns, in squares, uniform
DEPTH_SPREAD = 0.3  # each board set forward or back by up to this fraction of the largest board's side
FILL = (0.2, 0.8)  # the rig's extent over the image width that the camera's distances span
AIM_FRACTION = 0.1  # aim jitter as a fraction of the rig's extent
MAX_DRAWS = 1000  # draws of one rig before giving up
SAG_MM = 3.0  # a printed sheet bends, peak off flat U(0, this) mm either way, along one of its axes
PLACEMENT_DEG = 0.2  # each board sits turned off its nominal pose by N(0, this) deg about a random axis ...
PLACEMENT_MM = 0.5  # ... and moved by N(0, this) mm per axis


def _tilt(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) board -> {W}: facing the camera (normal +z), tilted by TILT_DEG about a random in-plane axis."""
    angle = math.radians(rng.uniform(*TILT_DEG))
    azimuth = rng.uniform(0.0, 2.0 * math.pi)
    spin = rvec_to_matrix(np.array([0.0, 0.0, rng.uniform(-math.pi, math.pi)]))
    return rvec_to_matrix(angle * np.array([math.cos(azimuth), math.sin(azimuth), 0.0])) @ spin


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (degrees) between two boards' normals."""
    return math.degrees(math.acos(float(np.clip(Ra[:, 2] @ Rb[:, 2], -1.0, 1.0))))


def random_rig(rng: np.random.Generator) -> Rig:
    """A random multi-plane rig (see the module doc), deterministic per generator state: drawn again until its
    corners span 3D (``spans_3d`` at RIG_VIEW_RATIO, as a rig photo must; 8 % of first draws do not, a wide rig
    of nearly facing boards)."""
    for _ in range(MAX_DRAWS):
        rig = _draw_rig(rng)
        if spans_3d(rig.points(), RIG_VIEW_RATIO):
            return rig
    raise RigError(f"no random rig out of {MAX_DRAWS} draws spans 3D")  # never reached: 8 % fail one draw


def _draw_rig(rng: np.random.Generator) -> Rig:
    """One draw of ``random_rig``, whether or not it spans 3D."""
    n = int(rng.integers(BOARDS[0], BOARDS[1] + 1))
    square = float(rng.uniform(*SQUARE_MM))
    inner = [tuple(int(v) - 1 for v in rng.integers(SQUARES[0], SQUARES[1] + 1, 2)) for _ in range(n)]
    rotations = [_tilt(rng) for _ in range(n)]
    while _angle_deg(rotations[0], rotations[1]) < MIN_PLANE_ANGLE_DEG:
        rotations[1] = _tilt(rng)
    side_mm = [(nx + 1) * square for nx, _ in inner], [(ny + 1) * square for _, ny in inner]
    cell = max(max(side_mm[0]), max(side_mm[1])) + rng.uniform(*GAP_SQUARES) * square  # one board per cell
    columns = math.ceil(math.sqrt(n))
    boards = []
    for k, ((nx, ny), R) in enumerate(zip(inner, rotations)):
        row, col = divmod(k, columns)
        centre = np.array([col * cell, row * cell, rng.uniform(-DEPTH_SPREAD, DEPTH_SPREAD) * cell])
        centre_local = np.array([(nx - 1) * square / 2.0, (ny - 1) * square / 2.0, 0.0])  # the grid's middle
        tvec = centre - R @ centre_local
        boards.append(Board(f"b{k}", (nx, ny), square, tuple(matrix_to_rvec(R)), tuple(tvec)))
    return Rig(tuple(boards))


def extent_mm(rig: Rig) -> float:
    """The rig's largest extent across the view (mm): the larger side of its corners' x-y bounding box."""
    points = rig.points()
    return float(np.max(points[:, :2].max(0) - points[:, :2].min(0)))


def framed(profile: DeviceProfile, rig: Rig, fill: tuple = FILL) -> DeviceProfile:
    """The camera with its distances set so ``rig`` fills ``fill`` (low, high) of the image width, aim jitter
    AIM_FRACTION of its extent."""
    if not 0.0 < fill[0] < fill[1] <= 1.0:
        raise InputError(f"fill must be 0 < low < high <= 1 of the image width, got {fill!r}")
    width_px = profile.image_size_px[0]
    span_mm = extent_mm(rig)
    distance = [span_mm * profile.focal_px / (part * width_px) for part in fill[::-1]]
    return replace(profile, distance_mm=(distance[0], distance[1]), aim_jitter_mm=AIM_FRACTION * span_mm)


def build_errors_mm(rig: Rig, rng: np.random.Generator) -> np.ndarray:
    """(P, 3) mm in {W}: where each corner of the built rig lies off its nominal point, board by board: a cylindrical
    sag of peak U(-SAG_MM, SAG_MM) along the board's normal, across its x or y axis (zero at the edges of its
    grid), then the board turned by N(0, PLACEMENT_DEG) about a random axis through its grid's centre and moved by
    N(0, PLACEMENT_MM) per axis."""
    out = []
    for board in rig.boards:
        local = board.local_points()
        centre = local.mean(0)
        axis = int(rng.integers(2))
        half = max(float(np.ptp(local[:, axis])) / 2.0, 1e-9)
        sag = rng.uniform(-SAG_MM, SAG_MM) * (1.0 - ((local[:, axis] - centre[axis]) / half) ** 2)
        bent = local + sag[:, None] * np.array([0.0, 0.0, 1.0])
        direction = rng.normal(size=3)
        turn = rvec_to_matrix(math.radians(rng.normal(0.0, PLACEMENT_DEG)) * direction / np.linalg.norm(direction))
        placed = (bent - centre) @ turn.T + centre + rng.normal(0.0, PLACEMENT_MM, 3)
        R = board.rotation()
        out.append((placed - local) @ R.T)
    return np.concatenate(out)

"""The set-ups the simulator photographs, in {W} (mm): the rig's boards (``rig_scene``) and the paper's natural
test (``natural_scene``: two LEGO-like buildings beside a board), with their points' normals, groups and the opaque
surfaces that hide points (``occluded``). Random natural scenes (``sim.natural``) are built from the same parts."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dimenet.runtime.formats.rig import Board, Rig


@dataclass(frozen=True)
class Scene:
    """A photographed set-up in {W} (mm): points, their surface normals and groups, and opaque surfaces."""

    points: np.ndarray  # (N, 3) mm
    normals: np.ndarray  # (N, 3) unit normals towards the side the point is seen from
    group: np.ndarray  # (N,) int: board index, or -1 for natural (building) features
    surfaces: np.ndarray  # (M, 3, 3) mm: opaque rectangles as (corner, edge a, edge b)

    @property
    def centre(self) -> np.ndarray:
        """(3,) centre of the points' bounding box (mm): where the camera aims and focuses."""
        return (self.points.min(0) + self.points.max(0)) / 2.0


@dataclass(frozen=True)
class NaturalSet:
    """A natural scene as the simulator photographs it: ``scene`` (a board, group 0, and the labelled features,
    group -1), the labels' 2D noise ``label_sigma_px`` (std per axis), the features' 3D error ``model_sigma_mm``
    (std per axis), the fewest features a usable frame sees (``min_seen``), and the scene's kind."""

    scene: Scene
    label_sigma_px: float
    model_sigma_mm: float
    min_seen: int
    kind: str

    def view_ok(self, scene: Scene, seen: np.ndarray) -> bool:
        """Usable: the board seen whole and at least ``min_seen`` features."""
        return bool(seen[scene.group == 0].all()) and int(np.count_nonzero(seen[scene.group < 0])) >= self.min_seen


def board_surface(board: Board) -> np.ndarray:
    """(3, 3) the board's printed pattern, one square beyond the inner corners, as (corner, edge a, edge b)."""
    nx, ny = board.inner_corners
    s = board.square_mm
    R = board.rotation()
    corner = R @ np.array([-s, -s, 0.0]) + np.asarray(board.tvec_mm)
    return np.stack([corner, R[:, 0] * (nx + 1) * s, R[:, 1] * (ny + 1) * s])


def occluded(points_mm: np.ndarray, camera_mm: np.ndarray, surfaces: np.ndarray) -> np.ndarray:
    """(N,) whether the line of sight from the camera to each point crosses an opaque surface first.

    A point lying on a surface is not hidden by that surface (the crossing must be strictly before it).
    """
    corner, a, b = surfaces[:, 0], surfaces[:, 1], surfaces[:, 2]  # (M, 3)
    n = np.cross(a, b)
    ray = points_mm - camera_mm  # (N, 3)
    denom = ray @ n.T  # (N, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((corner - camera_mm) * n).sum(1) / denom
    hit = camera_mm + t[..., None] * ray[:, None, :] - corner  # (N, M, 3)
    u = (hit * a).sum(-1) / (a * a).sum(-1)
    v = (hit * b).sum(-1) / (b * b).sum(-1)
    inside = (t > 0) & (t < 1 - 1e-9) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    return inside.any(1)


def rig_scene(rig: Rig) -> Scene:
    """The rig's corners; a board is seen from its printed side, -normal."""
    normals = np.concatenate([np.tile(-b.normal(), (b.n_points, 1)) for b in rig.boards])
    return Scene(
        points=rig.points(),
        normals=normals,
        group=rig.board_of_point,
        surfaces=np.stack([board_surface(b) for b in rig.boards]),
    )


def _face(origin, u_axis, v_axis, st_mm) -> np.ndarray:
    """Face coordinates (s, t) mm along u and v from ``origin`` -> (N, 3) mm."""
    st = np.asarray(st_mm, dtype=np.float64)
    return np.asarray(origin, float) + st[:, :1] * np.asarray(u_axis, float) + st[:, 1:] * np.asarray(v_axis, float)


def _rect(s0, t0, width, height) -> list:
    """The 4 corners (s, t) of a rectangle on a face (window, door, facade)."""
    return [(s0, t0), (s0 + width, t0), (s0, t0 + height), (s0 + width, t0 + height)]


def box_surfaces(low_mm, high_mm) -> np.ndarray:
    """(6, 3, 3) the faces of the axis-aligned box [low, high] (mm) as (corner, edge a, edge b)."""
    low, size = np.asarray(low_mm, float), np.asarray(high_mm, float) - np.asarray(low_mm, float)
    faces = []
    for axis in range(3):
        a, b = np.eye(3)[[(axis + 1) % 3, (axis + 2) % 3]] * size[[(axis + 1) % 3, (axis + 2) % 3], None]
        for at in (0.0, size[axis]):
            faces.append([low + np.eye(3)[axis] * at, a, b])
    return np.array(faces)


def buildings() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two LEGO-like buildings: labelled features (47 left + 19 right) in {W} (mm), their normals,
    and the boxes' faces (opaque surfaces).

    Boxes stand on a table (y = 130 mm) left and right of the middle board, in line with it
    (board plane z = 0): the left one x in [-300, -160], 210 mm tall, z in [-50, 50]; the right
    one x in [160, 260], 120 mm tall, z in [-30, 50]. Features are facade, window and door
    corners on the front face (towards -z) and on the side facing the middle board.
    """
    ex, ey, ez = np.eye(3)
    # Left building: front face 140 x 210 mm, inner (right) side face 100 mm deep.
    front = [
        *_rect(0, 0, 140, 210),
        *(c for s in (20, 90) for t in (20, 70, 120) for c in _rect(s, t, 30, 30)),
        *_rect(55, 160, 30, 50),
        (70, 8),
    ]
    side = [(100, 0), (100, 210), *(c for t in (20, 70, 120) for c in _rect(35, t, 30, 30))]
    left = [(_face((-300, -80, -50), ex, ey, front), -ez), (_face((-160, -80, -50), ez, ey, side), ex)]
    # Right building: front face 100 x 120 mm, inner (left) side face 80 mm deep.
    front = [*_rect(0, 0, 100, 120), *_rect(12, 15, 30, 30), *_rect(58, 15, 30, 30), *_rect(35, 70, 30, 50)]
    side = [(80, 0), (80, 120), (40, 40)]
    right = [(_face((160, 10, -30), ex, ey, front), -ez), (_face((160, 10, -30), ez, ey, side), -ex)]
    parts = left + right
    points = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([np.tile(n, (len(p), 1)) for p, n in parts])
    surfaces = np.concatenate(
        [box_surfaces((-300, -80, -50), (-160, 130, 50)), box_surfaces((160, 10, -30), (260, 130, 50))]
    )
    return points, normals, surfaces


def facing_board(board: Board, z_mm: float = 0.0) -> Board:
    """``board`` facing the camera (no turn), its inner corners centred on (0, 0, z_mm) in {W}."""
    half = (np.asarray(board.inner_corners) - 1) * board.square_mm / 2.0
    return replace(board, rvec=(0.0, 0.0, 0.0), tvec_mm=(-float(half[0]), -float(half[1]), z_mm))


def board_and_features(board: Board, features: np.ndarray, normals: np.ndarray, boxes: np.ndarray) -> Scene:
    """A natural set-up: ``board``'s corners (group 0, seen from its printed side) and labelled features (N, 3) mm
    (group -1) with their normals; opaque: the board's pattern and ``boxes`` (M, 3, 3)."""
    return Scene(
        points=np.concatenate([board.points(), features]),
        normals=np.concatenate([np.tile(-board.normal(), (board.n_points, 1)), normals]),
        group=np.r_[np.zeros(board.n_points, np.int64), np.full(len(features), -1)],
        surfaces=np.concatenate([board_surface(board)[None], boxes]),
    )


def natural_scene(board: Board) -> Scene:
    """The LEGO test set-up: ``board``'s pattern facing the camera at the origin, buildings beside it."""
    return board_and_features(facing_board(board), *buildings())

"""Random natural scenes: labelled features of a room, a street of buildings or objects on a table, around one
printed board, for the natural test frames of a random-scene family (models_spec/simulator.md, "Scene family").

The paper's natural test is one scene (``scene_geometry.natural_scene``: two LEGO buildings beside a board, 66 labels
with 4.9 px noise). A model that must hold on any scene is checked on many: ``random_natural`` draws one of
NATURAL_KINDS at the size of the camera's rig (so the camera's distances frame it as they frame the rig), with
NATURAL_POINTS labelled features (log-uniform), a hand-labelling noise of LABEL_NOISE_PX and a 3D error (a scan or
a CAD model placed by hand) of MODEL_ERROR of its extent. The board (the rig's first, facing the camera at the
scene's centre) is seen whole in every frame: its corners are where the frame's errors are measured, as the
paper's LEGO board is; only the features are inference points.

Frames: {W} (mm) with the camera looking along +z and y pointing down: a floor is a plane of constant y below the
board, facing -y.
"""

from __future__ import annotations

import math

import numpy as np

from dimenet.runtime.formats.rig import Board
from dimenet.runtime.sim.scene_geometry import NaturalSet, board_and_features, board_surface, box_surfaces, facing_board

NATURAL_KINDS = ("room", "buildings", "objects")
NATURAL_POINTS = (16, 600)  # labelled features per scene, log-uniform
LABEL_NOISE_PX = (0.3, 5.0)  # the labels' 2D noise, std per image axis, uniform per scene
MODEL_ERROR = (0.001, 0.005)  # the features' 3D error, std per axis as a fraction of the scene's extent, uniform
MIN_SEEN = (12, 0.4)  # a frame is usable with at least this many of its features seen, and this share


def _on_face(origin, a, b, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) mm: points uniform on the parallelogram origin + s a + t b, s, t in [0, 1]."""
    st = rng.uniform(0.0, 1.0, (n, 2))
    return np.asarray(origin, float) + st[:, :1] * np.asarray(a, float) + st[:, 1:] * np.asarray(b, float)


def _faces_points(faces: list, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n points spread over ``faces`` [(corner, edge a, edge b, outward normal)] by area: (n, 3) mm and normals."""
    area = np.array([np.linalg.norm(np.cross(a, b)) for _, a, b, _ in faces])
    counts = rng.multinomial(n, area / area.sum())
    points = [_on_face(c, a, b, k, rng) for (c, a, b, _), k in zip(faces, counts)]
    normals = [np.tile(np.asarray(nrm, float), (k, 1)) for (_, _, _, nrm), k in zip(faces, counts)]
    return np.concatenate(points), np.concatenate(normals)


def _box(low, high) -> tuple[list, np.ndarray]:
    """The box [low, high] (mm): the faces a camera in front of it and above its base can see, as (corner, edge a,
    edge b, outward normal) (its front (-z), top (-y) and two sides; features are labelled there), and all six
    as opaque surfaces (``box_surfaces``)."""
    surfaces = box_surfaces(low, high)
    sides = ((0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1))  # box_surfaces' order
    faces = [
        (corner, a, b, np.eye(3)[axis] * side)
        for (corner, a, b), (axis, side) in zip(surfaces, sides)
        if (axis, side) not in ((1, 1), (2, 1))
    ]
    return faces, surfaces


def _room(extent: float, clear: float, rng: np.random.Generator) -> tuple[list, np.ndarray]:
    """A room's corner: back wall, floor, a side wall and a table behind the board (faces to scatter features on,
    opaque boxes)."""
    half, depth, floor = extent / 2.0, extent * rng.uniform(0.6, 1.2), extent * rng.uniform(0.3, 0.45)
    back, near = depth / 2.0, -depth / 2.0
    side = -half if rng.random() < 0.5 else half
    faces = [
        ((-half, -floor, back), (2 * half, 0, 0), (0, 2 * floor, 0), (0, 0, -1.0)),  # back wall
        ((-half, floor, near), (2 * half, 0, 0), (0, 0, depth), (0, -1.0, 0)),  # floor
        ((side, -floor, near), (0, 0, depth), (0, 2 * floor, 0), (-math.copysign(1.0, side), 0, 0)),  # side wall
    ]
    size = extent * rng.uniform(0.2, 0.35, 3) * (1.0, 0.5, 1.0)
    low = np.array([rng.uniform(-half, half - size[0]), floor - size[1], rng.uniform(0.0, back - size[2])])
    seen, surfaces = _box(low, low + size)
    return faces + seen, surfaces


def _buildings(extent: float, clear: float, rng: np.random.Generator) -> tuple[list, np.ndarray]:
    """2-4 buildings side by side behind the board, each set back by its own distance: their faces and boxes."""
    n = int(rng.integers(2, 5))
    ground = extent * rng.uniform(0.3, 0.45)
    widths = rng.uniform(0.5, 1.0, n)
    widths *= extent / widths.sum()
    x = -extent / 2.0
    faces, boxes = [], []
    for w in widths:
        height, deep = extent * rng.uniform(0.3, 0.8), extent * rng.uniform(0.15, 0.4)
        low = np.array([x + 0.05 * w, ground - height, rng.uniform(0.0, 0.3) * extent])
        high = low + (0.9 * w, height, deep)
        seen, surfaces = _box(low, high)
        faces += seen
        boxes.append(surfaces)
        x += w
    return faces, np.concatenate(boxes)


def _objects(extent: float, clear: float, rng: np.random.Generator) -> tuple[list, np.ndarray]:
    """1-3 boxes on a table top, left or right of the board and clear of it (``clear`` mm from its centre line):
    their faces, the table's, and the boxes."""
    table = extent * rng.uniform(0.2, 0.4)
    faces = [((-extent / 2.0, table, -extent * 0.5), (extent, 0, 0), (0, 0, extent * 0.6), (0, -1.0, 0))]
    boxes = []
    for _ in range(int(rng.integers(1, 4))):
        size = extent * rng.uniform(0.1, 0.3, 3)
        x = rng.uniform(clear, max(clear, extent / 2.0 - size[0]))
        low = np.array([x if rng.random() < 0.5 else -x - size[0], table - size[1], -extent * rng.uniform(0.1, 0.45)])
        seen, surfaces = _box(low, low + size)
        faces += seen
        boxes.append(surfaces)
    return faces, np.concatenate(boxes)


_KINDS = {"room": _room, "buildings": _buildings, "objects": _objects}


def random_natural(board: Board, extent_mm: float, rng: np.random.Generator) -> NaturalSet:
    """A random natural scene of ``extent_mm`` across the view around ``board`` (facing the camera at the origin),
    deterministic per generator state (see the module doc)."""
    kind = NATURAL_KINDS[int(rng.integers(len(NATURAL_KINDS)))]
    clear = (board.inner_corners[0] + 1) * board.square_mm / 2.0
    faces, boxes = _KINDS[kind](extent_mm, clear, rng)
    n = int(round(math.exp(rng.uniform(*np.log(NATURAL_POINTS)))))
    features, normals = _faces_points(faces, n, rng)
    middle = facing_board(board, -extent_mm * 0.05)
    # Features the board covers are not there to label: keep those off its pattern.
    corner, a, b = board_surface(middle)
    uv = np.linalg.lstsq(np.stack([a, b], 1), (features - corner).T, rcond=None)[0].T
    hidden = np.all((uv >= 0) & (uv <= 1), 1) & (features[:, 2] > middle.tvec_mm[2])
    features, normals = features[~hidden], normals[~hidden]
    return NaturalSet(
        scene=board_and_features(middle, features, normals, boxes),
        label_sigma_px=float(rng.uniform(*LABEL_NOISE_PX)),
        model_sigma_mm=float(rng.uniform(*MODEL_ERROR) * extent_mm),
        min_seen=max(MIN_SEEN[0], int(math.ceil(MIN_SEEN[1] * len(features)))),
        kind=kind,
    )

"""Photo renderer for ingestion tests: hand-held photos of the rig through the simulator's OIS camera.

Each photo is the simulator's hand-held shot (``simulator.shoot``: OIS principal-point shift, focus
breathing, pose, visibility rule), optionally held upside down, then drawn:

- background clutter (a smooth colour field, random shapes and lines; ``drawing`` draws);
- every board facing the camera, far to near: its printed pattern (plain checkerboard, or the
  OpenCV ChArUco image when the board has ``aruco``) on white paper with a half-square margin,
  mapped onto its plane by the exact homography K·[r1 r2 t] with ``cv2.warpPerspective`` into a
  4x supersampled patch, then box-filtered (``INTER_AREA``) to the native pixels (anti-aliased
  edges whose 50 % level sits exactly on the true edge);
- optionally an occluding rectangle over part of one board ("covered" photos);
- optionally lens distortion (OpenCV's model about the profile's nominal K, as the simulator's):
  the pinhole picture is drawn on a canvas large enough for every pixel's undistorted source and
  warped through the lens (``LensWarp``); the truth's corners are then the distorted pixels;
- vignetting, optical blur (Gaussian), sensor noise (read + shot) and JPEG/PNG encoding.

Pixels are x right, y down, origin at the centre of the top-left pixel (as in ``geometry``);
3D in mm in the rig frame {W}. The truth (``truth.npz``, see models_spec/ingest.md) holds per photo
the true K (px), the pose {W}->{C}, every rig corner's true pixel and whether its board is seen.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from dimenet.runtime import __version__
from dimenet.runtime.errors import InputError, RigError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.rig import Board, Rig, rig_to_dict
from dimenet.runtime.geometry import (
    RIG_VIEW_RATIO,
    camera_centre,
    facing,
    matrix_to_rvec,
    project,
    rvec_to_matrix,
    spans_3d,
    to_camera,
    undistort_points,
)
from dimenet.runtime.sim.drawing import clutter, draw_board, paper_rect_mm, sensor
from dimenet.runtime.sim.profiles import DeviceProfile
from dimenet.runtime.sim.scene_geometry import Scene, rig_scene
from dimenet.runtime.sim.simulator import MAX_POSE_ATTEMPTS, lens_image, rig_view_ok, sample_pose, shoot

GENERATOR = "dimenet.render"
TRUTH_FILE = "truth.npz"
FORMATS = ("jpg", "png")
VARIANT_CYCLE = 5  # of every 5 photos, the 2nd is taken upside down and the 4th has a board covered
# The lens's warp is undistorted exactly every LENS_MAP_STEP px and bilinear between: the
# displacement's curvature leaves < 1e-3 px (k1 = -0.11 at 12 MP: 1.8e-4 px/px^2 x 4^2 / 8).
LENS_MAP_STEP = 4


@dataclass(frozen=True)
class Shot:
    """One photo's truth: K (3, 3) px, pose {W}->{C} (rvec rad, tvec mm), every rig corner's true pixel
    (P, 2) and whether it is seen (P,): its board lies wholly in the image, faces the camera, is hidden
    by no other board and is not touched by the occluder."""

    K: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    corners_px: np.ndarray
    seen: np.ndarray
    upside_down: bool
    covered_board: int  # index of the board under the occluder, -1 for none
    cover_px: Optional[tuple[int, int, int, int]]  # occluder x0, y0, x1, y1 (px, inclusive), or None


@dataclass(frozen=True)
class LensWarp:
    """A lens (``dist_coeffs`` about the profile's nominal K) and where each pixel of the distorted
    photo comes from on the pinhole canvas: map_x, map_y (h, w) float32 px on a canvas of
    canvas_size (width, height) px that extends the image by margin (left, top) px, so the canvas's
    K is the pinhole K shifted by the margin."""

    dist_coeffs: np.ndarray
    map_x: np.ndarray
    map_y: np.ndarray
    margin: tuple[int, int]
    canvas_size: tuple[int, int]


def _bilinear_upsample(coarse: np.ndarray, step: int, size: tuple[int, int]) -> np.ndarray:
    """(gh, gw) samples every ``step`` px -> (h, w) bilinear between them, exact weights."""
    w, h = size
    x, y = np.arange(w), np.arange(h)
    ix, fx = x // step, (x % step) / step
    iy, fy = y // step, (y % step) / step
    rows = coarse[:, ix] * (1.0 - fx) + coarse[:, ix + 1] * fx
    return rows[iy] * (1.0 - fy)[:, None] + rows[iy + 1] * fy[:, None]


def lens_warp(profile: DeviceProfile, dist_coeffs: np.ndarray) -> LensWarp:
    """The warp of the profile's image through the lens (``dist_coeffs`` about its nominal K)."""
    w, h = profile.image_size_px
    s = LENS_MAP_STEP
    grid = np.stack(np.meshgrid(np.arange(0, w + s, s, dtype=np.float64), np.arange(0, h + s, s, dtype=np.float64)), -1)
    source = undistort_points(grid, profile.nominal_K, dist_coeffs)
    maps = [_bilinear_upsample(source[..., c], s, (w, h)) for c in (0, 1)]
    lo = np.floor(np.minimum([m.min() for m in maps], 0.0)).astype(int) - 2
    hi = np.ceil(np.maximum([m.max() for m in maps], [w - 1, h - 1])).astype(int) + 2
    margin = (int(-lo[0]), int(-lo[1]))
    return LensWarp(
        dist_coeffs=np.asarray(dist_coeffs, np.float64),
        map_x=(maps[0] + margin[0]).astype(np.float32),
        map_y=(maps[1] + margin[1]).astype(np.float32),
        margin=margin,
        canvas_size=(int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)),
    )


def scaled_profile(profile: DeviceProfile, factor: float) -> DeviceProfile:
    """The same camera with ``factor`` times fewer pixels per side (pitch x factor): same field of view.

    For fast tests: the image size is rounded to whole pixels; the optical-centre offset scales too.
    """
    if not factor >= 1.0:
        raise InputError(f"scale factor must be >= 1, got {factor}")
    w, h = profile.image_size_px
    return replace(
        profile,
        image_size_px=(round(w / factor), round(h / factor)),
        pixel_pitch_um=profile.pixel_pitch_um * factor,
        centre_offset_px=tuple(c / factor for c in profile.centre_offset_px),
    )


def paper_corners_mm(board: Board) -> np.ndarray:
    """(4, 3) the paper's corners in {W} (mm)."""
    x0, y0, x1, y1 = paper_rect_mm(board)
    local = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return local @ board.rotation().T + np.asarray(board.tvec_mm)


def paper_scene(rig: Rig) -> Scene:
    """The rig's corners with each board's whole paper (pattern + margin) as its opaque surface."""

    def surface(board: Board) -> np.ndarray:
        c = paper_corners_mm(board)
        return np.stack([c[0], c[1] - c[0], c[3] - c[0]])

    return replace(rig_scene(rig), surfaces=np.stack([surface(b) for b in rig.boards]))


def upside_down_pose(profile: DeviceProfile, centre_mm: np.ndarray, rng: np.random.Generator):
    """``simulator.sample_pose`` rolled 180° about the optical axis: the phone held upside down."""
    rvec, tvec = sample_pose(profile, centre_mm, rng)
    flip = np.diag([-1.0, -1.0, 1.0])
    return matrix_to_rvec(flip @ rvec_to_matrix(rvec)), flip @ tvec


def board_count(rig: Rig, seen: np.ndarray) -> int:
    return len(np.unique(rig.board_of_point[seen]))


def cover_rect(
    paper_px: np.ndarray, image_size: tuple[int, int], rng: np.random.Generator
) -> tuple[int, int, int, int]:
    """An occluder (x0, y0, x1, y1 px, inclusive) hiding 40-100 % of a board's paper from one side."""
    w, h = image_size
    lo, hi = paper_px.min(0) - 5.0, paper_px.max(0) + 5.0
    side = int(rng.integers(4))
    cut = lo + rng.uniform(0.4, 1.0) * (hi - lo) if side < 2 else hi - rng.uniform(0.4, 1.0) * (hi - lo)
    x0, y0, x1, y1 = lo[0], lo[1], hi[0], hi[1]
    if side == 0:
        x1 = cut[0]
    elif side == 1:
        y1 = cut[1]
    elif side == 2:
        x0 = cut[0]
    else:
        y0 = cut[1]
    return (
        int(np.clip(np.floor(x0), 0, w - 1)),
        int(np.clip(np.floor(y0), 0, h - 1)),
        int(np.clip(np.ceil(x1), 0, w - 1)),
        int(np.clip(np.ceil(y1), 0, h - 1)),
    )


def pattern_quad_px(board: Board, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(4, 2) the printed pattern's outer corners (one square beyond the inner corners) in px."""
    nx, ny = board.inner_corners
    s = board.square_mm
    local = np.array([[-s, -s, 0.0], [nx * s, -s, 0.0], [nx * s, ny * s, 0.0], [-s, ny * s, 0.0]])
    return project(local @ board.rotation().T + np.asarray(board.tvec_mm), K, rvec, tvec)


def covered_boards(
    rig: Rig, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, rect: tuple[int, int, int, int]
) -> np.ndarray:
    """(P,) whether each corner's board has its printed pattern touched by the occluder (board lost)."""
    x0, y0, x1, y1 = rect
    box = np.array([[x0, y0], [x1 + 1, y0], [x1 + 1, y1 + 1], [x0, y1 + 1]], np.float32)
    hit = [
        cv2.intersectConvexConvex(pattern_quad_px(b, K, rvec, tvec).astype(np.float32), box)[0] > 0 for b in rig.boards
    ]
    return np.asarray(hit)[rig.board_of_point]


def view_rule(rig: Rig, min_boards: int) -> Callable[[Scene, np.ndarray], bool]:
    """When a shot's view is usable: a one-board rig's board seen whole (a planar view: one printed
    checkerboard photographed from many views); else the simulator's rig view (``rig_view_ok``: >= 2
    boards spanning 3D) with at least ``min_boards`` boards seen."""
    if len(rig.boards) == 1:
        return lambda scene, seen: board_count(rig, seen) == 1
    return lambda scene, seen: rig_view_ok(scene, seen) and board_count(rig, seen) >= min_boards


def plan_shot(
    rig: Rig,
    profile: DeviceProfile,
    rng: np.random.Generator,
    *,
    upside_down: bool,
    covered: bool,
    dist_coeffs: Optional[np.ndarray] = None,
) -> Shot:
    """Pose, K and truth of one photo: the simulator's hand-held shot (``simulator.shoot``) of the rig's papers,
    through the lens ``dist_coeffs`` (about the nominal K) when given: its corners are then the distorted pixels.

    A covered photo (of a rig of >= 3 boards; on a smaller rig it is not covered) puts an occluder over
    part of one of >= 3 boards seen; every board whose printed pattern the occluder touches is lost; the
    photo keeps >= 2 boards seen, spanning 3D.
    """
    scene = paper_scene(rig)
    covered = covered and len(rig.boards) >= 3
    usable = view_rule(rig, 3 if covered else 2)
    pose = upside_down_pose if upside_down else sample_pose
    for _ in range(MAX_POSE_ATTEMPTS):
        K, rvec, tvec, px, seen = shoot(scene, profile, rng, usable, pose, dist_coeffs)
        if dist_coeffs is not None:
            px = lens_image(px, profile, dist_coeffs)[0]
        if not covered:
            return Shot(K, rvec, tvec, px, seen, upside_down, -1, None)
        board = int(rng.choice(np.unique(rig.board_of_point[seen])))
        paper_px = project(paper_corners_mm(rig.boards[board]), K, rvec, tvec)
        rect = cover_rect(paper_px, profile.image_size_px, rng)
        kept = seen & ~covered_boards(rig, K, rvec, tvec, rect)
        if board_count(rig, kept) >= 2 and spans_3d(rig.points()[kept], RIG_VIEW_RATIO):
            return Shot(K, rvec, tvec, px, kept, upside_down, board, rect)
    raise RigError(f"no covered view out of {MAX_POSE_ATTEMPTS} keeps 2 whole boards with profile {profile.name!r}")


def render_photo(
    rig: Rig,
    profile: DeviceProfile,
    rng: np.random.Generator,
    *,
    upside_down: bool = False,
    covered: bool = False,
    lens: Optional[LensWarp] = None,
) -> tuple[np.ndarray, Shot]:
    """One photo (h, w, 3) uint8 BGR and its truth, through ``lens`` when given."""
    dist = None if lens is None else lens.dist_coeffs
    shot = plan_shot(rig, profile, rng, upside_down=upside_down, covered=covered, dist_coeffs=dist)
    size, (mx, my) = (profile.image_size_px, (0, 0)) if lens is None else (lens.canvas_size, lens.margin)
    K = shot.K + np.array([[0.0, 0.0, mx], [0.0, 0.0, my], [0.0, 0.0, 0.0]])  # the canvas's pinhole K
    canvas = clutter(size, rng)
    zbuf = np.zeros(canvas.shape[:2], np.float32)
    centres = np.array([b.points().mean(0) for b in rig.boards])
    depth = to_camera(centres, shot.rvec, shot.tvec)[:, 2]
    front = facing(centres, -np.array([b.normal() for b in rig.boards]), camera_centre(shot.rvec, shot.tvec))
    for b in np.argsort(depth)[::-1]:
        board = rig.boards[b]
        if depth[b] <= 0 or not front[b]:
            continue  # behind the camera, or seen from the back: not drawn
        white = float(rng.uniform(170, 235))
        draw_board(canvas, zbuf, board, K, shot.rvec, shot.tvec, white, white * float(rng.uniform(0.08, 0.18)))
    if shot.cover_px is not None:
        x0, y0, x1, y1 = shot.cover_px
        canvas[my + y0 : my + y1 + 1, mx + x0 : mx + x1 + 1] = rng.uniform(30, 220, 3).astype(np.float32)
    canvas *= rng.uniform(0.93, 1.07, 3).astype(np.float32)  # white balance
    if lens is not None:
        canvas = cv2.remap(canvas, lens.map_x, lens.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return sensor(canvas, rng), shot


def photo_variant(k: int) -> tuple[bool, bool]:
    """Whether photo k is upside down (k % VARIANT_CYCLE == 1) and has a board covered (k % VARIANT_CYCLE == 3)."""
    return k % VARIANT_CYCLE == 1, k % VARIANT_CYCLE == 3


def render_photos(
    rig: Rig, profile: DeviceProfile, n: int, *, seed: int = 0, dist_coeffs: Optional[np.ndarray] = None
) -> Iterator[tuple[np.ndarray, Shot]]:
    """``n`` photos (through the lens ``dist_coeffs`` about the nominal K, when given); photo k draws
    from its own generator (seed, k), so any subset re-renders identically."""
    lens = None if dist_coeffs is None else lens_warp(profile, dist_coeffs)
    for k in range(n):
        upside_down, covered = photo_variant(k)
        rng = np.random.default_rng([seed, k])
        yield render_photo(rig, profile, rng, upside_down=upside_down, covered=covered, lens=lens)


def encode(img: np.ndarray, fmt: str) -> bytes:
    """JPEG (quality 92) or PNG bytes of a BGR image."""
    params = [cv2.IMWRITE_JPEG_QUALITY, 92] if fmt == "jpg" else []
    ok, buf = cv2.imencode(f".{fmt}", img, params)
    if not ok:
        raise InputError(f"OpenCV cannot encode {fmt} images")
    return buf.tobytes()


def truth_arrays(
    rig: Rig,
    profile: DeviceProfile,
    seed: int,
    files: list[str],
    shots: list[Shot],
    dist_coeffs: Optional[np.ndarray] = None,
) -> dict[str, np.ndarray]:
    """The ``truth.npz`` arrays (see models_spec/ingest.md), with the lens when there is one."""
    meta = {
        "generator": GENERATOR,
        "version": __version__,
        "seed": int(seed),
        "profile": profile.name,
        "device": asdict(profile),
        "rig": rig_to_dict(rig),
        "units": {"2d": "px", "3d": "mm"},
    }
    lens = (
        {} if dist_coeffs is None else {"dist_coeffs": np.asarray(dist_coeffs, np.float64), "dist_K": profile.nominal_K}
    )
    return lens | {
        "frame_id": np.array(files),
        "K": np.stack([s.K for s in shots]),
        "rvec": np.stack([s.rvec for s in shots]),
        "tvec": np.stack([s.tvec for s in shots]),
        "corners_px": np.stack([s.corners_px for s in shots]),
        "seen": np.stack([s.seen for s in shots]),
        "board_of_point": rig.board_of_point,
        "upside_down": np.array([s.upside_down for s in shots]),
        "covered_board": np.array([s.covered_board for s in shots], np.int64),
        "image_size": np.array(profile.image_size_px, np.int64),
        "meta": np.array(json.dumps(meta, sort_keys=True)),
    }


def photo_name(k: int, fmt: str) -> str:
    """The file name of photo ``k`` (from 0) of a render: photo-0000.jpg, ..."""
    return f"photo-{k:04d}.{fmt}"


def write_render(
    out_dir: str | Path,
    rig: Rig,
    profile: DeviceProfile,
    n: int,
    *,
    seed: int = 0,
    fmt: str = "jpg",
    progress=iter,
    dist_coeffs: Optional[np.ndarray] = None,
) -> Path:
    """Render ``n`` photos into ``out_dir`` as photo-0000.<fmt>, … and write ``truth.npz``; returns its path.
    ``dist_coeffs``: the lens (OpenCV's model about the profile's nominal K), or None (pinhole).

    ``progress`` wraps the photo iterator (e.g. ``dimenet.runtime.jobs.progress.progress``).
    """
    if fmt not in FORMATS:
        raise InputError(f"unknown photo format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if n < 1:
        raise InputError(f"the number of photos must be >= 1, got {n}")
    out = Path(out_dir)
    files, shots = [], []
    photos = render_photos(rig, profile, n, seed=seed, dist_coeffs=dist_coeffs)
    for k, (img, shot) in enumerate(progress(photos)):
        name = photo_name(k, fmt)
        data = encode(img, fmt)
        atomic_write(out / name, lambda f, data=data: f.write(data))
        files.append(name)
        shots.append(shot)
    arrays = truth_arrays(rig, profile, seed, files, shots, dist_coeffs)
    return atomic_write(out / TRUTH_FILE, lambda f: np.savez_compressed(f, **arrays))

"""The DIME-Net input: the gridified OIS discrepancy feature (paper Sec. IV-A).

One implementation, numpy only, used by training, evaluation, export checks and the runtime.

1. Pose {W}->{C0}: PnP under the prior K_c on the frame's inference points (SQPnP).
2. Point feature f_i = [dx, dy, X, Y, 1/Z]: dx, dy = K_c proj(X_C0) - x (px, the projection
   model discrepancy, PMD) and (X, Y, Z) the point in {C0} (mm).
3. Each cell of the u x v grid (``rectify.grid``) holds the mean of its points' features;
   empty cells are zero. Flattened cell by cell in (row, column) order, channels inside.
4. Every channel is multiplied by a fixed scale (no shift, so a zero feature stays zero).

Scale-free depth (``FeatureSpec.depth_mm``, spec >= 1.5): each frame's {C0} points are first
scaled by depth_mm / Z_mean, Z_mean the mean depth of its inference points, so X, Y and 1/Z
no longer depend on the world unit (mm, m, inches) nor on how far the scene is: they read as
millimetres of a scene depth_mm away. With the PMD measured in a canonical camera's pixels
(``rectify.user_camera``), the whole feature is then scale free.

Variants (paper Table 3): A all five channels; B PMD only; C PMD + 1/Z; D PMD + X, Y;
E X, Y, 1/Z only.

The feature is its encoders' inputs one after another (``rectify.encoders``, one module each): the grid
above, then the data step (``FeatureSpec.data_step``, spec >= 1.7) and the moments (``FeatureSpec.moments``,
spec >= 1.11), both read from the frame's monomial Gram (training/METHOD.md, "Any scene: the encoder").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Optional

import cv2
import numpy as np

from dimenet.runtime import native
from dimenet.runtime.errors import InputError
from dimenet.runtime.geometry import FEW_POSES, MIN_POSE_POINTS, monomial_gram, rotation_matrices, solve_pnp_start
from dimenet.runtime.json_text import JsonProblem, is_number, required, shown
from dimenet.runtime.rectify.encoders import ENCODERS, grid
from dimenet.runtime.rectify.encoders.grid import CHANNELS, VARIANTS
from dimenet.runtime.rectify.grid import Grid

# Fixed per-channel scales bringing each channel to order 1 on hand-held rig data:
# PMD of ~10 px, {C0} coordinates of ~100 mm, inverse depth of ~1/500 mm^-1.
DEFAULT_SCALE = {"dx": 0.1, "dy": 0.1, "X": 0.01, "Y": 0.01, "inv_z": 500.0}


@dataclass(frozen=True)
class FeatureSpec:
    """What the network sees: grid, channel variant and per-channel scale (units: 1/px, 1/mm, mm)."""

    grid: Grid = Grid(8, 6)
    variant: str = "A"
    scale: dict = field(default_factory=lambda: dict(DEFAULT_SCALE))
    depth_mm: Optional[float] = None  # None: {C0} in the frame's own unit; else scale-free depth (above)
    data_step: bool = False  # the frame's own Gauss-Newton step on K after the grid (above)
    moments: bool = False  # the point set's moments after the step (above)

    def __post_init__(self) -> None:
        if self.depth_mm is not None and not (math.isfinite(self.depth_mm) and self.depth_mm > 0):
            raise InputError(f"feature depth_mm must be a positive number, got {self.depth_mm!r}")
        if self.variant not in VARIANTS:
            raise InputError(f"feature variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}")
        missing = [c for c in CHANNELS if c not in self.scale]
        if missing:
            raise InputError(f"feature scale lacks channel {missing[0]!r}")

    @property
    def channels(self) -> tuple:
        return VARIANTS[self.variant]

    @cached_property
    def channel_scale(self) -> np.ndarray:
        """(C,) the per-channel scales in channel order (computed once per spec)."""
        return np.array([self.scale[c] for c in self.channels])

    @cached_property
    def depth_exponents(self) -> np.ndarray:
        """(C,) the power of a frame's depth factor each channel takes with ``depth_mm``: X, Y 1,
        1/Z -1, the PMD 0."""
        return np.array([{"X": 1.0, "Y": 1.0, "inv_z": -1.0}.get(c, 0.0) for c in self.channels])

    @cached_property
    def native_layout(self) -> np.ndarray:
        """(17,) the spec packed for the compiled core (runtime/native/_module.c): grid columns and rows,
        the channel count, the channels' indices into CHANNELS and their scales (each padded to 5),
        depth_mm (0: None), data_step, moments, the PMD's scale."""
        index = [CHANNELS.index(c) for c in self.channels]
        pad = [0] * (len(CHANNELS) - len(index))
        head = [self.grid.cols, self.grid.rows, len(index), *index, *pad, *self.channel_scale.tolist(), *pad]
        tail = [self.depth_mm or 0.0, float(self.data_step), float(self.moments), self.scale["dx"]]
        return np.array(head + tail, dtype=np.float64)

    @cached_property
    def native_call(self) -> tuple:
        """(``native_layout``, (1, size)): what the compiled core's one-frame call takes, in one lookup."""
        return self.native_layout, (1, self.size)

    @property
    def grid_size(self) -> int:
        """The grid's inputs: channels x cells, first in the feature."""
        return grid.size(self)

    @property
    def size(self) -> int:
        """The feature's inputs: every encoder's (``rectify.encoders``)."""
        return sum(encoder.size(self) for encoder in ENCODERS.values())

    def to_dict(self) -> dict:
        d = {"grid": str(self.grid), "variant": self.variant, "scale": dict(self.scale)}
        if self.depth_mm is not None:
            d["depth_mm"] = self.depth_mm
        if self.data_step:
            d["data_step"] = True
        if self.moments:
            d["moments"] = True
        return d

    @classmethod
    def from_dict(cls, d: Any, image_size: Optional[tuple] = None) -> FeatureSpec:
        """From a spec's ``features`` object, every field checked (JsonProblem, a ValueError,
        names it); with ``image_size`` (width, height) px, the grid must fit the image."""
        if not isinstance(d, dict):
            raise JsonProblem(f"features must be an object, got {shown(d)}")
        grid_text, variant, scale = required(d, "grid"), required(d, "variant"), required(d, "scale")
        if not isinstance(grid_text, str):
            raise JsonProblem(f"features.grid must be a string like '8x6', got {shown(grid_text)}")
        try:
            grid = Grid.parse(grid_text)
        except ValueError as exc:
            raise JsonProblem(f"features.{exc}") from None
        if image_size is not None and not grid.fits(image_size):
            raise JsonProblem(
                f"features.grid {grid} has more cells than the {image_size[0]}x{image_size[1]} image has pixels"
            )
        if not isinstance(variant, str):
            raise JsonProblem(f"features.variant must be a string, got {shown(variant)}")
        if not isinstance(scale, dict):
            raise JsonProblem(f"features.scale must be an object, got {shown(scale)}")
        unknown = [key for key in scale if key not in CHANNELS]
        if unknown:
            raise JsonProblem(f"features.scale has an unknown channel {unknown[0]!r} (channels: {', '.join(CHANNELS)})")
        for channel in CHANNELS:
            value = scale.get(channel)
            if not (is_number(value) and value > 0):
                raise JsonProblem(f"features.scale.{channel} must be a positive number, got {shown(value)}")
        depth_mm = d.get("depth_mm")
        if depth_mm is not None and not (is_number(depth_mm) and depth_mm > 0):
            raise JsonProblem(f"features.depth_mm must be a positive number, got {shown(depth_mm)}")
        data_step, moments = d.get("data_step", False), d.get("moments", False)
        for name, value in (("data_step", data_step), ("moments", moments)):
            if not isinstance(value, bool):
                raise JsonProblem(f"features.{name} must be true or false, got {shown(value)}")
        try:
            return cls(
                grid=grid,
                variant=variant,
                scale={c: float(scale[c]) for c in CHANNELS},
                depth_mm=None if depth_mm is None else float(depth_mm),
                data_step=data_step,
                moments=moments,
            )
        except ValueError as exc:
            raise JsonProblem(f"features: {exc}") from None


def poses_c0(points_2d, points_3d, mask, K_c) -> tuple[np.ndarray, np.ndarray]:
    """Pose {W}->{C0} of each of F frames: SQPnP under K_c on the masked points (mask None:
    all). (F, 3) each; InputError naming the first frame that has none."""
    rvec, tvec, reasons = c0_poses(points_2d, points_3d, mask, K_c)
    for b, reason in enumerate(reasons):
        if reason is not None:
            raise InputError(f"frame {b}: {reason}")
    return rvec, tvec


def c0_poses(points_2d, points_3d, mask, K_c) -> tuple[np.ndarray, np.ndarray, list]:
    """``poses_c0``'s poses (F, 3) each (zero where there is none) and per frame None or why it has no pose."""
    F = len(points_2d)
    rvec, tvec = np.zeros((F, 3)), np.zeros((F, 3))
    reasons: list = [None] * F
    for b in range(F):
        m = slice(None) if mask is None else mask[b]
        n = points_2d.shape[1] if mask is None else int(m.sum())
        if n < MIN_POSE_POINTS:
            reasons[b] = f"{n} inference points, the C0 pose needs >= {MIN_POSE_POINTS}"
            continue
        try:
            rvec[b], tvec[b] = solve_pnp_start(points_2d[b][m], points_3d[b][m], K_c)
        except InputError as exc:
            reasons[b] = str(exc)
    return rvec, tvec, reasons


def point_features(points_2d, points_3d, K_c, rvec, tvec) -> np.ndarray:
    """(F, N, 5) raw [dx, dy, X, Y, 1/Z] (px, px, mm, mm, 1/mm) in {C0}; unmasked values are arbitrary."""
    points_2d = np.asarray(points_2d, dtype=np.float64)
    out = np.empty((len(points_2d), len(CHANNELS), points_2d.shape[1]))
    _point_features_into(out, points_2d, np.asarray(points_3d, dtype=np.float64), K_c, rvec, tvec)
    return np.ascontiguousarray(np.swapaxes(out, 1, 2))


def _point_features_into(out, points_2d, points_3d, K_c, rvec, tvec, mask=None, depth_sums: bool = False):
    """The raw point features of ``point_features`` channel-major into out[:, :5] of an (F, >= 5, N) array.

    One map P (5 x 4) takes each {W} point X to [u, v, X_C0, Y_C0, Z_C0] with (u, v, Z_C0) =
    K_c (R X + t); then 1/Z, and dx, dy = u / Z - x, v / Z - y. With ``depth_sums``, returns
    (F,) the sum of Z_C0 over each frame's ``mask`` (F, N) points (None: all), else None.

    R is OpenCV's Rodrigues of each pose, and P's products are summed term by term in a fixed order
    ((p0 X + p1 Y) + p2 Z) + p3, not by BLAS (geometry.normal_equations' docstring: the compiled core
    gives the same rows to the bit, so the data step's inputs too).
    """
    F = len(points_2d)
    P = np.empty((F, 5, 4))  # rows: K_c[:2] [R | t], then [R | t]
    rvec = np.ascontiguousarray(rvec, dtype=np.float64)
    P[:, 2:, :3] = rotation_matrices(rvec) if F <= FEW_POSES else [cv2.Rodrigues(r)[0] for r in rvec]
    P[:, 2:, 3] = tvec
    K_rows = np.asarray(K_c, dtype=np.float64)[:2, :, None]
    P[:, :2] = np.multiply(K_rows, P[:, None, 2:], out=np.empty((F, 2, 3, 4))).sum(2)  # C order: k first to last
    rows = np.multiply(P[:, :, :1], points_3d[:, None, :, 0], out=out[:, :5])
    rows += P[:, :, 1:2] * points_3d[:, None, :, 1]
    rows += P[:, :, 2:3] * points_3d[:, None, :, 2]
    rows += P[:, :, 3:]
    sums = None
    if depth_sums:
        sums = rows[:, 4].sum(1) if mask is None else np.where(mask, rows[:, 4], 0.0).sum(1)
    inv_z = np.divide(1.0, rows[:, 4:5], out=rows[:, 4:5])
    pmd = rows[:, :2]
    pmd *= inv_z
    pmd -= np.swapaxes(points_2d, 1, 2)
    return sums


def grid_features(
    points_2d, points_3d, mask, K_c, image_size, spec: FeatureSpec, *, poses=None, return_points: bool = False
):
    """The flattened, scaled grid feature of F frames: (F, spec.size) float64.

    points_2d (F, N, 2) px; points_3d (F, N, 3) mm in {W}; mask (F, N) bool, the inference
    points (None: every point); K_c (3, 3) the prior; image_size (width, height) px.
    ``poses`` (rvec, tvec) of {W}->{C0} may be passed when already known (else solved here
    with SQPnP).

    With ``return_points``, returns (feature, points): points (F, 6, N) the raw unscaled point
    rows [dx, dy, X, Y, 1/Z, 1] channel-major (px, px, mm, mm, 1/mm, 1) in {C0} (in the frame's
    own unit also when ``spec.depth_mm`` is set), arbitrary on unmasked points; rows 0-1 (the
    PMD) are each point's reprojection residual under K_c at the C0 pose.
    """
    points_2d, points_3d, mask, (rvec, tvec) = _prepared(points_2d, points_3d, mask, K_c, poses)
    if native.core is not None:  # the compiled core (runtime/native); the numpy below is its reference
        return _native_grid_features(points_2d, points_3d, mask, rvec, tvec, K_c, image_size, spec, return_points)
    F, N = points_2d.shape[:2]
    if mask is not None:
        points_2d = np.where(mask[..., None], points_2d, 0.0)
        points_3d = np.where(mask[..., None], points_3d, 0.0)
    # Channel-major point rows [dx, dy, X, Y, 1/Z, 1] (F, 6, N); the last one counts points.
    points = np.empty((F, len(CHANNELS) + 1, N))
    z_sums = _point_features_into(points, points_2d, points_3d, K_c, rvec, tvec, mask, spec.depth_mm is not None)
    points[:, -1] = 1.0
    feats = grid.encode(points, points_2d, mask, z_sums, image_size, spec)
    if spec.size > spec.grid_size:
        feats = np.concatenate([feats, gram_inputs(points, mask, K_c, spec)], 1)
    return (feats, points) if return_points else feats


def _prepared(points_2d, points_3d, mask, K_c, poses) -> tuple:
    """``grid_features``' inputs as both its paths take them: points_2d, points_3d float64 C-contiguous, mask
    bool C-contiguous or None when it holds every point, and the C0 poses (rvec, tvec), solved when not given."""
    points_2d = np.ascontiguousarray(points_2d, dtype=np.float64)
    points_3d = np.ascontiguousarray(points_3d, dtype=np.float64)
    if mask is not None:
        mask = np.ascontiguousarray(mask, dtype=bool)
        if mask.all():
            mask = None
    return points_2d, points_3d, mask, poses if poses is not None else poses_c0(points_2d, points_3d, mask, K_c)


def gram_inputs(points: np.ndarray, mask, K_c, spec: FeatureSpec) -> np.ndarray:
    """(F, D) the inputs after the grid of F frames: each encoder after the grid that the spec uses, in the
    registry's order (``rectify.encoders``), from each frame's ``monomial_gram``. points (F, 6, N) the raw
    point rows (``grid_features``'s: the PMD in rows 0-1, X, Y, 1/Z in {C0} in rows 2-4), mask (F, N) bool
    their inference points (None: all), K_c (3, 3) px."""
    used = [encoder for encoder in ENCODERS.values() if encoder is not grid and encoder.size(spec)]
    out = np.empty((len(points), spec.size - spec.grid_size))
    for b in range(len(points)):
        rows = points[b] if mask is None else points[b][:, mask[b]]
        n = rows.shape[1]
        G = monomial_gram(rows[2:5], rows[:2])
        start = 0
        for encoder in used:
            stop = start + encoder.size(spec)
            out[b, start:stop] = encoder.encode(G, n, K_c, spec)
            start = stop
    return out


def native_frame_features(points_2d, points_3d, K_c, image_size, spec: FeatureSpec, rvec, tvec) -> tuple:
    """The rectifier's hot path (``stages.frame_features``) in one call of the compiled core (``native.core``
    must be set): one frame's (1, D) feature at its C0 pose (rvec, tvec (3,)) and e_c (px), the mean norm
    of its PMD; InputError when a point lies behind the camera, or as ``grid_features``'s. points_2d
    (N, 2) px, points_3d (N, 3) mm, K_c (3, 3) px float64."""
    layout, shape = spec.native_call
    feats = np.empty(shape)
    size = image_size if type(image_size) is tuple else tuple(image_size)
    try:  # the arrays as they come (validated_frame's are float64, C-contiguous)
        e_c = native.core.frame_features(points_2d, points_3d, rvec, tvec, K_c, size, layout, feats)
    except TypeError:  # another type or layout: as numpy would take them
        p2, p3 = np.ascontiguousarray(points_2d, np.float64), np.ascontiguousarray(points_3d, np.float64)
        r, t = np.ascontiguousarray(rvec, np.float64), np.ascontiguousarray(tvec, np.float64)
        K = np.ascontiguousarray(K_c, np.float64)
        e_c = native.core.frame_features(p2, p3, r, t, K, size, layout, feats)
    return feats, e_c


def _native_grid_features(points_2d, points_3d, mask, rvec, tvec, K_c, image_size, spec: FeatureSpec, return_points):
    """``grid_features`` through the compiled core (``native.core``) on ``_prepared``'s inputs: the same
    outputs and InputErrors, one kernel call for the F frames (tests/native/ hold the two equal)."""
    F, N = points_2d.shape[:2]
    feats = np.empty((F, spec.size))
    points = np.empty((F, len(CHANNELS) + 1, N)) if return_points else None
    native.core.grid_features(
        points_2d,
        points_3d,
        mask,
        np.ascontiguousarray(rvec, dtype=np.float64),
        np.ascontiguousarray(tvec, dtype=np.float64),
        np.ascontiguousarray(K_c, dtype=np.float64),
        float(image_size[0]),
        float(image_size[1]),
        spec.native_layout,
        feats,
        points,
        None,
        False,
    )
    return (feats, points) if return_points else feats

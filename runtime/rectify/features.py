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

The data step (``FeatureSpec.data_step``, spec >= 1.7; not the paper's): after the grid, STEP_SIZE
more inputs say what the frame's own points say of K. One Gauss-Newton step over (pose, K) from
the C0 pose and K_c (``geometry.prior_step``) with a weak prior on K (1 sigma STEP_PRIOR_REL * fx_c
px per parameter): its Delta K (fx, fy, cx, cy) px times the PMD's scale, then the log of each
parameter's posterior sigma over the prior's (0 where the points do not fix it, e.g. f and c on
one plane). The step's Delta K is clipped to +- STEP_CLIP_REL * fx_c. The grid says where the points
are; the step is how they fix K, whatever the scene (training/METHOD.md, "Any scene: the encoder").

The moments (``FeatureSpec.moments``, spec >= 1.11; not the paper's): after the step, MOMENT_SIZE
more inputs, the frame's point set pooled whatever its layout: the mean over its points of every
product of two of [1, a, b, ab, a^2, b^2, z, a z, b z, s dx, s dy], a = X/Z and b = Y/Z in {C0}, z
the point's inverse depth over the frame's mean inverse depth and s the PMD's scale (the upper
triangle in row order, less the two that are always 1). The geometry's moments say how the
points spread over the image and in depth (one plane or several, clustered or covering); the
PMD's how it varies over them. They are the normal equations' own statistics
(``geometry.monomial_gram``), so the step costs nothing more to read them.
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
from dimenet.runtime.geometry import (
    FEW_POSES,
    MIN_POSE_POINTS,
    gram_normal_equations,
    monomial_gram,
    prior_step,
    rotation_matrices,
    solve_pnp_start,
)
from dimenet.runtime.json_text import JsonProblem, is_number, required, shown
from dimenet.runtime.rectify.grid import Grid

CHANNELS = ("dx", "dy", "X", "Y", "inv_z")
VARIANTS = {
    "A": ("dx", "dy", "X", "Y", "inv_z"),
    "B": ("dx", "dy"),
    "C": ("dx", "dy", "inv_z"),
    "D": ("dx", "dy", "X", "Y"),
    "E": ("X", "Y", "inv_z"),
}
# The data step's inputs: Delta K (4) then log sigma ratios (4); its prior's 1 sigma over fx_c; the
# noise floor of its data weight (px).
STEP_SIZE = 8
STEP_PRIOR_REL = 0.1
# The step's Delta K is clipped to +- this x fx_c before scaling: OIS moves c by up to ~0.02 fx and a factory K_c
# is off by up to 0.03 f; a step past 0.05 fx_c is the prior's doing on points that fix no K (inputs of order 1).
STEP_CLIP_REL = 0.05
STEP_NOISE_FLOOR_PX = 0.1


# The moments: the upper triangle of the 11 x 11 monomial Gram, less [1 * 1] and [1 * z] (both 1).
def _moment_index() -> np.ndarray:
    rows, cols = np.triu_indices(11)
    keep = ~((rows == 0) & ((cols == 0) | (cols == 6)))
    return np.ravel_multi_index((rows[keep], cols[keep]), (11, 11))


MOMENT_INDEX = _moment_index()  # into the raveled Gram
MOMENT_SIZE = len(MOMENT_INDEX)
# A posterior variance over the prior's below this reads as this (no log of 0 from a failed inverse).
STEP_VARIANCE_FLOOR = 1e-30
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
        return len(self.channels) * self.grid.n_cells

    @property
    def size(self) -> int:
        return self.grid_size + (STEP_SIZE if self.data_step else 0) + (MOMENT_SIZE if self.moments else 0)

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


def _depth_factors(z_sums: np.ndarray, counts, depth_mm: float) -> np.ndarray:
    """(F,) the scale-free depth factor depth_mm / Z_mean of each frame from the sums (F,) of
    its inference points' depths and their counts; 1 where Z_mean <= 0 (a frame with points
    behind the camera keeps its signs, and the rectifier refuses it)."""
    return np.divide(depth_mm * np.asarray(counts, np.float64), z_sums, out=np.ones(len(z_sums)), where=z_sums > 0)


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
    if native.core is not None:  # the compiled core (runtime/native); the numpy below is its reference
        return _native_grid_features(points_2d, points_3d, mask, K_c, image_size, spec, poses, return_points)
    points_2d = np.asarray(points_2d, dtype=np.float64)
    points_3d = np.asarray(points_3d, dtype=np.float64)
    F, N = points_2d.shape[:2]
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.all():
            mask = None
    rvec, tvec = poses if poses is not None else poses_c0(points_2d, points_3d, mask, K_c)
    if mask is not None:
        points_2d = np.where(mask[..., None], points_2d, 0.0)
        points_3d = np.where(mask[..., None], points_3d, 0.0)
    # Channel-major point rows [dx, dy, X, Y, 1/Z, 1] (F, 6, N); the last one counts points.
    rows = np.empty((F, len(CHANNELS) + 1, N))
    relative = spec.depth_mm is not None
    z_sums = _point_features_into(rows, points_2d, points_3d, K_c, rvec, tvec, mask, relative)
    rows[:, -1] = 1.0
    points = rows
    channels = spec.channels
    if channels != CHANNELS:
        rows = rows[:, [CHANNELS.index(c) for c in channels] + [len(CHANNELS)]]
    width = rows.shape[1]
    bins = F * spec.grid.n_cells  # cell bins of all frames; one block of them per channel
    if spec.grid.n_cells == 1:  # one cell holds every point: no cell index
        sums = (rows.sum(2) if mask is None else np.sum(rows, axis=2, where=mask[:, None, :])).T
    else:
        sums = _cell_sums(rows, points_2d, mask, image_size, spec.grid)
    means = sums[:-1] / np.maximum(sums[-1], 1.0)
    if not relative:
        means *= spec.channel_scale[:, None]
    else:  # X, Y times the frame's depth factor, 1/Z over it: cell means scale alike
        # One frame (the rectifier's hot path): float arithmetic, 1 µs against _depth_factors's 12 µs of
        # tiny array calls; tests/rectify/test_features.py holds the two equal.
        if F == 1 and mask is None:
            z_sum = float(z_sums[0])
            factor = spec.depth_mm * N / z_sum if z_sum > 0 else 1.0
            means *= (spec.channel_scale * factor**spec.depth_exponents)[:, None]
        else:
            factor = _depth_factors(z_sums, N if mask is None else mask.sum(1), spec.depth_mm)
            scale = spec.channel_scale[:, None, None] * factor[None, :, None] ** spec.depth_exponents[:, None, None]
            means.reshape(width - 1, F, -1)[...] *= scale
    feats = means.T.reshape(F, bins // F * (width - 1))
    if spec.data_step or spec.moments:
        feats = np.concatenate([feats, gram_inputs(points, mask, K_c, spec)], 1)
    return (feats, points) if return_points else feats


def _cell_sums(rows: np.ndarray, points_2d: np.ndarray, mask, image_size, grid: Grid) -> np.ndarray:
    """(W, F * cells): per channel of the point rows (F, W, N) and per cell of each of the F frames,
    the sum of its ``mask`` (F, N) points' values (None: all) in point order."""
    F, width = rows.shape[:2]
    bins = F * grid.n_cells
    cells = grid.cell_index(points_2d, image_size)
    if F > 1:
        cells += grid.n_cells * np.arange(F)[:, None]
    index = cells[:, None, :] + np.arange(0, width * bins, bins)[:, None]
    if mask is None:
        index, weights = index.ravel(), rows.ravel()
    else:
        index, weights = np.swapaxes(index, 1, 2)[mask], np.swapaxes(rows, 1, 2)[mask]
    return np.bincount(index.ravel(), weights=weights.ravel(), minlength=width * bins).reshape(width, bins)


def gram_inputs(points: np.ndarray, mask, K_c, spec: FeatureSpec) -> np.ndarray:
    """(F, D) the inputs after the grid of F frames: the data step's STEP_SIZE with
    ``spec.data_step``, then the MOMENT_SIZE moments with ``spec.moments`` (module docstring),
    both from each frame's ``monomial_gram``. points (F, 6, N) the raw point rows
    (``grid_features``'s: the PMD in rows 0-1, X, Y, 1/Z in {C0} in rows 2-4), mask (F, N) bool
    their inference points (None: all), K_c (3, 3) px."""
    fx_c, fy_c = float(K_c[0, 0]), float(K_c[1, 1])
    prior_var, clip_px = (STEP_PRIOR_REL * fx_c) ** 2, STEP_CLIP_REL * fx_c
    precision = np.eye(4) / prior_var
    pmd_scale = spec.scale["dx"]
    out = np.empty((len(points), spec.size - spec.grid_size))
    for b in range(len(points)):
        rows = points[b] if mask is None else points[b][:, mask[b]]
        n = rows.shape[1]
        G = monomial_gram(rows[2:5], rows[:2])
        if spec.data_step:
            JJ, Jr, rss = gram_normal_equations(G, fx_c, fy_c)
            step, cov, _ = prior_step(JJ, Jr, rss, 2 * n, precision, noise_floor_px=STEP_NOISE_FLOOR_PX)
            out[b, :STEP_SIZE] = _step_inputs(
                step[6:].tolist(), cov.diagonal()[6:].tolist(), prior_var, clip_px, pmd_scale
            )
        if spec.moments:
            out[b, -MOMENT_SIZE:] = _moment_inputs(G, n, pmd_scale)
    return out


def _step_inputs(step_px: list, variance_px2: list, prior_var: float, clip_px: float, pmd_scale: float) -> list:
    """The data step's STEP_SIZE inputs from its step (4,) px and posterior variances (4,) px^2 of
    (fx, fy, cx, cy), its prior's variance (px^2) and clip (px): the clipped step times the PMD's
    scale, then the log sigma ratios (floats: 3 against 9 µs for numpy's calls on 4 values)."""
    shown = [min(max(d, -clip_px), clip_px) * pmd_scale for d in step_px]
    return shown + [0.5 * math.log(max(v / prior_var, STEP_VARIANCE_FLOOR)) for v in variance_px2]


def _moment_inputs(G: np.ndarray, n: int, pmd_scale: float) -> np.ndarray:
    """(MOMENT_SIZE,) the moments of one frame of n points from its monomial Gram G (11, 11): each
    monomial's scale s (1, z's n / sum(1/Z), the PMD's scale), then s_i s_j G_ij / n."""
    z_scale = n / G[0, 6] if G[0, 6] > 0 else 1.0
    s = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, z_scale, z_scale, z_scale, pmd_scale, pmd_scale])
    return (G * np.outer(s, s / n)).ravel()[MOMENT_INDEX]


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


def _native_grid_features(points_2d, points_3d, mask, K_c, image_size, spec: FeatureSpec, poses, return_points: bool):
    """``grid_features`` through the compiled core (``native.core``): the same inputs, outputs and
    InputErrors, one kernel call for the F frames (tests/native/ hold the two equal)."""
    points_2d = np.ascontiguousarray(points_2d, dtype=np.float64)
    points_3d = np.ascontiguousarray(points_3d, dtype=np.float64)
    F, N = points_2d.shape[:2]
    if mask is not None:
        mask = np.ascontiguousarray(mask, dtype=bool)
        if mask.all():
            mask = None
    rvec, tvec = poses if poses is not None else poses_c0(points_2d, points_3d, mask, K_c)
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

"""The grid encoder (paper Sec. IV-A): the per-cell means of the point features, first in the feature.

Each cell of the u x v grid (``rectify.grid``) holds the mean of its points' [dx, dy, X, Y, 1/Z] rows
(``rectify.features``), empty cells zero, flattened cell by cell in (row, column) order with the spec's
channels inside, each channel times its fixed scale (with ``depth_mm``, X and Y times the frame's depth
factor and 1/Z over it). Compiled: the first ``size`` values of ``dimenet_frame_features``' output
(runtime/native/dimenet_features.c).
"""

from __future__ import annotations

import numpy as np

NAME = "grid"
CHANNELS = ("dx", "dy", "X", "Y", "inv_z")  # the point rows' channels (rectify.features.point_features)
VARIANTS = {  # the channels each variant reads (paper Table 3)
    "A": ("dx", "dy", "X", "Y", "inv_z"),
    "B": ("dx", "dy"),
    "C": ("dx", "dy", "inv_z"),
    "D": ("dx", "dy", "X", "Y"),
    "E": ("X", "Y", "inv_z"),
}


def size(spec) -> int:
    """Channels x cells: every spec has the grid."""
    return len(spec.channels) * spec.grid.n_cells


def encode(rows: np.ndarray, points_2d: np.ndarray, mask, z_sums, image_size, spec) -> np.ndarray:
    """(F, size) the grid inputs of F frames from their raw point rows (F, 6, N) [dx, dy, X, Y, 1/Z, 1]
    channel-major, the (masked) points_2d (F, N, 2) px, mask (F, N) bool (None: all points), z_sums (F,)
    their depth sums (with ``spec.depth_mm``) and image_size (width, height) px."""
    F, N = rows.shape[0], rows.shape[2]
    if spec.channels != CHANNELS:
        rows = rows[:, [CHANNELS.index(c) for c in spec.channels] + [len(CHANNELS)]]
    width = rows.shape[1]
    bins = F * spec.grid.n_cells  # cell bins of all frames; one block of them per channel
    if spec.grid.n_cells == 1:  # one cell holds every point: no cell index
        sums = (rows.sum(2) if mask is None else np.sum(rows, axis=2, where=mask[:, None, :])).T
    else:
        sums = _cell_sums(rows, points_2d, mask, image_size, spec.grid)
    means = sums[:-1] / np.maximum(sums[-1], 1.0)
    if spec.depth_mm is None:
        means *= spec.channel_scale[:, None]
    else:  # X, Y times the frame's depth factor, 1/Z over it: cell means scale alike
        # One frame (the rectifier's hot path): float arithmetic, 1 µs against depth_factors's 12 µs of
        # tiny array calls; tests/rectify/test_features.py holds the two equal.
        if F == 1 and mask is None:
            z_sum = float(z_sums[0])
            factor = spec.depth_mm * N / z_sum if z_sum > 0 else 1.0
            means *= (spec.channel_scale * factor**spec.depth_exponents)[:, None]
        else:
            factor = depth_factors(z_sums, N if mask is None else mask.sum(1), spec.depth_mm)
            scale = spec.channel_scale[:, None, None] * factor[None, :, None] ** spec.depth_exponents[:, None, None]
            means.reshape(width - 1, F, -1)[...] *= scale
    return means.T.reshape(F, bins // F * (width - 1))


def depth_factors(z_sums: np.ndarray, counts, depth_mm: float) -> np.ndarray:
    """(F,) the scale-free depth factor depth_mm / Z_mean of each frame from the sums (F,) of
    its inference points' depths and their counts; 1 where Z_mean <= 0 (a frame with points
    behind the camera keeps its signs, and the rectifier refuses it)."""
    return np.divide(depth_mm * np.asarray(counts, np.float64), z_sums, out=np.ones(len(z_sums)), where=z_sums > 0)


def _cell_sums(rows: np.ndarray, points_2d: np.ndarray, mask, image_size, grid) -> np.ndarray:
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

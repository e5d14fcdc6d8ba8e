"""Test conditions of the paper's evaluation: fewer points, noisier points, emptied grid cells;
and beyond it, the points of one plane (the planar scene without the rig's board identity)
and those of two objects apart in the image (hand-labelled natural features).

Each function takes a Dataset and a ``numpy.random.Generator`` and returns a new Dataset
(the input is never modified). Point dropping and cell emptying act on ``infer_mask`` only
(the points the model may use); evaluation still uses every valid point (paper Sec. V-C).
"""

from __future__ import annotations

import math
from dataclasses import replace
from numbers import Real

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.geometry import MIN_POINTS
from dimenet.runtime.rectify.grid import Grid


def _check_generator(rng) -> None:
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")


def _check_sigma(value, name: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value) or value < 0:
        raise InputError(f"{name} must be a finite number >= 0 ({unit}), got {value!r}")
    return float(value)


def _per_frame(value, ds: Dataset) -> np.ndarray:
    """A scalar or an (F,) array of per-frame values, as an (F,) array."""
    arr = np.asarray(value)
    if arr.ndim == 0:
        return np.full(ds.n_frames, arr.item())
    if arr.shape != (ds.n_frames,):
        raise InputError(f"per-frame values must be a scalar or have shape ({ds.n_frames},), got {arr.shape}")
    return arr


def drop_inference_points(ds: Dataset, n, rng: np.random.Generator) -> Dataset:
    """Keep n uniformly sampled inference points per frame (paper Table 4); frames with <= n keep all.
    ``n`` is one integer or one per frame."""
    _check_generator(rng)
    ns = _per_frame(n, ds)
    if isinstance(n, bool) or ns.dtype.kind not in "iu" or np.any(ns < MIN_POINTS):
        raise InputError(f"n must be an integer >= {MIN_POINTS} (a pose needs them), got {n!r}")
    infer = ds.infer_mask.copy()
    for f in range(ds.n_frames):
        idx = np.flatnonzero(infer[f])
        if len(idx) > ns[f]:
            infer[f, rng.choice(idx, len(idx) - ns[f], replace=False)] = False
    return replace(ds, infer_mask=infer)


def add_noise(ds: Dataset, sigma_2d_px, sigma_3d_mm, rng: np.random.Generator) -> Dataset:
    """Zero-mean Gaussian noise on every valid point: std sigma_2d_px per image axis (px) and
    sigma_3d_mm per 3D axis (mm) (paper Table 4, lower half). Invalid points stay as they are.
    Each sigma is one number or one per frame. The frames' label noise (``label_noise_px``) grows by the 2D
    noise; with 3D noise it is no longer known (it projects by each point's depth) and is dropped."""
    _check_generator(rng)
    s2 = np.array([_check_sigma(s, "sigma_2d_px", "px") for s in _per_frame(sigma_2d_px, ds)])[:, None, None]
    s3 = np.array([_check_sigma(s, "sigma_3d_mm", "mm") for s in _per_frame(sigma_3d_mm, ds)])[:, None, None]
    v = ds.valid[..., None]
    p2 = np.where(v, ds.points_2d + rng.normal(0.0, 1.0, ds.points_2d.shape) * s2, ds.points_2d)
    p3 = np.where(v, ds.points_3d + rng.normal(0.0, 1.0, ds.points_3d.shape) * s3, ds.points_3d)
    noise = ds.label_noise_px
    if noise is not None:
        noise = None if np.any(s3 > 0) else np.sqrt(noise**2 + s2[:, 0, 0] ** 2)
    return replace(ds, points_2d=p2, points_3d=p3, label_noise_px=noise)


def _occupied_cells(ds: Dataset, grid: Grid) -> tuple[np.ndarray, list[np.ndarray]]:
    """Cell index (F, P) of every point, and per frame the sorted cells holding inference points."""
    if not isinstance(grid, Grid):
        raise InputError(f"grid must be a Grid (e.g. Grid.parse('8x6')), got {grid!r}")
    cells = grid.cell_index(ds.points_2d, ds.image_size)
    return cells, [np.unique(cells[f][ds.infer_mask[f]]) for f in range(ds.n_frames)]


def empty_cells(ds: Dataset, eta, grid: Grid, rng: np.random.Generator) -> Dataset:
    """Empty a fraction eta of each frame's occupied grid cells (paper Table 2).

    Of the m_p cells holding inference points, round(eta·m_p) (halves up) uniformly chosen cells
    lose their points from ``infer_mask``; at least one occupied cell always remains.
    ``eta`` is one number or one per frame.
    """
    _check_generator(rng)
    etas = _per_frame(eta, ds)
    if isinstance(eta, bool) or etas.dtype.kind not in "iuf" or not np.all((etas >= 0.0) & (etas < 1.0)):
        raise InputError(f"eta must be a number in [0, 1), got {eta!r}")
    cells, occupied = _occupied_cells(ds, grid)
    infer = ds.infer_mask.copy()
    for f, occ in enumerate(occupied):
        k = min(int(math.floor(etas[f] * len(occ) + 0.5)), len(occ) - 1)
        if k > 0:
            infer[f] &= ~np.isin(cells[f], rng.choice(occ, k, replace=False))
    return replace(ds, infer_mask=infer)


PLANE_TOLERANCE = 1e-3  # of the distance between a point and its nearest neighbour: "on the plane"


def _keep_in_each_frame(ds: Dataset, points: np.ndarray, min_points: int, choose) -> Dataset:
    """Per frame with at least ``min_points`` inference points, keep those that
    ``choose(points[f, inference])`` selects (a boolean mask or indices over them), or all of
    them where it returns None. Frames are visited in order, so the draws of ``choose`` are too."""
    infer = ds.infer_mask.copy()
    for f in range(ds.n_frames):
        idx = np.flatnonzero(infer[f])
        if len(idx) < min_points:
            continue
        keep = choose(points[f, idx])
        if keep is not None:
            infer[f] = False
            infer[f, idx[keep]] = True
    return replace(ds, infer_mask=infer)


def _on_one_plane(X: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """Mask of the points X (N, 3) on the plane of a random one and its three nearest; None if collinear."""
    distance = np.linalg.norm(X - X[rng.integers(len(X))], axis=1)
    near = np.argsort(distance)[:4]
    centre = X[near].mean(0)
    _, s, vt = np.linalg.svd(X[near] - centre)
    if s[1] <= 1e-6 * s[0]:
        return None
    return np.abs((X - centre) @ vt[2]) <= PLANE_TOLERANCE * distance[near[1]]


def one_plane(ds: Dataset, rng: np.random.Generator) -> Dataset:
    """Keep, per frame, the inference points on one plane: that through a uniformly chosen
    inference point and its three nearest ones (in 3D), within PLANE_TOLERANCE of the distance
    to the nearest. Frames with fewer than four inference points, or where those four are
    collinear, keep their points."""
    _check_generator(rng)
    return _keep_in_each_frame(ds, ds.points_3d, 4, lambda X: _on_one_plane(X, rng))


def _on_two_objects(x: np.ndarray, rng: np.random.Generator, group_points: tuple, n_points: tuple) -> np.ndarray:
    """Indices of the points x (N, 2) px that two_objects keeps."""
    first = rng.integers(len(x))
    distance = np.linalg.norm(x - x[first], axis=1)
    second = rng.choice(len(x), p=distance / distance.sum()) if distance.sum() > 0 else first
    groups = set()
    for to_centre in (distance, np.linalg.norm(x - x[second], axis=1)):
        nearest = np.argsort(to_centre, kind="stable")
        groups.update(nearest[: rng.integers(group_points[0], group_points[1] + 1)].tolist())
    groups = np.array(sorted(groups))
    return rng.choice(groups, min(len(groups), int(rng.integers(n_points[0], n_points[1] + 1))), replace=False)


def two_objects(
    ds: Dataset, rng: np.random.Generator, group_points: tuple = (60, 140), n_points: tuple = (40, 100)
) -> Dataset:
    """Keep, per frame, the inference points a user would label on two objects apart in the
    image (the paper's LEGO test: two buildings): around a uniformly chosen inference point and
    a second one drawn with probability proportional to its distance (px) from the first, the
    g ~ U(group_points) inference points nearest (px) to each; of these, n ~ U(n_points) drawn
    uniformly stay. Both ranges are inclusive. Frames with fewer than two inference points keep
    them. Label noise is ``add_noise``'s."""
    _check_generator(rng)
    for name, (low, high) in (("group_points", group_points), ("n_points", n_points)):
        if not MIN_POINTS <= low <= high:
            raise InputError(f"{name} must be a range ({MIN_POINTS} <= low <= high), got {(low, high)!r}")
    return _keep_in_each_frame(ds, ds.points_2d, 2, lambda x: _on_two_objects(x, rng, group_points, n_points))


def occupancy(ds: Dataset, grid: Grid) -> float:
    """Mean grid occupancy gamma = m_p / (u·v) over frames, m_p = cells holding inference points."""
    _, occupied = _occupied_cells(ds, grid)
    return float(np.mean([len(occ) for occ in occupied])) / grid.n_cells

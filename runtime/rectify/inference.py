"""The network's K for a batch of frames, written once for the rectifier's batches and the
evaluation's predictors: grid feature -> Delta K -> the K-bounds rule, and the statistics the
uncertainty model reads."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from dimenet.runtime.geometry import covariance_invariants_batch, k_params, mean_residual_norms
from dimenet.runtime.rectify.features import CHANNELS, FeatureSpec, grid_features
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.uncertainty import input_statistics


@dataclass(frozen=True)
class NetworkK:
    """B frames through the network: features (B, D) the grid feature; points (B, 6, N) its raw
    point rows (``grid_features(..., return_points=True)``: rows 0-1, the PMD, are each point's
    residual under K_c at the C0 pose); delta_k (B, 4) px; k = k_c + delta_k (B, 4) px (fx, fy,
    cx, cy); plausible (B,) bool, k inside the spec's K_bounds (``ModelSpec.k_within_bounds``)."""

    features: np.ndarray
    points: np.ndarray
    delta_k: np.ndarray
    k: np.ndarray
    plausible: np.ndarray

    def pmd_norms(self, mask: Optional[np.ndarray]) -> np.ndarray:
        """(B,) px: the mean PMD norm over each frame's ``mask`` (B, N) points (None: all)."""
        return mean_residual_norms(self.points[:, :2], mask)


def network_k(
    spec: ModelSpec,
    delta_k: Callable[[np.ndarray], np.ndarray],
    points_2d: np.ndarray,
    points_3d: np.ndarray,
    mask: Optional[np.ndarray],
    poses: Optional[tuple] = None,
) -> NetworkK:
    """The network's K of B frames from their inference points ``mask`` (B, N) bool (None: all):
    points_2d (B, N, 2) px, points_3d (B, N, 3) mm in {W}; delta_k maps features (B, D) float32 to
    (B, 4) px (a model backend); poses (rvec_c0, tvec_c0) the C0 poses, else solved here. A frame without
    an inference point (a batch's refused frame) is not read: its features and point rows are 0, its
    Delta K 0."""
    read = None if mask is None else mask.any(1)
    if read is not None and not read.all():
        B, N = points_2d.shape[:2]
        feats, points, dk = np.zeros((B, spec.features.size)), np.zeros((B, len(CHANNELS) + 1, N)), np.zeros((B, 4))
        if read.any():
            some = network_k(
                spec,
                delta_k,
                points_2d[read],
                points_3d[read],
                mask[read],
                None if poses is None else (poses[0][read], poses[1][read]),
            )
            feats[read], points[read], dk[read] = some.features, some.points, some.delta_k
    else:
        feats, points = grid_features(
            points_2d, points_3d, mask, spec.K_c, spec.image_size, spec.features, poses=poses, return_points=True
        )
        dk = np.asarray(delta_k(feats.astype(np.float32)), dtype=np.float64)
    k = k_params(spec.K_c) + dk
    return NetworkK(features=feats, points=points, delta_k=dk, k=k, plausible=spec.k_within_bounds(k))


def network_statistics(
    net: NetworkK,
    rows: np.ndarray,
    mask: np.ndarray,
    points_3d: np.ndarray,
    features: FeatureSpec,
    pmd_norms: Optional[np.ndarray] = None,
    invariants_3d: Optional[tuple] = None,
) -> np.ndarray:
    """The uncertainty statistics (``rectify.uncertainty.input_statistics``) of the frames
    ``rows`` (B,) bool of ``net``, from their inference points ``mask`` (B, N) bool and
    points_3d (B, N, 3) mm, ``features`` the model's FeatureSpec (its grid part is read): (R, 4) for
    the R selected frames. ``pmd_norms`` (R,) px and
    ``invariants_3d`` (the ``covariance_invariants_batch`` of their inference points) may be
    passed when the caller has them."""
    m = mask[rows]
    if pmd_norms is None:
        pmd_norms = mean_residual_norms(net.points[rows, :2], m)
    if invariants_3d is None:
        invariants_3d = covariance_invariants_batch(points_3d[rows], m)
    grid = net.features[rows, : features.grid_size]
    return input_statistics(grid, m.sum(1), pmd_norms, invariants_3d, len(features.channels))

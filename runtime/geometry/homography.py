"""The homography floor of a planar frame: the best reprojection error any pinhole camera reaches
on points of one plane.

The image of a plane under any K (zero skew) and pose is a homography of the plane's own
coordinates, and a generic homography is one (its two constraints on the image of the absolute
conic leave K two degrees of freedom), so the least-squares homography's error is what no K can
beat. It stands in for e* on a frame whose K is not observable (one view of one plane):
training/METHOD.md, "Metric and protocol".
"""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.geometry.projection import residual_norms


def plane_coordinates(points_3d: np.ndarray) -> np.ndarray:
    """(N, 3) points of one plane (mm) -> (N, 2) their coordinates (mm) along the plane's two
    principal axes about their centroid."""
    centred = points_3d - points_3d.mean(0)
    axes = np.linalg.svd(centred, full_matrices=False)[2][:2]
    return centred @ axes.T


def homography_floor(points_2d: np.ndarray, points_3d: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per frame of B, the mean Euclidean reprojection error (px, over its valid points) of the
    least-squares homography from its 3D points' plane coordinates to its 2D points (px)
    (``cv2.findHomography``: DLT, then Levenberg-Marquardt on the reprojection error, as e* is
    fitted): points_2d (B, N, 2) px, points_3d (B, N, 3), valid (B, N) bool -> (B,) px. NaN for a
    frame of fewer than 4 points or no homography."""
    floors = np.full(len(points_2d), np.nan)
    for b in range(len(points_2d)):
        x, X = points_2d[b][valid[b]], points_3d[b][valid[b]]
        if len(x) < 4:
            continue
        uv = np.ascontiguousarray(plane_coordinates(X))
        H, _ = cv2.findHomography(uv, np.ascontiguousarray(x), 0)
        if H is None or not np.all(np.isfinite(H)):
            continue
        floors[b] = float(residual_norms((cv2.perspectiveTransform(uv[None], H)[0] - x).T).mean())
    return floors

"""Pinhole geometry, the one home of projection, rotation, PnP starts and least squares.

Pure numpy/OpenCV functions; conventions in models_spec/conventions.md. The package exports
the functions of its modules (camera, rotation, spread, pnp, normal_equations);
``least_squares`` (the batched LM core) is imported as a module.
"""

from dimenet.runtime.geometry.camera import (
    MIN_DEPTH_MM,
    camera_centre,
    camera_xy_inverse_depth,
    facing,
    k_matrix,
    k_params,
    mean_over,
    mean_reprojection_error,
    mean_residual_norms,
    min_depths,
    project,
    project_camera,
    reprojection_errors,
    reprojection_residuals,
    rescaled_k,
    rescaled_px,
    residual_norms,
    to_camera,
)
from dimenet.runtime.geometry.normal_equations import frame_normal_equations
from dimenet.runtime.geometry.pnp import (
    MIN_POINTS,
    MIN_POSE_POINTS,
    check_not_degenerate,
    dlt_camera,
    planar_focal,
    solve_pnp_start,
)
from dimenet.runtime.geometry.rotation import (
    FEW_POSES,
    left_update,
    matrix_to_rvec,
    rotation_matrices,
    rvec_to_matrix,
    skew,
)
from dimenet.runtime.geometry.spread import (
    MAX_COORDINATE,
    PLANAR_RATIO,
    RIG_VIEW_RATIO,
    covariance_invariants,
    covariance_invariants_batch,
    spans_3d,
)

__all__ = [
    "MIN_DEPTH_MM",
    "k_params",
    "k_matrix",
    "rescaled_px",
    "rescaled_k",
    "to_camera",
    "project_camera",
    "project",
    "camera_xy_inverse_depth",
    "reprojection_residuals",
    "residual_norms",
    "reprojection_errors",
    "mean_reprojection_error",
    "min_depths",
    "mean_over",
    "mean_residual_norms",
    "camera_centre",
    "facing",
    "FEW_POSES",
    "skew",
    "rvec_to_matrix",
    "rotation_matrices",
    "matrix_to_rvec",
    "left_update",
    "PLANAR_RATIO",
    "RIG_VIEW_RATIO",
    "MAX_COORDINATE",
    "covariance_invariants",
    "covariance_invariants_batch",
    "spans_3d",
    "MIN_POINTS",
    "MIN_POSE_POINTS",
    "check_not_degenerate",
    "solve_pnp_start",
    "dlt_camera",
    "planar_focal",
    "frame_normal_equations",
]

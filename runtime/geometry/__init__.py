"""Pinhole geometry, the one home of projection, rotation, PnP starts and least squares.

Pure numpy/OpenCV functions; conventions in models_spec/conventions.md. Everything outside
geometry imports from this package (``from dimenet.runtime.geometry import project``): it hands
on the public functions of its modules (projection, rotation, spread, pnp, normal_equations,
residual_structure, homography, distortion, least_squares, lens_bundle); ``least_squares`` and
``lens_division``, whose names are generic (``fit``, ``distort``), are also taken as modules.
"""

from dimenet.runtime.geometry.distortion import (
    distort_points,
    distort_points_with_jacobians,
    mean_distorted_error,
    undistort_points,
)
from dimenet.runtime.geometry.homography import homography_floor, plane_coordinates
from dimenet.runtime.geometry.least_squares import calibrate, solve_pnp
from dimenet.runtime.geometry.lens_bundle import fit_lens_bundle
from dimenet.runtime.geometry.normal_equations import (
    frame_normal_equations,
    gram_normal_equations,
    monomial_gram,
    prior_posterior,
    prior_step,
)
from dimenet.runtime.geometry.pnp import (
    MIN_POINTS,
    MIN_POSE_POINTS,
    check_not_degenerate,
    dlt_camera,
    planar_focal,
    solve_pnp_start,
)
from dimenet.runtime.geometry.projection import (
    MIN_DEPTH_MM,
    camera_centre,
    camera_xy_inverse_depth,
    facing,
    frame_error_and_depth,
    frame_mean_norm,
    frame_residuals,
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
from dimenet.runtime.geometry.residual_structure import (
    MIN_STRUCTURE_POINTS,
    ResidualStructure,
    residual_structure,
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
    "homography_floor",
    "plane_coordinates",
    "MIN_STRUCTURE_POINTS",
    "ResidualStructure",
    "residual_structure",
    "distort_points",
    "distort_points_with_jacobians",
    "mean_distorted_error",
    "undistort_points",
    "calibrate",
    "solve_pnp",
    "fit_lens_bundle",
    "frame_error_and_depth",
    "frame_mean_norm",
    "frame_residuals",
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
    "gram_normal_equations",
    "monomial_gram",
    "prior_posterior",
    "prior_step",
]

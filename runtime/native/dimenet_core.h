/* dimenet_core: the compiled core of the DIME-Net runtime's per-frame feature stage.
 *
 * A plain C99 library (libc and libm only): a mobile app compiles dimenet_*.c beside ONNX Runtime
 * Mobile and feeds the feature it writes to the model, as the Python runtime does through its thin
 * CPython binding (_module*.c). The numpy code is the reference (runtime/rectify/features.py,
 * runtime/geometry/normal_equations.py); this library computes the same numbers, in the same
 * operation order where it can (sums in point order, numpy's pairwise sums where numpy sums an axis,
 * OpenCV's Rodrigues formula and Cholesky inverse), within 1e-12 of the scaled features
 * (tests/native/): bit for bit where the reference fixes its order (its data step, whose Hessian
 * can have a condition number near 1e9, must be). Compile it with floating-point contraction off
 * (gcc/clang: -ffp-contract=off) so that a * b + c is not fused into one rounding: the reference does not fuse.
 *
 * Units and frames: pixels (px) in the image the prior K_c describes, OpenCV's convention (the
 * centre of the top-left pixel at (0, 0)); points in the world frame {W} in the scene's unit (mm in
 * the names); {C0} the camera frame of the pose {W} -> {C0} solved under K_c (the C0 pose), X_C0 =
 * R(rvec) X_W + tvec, Z_C0 > 0 in front of the camera.
 *
 * Rules of every entry point: sizes and bounds come from the caller; every buffer is the caller's
 * (outputs and a scratch buffer sized by dimenet_scratch_doubles), nothing is allocated; no state is
 * kept between calls (any number of threads may call at once on their own buffers); a bad argument
 * returns an error code (DIMENET_E_*), never an abort. NaN and inf in the inputs are not errors: they
 * propagate as numpy's do (a NaN pixel falls in the first cell), until a check below refuses them. */
#ifndef DIMENET_CORE_H
#define DIMENET_CORE_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Error codes (dimenet_error_message gives each one's text). */
#define DIMENET_OK 0
#define DIMENET_E_ARGUMENT 1          /* a NULL pointer, a bad spec or a buffer of the wrong size */
#define DIMENET_E_BEHIND_CAMERA 2     /* a used point is not in front of the camera at the C0 pose */
#define DIMENET_E_HESSIAN_DIAGONAL 3  /* the data step's Hessian has a zero or non-finite diagonal */
#define DIMENET_E_NOT_POSITIVE_DEFINITE 4 /* the data step's Hessian is not positive definite */
#define DIMENET_E_NO_POSE_STEP 5      /* dimenet_pose_steps: a step's pose block is not positive definite,
                                         or the pose is not finite */
#define DIMENET_E_PRIOR_COVARIANCE 6  /* dimenet_map_step: the prior's covariance is not positive definite */

/* A point's raw channels, in the reference's CHANNELS order: the projection model discrepancy (PMD)
 * dx, dy = K_c proj(X_C0) - x (px), then X_C0, Y_C0 (mm) and 1 / Z_C0 (1/mm). */
#define DIMENET_CHANNEL_DX 0
#define DIMENET_CHANNEL_DY 1
#define DIMENET_CHANNEL_X 2
#define DIMENET_CHANNEL_Y 3
#define DIMENET_CHANNEL_INV_Z 4
#define DIMENET_CHANNELS 5
/* The point rows a frame writes (dimenet_frame_features' point_rows): the five channels, then 1. */
#define DIMENET_POINT_ROWS 6
/* The data step's inputs: Delta K (fx, fy, cx, cy) times the PMD's scale, then the four log sigma ratios. */
#define DIMENET_STEP_SIZE 8
/* The moments: the upper triangle of the 11 x 11 monomial Gram, less its [1 * 1] and [1 * z]. */
#define DIMENET_MOMENT_SIZE 64
/* The monomials of a point: 1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z (a = X/Z, b = Y/Z), dx, dy. */
#define DIMENET_GRAM_SIZE 11

/* The feature of a model (its spec's "features" object, models_spec/model-v1.md) and the camera it
 * serves. */
typedef struct dimenet_feature_spec {
    int grid_cols;                   /* u, cells along x, >= 1 */
    int grid_rows;                   /* v, cells along y, >= 1 */
    double image_width_px;           /* the image the grid splits: finite, > 0 */
    double image_height_px;
    int n_channels;                  /* 1 to DIMENET_CHANNELS (variant A: 5, B: 2, C: 3, D: 4, E: 3) */
    int channels[DIMENET_CHANNELS];  /* the first n_channels: DIMENET_CHANNEL_* in the feature's order */
    double channel_scale[DIMENET_CHANNELS]; /* the scale of each of them (1/px, 1/mm or mm) */
    double depth_mm;                 /* scale-free depth: each frame's {C0} read as if its mean depth
                                        were depth_mm (finite, > 0); 0: the frame's own unit */
    int data_step;                   /* nonzero: the data step's DIMENET_STEP_SIZE inputs follow the grid */
    int moments;                     /* nonzero: then the DIMENET_MOMENT_SIZE moments */
    double pmd_scale_per_px;         /* the PMD's scale (the spec's dx scale), the step's and moments' */
    double K_c_px[9];                /* the prior K_c (3 x 3, row major, px): fx_c K_c_px[0], fy_c [4] */
} dimenet_feature_spec;

/* What a frame's kernel measured beside its feature. */
typedef struct dimenet_frame_stats {
    double e_c_px;       /* mean Euclidean norm of the used points' PMD (px): e(K_c) at the C0 pose
                            (geometry.frame_mean_norm: the norms summed in cv::sum's order, four
                            at a time); NaN without a used point */
    size_t n_used;       /* the points the mask keeps (all without one) */
    size_t n_behind;     /* of them, those with 1 / Z_C0 <= 0 */
} dimenet_frame_stats;

/* Flag of dimenet_frame_features: refuse a frame whose used points are not all in front of the
 * camera (1 / Z_C0 outside [0, inf), NaN included) with DIMENET_E_BEHIND_CAMERA, after the feature
 * (so a Hessian error comes first, as in the reference). Without it the feature is computed anyway
 * (the reference's grid_features). */
#define DIMENET_REFUSE_BEHIND_CAMERA 1u

/* The feature's length for a spec: n_channels x cells, + DIMENET_STEP_SIZE, + DIMENET_MOMENT_SIZE.
 * DIMENET_E_ARGUMENT for a spec that is not valid (the checks above) or whose length overflows. */
int dimenet_feature_size(const dimenet_feature_spec *spec, size_t *n_features);

/* The doubles of scratch dimenet_frame_features needs for a frame of n_points points:
 * 18 n_points + 6 cells. DIMENET_E_ARGUMENT for a bad spec or an overflow. */
int dimenet_scratch_doubles(const dimenet_feature_spec *spec, size_t n_points, size_t *n_scratch);

/* One frame's feature (the reference's grid_features for one frame, then gram_inputs), at its C0
 * pose.
 *
 * points_2d_px (n_points x 2, x then y), points_3d_w_mm (n_points x 3) the correspondences; mask
 * (n_points, nonzero: used) the points the feature reads, NULL: all; rvec_w_to_c0_rad and
 * tvec_w_to_c0_mm (3 each) the C0 pose; flags 0 or DIMENET_REFUSE_BEHIND_CAMERA.
 * Writes features (n_features, which must be dimenet_feature_size's) and, when point_rows is not
 * NULL, the raw point rows (DIMENET_POINT_ROWS x n_points, channel major: dx, dy px, X_C0, Y_C0 mm,
 * 1/Z_C0 1/mm, 1; an unused point's rows are those of a point at the origin of {W} seen at pixel
 * (0, 0)); stats (may be NULL). scratch: n_scratch >= dimenet_scratch_doubles's doubles.
 * Returns DIMENET_OK, DIMENET_E_ARGUMENT, DIMENET_E_HESSIAN_DIAGONAL, DIMENET_E_NOT_POSITIVE_DEFINITE
 * (the data step on points that fix no pose) or DIMENET_E_BEHIND_CAMERA (with the flag); on an error
 * the outputs are unspecified. */
int dimenet_frame_features(const dimenet_feature_spec *spec, size_t n_points, const double *points_2d_px,
                           const double *points_3d_w_mm, const unsigned char *mask, const double rvec_w_to_c0_rad[3],
                           const double tvec_w_to_c0_mm[3], unsigned flags, double *features, size_t n_features,
                           double *point_rows, double *scratch, size_t n_scratch, dimenet_frame_stats *stats);

/* rectify.uncertainty.occupied_cells of one frame: of the n_cells cells of its grid feature (n_cells x
 * n_channels, cell by cell, channels inside), those with a channel that is not 0 (a NaN counts). *occupied the
 * count. DIMENET_E_ARGUMENT for a NULL pointer, no channel or a size that overflows. */
int dimenet_occupied_cells(size_t n_cells, size_t n_channels, const double *grid, size_t *occupied);

/* rectify.uncertainty.Uncertainty.frame_covariance: the network's covariance of Delta K (4 x 4 px^2, row major,
 * into k_cov_px2) of one frame from its statistics n_points and occupied_cells (counts >= 1), mean_pmd_px and
 * thickness_3d, the last two floored at d_floor_px and t_floor (Python's max: a NaN stays). With z = (log n,
 * log m, log d, log t) and coef (4 x (1 + n_columns), row major) weighing [1, z[columns[0]], ...], sigma_p =
 * exp(coef_p0 + coef_p1 z[columns[0]] + ...) summed left to right, and k_cov_px2[p][q] = (sigma_p sigma_q)
 * correlation[p][q]. DIMENET_E_ARGUMENT for a NULL pointer, more than four columns, a column outside 0 to 3 or a
 * count below 1. */
int dimenet_network_covariance(double n_points, double occupied_cells, double mean_pmd_px, double thickness_3d,
                               double d_floor_px, double t_floor, size_t n_columns, const unsigned char *columns,
                               const double *coef, const double correlation[16], double k_cov_px2[16]);

/* The monomial Gram (DIMENET_GRAM_SIZE x DIMENET_GRAM_SIZE, row major) Q Q^T of n_points points, Q the
 * monomials 1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z (a = X/Z, b = Y/Z) and the residuals r_u, r_v of each:
 * x_c0_mm, y_c0_mm, inv_z_c0_per_mm the points in {C} (n_points each), residual_u_px, residual_v_px
 * theirs (the reference's geometry.monomial_gram: each entry numpy's pairwise sum over the points). */
int dimenet_monomial_gram(size_t n_points, const double *x_c0_mm, const double *y_c0_mm,
                          const double *inv_z_c0_per_mm, const double *residual_u_px, const double *residual_v_px,
                          double gram[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE]);

/* The inverse (10 x 10, row major) of the Gauss-Newton Hessian weight J J^T + the prior's precision
 * k_precision_per_px2 on the diagonal of the K block (the reference's geometry.prior_posterior with a
 * diagonal prior): jj (10 x 10) over (w rad, tau mm, fx, fy, cx, cy px), inverted with its diagonal
 * scaled to 1 by OpenCV's Cholesky. DIMENET_E_HESSIAN_DIAGONAL, DIMENET_E_NOT_POSITIVE_DEFINITE. */
int dimenet_prior_posterior(const double jj[100], double k_precision_per_px2, double weight_per_px2,
                            double inverse[100]);

/* The most Gauss-Newton steps dimenet_pose_steps takes. */
#define DIMENET_MAX_POSE_STEPS 64

/* The doubles of scratch dimenet_pose_steps needs for n_points points: 12 n_points. DIMENET_E_ARGUMENT
 * on an overflow. */
int dimenet_pose_scratch_doubles(size_t n_points, size_t *n_scratch);

/* The pose under the pinhole k_px (fx, fy, cx, cy) after `steps` (0 to DIMENET_MAX_POSE_STEPS)
 * Gauss-Newton steps of the reprojection error from the start pose (the reference's
 * geometry.pose_step.pose_steps, to the bit): the pose perturbed on the left (X_C -> exp([w]x) X_C +
 * tau), the step -(J J^T)^-1 J r of geometry.pose_step.pose_normal_equations (40 products of the pose's
 * Jacobian rows and the residuals at the current pose, numpy's pairwise sums), solved by Cholesky; the rotation carried
 * as a unit quaternion. points_2d_px (n_points x 2), points_3d_w_mm (n_points x 3); rvec_rad, tvec_mm
 * (3 each) the result (may alias the start); when e_px and depth_mm are both not NULL, the mean
 * reprojection error (px) and the smallest Z_C (mm) at that pose (geometry.frame_error_and_depth, to the
 * bit; with steps 0, that function alone). scratch: n_scratch >= dimenet_pose_scratch_doubles's (not read,
 * may be NULL, with steps 0). Returns DIMENET_OK, DIMENET_E_ARGUMENT or DIMENET_E_NO_POSE_STEP (the
 * outputs then untouched). */
int dimenet_pose_steps(size_t n_points, const double *points_2d_px, const double *points_3d_w_mm,
                       const double k_px[4], const double rvec_start_rad[3], const double tvec_start_mm[3], int steps,
                       double rvec_rad[3], double tvec_mm[3], double *e_px, double *depth_mm, double *scratch,
                       size_t n_scratch);

/* The doubles of scratch dimenet_map_step needs for n_points points: 9 n_points. DIMENET_E_ARGUMENT on an
 * overflow. */
int dimenet_map_scratch_doubles(size_t n_points, size_t *n_scratch);

/* Mode map's Gauss-Newton step (the reference's geometry.map_step.map_steps with one step, to the bit): the
 * MAP cost sum |pi(k, R X + t) - x|^2 / s^2 + (k - k_prior)^T P (k - k_prior) over (pose, k) from k_prior_px
 * (fx, fy, cx, cy) and the start pose rvec_start_rad, tvec_start_mm {W}->{C} turned first by turn_rad (3;
 * NULL: not turned), P the inverse of the prior's covariance k_cov_prior_px2 (4 x 4, row major; its lower
 * triangle is read, as OpenCV's Cholesky inverse reads it). s^2 is noise_px^2 floored at noise_floor_px^2, or
 * with noise_px < 0 the frame's own estimate (geometry.prior_step). The step is taken when it does not raise
 * the cost: *steps 1, k_px, R_w_to_c (3 x 3 row major), tvec_mm and residuals_px (n_points x 2: u, v) there;
 * else *steps 0 and the start's (k_prior, the turned pose). At that result, *e_px is the residuals' mean norm
 * (geometry.frame_mean_norm) and *depth_mm the smallest Z_C (NaN when one is NaN). cov (10 x 10) is the
 * inverse Gauss-Newton Hessian at the start over (w rad, tau mm, fx, fy, cx, cy px), *weight_per_px2 1 / s^2.
 * points_2d_px (n_points x 2), points_3d_w_mm (n_points x 3), n_points >= 1. scratch: n_scratch >=
 * dimenet_map_scratch_doubles's. Returns DIMENET_OK, DIMENET_E_ARGUMENT, DIMENET_E_PRIOR_COVARIANCE (its
 * Cholesky factorisation fails), DIMENET_E_HESSIAN_DIAGONAL or DIMENET_E_NOT_POSITIVE_DEFINITE (the points fix
 * no pose); the outputs are unspecified on an error. */
int dimenet_map_step(size_t n_points, const double *points_2d_px, const double *points_3d_w_mm,
                     const double k_prior_px[4], const double k_cov_prior_px2[16], const double rvec_start_rad[3],
                     const double tvec_start_mm[3], const double turn_rad[3], double noise_px, double noise_floor_px,
                     double k_px[4], double R_w_to_c[9], double tvec_mm[3], double cov[100], double *weight_per_px2,
                     double *residuals_px, double *e_px, double *depth_mm, int *steps, double *scratch,
                     size_t n_scratch);

/* Mode map's posterior of K (rectify.map_fit's K_cov, to the bit): the K block of cov (10 x 10, the map step's
 * inverse Hessian over (w, tau, fx, fy, cx, cy)), symmetrised as (A + A^T) / 2, then widened as
 * rectify.uncertainty.Uncertainty.map_covariance does when data_correlation (rho, 4) has a nonzero entry: each
 * parameter's standard deviation by sqrt(1 + 2 rho w sqrt(max(r (1 - r), 0))), r its posterior over its prior
 * variance (k_cov_prior_px2, the network's 4 x 4 px^2), w = s^2 / (s^2 + noise_scale_px^2) with s = noise_px
 * the frame's 2D noise; and when data_bias (b, 4) has a nonzero entry, plus the prior's covariance times b_p b_q.
 * k_cov_px2 (4 x 4 px^2, row major) the result. DIMENET_E_ARGUMENT for a NULL pointer. */
int dimenet_map_posterior(const double cov[100], const double k_cov_prior_px2[16], double noise_px,
                          const double data_correlation[4], double noise_scale_px, const double data_bias[4],
                          double k_cov_px2[16]);

/* One frame of the stream's Kalman filter over k = (fx, fy, cx, cy) px (rectify.stream_filter.stream_step to the
 * bit): the state k (4) px, P (4 x 4 px^2, row major) reset to (k_prior, Q) when reset, else carried dt_s >= 0 s
 * by the AR(1) about the priors (a = exp(-dt_s / tau_s), k' = k_prior + a (k - k_prior_last), P' = a_i a_j P +
 * (1 - a_i a_j) Q); then, unless reset, an innovation z - k whose squared norm under S = P + R exceeds chi2_limit
 * resets it (*jumped 1); then updated by the frame's z (4) px, R (4 x 4) px^2 with gain P S^-1 and P symmetrised
 * (*updated 1; 0 where S is not positive definite, the state then only carried) into k_out, P_out.
 * DIMENET_E_ARGUMENT for a NULL pointer or, unless reset, dt_s < 0 or NaN. */
int dimenet_stream_step(const double k[4], const double P[16], const double k_prior_last[4], const double k_prior[4],
                        const double z[4], const double R[16], const double Q[16], const double tau_s[4], double dt_s,
                        int reset, double chi2_limit, double k_out[4], double P_out[16], int *jumped, int *updated);

/* Bits of dimenet_frame_checks' result. */
#define DIMENET_CHECK_OUTSIDE 1u     /* a value not finite, a 2D point outside the image or a 3D coordinate
                                        outside [-max_coordinate, max_coordinate) */
#define DIMENET_CHECK_NOT_SPREAD 2u  /* the 2D or the 3D points are not clearly spread (the caller then
                                        decides with its exact test, rectify.checks.check_spread) */

/* The input rules' fast tests on one frame (rectify.checks.validated_frame's all_inside and clearly_spread):
 * points_2d_image_px (n_points x 2) the points as given, inside the image when each lies in [-0.5,
 * width_px - 0.5] x [-0.5, height_px - 0.5]; points_3d_w_mm (n_points x 3) each coordinate in
 * [-max_coordinate, max_coordinate); points_2d_px (n_points x 2, the model's pixels) and points_3d_w_mm
 * clearly spread: with T the trace and S the sum of principal 2 x 2 minors of their sample covariance
 * (1 / n), S > 3 spread_ratio T^2 and T > D spread_absolute scale^2, scale = max(|coordinate|, 1)
 * (a sufficient test). *result: 0 or the DIMENET_CHECK_* bits. invariants_3d (may be NULL): the trace, the
 * sum of principal 2 x 2 minors and the determinant of the 3D points' sample covariance (mm^2, mm^4, mm^6;
 * geometry.covariance_invariants to the bit: sums in point order) when the points are inside (the result is
 * not DIMENET_CHECK_OUTSIDE), else NaN. DIMENET_E_ARGUMENT for a NULL pointer or n_points < 1. */
int dimenet_frame_checks(size_t n_points, const double *points_2d_image_px, const double *points_2d_px,
                         const double *points_3d_w_mm, double width_px, double height_px, double max_coordinate,
                         double spread_ratio, double spread_absolute, unsigned *result, double invariants_3d[3]);

/* geometry.pnp.power_of_two_unit, to the bit: the power of two nearest the RMS norm of the points (mm; the
 * n_values / 3 rows of points_3d_w_mm, any n_values), by which a PnP solver's absolute tolerances see every
 * scene at the same size; 1 when that norm is 0 or not finite (a NaN or inf among the values included), at
 * most 2^1023.
 * *unit_mm the result. DIMENET_E_ARGUMENT for a NULL pointer. */
int dimenet_power_of_two_unit(size_t n_values, const double *points_3d_w_mm, double *unit_mm);

/* The text of an error code (the reference's InputError message where it has one); never NULL. */
const char *dimenet_error_message(int code);

#ifdef __cplusplus
}
#endif

#endif /* DIMENET_CORE_H */

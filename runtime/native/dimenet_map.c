/* dimenet_map: mode map's Gauss-Newton step over (pose, K) with the network's prior on K
 * (geometry/map_step.py, map_steps with one step), to the bit: every product in the reference's fixed order;
 * and its posterior of K, widened as the uncertainty model says (rectify/map_fit.py, rectify/uncertainty.py). */
#include "dimenet_internal.h"

#include <math.h>
#include <string.h>

/* Scratch doubles per point: X_C, Y_C, 1/Z_C and the residuals at the start (5), the residuals at the step
 * (2) and their squares (2). */
#define MAP_SCRATCH_PER_POINT 9

int dimenet_map_scratch_doubles(size_t n_points, size_t *n_scratch)
{
    if (n_scratch == NULL || n_points > ((size_t)-1) / sizeof(double) / MAP_SCRATCH_PER_POINT) {
        return DIMENET_E_ARGUMENT;
    }
    *n_scratch = MAP_SCRATCH_PER_POINT * n_points;
    return DIMENET_OK;
}

/* geometry.rotated: A (3 x 3) times B (3 x m, row major), ((A_i0 B_0j + A_i1 B_1j) + A_i2 B_2j). */
static void rotated(const double A[9], const double *B, int m, double *out)
{
    int i, j;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < m; j++) {
            out[i * m + j] = (A[3 * i] * B[j] + A[3 * i + 1] * B[m + j]) + A[3 * i + 2] * B[2 * m + j];
        }
    }
}

/* geometry.camera_rows, 1 / Z_C and geometry.pinhole_residuals (no skew) of the points at the pose (R, t)
 * under k: x, y, inv_z (may be NULL: not kept), du, dv (n each); returns the smallest Z_C (mm; np.min's: NaN
 * when one is NaN). */
static double pinhole_rows(size_t n, const double *p2, const double *p3, const double R[9], const double t[3],
                           const double k[4], double *x, double *y, double *inv_z, double *du, double *dv)
{
    double depth = HUGE_VAL;
    size_t i;
    for (i = 0; i < n; i++) {
        double X = p3[3 * i], Y = p3[3 * i + 1], Z = p3[3 * i + 2];
        double xc = ((R[0] * X + R[1] * Y) + R[2] * Z) + t[0];
        double yc = ((R[3] * X + R[4] * Y) + R[5] * Z) + t[1];
        double zc = ((R[6] * X + R[7] * Y) + R[8] * Z) + t[2];
        double iz = 1.0 / zc;
        du[i] = ((xc * iz) * k[0] + k[2]) - p2[2 * i];
        dv[i] = ((yc * iz) * k[1] + k[3]) - p2[2 * i + 1];
        if (inv_z != NULL) {
            x[i] = xc, y[i] = yc, inv_z[i] = iz;
        }
        depth = dimenet__depth_min(depth, zc);
    }
    return depth;
}

int dimenet_map_step(size_t n_points, const double *points_2d_px, const double *points_3d_w_mm,
                     const double k_prior_px[4], const double k_cov_prior_px2[16], const double rvec_start_rad[3],
                     const double tvec_start_mm[3], const double turn_rad[3], double noise_px, double noise_floor_px,
                     double k_px[4], double R_w_to_c[9], double tvec_mm[3], double cov[100], double *weight_per_px2,
                     double *residuals_px, double *e_px, double *depth_mm, int *steps, double *scratch,
                     size_t n_scratch)
{
    const size_t N = n_points;
    double R0[9], R[9], t[3], T[9], G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE], JJ[100], Jr[10], rss, step[10];
    double weight, dR[9], R_new[9], t_new[3], k_new[4], d[4], Pd[4], cost, cost_new, depth, depth_new;
    double prior_cov[16], precision[16];
    double *x, *y, *inv_z, *du, *dv, *du_new, *dv_new, *squares;
    dimenet__norm_sum norms = {{0.0}, 0.0, 0};
    size_t need = 0, i;
    int code, k, taken;
    dimenet__gram_points points;

    if (dimenet_map_scratch_doubles(N, &need) != DIMENET_OK || N < 1 || points_2d_px == NULL
        || points_3d_w_mm == NULL || k_prior_px == NULL || k_cov_prior_px2 == NULL || rvec_start_rad == NULL
        || tvec_start_mm == NULL || k_px == NULL || R_w_to_c == NULL || tvec_mm == NULL || cov == NULL
        || weight_per_px2 == NULL || residuals_px == NULL || e_px == NULL || depth_mm == NULL || steps == NULL
        || scratch == NULL || n_scratch < need) {
        return DIMENET_E_ARGUMENT;
    }
    x = scratch, y = x + N, inv_z = y + N, du = inv_z + N, dv = du + N;
    du_new = dv + N, dv_new = du_new + N, squares = dv_new + N;

    /* the prior's precision: cv2.invert(K_cov, DECOMP_CHOLESKY) */
    memcpy(prior_cov, k_cov_prior_px2, sizeof prior_cov);
    if (!dimenet__cholesky_inverse(prior_cov, 4, precision)) {
        return DIMENET_E_PRIOR_COVARIANCE;
    }

    /* the start pose, turned (geometry.map_step.principal_point_turn's rotation) */
    dimenet__rodrigues(rvec_start_rad, R0);
    if (turn_rad != NULL) {
        dimenet__rodrigues(turn_rad, T);
        rotated(T, R0, 3, R);
        rotated(T, tvec_start_mm, 1, t);
    } else {
        memcpy(R, R0, sizeof R);
        memcpy(t, tvec_start_mm, sizeof t);
    }
    /* frame_normal_equations at (k_prior, the start pose), then prior_step or the known noise's posterior */
    depth = pinhole_rows(N, points_2d_px, points_3d_w_mm, R, t, k_prior_px, x, y, inv_z, du, dv);
    points.lanes = NULL, points.stride = 0;
    points.x = x, points.y = y, points.inv_z = inv_z, points.du = du, points.dv = dv;
    dimenet__gram_of(&points, N, G);
    dimenet__gram_normal_equations(G, k_prior_px[0], k_prior_px[1], JJ, Jr, &rss);
    if (noise_px < 0.0) {
        code = dimenet__prior_step(JJ, Jr, rss, (long)(2 * N), precision, noise_floor_px, step, cov,
                                   &weight);
    } else { /* 1 / max(noise_px, floor) ** 2 (Python's max) */
        weight = 1.0 / dimenet__python_square(noise_floor_px > noise_px ? noise_floor_px : noise_px);
        code = dimenet__posterior_step(JJ, Jr, precision, weight, step, cov);
    }
    if (code != DIMENET_OK) {
        return code;
    }
    cost = weight * rss;

    /* the step: k + step[6:], the pose by geometry.left_update; its cost with the prior's term */
    for (k = 0; k < 4; k++) {
        k_new[k] = k_prior_px[k] + step[6 + k];
        d[k] = k_new[k] - k_prior_px[k];
    }
    dimenet__rodrigues(step, dR);
    rotated(dR, R, 3, R_new);
    rotated(dR, t, 1, t_new);
    for (k = 0; k < 3; k++) {
        t_new[k] += step[3 + k];
    }
    depth_new = pinhole_rows(N, points_2d_px, points_3d_w_mm, R_new, t_new, k_new, NULL, NULL, NULL, du_new, dv_new);
    for (i = 0; i < N; i++) { /* np.multiply(res, res).ravel().sum(): the u row, then the v row */
        squares[i] = du_new[i] * du_new[i];
        squares[N + i] = dv_new[i] * dv_new[i];
    }
    dimenet__matvec(precision, d, 4, Pd);
    cost_new = weight * dimenet__pairwise_sum(squares, 2 * N) + dimenet__pairwise_dot(d, Pd, 4);
    taken = cost_new <= cost;

    memcpy(k_px, taken ? k_new : k_prior_px, 4 * sizeof(double));
    memcpy(R_w_to_c, taken ? R_new : R, sizeof R);
    memcpy(tvec_mm, taken ? t_new : t, sizeof t);
    for (i = 0; i < N; i++) { /* and geometry.frame_mean_norm of them */
        residuals_px[2 * i] = taken ? du_new[i] : du[i];
        residuals_px[2 * i + 1] = taken ? dv_new[i] : dv[i];
        dimenet__norm_add(&norms, sqrt(residuals_px[2 * i] * residuals_px[2 * i]
                                       + residuals_px[2 * i + 1] * residuals_px[2 * i + 1]));
    }
    *e_px = dimenet__norm_mean(&norms);
    *depth_mm = taken ? depth_new : depth;
    *weight_per_px2 = weight;
    *steps = taken;
    return DIMENET_OK;
}

int dimenet_map_posterior(const double cov[100], const double k_cov_prior_px2[16], double noise_px,
                          const double data_correlation[4], double noise_scale_px, const double data_bias[4],
                          double k_cov_px2[16])
{
    double scale[4], w, s2;
    int i, j, widens = 0, biased = 0;
    if (cov == NULL || k_cov_prior_px2 == NULL || data_correlation == NULL || data_bias == NULL
        || k_cov_px2 == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (i = 0; i < 4; i++) { /* map_fit: (cov[6:, 6:] + cov[6:, 6:].T) / 2 */
        for (j = 0; j < 4; j++) {
            k_cov_px2[4 * i + j] = (cov[10 * (6 + i) + 6 + j] + cov[10 * (6 + j) + 6 + i]) / 2.0;
        }
        widens |= data_correlation[i] != 0.0;
        biased |= data_bias[i] != 0.0;
    }
    if (widens) { /* Uncertainty.posterior_scale, in Python's float order */
        s2 = noise_px * noise_px;
        w = s2 / (s2 + dimenet__python_square(noise_scale_px));
        for (i = 0; i < 4; i++) {
            double r = k_cov_px2[5 * i] / k_cov_prior_px2[5 * i], q = r * (1.0 - r);
            q = 0.0 > q ? 0.0 : q; /* Python's max(q, 0.0): q unless 0.0 is larger (a NaN stays) */
            scale[i] = data_correlation[i] != 0.0 ? sqrt(1.0 + 2.0 * data_correlation[i] * w * sqrt(q)) : 1.0;
        }
        for (i = 0; i < 4; i++) {
            for (j = 0; j < 4; j++) {
                k_cov_px2[4 * i + j] = k_cov_px2[4 * i + j] * (scale[i] * scale[j]);
            }
        }
    }
    if (biased) { /* + network * outer(b, b) */
        for (i = 0; i < 4; i++) {
            for (j = 0; j < 4; j++) {
                double b = data_bias[i] * data_bias[j];
                k_cov_px2[4 * i + j] = k_cov_px2[4 * i + j] + k_cov_prior_px2[4 * i + j] * b;
            }
        }
    }
    return DIMENET_OK;
}

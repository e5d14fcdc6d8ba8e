/* dimenet_pose: the pose under K as Gauss-Newton steps from the C0 pose (geometry/pose_step.py), and
 * e(K) with the depth test at a pose (geometry.frame_error_and_depth). */
#include "dimenet_internal.h"

#include <math.h>

/* -- the pose under K (geometry/pose_step.py) ------------------------------------------------- */

/* geometry.frame_error_and_depth under the pinhole k (skew 0) at the pose (rvec, tvec): the mean norm of
 * the residuals ((a fx + cx) - x, (b fy + cy) - y), summed in cv::sum's order (four at a time, then one
 * by one), and the smallest Z_C (np.min: NaN when one is NaN; inf without points). */
static void pose_error_and_depth(size_t N, const double *p2, const double *p3, const double k[4], const double r[3],
                                 const double t[3], double *e_px, double *depth_mm)
{
    double R[9], depth = HUGE_VAL;
    dimenet__norm_sum norms = {{0.0}, 0.0, 0};
    size_t i;
    dimenet__rodrigues(r, R);
    for (i = 0; i < N; i++) {
        double X = p3[3 * i], Y = p3[3 * i + 1], Z = p3[3 * i + 2];
        double xc = ((X * R[0] + Y * R[1]) + Z * R[2]) + t[0];
        double yc = ((X * R[3] + Y * R[4]) + Z * R[5]) + t[1];
        double zc = ((X * R[6] + Y * R[7]) + Z * R[8]) + t[2];
        double inv_z = 1.0 / zc, a = xc * inv_z, b = yc * inv_z;
        double du = (a * k[0] + k[2]) - p2[2 * i], dv = (b * k[1] + k[3]) - p2[2 * i + 1];
        depth = dimenet__depth_min(depth, zc);
        dimenet__norm_add(&norms, sqrt(du * du + dv * dv));
    }
    *e_px = dimenet__norm_mean(&norms);
    *depth_mm = depth;
}

/* pose_step.SMALL_ANGLE: below it, a rotation's quaternion <-> axis-angle use the series. */
#define POSE_SMALL_ANGLE 1e-8

/* pose_step.quaternion: axis-angle (rad) -> the unit quaternion (w, x, y, z). */
static void pose_quaternion(const double r[3], double q[4])
{
    double theta = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]), s;
    if (theta < POSE_SMALL_ANGLE) {
        s = 0.5 - theta * theta / 48.0;
        q[0] = 1.0 - theta * theta / 8.0;
    } else {
        s = sin(0.5 * theta) / theta;
        q[0] = cos(0.5 * theta);
    }
    q[1] = r[0] * s, q[2] = r[1] * s, q[3] = r[2] * s;
}

/* pose_step.axis_angle: a unit quaternion -> axis-angle (rad), angle in [0, pi]. */
static void pose_axis_angle(const double q[4], double r[3])
{
    double w = q[0], x = q[1], y = q[2], z = q[3], n, s;
    if (w < 0.0) {
        w = -w, x = -x, y = -y, z = -z;
    }
    n = sqrt(x * x + y * y + z * z);
    s = n < POSE_SMALL_ANGLE ? 2.0 / w : 2.0 * atan2(n, w) / n;
    r[0] = x * s, r[1] = y * s, r[2] = z * s;
}

/* pose_step.compose: the quaternion of rotation a after rotation b. */
static void pose_compose(const double a[4], const double b[4], double out[4])
{
    out[0] = ((a[0] * b[0] - a[1] * b[1]) - a[2] * b[2]) - a[3] * b[3];
    out[1] = ((a[0] * b[1] + a[1] * b[0]) + a[2] * b[3]) - a[3] * b[2];
    out[2] = ((a[0] * b[2] - a[1] * b[3]) + a[2] * b[0]) + a[3] * b[1];
    out[3] = ((a[0] * b[3] + a[1] * b[2]) - a[2] * b[1]) + a[3] * b[0];
}

/* The rows of pose_step.pose_normal_equations's stack E (12 x n): g_u at POSE_U, g_v at POSE_V, the residuals. */
#define POSE_ROWS 12
#define POSE_PAIRS 40
static const int POSE_U[5] = {0, 1, 2, 3, 5}, POSE_V[5] = {0, 1, 2, 4, 5};

/* pose_step._PAIRS: the upper triangles of the u rows (0-4) and the v rows (5-9), then each block's rows times its
 * residual (row 10, row 11). */
static void pose_pairs(int first[POSE_PAIRS], int second[POSE_PAIRS])
{
    int i, j, n = 0;
    for (i = 0; i < 5; i++) {
        for (j = i; j < 5; j++, n++) {
            first[n] = i, second[n] = j;
            first[n + 15] = 5 + i, second[n + 15] = 5 + j;
        }
    }
    for (i = 0; i < 5; i++) {
        first[30 + i] = i, second[30 + i] = 10;
        first[35 + i] = 5 + i, second[35 + i] = 11;
    }
}

/* pose_step.pose_normal_equations from the stack E (POSE_ROWS rows of n, filled by the caller): JJ = fx^2 S_u +
 * fy^2 S_v (6 x 6) and Jr = fx R_u + fy R_v. */
static void pose_normal_equations(const double *E, size_t n, double fx, double fy, double JJ[36], double Jr[6])
{
    double sums[POSE_PAIRS], S_u[36] = {0.0}, S_v[36] = {0.0}, R_u[6] = {0.0}, R_v[6] = {0.0};
    double fx2 = fx * fx, fy2 = fy * fy;
    int first[POSE_PAIRS], second[POSE_PAIRS], i, j, k = 0;
    pose_pairs(first, second);
    for (i = 0; i < POSE_PAIRS; i++) {
        sums[i] = dimenet__pairwise_dot(E + (size_t)first[i] * n, E + (size_t)second[i] * n, n);
    }
    for (i = 0; i < 5; i++) {
        for (j = i; j < 5; j++, k++) {
            S_u[POSE_U[i] * 6 + POSE_U[j]] = S_u[POSE_U[j] * 6 + POSE_U[i]] = sums[k];
            S_v[POSE_V[i] * 6 + POSE_V[j]] = S_v[POSE_V[j] * 6 + POSE_V[i]] = sums[15 + k];
        }
        R_u[POSE_U[i]] = sums[30 + i], R_v[POSE_V[i]] = sums[35 + i];
    }
    for (i = 0; i < 36; i++) {
        JJ[i] = fx2 * S_u[i] + fy2 * S_v[i];
    }
    for (i = 0; i < 6; i++) {
        Jr[i] = fx * R_u[i] + fy * R_v[i];
    }
}

/* pose_step.solve_pose_step: x = -JJ^-1 Jr (6 x 6) by Cholesky (L L^T), 0 when not positive definite. */
static int pose_solve(const double JJ[36], const double Jr[6], double x[6])
{
    double L[36], y[6], s;
    int i, j, k;
    for (i = 0; i < 6; i++) {
        for (j = 0; j <= i; j++) {
            s = JJ[i * 6 + j];
            for (k = 0; k < j; k++) {
                s -= L[i * 6 + k] * L[j * 6 + k];
            }
            if (i == j) {
                if (!(s > 0.0) || s == HUGE_VAL) {
                    return 0;
                }
                L[i * 6 + i] = sqrt(s);
            } else {
                L[i * 6 + j] = s / L[j * 6 + j];
            }
        }
    }
    for (i = 0; i < 6; i++) { /* L y = -g */
        s = -Jr[i];
        for (k = 0; k < i; k++) {
            s -= L[i * 6 + k] * y[k];
        }
        y[i] = s / L[i * 6 + i];
    }
    for (i = 5; i >= 0; i--) { /* L^T x = y */
        s = y[i];
        for (k = i + 1; k < 6; k++) {
            s -= L[k * 6 + i] * x[k];
        }
        x[i] = s / L[i * 6 + i];
    }
    return 1;
}

int dimenet_pose_scratch_doubles(size_t n_points, size_t *n_scratch)
{
    if (n_scratch == NULL || n_points > ((size_t)-1) / sizeof(double) / POSE_ROWS) {
        return DIMENET_E_ARGUMENT;
    }
    *n_scratch = POSE_ROWS * n_points;
    return DIMENET_OK;
}

int dimenet_pose_steps(size_t n_points, const double *points_2d_px, const double *points_3d_w_mm,
                       const double k_px[4], const double rvec_start_rad[3], const double tvec_start_mm[3], int steps,
                       double rvec_rad[3], double tvec_mm[3], double *e_px, double *depth_mm, double *scratch,
                       size_t n_scratch)
{
    const size_t N = n_points;
    double fx, fy, cx, cy, q[4], qw[4], qn[4], r[3], t[3], R[9], dR[9], JJ[36], Jr[6], step[6], t_new[3];
    double *E = scratch; /* POSE_ROWS rows of N: pose_step.pose_normal_equations's stack */
    size_t i, need;
    int s, c;

    if (dimenet_pose_scratch_doubles(N, &need) != DIMENET_OK || k_px == NULL || rvec_start_rad == NULL
        || tvec_start_mm == NULL || rvec_rad == NULL || tvec_mm == NULL || steps < 0
        || steps > DIMENET_MAX_POSE_STEPS || (N > 0 && (points_2d_px == NULL || points_3d_w_mm == NULL))
        || (steps > 0 && N > 0 && (scratch == NULL || n_scratch < need))) {
        return DIMENET_E_ARGUMENT;
    }
    fx = k_px[0], fy = k_px[1], cx = k_px[2], cy = k_px[3];
    for (c = 0; c < 3; c++) {
        r[c] = rvec_start_rad[c];
        t[c] = tvec_start_mm[c];
    }
    pose_quaternion(r, q);
    for (s = 0; s < steps; s++) {
        dimenet__rodrigues(r, R);
        for (i = 0; i < N; i++) { /* ((R_i0 X + R_i1 Y) + R_i2 Z) + t_i; a = X / Z, b = Y / Z; then the stack */
            double X = points_3d_w_mm[3 * i], Y = points_3d_w_mm[3 * i + 1], Z = points_3d_w_mm[3 * i + 2];
            double xc = ((X * R[0] + Y * R[1]) + Z * R[2]) + t[0];
            double yc = ((X * R[3] + Y * R[4]) + Z * R[5]) + t[1];
            double zc = ((X * R[6] + Y * R[7]) + Z * R[8]) + t[2];
            double inv_z = 1.0 / zc, a = xc * inv_z, b = yc * inv_z;
            E[i] = -(a * b);
            E[N + i] = a * a + 1.0;
            E[2 * N + i] = -b;
            E[3 * N + i] = inv_z;
            E[4 * N + i] = -(a * inv_z);
            E[5 * N + i] = -(b * b + 1.0);
            E[6 * N + i] = a * b;
            E[7 * N + i] = a;
            E[8 * N + i] = inv_z;
            E[9 * N + i] = -(b * inv_z);
            E[10 * N + i] = (a * fx + cx) - points_2d_px[2 * i];
            E[11 * N + i] = (b * fy + cy) - points_2d_px[2 * i + 1];
        }
        pose_normal_equations(E, N, fx, fy, JJ, Jr);
        if (!pose_solve(JJ, Jr, step)) {
            return DIMENET_E_NO_POSE_STEP;
        }
        dimenet__rodrigues(step, dR);
        for (c = 0; c < 3; c++) {
            t_new[c] = ((dR[c * 3] * t[0] + dR[c * 3 + 1] * t[1]) + dR[c * 3 + 2] * t[2]) + step[3 + c];
        }
        for (c = 0; c < 3; c++) {
            t[c] = t_new[c];
        }
        pose_quaternion(step, qw);
        pose_compose(qw, q, qn);
        for (c = 0; c < 4; c++) {
            q[c] = qn[c];
        }
        pose_axis_angle(q, r);
    }
    for (c = 0; c < 3 && steps > 0; c++) { /* no step: the start pose as it is */
        if (!(r[c] - r[c] == 0.0) || !(t[c] - t[c] == 0.0)) {
            return DIMENET_E_NO_POSE_STEP;
        }
    }
    for (c = 0; c < 3; c++) {
        rvec_rad[c] = r[c];
        tvec_mm[c] = t[c];
    }
    if (e_px != NULL && depth_mm != NULL) {
        pose_error_and_depth(N, points_2d_px, points_3d_w_mm, k_px, r, t, e_px, depth_mm);
    }
    return DIMENET_OK;
}

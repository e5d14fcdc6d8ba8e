/* dimenet_core: what the core's kernels share (see dimenet_core.h for the API, units and rules): the
 * error messages, the rotation, the monomial Gram and its normal equations, the prior's posterior.
 *
 * Each function names the numpy code it follows; the comments say where the operation order is the
 * reference's and where it cannot be (numpy's matrix products go through BLAS, whose summation order
 * and fused multiply-adds are its own: those sums are taken here in point order). */
#include "dimenet_internal.h"

#include <math.h>
#include <string.h>

static const char *const MESSAGES[] = {
    "ok",
    "dimenet_core: a NULL pointer, a bad feature spec or a buffer of the wrong size",
    "points lie behind the camera at the best pose under K_c",
    "the points fix no pose: the Gauss-Newton Hessian has a zero or non-finite diagonal",
    "the points fix no pose: the Gauss-Newton Hessian is not positive definite",
    "no Gauss-Newton step: the points fix no pose under K",
    "the prior's covariance of K is not positive definite",
};

const char *dimenet_error_message(int code)
{
    if (code < 0 || code >= (int)(sizeof MESSAGES / sizeof MESSAGES[0])) {
        return "dimenet_core: unknown error code";
    }
    return MESSAGES[code];
}

/* -- geometry --------------------------------------------------------------------------------- */

/* OpenCV's Rodrigues (cv::Rodrigues, vector to matrix): R = cos(t) I + (1 - cos(t)) r r^T + sin(t) [r]x. */
void dimenet__rodrigues(const double rvec[3], double R[9])
{
    double rx = rvec[0], ry = rvec[1], rz = rvec[2];
    double theta = sqrt(rx * rx + ry * ry + rz * rz);
    double c, s, c1, itheta;
    double rrt[9], r_x[9];
    int k;
    if (theta < 2.220446049250313e-16) { /* DBL_EPSILON */
        for (k = 0; k < 9; k++) {
            R[k] = (k % 4 == 0) ? 1.0 : 0.0;
        }
        return;
    }
    c = cos(theta);
    s = sin(theta);
    c1 = 1. - c;
    itheta = theta ? 1. / theta : 0.;
    rx *= itheta;
    ry *= itheta;
    rz *= itheta;
    rrt[0] = rx * rx, rrt[1] = rx * ry, rrt[2] = rx * rz;
    rrt[3] = rx * ry, rrt[4] = ry * ry, rrt[5] = ry * rz;
    rrt[6] = rx * rz, rrt[7] = ry * rz, rrt[8] = rz * rz;
    r_x[0] = 0, r_x[1] = -rz, r_x[2] = ry;
    r_x[3] = rz, r_x[4] = 0, r_x[5] = -rx;
    r_x[6] = -ry, r_x[7] = rx, r_x[8] = 0;
    for (k = 0; k < 9; k++) {
        R[k] = c * ((k % 4 == 0) ? 1.0 : 0.0) + c1 * rrt[k] + s * r_x[k];
    }
}

double dimenet__norm_mean(const dimenet__norm_sum *sum)
{
    double total = sum->total;
    size_t c;
    for (c = 0; c < sum->n % 4; c++) {
        total += sum->lanes[c];
    }
    return total / (double)sum->n;
}

/* OpenCV's Cholesky inverse (hal::Cholesky64f on a copy of a, the right hand side the identity). */
int dimenet__cholesky_inverse(double *a, int n, double *inverse)
{
    double *L = a, s, t;
    int i, j, k;
    for (i = 0; i < n; i++) {
        for (j = 0; j < n; j++) {
            inverse[i * n + j] = (i == j) ? 1.0 : 0.0;
        }
    }
    for (i = 0; i < n; i++) {
        for (j = 0; j < i; j++) {
            s = a[i * n + j];
            for (k = 0; k < j; k++) {
                s -= L[i * n + k] * L[j * n + k];
            }
            L[i * n + j] = s * L[j * n + j];
        }
        s = a[i * n + i];
        for (k = 0; k < j; k++) {
            t = L[i * n + k];
            s -= t * t;
        }
        if (s < 2.220446049250313e-16) {
            return 0;
        }
        L[i * n + i] = 1. / sqrt(s);
    }
    for (i = 0; i < n; i++) { /* L y = b */
        for (j = 0; j < n; j++) {
            s = inverse[i * n + j];
            for (k = 0; k < i; k++) {
                s -= L[i * n + k] * inverse[k * n + j];
            }
            inverse[i * n + j] = s * L[i * n + i];
        }
    }
    for (i = n - 1; i >= 0; i--) { /* L^T x = y */
        for (j = 0; j < n; j++) {
            s = inverse[i * n + j];
            for (k = n - 1; k > i; k--) {
                s -= L[k * n + i] * inverse[k * n + j];
            }
            inverse[i * n + j] = s * L[i * n + i];
        }
    }
    return 1;
}

double dimenet__python_square(double x)
{
    volatile double two = 2.0;
    return pow(x, two);
}

double dimenet__noise_weight(double rss, long dof, double floor_px)
{
    double v = rss / (double)(dof > 1 ? dof : 1);
    double floor2 = dimenet__python_square(floor_px);
    if (floor2 > v) {
        v = floor2;
    }
    return 1.0 / v;
}

double dimenet__pairwise_dot(const double *x, const double *y, size_t n)
{
    double r[8], res;
    size_t i, j;
    if (n < 8) {
        res = 0.0;
        for (i = 0; i < n; i++) {
            res += x[i] * y[i];
        }
        return res;
    }
    if (n > PAIRWISE_BLOCK) {
        size_t n2 = n / 2;
        n2 -= n2 % 8;
        return dimenet__pairwise_dot(x, y, n2) + dimenet__pairwise_dot(x + n2, y + n2, n - n2);
    }
    for (j = 0; j < 8; j++) {
        r[j] = x[j] * y[j];
    }
    for (i = 8; i < n - (n % 8); i += 8) {
        for (j = 0; j < 8; j++) {
            r[j] += x[i + j] * y[i + j];
        }
    }
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
    for (; i < n; i++) {
        res += x[i] * y[i];
    }
    return res;
}

void dimenet__matvec(const double *A, const double *x, int n, double *y)
{
    int i;
    for (i = 0; i < n; i++) {
        y[i] = dimenet__pairwise_dot(A + n * i, x, (size_t)n);
    }
}

int dimenet__prior_posterior(const double jj[100], const double k_precision_per_px2[16], double weight_per_px2,
                             double inverse[100])
{
    /* geometry.prior_posterior: H = JJ weight, + the precision on the K block; D = diag(H)^-1/2;
     * the inverse is D (D H D)^-1 D. */
    double H[100], d[10];
    int i, j;
    for (i = 0; i < 100; i++) {
        H[i] = jj[i] * weight_per_px2;
    }
    for (i = 6; i < 10; i++) {
        for (j = 6; j < 10; j++) {
            H[i * 10 + j] += k_precision_per_px2[(i - 6) * 4 + j - 6];
        }
    }
    for (i = 0; i < 10; i++) {
        double h = H[i * 10 + i];
        if (!(h > 0.0) || !(h - h == 0.0)) { /* not > 0, or inf / NaN */
            return DIMENET_E_HESSIAN_DIAGONAL;
        }
    }
    for (i = 0; i < 10; i++) {
        d[i] = 1.0 / sqrt(H[i * 10 + i]);
    }
    for (i = 0; i < 10; i++) {
        for (j = 0; j < 10; j++) {
            H[i * 10 + j] = H[i * 10 + j] * (d[i] * d[j]);
        }
    }
    if (!dimenet__cholesky_inverse(H, 10, inverse)) {
        return DIMENET_E_NOT_POSITIVE_DEFINITE;
    }
    for (i = 0; i < 10; i++) {
        for (j = 0; j < 10; j++) {
            inverse[i * 10 + j] *= d[i] * d[j];
        }
    }
    return DIMENET_OK;
}

int dimenet_prior_posterior(const double jj[100], double k_precision_per_px2, double weight_per_px2,
                            double inverse[100])
{
    double precision[16] = {0.0}; /* np.eye(4) / prior_var: 0.0 off the diagonal, added as numpy does */
    int k;
    if (jj == NULL || inverse == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (k = 0; k < 4; k++) {
        precision[5 * k] = k_precision_per_px2;
    }
    return dimenet__prior_posterior(jj, precision, weight_per_px2, inverse);
}

int dimenet__prior_step(const double JJ[100], const double Jr[10], double rss, long n_residuals,
                        const double k_precision_per_px2[16], double noise_floor_px, double step[10], double cov[100],
                        double *weight_per_px2)
{
    /* geometry.prior_step: the noise weight of the pose-only fit, then of the linearised step's residuals */
    double JJ_step[10], rss_step, weight = dimenet__noise_weight(rss, n_residuals - 6, noise_floor_px);
    int code = dimenet__prior_posterior(JJ, k_precision_per_px2, weight, cov), i, k;
    if (code != DIMENET_OK) {
        return code;
    }
    dimenet__matvec(cov, Jr, 10, step);
    for (k = 0; k < 10; k++) {
        step[k] *= weight;
    }
    for (k = 0; k < 10; k++) { /* step @ JJ: np.multiply(step[:, None], JJ).sum(0), first to last */
        double s = 0.0;
        for (i = 0; i < 10; i++) {
            s += step[i] * JJ[i * 10 + k];
        }
        JJ_step[k] = s;
    }
    rss_step = rss - 2.0 * dimenet__pairwise_dot(step, Jr, 10) + dimenet__pairwise_dot(JJ_step, step, 10);
    weight = dimenet__noise_weight(rss_step, n_residuals - 10, noise_floor_px);
    *weight_per_px2 = weight;
    return dimenet__posterior_step(JJ, Jr, k_precision_per_px2, weight, step, cov);
}

int dimenet__posterior_step(const double JJ[100], const double Jr[10], const double k_precision_per_px2[16],
                            double weight_per_px2, double step[10], double cov[100])
{
    int code = dimenet__prior_posterior(JJ, k_precision_per_px2, weight_per_px2, cov), k;
    if (code != DIMENET_OK) {
        return code;
    }
    dimenet__matvec(cov, Jr, 10, step);
    for (k = 0; k < 10; k++) {
        step[k] *= -weight_per_px2;
    }
    return DIMENET_OK;
}

/* The upper triangle of the Gram in row order: 66 products of two monomials. */
#define GRAM_UPPER 66

/* d += the 66 products q[a] q[b], b >= a, in row order (row a starts at 11 a - a (a - 1) / 2). */
static void gram_add(double d[GRAM_UPPER], const double *q, size_t stride)
{
    int a, b, k = 0;
    for (a = 0; a < DIMENET_GRAM_SIZE; a++) {
        for (b = a; b < DIMENET_GRAM_SIZE; b++, k++) {
            d[k] += q[(size_t)a * stride] * q[(size_t)b * stride];
        }
    }
}

/* numpy's pairwise sum of a contiguous float64 run (pairwise_sum_DOUBLE): what a.sum() gives. */
double dimenet__pairwise_sum(const double *a, size_t n)
{
    if (n < 8) {
        double res = 0.0;
        size_t i;
        for (i = 0; i < n; i++) {
            res += a[i];
        }
        return res;
    }
    if (n <= PAIRWISE_BLOCK) {
        double r[8], res;
        size_t i, j;
        for (j = 0; j < 8; j++) {
            r[j] = a[j];
        }
        for (i = 8; i < n - (n % 8); i += 8) {
            for (j = 0; j < 8; j++) {
                r[j] += a[i + j];
            }
        }
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++) {
            res += a[i];
        }
        return res;
    } else {
        size_t n2 = n / 2;
        n2 -= n2 % 8;
        return dimenet__pairwise_sum(a, n2) + dimenet__pairwise_sum(a + n2, n - n2);
    }
}

/* numpy's pairwise sum (dimenet__pairwise_sum above) of each of the 66 products over n points (8 <= n <= 128):
 * lanes[m * stride + i] monomial m of point i. The eight partial sums of a product (points j, j + 8,
 * j + 16, ...) stay in registers over the block, each rounded as in numpy's loop. */
static void gram_block(const double *lanes, size_t stride, size_t n, double out[GRAM_UPPER])
{
    size_t i, full = n - (n % 8);
    int a, b, j, k;
    for (a = 0, k = 0; a < DIMENET_GRAM_SIZE; a++) {
        for (b = a; b < DIMENET_GRAM_SIZE; b++, k++) {
            const double *qa = lanes + (size_t)a * stride, *qb = lanes + (size_t)b * stride;
            double r[8], res;
            for (j = 0; j < 8; j++) {
                r[j] = qa[j] * qb[j];
            }
            for (i = 8; i < full; i += 8) {
                for (j = 0; j < 8; j++) {
                    r[j] += qa[i + (size_t)j] * qb[i + (size_t)j];
                }
            }
            res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
            for (i = full; i < n; i++) {
                res += qa[i] * qb[i];
            }
            out[k] = res;
        }
    }
}

/* The monomials q of one point (geometry.normal_equations._monomials), then its residuals, into
 * q[m * stride]. */
void dimenet__monomials(double x_mm, double y_mm, double inv_z, double du_px, double dv_px, double *q, size_t stride)
{
    double a = x_mm * inv_z, b = y_mm * inv_z;
    q[0] = 1.0;
    q[stride] = a;
    q[2 * stride] = b;
    q[3 * stride] = a * b;
    q[4 * stride] = a * a;
    q[5 * stride] = b * b;
    q[6 * stride] = inv_z;
    q[7 * stride] = a * inv_z;
    q[8 * stride] = b * inv_z;
    q[9 * stride] = du_px;
    q[10 * stride] = dv_px;
}

/* geometry.monomial_gram's sums: numpy's pairwise sum of each product over the points start to
 * start + n (the same tree: blocks of at most 128 points, halves a multiple of 8 long). */
static void gram_pairwise(const dimenet__gram_points *p, size_t start, size_t n, double out[GRAM_UPPER])
{
    size_t i;
    int k;
    if (n > PAIRWISE_BLOCK) {
        double second[GRAM_UPPER];
        size_t n2 = n / 2;
        n2 -= n2 % 8;
        gram_pairwise(p, start, n2, out);
        gram_pairwise(p, start + n2, n - n2, second);
        for (k = 0; k < GRAM_UPPER; k++) {
            out[k] += second[k];
        }
        return;
    }
    if (p->lanes == NULL) { /* raw rows: their monomials into a block of lanes first */
        double lanes[DIMENET_GRAM_SIZE * PAIRWISE_BLOCK];
        for (i = 0; i < n; i++) {
            dimenet__monomials(p->x[start + i], p->y[start + i], p->inv_z[start + i], p->du[start + i],
                               p->dv[start + i], lanes + i, PAIRWISE_BLOCK);
        }
        if (n >= 8) {
            gram_block(lanes, PAIRWISE_BLOCK, n, out);
            return;
        }
        for (k = 0; k < GRAM_UPPER; k++) {
            out[k] = 0.0;
        }
        for (i = 0; i < n; i++) {
            gram_add(out, lanes + i, PAIRWISE_BLOCK);
        }
        return;
    }
    if (n >= 8) {
        gram_block(p->lanes + start, p->stride, n, out);
        return;
    }
    for (k = 0; k < GRAM_UPPER; k++) { /* fewer than 8: one by one from 0 */
        out[k] = 0.0;
    }
    for (i = 0; i < n; i++) {
        gram_add(out, p->lanes + start + i, p->stride);
    }
}

void dimenet__gram_of(const dimenet__gram_points *p, size_t n, double G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE])
{
    double upper[GRAM_UPPER];
    int a, b, k = 0;
    gram_pairwise(p, 0, n, upper);
    for (a = 0; a < DIMENET_GRAM_SIZE; a++) {
        for (b = a; b < DIMENET_GRAM_SIZE; b++, k++) {
            G[a * DIMENET_GRAM_SIZE + b] = upper[k];
            G[b * DIMENET_GRAM_SIZE + a] = upper[k];
        }
    }
}

int dimenet_monomial_gram(size_t n_points, const double *x_c0_mm, const double *y_c0_mm,
                          const double *inv_z_c0_per_mm, const double *residual_u_px, const double *residual_v_px,
                          double gram[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE])
{
    dimenet__gram_points p;
    if (gram == NULL || (n_points > 0 && (x_c0_mm == NULL || y_c0_mm == NULL || inv_z_c0_per_mm == NULL
                                          || residual_u_px == NULL || residual_v_px == NULL))) {
        return DIMENET_E_ARGUMENT;
    }
    p.lanes = NULL, p.stride = 0;
    p.x = x_c0_mm, p.y = y_c0_mm, p.inv_z = inv_z_c0_per_mm, p.du = residual_u_px, p.dv = residual_v_px;
    dimenet__gram_of(&p, n_points, gram);
    return DIMENET_OK;
}

/* The coefficient matrix C (20 x 9) of geometry.gram_normal_equations: fx B[0] + fy B[1] + B[2] of
 * JACOBIAN_BASIS. Row 2p + c (c = 0: u, 1: v) holds dr_c / dp_p in the monomials. */
static void jacobian_coefficients(double fx, double fy, double C[20 * 9])
{
    memset(C, 0, sizeof(double) * 20 * 9);
    /* du/dp = fx [-ab, 1 + a^2, -b, 1/Z, 0, -a/Z], then [a, 0, 1, 0] */
    C[0 * 9 + 3] = -fx, C[2 * 9 + 0] = fx, C[2 * 9 + 4] = fx, C[4 * 9 + 2] = -fx;
    C[6 * 9 + 6] = fx, C[10 * 9 + 7] = -fx, C[12 * 9 + 1] = 1.0, C[16 * 9 + 0] = 1.0;
    /* dv/dp = fy [-1 - b^2, ab, a, 0, 1/Z, -b/Z], then [0, b, 0, 1] */
    C[1 * 9 + 0] = -fy, C[1 * 9 + 5] = -fy, C[3 * 9 + 3] = fy, C[5 * 9 + 1] = fy;
    C[9 * 9 + 6] = fy, C[11 * 9 + 8] = -fy, C[15 * 9 + 2] = 1.0, C[19 * 9 + 0] = 1.0;
}

/* geometry.gram_normal_equations: J J^T (10 x 10), J r (10) and r.r (px^2) from the Gram. */
void dimenet__gram_normal_equations(const double *G, double fx, double fy, double JJ[100], double Jr[10], double *rss)
{
    double C[20 * 9], M[20 * 9], Cr[20 * 2];
    int r, q, k, i, j, c;
    jacobian_coefficients(fx, fy, C);
    for (r = 0; r < 20; r++) { /* M = C G[:9, :9]; Cr = C G[:9, 9:] */
        for (q = 0; q < 9; q++) {
            double s = 0.0;
            for (k = 0; k < 9; k++) {
                s += C[r * 9 + k] * G[k * DIMENET_GRAM_SIZE + q];
            }
            M[r * 9 + q] = s;
        }
        for (c = 0; c < 2; c++) {
            double s = 0.0;
            for (k = 0; k < 9; k++) {
                s += C[r * 9 + k] * G[k * DIMENET_GRAM_SIZE + 9 + c];
            }
            Cr[r * 2 + c] = s;
        }
    }
    for (i = 0; i < 10; i++) { /* M.reshape(10, 18) @ C.reshape(10, 18).T */
        for (j = 0; j < 10; j++) {
            double s = 0.0;
            for (k = 0; k < 18; k++) {
                s += M[(2 * i) * 9 + k] * C[(2 * j) * 9 + k];
            }
            JJ[i * 10 + j] = s;
        }
        Jr[i] = Cr[(2 * i) * 2 + 0] + Cr[(2 * i + 1) * 2 + 1];
    }
    *rss = G[9 * DIMENET_GRAM_SIZE + 9] + G[10 * DIMENET_GRAM_SIZE + 10];
}

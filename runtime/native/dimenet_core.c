/* dimenet_core: the feature stage in C99 (see dimenet_core.h for the API, units and rules).
 *
 * Each function names the numpy code it follows; the comments say where the operation order is the
 * reference's and where it cannot be (numpy's matrix products go through BLAS, whose summation order
 * and fused multiply-adds are its own: those sums are taken here in point order). */
#include "dimenet_core.h"

#include <math.h>
#include <string.h>

/* The data step's constants (rectify/features.py): the prior's 1 sigma over fx_c, the clip of its
 * Delta K over fx_c, the noise floor of its data weight (px), the floor of a variance ratio. */
#define STEP_PRIOR_REL 0.1
#define STEP_CLIP_REL 0.05
#define STEP_NOISE_FLOOR_PX 0.1
#define STEP_VARIANCE_FLOOR 1e-30
/* x^2 as the reference's Python computes it: libm's pow(x, 2.0), which is not always x * x's rounding
 * (glibc's pow is within 0.52 ulp, not correctly rounded). The exponent is read through a volatile so
 * that the compiler does not turn the call into x * x. */
static double python_square(double x)
{
    volatile double two = 2.0;
    return pow(x, two);
}

/* numpy's pairwise summation block (numpy/_core/src/umath/loops_utils.h.src). */
#define PAIRWISE_BLOCK 128
/* Scratch doubles per point: the point rows (6), its depth (1), its monomials (11). */
#define SCRATCH_PER_POINT 18

static const char *const MESSAGES[] = {
    "ok",
    "dimenet_core: a NULL pointer, a bad feature spec or a buffer of the wrong size",
    "points lie behind the camera at the best pose under K_c",
    "the points fix no pose: the Gauss-Newton Hessian has a zero or non-finite diagonal",
    "the points fix no pose: the Gauss-Newton Hessian is not positive definite",
    "no Gauss-Newton step: the points fix no pose under K",
};

const char *dimenet_error_message(int code)
{
    if (code < 0 || code >= (int)(sizeof MESSAGES / sizeof MESSAGES[0])) {
        return "dimenet_core: unknown error code";
    }
    return MESSAGES[code];
}

/* -- sizes ------------------------------------------------------------------------------------ */

static int spec_cells(const dimenet_feature_spec *spec, size_t *cells)
{
    int c;
    if (spec == NULL || cells == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    if (spec->grid_cols < 1 || spec->grid_rows < 1 || spec->n_channels < 1 || spec->n_channels > DIMENET_CHANNELS) {
        return DIMENET_E_ARGUMENT;
    }
    if (!(spec->image_width_px > 0.0 && spec->image_width_px <= 1e300 && spec->image_height_px > 0.0
          && spec->image_height_px <= 1e300)) {
        return DIMENET_E_ARGUMENT;
    }
    if (!(spec->depth_mm == 0.0 || (spec->depth_mm > 0.0 && spec->depth_mm <= 1e300))) {
        return DIMENET_E_ARGUMENT;
    }
    for (c = 0; c < spec->n_channels; c++) {
        if (spec->channels[c] < 0 || spec->channels[c] >= DIMENET_CHANNELS) {
            return DIMENET_E_ARGUMENT;
        }
    }
    if ((size_t)spec->grid_rows > ((size_t)-1) / DIMENET_POINT_ROWS / (size_t)spec->grid_cols) {
        return DIMENET_E_ARGUMENT;
    }
    *cells = (size_t)spec->grid_cols * (size_t)spec->grid_rows;
    return DIMENET_OK;
}

int dimenet_feature_size(const dimenet_feature_spec *spec, size_t *n_features)
{
    size_t cells, size;
    int code = spec_cells(spec, &cells);
    if (code != DIMENET_OK || n_features == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    size = cells * (size_t)spec->n_channels; /* <= 6 cells: no overflow (spec_cells) */
    if (spec->data_step) {
        size += DIMENET_STEP_SIZE;
    }
    if (spec->moments) {
        size += DIMENET_MOMENT_SIZE;
    }
    if (size < cells) {
        return DIMENET_E_ARGUMENT;
    }
    *n_features = size;
    return DIMENET_OK;
}

int dimenet_scratch_doubles(const dimenet_feature_spec *spec, size_t n_points, size_t *n_scratch)
{
    size_t cells, limit = ((size_t)-1) / sizeof(double);
    if (spec_cells(spec, &cells) != DIMENET_OK || n_scratch == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    /* rows (6 n) and depths (n), the cell sums (6 cells), then the used points' monomials (11 n) */
    if (n_points > (limit - DIMENET_POINT_ROWS * cells) / SCRATCH_PER_POINT) {
        return DIMENET_E_ARGUMENT;
    }
    *n_scratch = SCRATCH_PER_POINT * n_points + DIMENET_POINT_ROWS * cells;
    return DIMENET_OK;
}

/* -- numpy's sums ----------------------------------------------------------------------------- */

/* numpy's pairwise sum of a contiguous float64 run (pairwise_sum_DOUBLE): what a.sum() gives. */
static double pairwise_sum(const double *a, size_t n)
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
        return pairwise_sum(a, n2) + pairwise_sum(a + n2, n - n2);
    }
}

/* numpy's sum of a run under a where= mask: each run of kept values pairwise, the runs in order. */
static double masked_sum(const double *a, const unsigned char *mask, size_t n)
{
    double res = 0.0;
    size_t i = 0, j;
    while (i < n) {
        if (!mask[i]) {
            i++;
            continue;
        }
        for (j = i; j < n && mask[j]; j++) {
        }
        res += pairwise_sum(a + i, j - i);
        i = j;
    }
    return res;
}

/* -- geometry --------------------------------------------------------------------------------- */

/* OpenCV's Rodrigues (cv::Rodrigues, vector to matrix): R = cos(t) I + (1 - cos(t)) r r^T + sin(t) [r]x. */
static void rodrigues(const double rvec[3], double R[9])
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

/* OpenCV's Cholesky inverse (cv::invert with DECOMP_CHOLESKY: hal::Cholesky64f on a copy, the right
 * hand side the identity): 0 when a pivot falls below DBL_EPSILON. a (n x n) is overwritten. */
static int cholesky_inverse(double *a, int n, double *inverse)
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

int dimenet_prior_posterior(const double jj[100], double k_precision_per_px2, double weight_per_px2,
                            double inverse[100])
{
    /* geometry.prior_posterior: H = JJ weight, + the precision on the K block; D = diag(H)^-1/2;
     * the inverse is D (D H D)^-1 D. */
    double H[100], d[10];
    int i, j;
    if (jj == NULL || inverse == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (i = 0; i < 100; i++) {
        H[i] = jj[i] * weight_per_px2;
    }
    for (i = 6; i < 10; i++) {
        for (j = 6; j < 10; j++) { /* np.eye(4) / prior_var: 0.0 off the diagonal, added as numpy does */
            H[i * 10 + j] += (i == j) ? k_precision_per_px2 : 0.0;
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
    if (!cholesky_inverse(H, 10, inverse)) {
        return DIMENET_E_NOT_POSITIVE_DEFINITE;
    }
    for (i = 0; i < 10; i++) {
        for (j = 0; j < 10; j++) {
            inverse[i * 10 + j] *= d[i] * d[j];
        }
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

/* numpy's pairwise sum (pairwise_sum above) of each of the 66 products over n points (8 <= n <= 128):
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
static void monomials(double x_mm, double y_mm, double inv_z, double du_px, double dv_px, double *q, size_t stride)
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

/* Where a Gram's points are: their monomials side by side (lanes, stride apart), or their raw rows. */
typedef struct {
    const double *lanes;
    size_t stride;
    const double *x, *y, *inv_z, *du, *dv;
} gram_points;

/* geometry.monomial_gram's sums: numpy's pairwise sum of each product over the points start to
 * start + n (the same tree: blocks of at most 128 points, halves a multiple of 8 long). */
static void gram_pairwise(const gram_points *p, size_t start, size_t n, double out[GRAM_UPPER])
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
            monomials(p->x[start + i], p->y[start + i], p->inv_z[start + i], p->du[start + i], p->dv[start + i],
                      lanes + i, PAIRWISE_BLOCK);
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

static void gram_of(const gram_points *p, size_t n, double G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE])
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
    gram_points p;
    if (gram == NULL || (n_points > 0 && (x_c0_mm == NULL || y_c0_mm == NULL || inv_z_c0_per_mm == NULL
                                          || residual_u_px == NULL || residual_v_px == NULL))) {
        return DIMENET_E_ARGUMENT;
    }
    p.lanes = NULL, p.stride = 0;
    p.x = x_c0_mm, p.y = y_c0_mm, p.inv_z = inv_z_c0_per_mm, p.du = residual_u_px, p.dv = residual_v_px;
    gram_of(&p, n_points, gram);
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
static void gram_normal_equations(const double *G, double fx, double fy, double JJ[100], double Jr[10], double *rss)
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

/* geometry.normal_equations._noise_weight: 1 / max(rss / max(dof, 1), floor^2) (Python's max). */
static double noise_weight(double rss, long dof, double floor_px)
{
    double v = rss / (double)(dof > 1 ? dof : 1);
    double floor2 = python_square(floor_px);
    if (floor2 > v) {
        v = floor2;
    }
    return 1.0 / v;
}

/* a . b of two 10-vectors: numpy's pairwise sum of the products (np.multiply(a, b).sum()). */
static double dot10(const double a[10], const double b[10])
{
    double products[10];
    int k;
    for (k = 0; k < 10; k++) {
        products[k] = a[k] * b[k];
    }
    return pairwise_sum(products, 10);
}

/* A x, each row as dot10 (geometry.normal_equations._matvec). */
static void matvec10(const double A[100], const double x[10], double y[10])
{
    int i;
    for (i = 0; i < 10; i++) {
        y[i] = dot10(A + 10 * i, x);
    }
}

/* rectify.features.gram_inputs' data step for one frame: geometry.prior_step, then _step_inputs. */
static int data_step(const double *G, size_t n, double fx_c, double fy_c, double pmd_scale, double out[8])
{
    double prior_var = python_square(STEP_PRIOR_REL * fx_c);
    double clip_px = STEP_CLIP_REL * fx_c, precision = 1.0 / prior_var;
    double JJ[100], Jr[10], rss, inv[100], step[10], JJ_step[10], weight, rss_step;
    long n_residuals = (long)(2 * n);
    int code, k;
    gram_normal_equations(G, fx_c, fy_c, JJ, Jr, &rss);
    /* prior_step: the noise weight of the pose-only fit, then of the linearised step's residuals */
    weight = noise_weight(rss, n_residuals - 6, STEP_NOISE_FLOOR_PX);
    code = dimenet_prior_posterior(JJ, precision, weight, inv);
    if (code != DIMENET_OK) {
        return code;
    }
    matvec10(inv, Jr, step);
    for (k = 0; k < 10; k++) {
        step[k] *= weight;
    }
    for (k = 0; k < 10; k++) { /* step @ JJ: np.multiply(step[:, None], JJ).sum(0), first to last */
        int i;
        double s = 0.0;
        for (i = 0; i < 10; i++) {
            s += step[i] * JJ[i * 10 + k];
        }
        JJ_step[k] = s;
    }
    rss_step = rss - 2.0 * dot10(step, Jr) + dot10(JJ_step, step);
    weight = noise_weight(rss_step, n_residuals - 10, STEP_NOISE_FLOOR_PX);
    code = dimenet_prior_posterior(JJ, precision, weight, inv);
    if (code != DIMENET_OK) {
        return code;
    }
    matvec10(inv, Jr, step);
    for (k = 0; k < 4; k++) { /* _step_inputs: the clipped Delta K times the PMD's scale (Python's min, max) */
        double d = step[6 + k] * -weight;
        if (-clip_px > d) {
            d = -clip_px;
        }
        if (clip_px < d) {
            d = clip_px;
        }
        out[k] = d * pmd_scale;
    }
    for (k = 0; k < 4; k++) { /* then the log sigma ratios */
        double v = inv[(6 + k) * 10 + 6 + k] / prior_var;
        if (STEP_VARIANCE_FLOOR > v) {
            v = STEP_VARIANCE_FLOOR;
        }
        out[4 + k] = 0.5 * log(v);
    }
    return DIMENET_OK;
}

/* rectify.features._moment_inputs: s_i s_j G_ij / n over the upper triangle less [0, 0] and [0, 6]. */
static void moment_inputs(const double *G, size_t n, double pmd_scale, double out[DIMENET_MOMENT_SIZE])
{
    double s[DIMENET_GRAM_SIZE], s_n[DIMENET_GRAM_SIZE], z_scale;
    double count = (double)n;
    int i, j, k = 0;
    z_scale = G[6] > 0 ? count / G[6] : 1.0;
    for (i = 0; i < DIMENET_GRAM_SIZE; i++) {
        s[i] = i < 6 ? 1.0 : (i < 9 ? z_scale : pmd_scale);
    }
    for (i = 0; i < DIMENET_GRAM_SIZE; i++) {
        s_n[i] = s[i] / count;
    }
    for (i = 0; i < DIMENET_GRAM_SIZE; i++) {
        for (j = i; j < DIMENET_GRAM_SIZE; j++) {
            if (i == 0 && (j == 0 || j == 6)) {
                continue;
            }
            out[k++] = G[i * DIMENET_GRAM_SIZE + j] * (s[i] * s_n[j]);
        }
    }
}

/* -- the frame kernel ------------------------------------------------------------------------- */

int dimenet_frame_features(const dimenet_feature_spec *spec, size_t n_points, const double *points_2d_px,
                           const double *points_3d_w_mm, const unsigned char *mask, const double rvec_w_to_c0_rad[3],
                           const double tvec_w_to_c0_mm[3], unsigned flags, double *features, size_t n_features,
                           double *point_rows, double *scratch, size_t n_scratch, dimenet_frame_stats *stats)
{
    /* depth exponents of the channels (features.py FeatureSpec.depth_exponents): X, Y 1, 1/Z -1 */
    static const double DEPTH_EXPONENT[DIMENET_CHANNELS] = {0.0, 0.0, 1.0, 1.0, -1.0};
    size_t cells = 0, size, need, i, cell;
    const size_t N = n_points;
    double R[9], P[5][4], G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE];
    double *rows, *depths, *sums, *counts, multiplier[DIMENET_CHANNELS], *channel_sums[DIMENET_CHANNELS];
    double scale_x, scale_y, last_x, last_y, norm_sum = 0.0, norms[4], *lanes;
    double p00, p01, p02, p03, p10, p11, p12, p13, p20, p21, p22, p23, p30, p31, p32, p33, p40, p41, p42, p43;
    size_t n_used = 0, n_behind = 0;
    int all_in_front = 1, all_channels = 1, C, k, r, cols, channel[DIMENET_CHANNELS], code = DIMENET_OK;

    if (dimenet_feature_size(spec, &size) != DIMENET_OK || dimenet_scratch_doubles(spec, N, &need) != DIMENET_OK) {
        return DIMENET_E_ARGUMENT;
    }
    if (features == NULL || n_features != size || scratch == NULL || n_scratch < need || rvec_w_to_c0_rad == NULL
        || tvec_w_to_c0_mm == NULL || (N > 0 && (points_2d_px == NULL || points_3d_w_mm == NULL))
        || (flags & ~DIMENET_REFUSE_BEHIND_CAMERA) != 0) {
        return DIMENET_E_ARGUMENT;
    }
    spec_cells(spec, &cells);
    C = spec->n_channels;
    cols = spec->grid_cols;
    rows = point_rows != NULL ? point_rows : scratch;
    depths = scratch + DIMENET_POINT_ROWS * N;
    sums = depths + N; /* (C + 1) x cells: the channels' sums, then the counts */
    counts = sums + (size_t)C * cells;
    lanes = spec->data_step || spec->moments ? sums + DIMENET_POINT_ROWS * cells : NULL; /* 11 x N */

    /* _point_features_into: P (5 x 4) = [K_c[:2] [R | t]; [R | t]]; each point's row P [X 1] */
    rodrigues(rvec_w_to_c0_rad, R);
    for (r = 0; r < 3; r++) {
        for (k = 0; k < 3; k++) {
            P[2 + r][k] = R[r * 3 + k];
        }
        P[2 + r][3] = tvec_w_to_c0_mm[r];
    }
    for (r = 0; r < 2; r++) {
        for (k = 0; k < 4; k++) {
            P[r][k] = spec->K_c_px[r * 3 + 0] * P[2][k] + spec->K_c_px[r * 3 + 1] * P[3][k]
                      + spec->K_c_px[r * 3 + 2] * P[4][k];
        }
    }
    p00 = P[0][0], p01 = P[0][1], p02 = P[0][2], p03 = P[0][3], p10 = P[1][0], p11 = P[1][1], p12 = P[1][2];
    p13 = P[1][3], p20 = P[2][0], p21 = P[2][1], p22 = P[2][2], p23 = P[2][3], p30 = P[3][0], p31 = P[3][1];
    p32 = P[3][2], p33 = P[3][3], p40 = P[4][0], p41 = P[4][1], p42 = P[4][2], p43 = P[4][3];
    /* the point rows; the unused points' from a point zeroed as grid_features zeroes them (np.where) */
    for (i = 0; i < N; i++) {
        int used = mask == NULL || mask[i];
        double x = used ? points_2d_px[2 * i] : 0.0, y = used ? points_2d_px[2 * i + 1] : 0.0;
        double X = used ? points_3d_w_mm[3 * i] : 0.0, Y = used ? points_3d_w_mm[3 * i + 1] : 0.0;
        double Z = used ? points_3d_w_mm[3 * i + 2] : 0.0;
        double u = ((p00 * X + p01 * Y) + p02 * Z) + p03, v = ((p10 * X + p11 * Y) + p12 * Z) + p13;
        double xc = ((p20 * X + p21 * Y) + p22 * Z) + p23, yc = ((p30 * X + p31 * Y) + p32 * Z) + p33;
        double zc = ((p40 * X + p41 * Y) + p42 * Z) + p43, inv_z = 1.0 / zc;
        rows[i] = u * inv_z - x;
        rows[N + i] = v * inv_z - y;
        rows[2 * N + i] = xc;
        rows[3 * N + i] = yc;
        rows[4 * N + i] = inv_z;
        rows[5 * N + i] = 1.0;
        depths[i] = used ? zc : 0.0;
    }

    /* the used points: e_c's norms in OpenCV's order (cv::sum: four at a time, then one by one), the
     * cells' sums in point order (np.bincount), the Gram's monomials side by side */
    memset(sums, 0, sizeof(double) * (size_t)(C + 1) * cells);
    for (k = 0; k < C; k++) {
        channel[k] = spec->channels[k];
        channel_sums[k] = sums + (size_t)k * cells;
        all_channels &= C == DIMENET_CHANNELS && channel[k] == k;
    }
    /* Grid.cell_index: x u / width and y v / height clamped to [0, u - 1] x [0, v - 1] (np.fmax sends
     * NaN to 0), floored by the cast */
    scale_x = (double)cols / spec->image_width_px;
    scale_y = (double)spec->grid_rows / spec->image_height_px;
    last_x = (double)(cols - 1);
    last_y = (double)(spec->grid_rows - 1);
    for (i = 0; i < N; i++) {
        double du, dv, inv_z, cx, cy;
        if (mask != NULL && !mask[i]) {
            continue;
        }
        du = rows[i], dv = rows[N + i], inv_z = rows[4 * N + i];
        norms[n_used % 4] = sqrt(du * du + dv * dv);
        if (n_used % 4 == 3) {
            norm_sum += ((norms[0] + norms[1]) + norms[2]) + norms[3];
        }
        n_behind += inv_z <= 0.0;
        all_in_front &= inv_z >= 0.0 && inv_z < HUGE_VAL;
        if (lanes != NULL) {
            monomials(rows[2 * N + i], rows[3 * N + i], inv_z, du, dv, lanes + n_used, N);
        }
        n_used++;
        if (cells > 1) {
            cx = points_2d_px[2 * i] * scale_x;
            cy = points_2d_px[2 * i + 1] * scale_y;
            cx = cx >= 0.0 ? (cx < last_x ? cx : last_x) : 0.0;
            cy = cy >= 0.0 ? (cy < last_y ? cy : last_y) : 0.0;
            cell = (size_t)cy * (size_t)cols + (size_t)cx;
            if (all_channels) { /* variant A: the five channels in order */
                sums[cell] += du, sums[cells + cell] += dv, sums[2 * cells + cell] += rows[2 * N + i];
                sums[3 * cells + cell] += rows[3 * N + i], sums[4 * cells + cell] += inv_z;
            } else {
                for (k = 0; k < C; k++) {
                    channel_sums[k][cell] += rows[(size_t)channel[k] * N + i];
                }
            }
            counts[cell] += 1.0;
        }
    }
    for (k = 0; k < (int)(n_used % 4); k++) {
        norm_sum += norms[k];
    }
    if (cells == 1) { /* numpy's sum over the points' axis (pairwise; under a mask, run by run) */
        for (k = 0; k < C; k++) {
            const double *row = rows + (size_t)channel[k] * N;
            sums[k] = mask == NULL ? pairwise_sum(row, N) : masked_sum(row, mask, N);
        }
        counts[0] = (double)n_used;
    }

    /* the cell means times the channels' scales (with depth_mm: times depth factor ^ exponent) */
    if (spec->depth_mm > 0.0) {
        double z_sum = pairwise_sum(depths, N); /* the unused points' depths are 0 (np.where) */
        double factor = z_sum > 0 ? spec->depth_mm * (double)n_used / z_sum : 1.0;
        for (k = 0; k < C; k++) {
            multiplier[k] = spec->channel_scale[k] * pow(factor, DEPTH_EXPONENT[spec->channels[k]]);
        }
    } else {
        for (k = 0; k < C; k++) {
            multiplier[k] = spec->channel_scale[k];
        }
    }
    for (cell = 0; cell < cells; cell++) {
        double count = counts[cell] > 1.0 ? counts[cell] : 1.0;
        for (k = 0; k < C; k++) {
            double mean = sums[(size_t)k * cells + cell] / count;
            features[cell * (size_t)C + (size_t)k] = mean * multiplier[k];
        }
    }

    /* gram_inputs: the data step, then the moments, from the used points' monomial Gram */
    if (lanes != NULL) {
        double *out = features + cells * (size_t)C;
        gram_points p;
        memset(&p, 0, sizeof p);
        p.lanes = lanes, p.stride = N;
        gram_of(&p, n_used, G);
        if (spec->data_step) {
            code = data_step(G, n_used, spec->K_c_px[0], spec->K_c_px[4], spec->pmd_scale_per_px, out);
            out += DIMENET_STEP_SIZE;
        }
        if (code == DIMENET_OK && spec->moments) {
            moment_inputs(G, n_used, spec->pmd_scale_per_px, out);
        }
    }

    if (stats != NULL) {
        stats->e_c_px = n_used > 0 ? norm_sum / (double)n_used : NAN;
        stats->n_used = n_used;
        stats->n_behind = n_behind;
    }
    if (code == DIMENET_OK && (flags & DIMENET_REFUSE_BEHIND_CAMERA) && !all_in_front) {
        code = DIMENET_E_BEHIND_CAMERA;
    }
    return code;
}

/* -- the pose under K (geometry/pose_step.py) ------------------------------------------------- */

/* geometry.frame_error_and_depth under the pinhole k (skew 0) at the pose (rvec, tvec): the mean norm of
 * the residuals ((a fx + cx) - x, (b fy + cy) - y), summed in cv::sum's order (four at a time, then one
 * by one), and the smallest Z_C (np.min: NaN when one is NaN; inf without points). */
static void pose_error_and_depth(size_t N, const double *p2, const double *p3, const double k[4], const double r[3],
                                 const double t[3], double *e_px, double *depth_mm)
{
    double R[9], norms[4], norm_sum = 0.0, depth = HUGE_VAL;
    size_t i;
    int c;
    rodrigues(r, R);
    for (i = 0; i < N; i++) {
        double X = p3[3 * i], Y = p3[3 * i + 1], Z = p3[3 * i + 2];
        double xc = ((X * R[0] + Y * R[1]) + Z * R[2]) + t[0];
        double yc = ((X * R[3] + Y * R[4]) + Z * R[5]) + t[1];
        double zc = ((X * R[6] + Y * R[7]) + Z * R[8]) + t[2];
        double inv_z = 1.0 / zc, a = xc * inv_z, b = yc * inv_z;
        double du = (a * k[0] + k[2]) - p2[2 * i], dv = (b * k[1] + k[3]) - p2[2 * i + 1];
        if (zc < depth || zc != zc) {
            depth = depth != depth ? depth : zc;
        }
        norms[i % 4] = sqrt(du * du + dv * dv);
        if (i % 4 == 3) {
            norm_sum += ((norms[0] + norms[1]) + norms[2]) + norms[3];
        }
    }
    for (c = 0; c < (int)(N % 4); c++) {
        norm_sum += norms[c];
    }
    *e_px = norm_sum / (double)N;
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

/* pose_step.solve_pose_step: x = -(JJ[:6, :6])^-1 Jr[:6] by Cholesky (L L^T), 0 when not positive definite. */
static int pose_solve(const double JJ[100], const double Jr[10], double x[6])
{
    double L[36], y[6], s;
    int i, j, k;
    for (i = 0; i < 6; i++) {
        for (j = 0; j <= i; j++) {
            s = JJ[i * 10 + j];
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
    if (n_scratch == NULL || n_points > ((size_t)-1) / sizeof(double) / 5) {
        return DIMENET_E_ARGUMENT;
    }
    *n_scratch = 5 * n_points;
    return DIMENET_OK;
}

int dimenet_pose_steps(size_t n_points, const double *points_2d_px, const double *points_3d_w_mm,
                       const double k_px[4], const double rvec_start_rad[3], const double tvec_start_mm[3], int steps,
                       double rvec_rad[3], double tvec_mm[3], double *e_px, double *depth_mm, double *scratch,
                       size_t n_scratch)
{
    const size_t N = n_points;
    double fx, fy, cx, cy, q[4], qw[4], qn[4], r[3], t[3], R[9], dR[9], G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE];
    double JJ[100], Jr[10], rss, step[6], t_new[3];
    double *xs, *ys, *inv_zs, *dus, *dvs;
    size_t i, need;
    int s, c;
    gram_points p;

    if (dimenet_pose_scratch_doubles(N, &need) != DIMENET_OK || k_px == NULL || rvec_start_rad == NULL
        || tvec_start_mm == NULL || rvec_rad == NULL || tvec_mm == NULL || steps < 0
        || steps > DIMENET_MAX_POSE_STEPS || (N > 0 && (points_2d_px == NULL || points_3d_w_mm == NULL))
        || (steps > 0 && N > 0 && (scratch == NULL || n_scratch < need))) {
        return DIMENET_E_ARGUMENT;
    }
    fx = k_px[0], fy = k_px[1], cx = k_px[2], cy = k_px[3];
    xs = ys = inv_zs = dus = dvs = scratch; /* no step: not read (NULL allowed) */
    if (steps > 0 && N > 0) {
        ys = xs + N, inv_zs = ys + N, dus = inv_zs + N, dvs = dus + N;
    }
    for (c = 0; c < 3; c++) {
        r[c] = rvec_start_rad[c];
        t[c] = tvec_start_mm[c];
    }
    pose_quaternion(r, q);
    for (s = 0; s < steps; s++) {
        rodrigues(r, R);
        for (i = 0; i < N; i++) { /* ((R_i0 X + R_i1 Y) + R_i2 Z) + t_i, then fx X / Z + cx - x */
            double X = points_3d_w_mm[3 * i], Y = points_3d_w_mm[3 * i + 1], Z = points_3d_w_mm[3 * i + 2];
            double xc = ((X * R[0] + Y * R[1]) + Z * R[2]) + t[0];
            double yc = ((X * R[3] + Y * R[4]) + Z * R[5]) + t[1];
            double zc = ((X * R[6] + Y * R[7]) + Z * R[8]) + t[2];
            double inv_z = 1.0 / zc;
            xs[i] = xc, ys[i] = yc, inv_zs[i] = inv_z;
            dus[i] = ((xc * inv_z) * fx + cx) - points_2d_px[2 * i];
            dvs[i] = ((yc * inv_z) * fy + cy) - points_2d_px[2 * i + 1];
        }
        memset(&p, 0, sizeof p);
        p.x = xs, p.y = ys, p.inv_z = inv_zs, p.du = dus, p.dv = dvs;
        gram_of(&p, N, G);
        gram_normal_equations(G, fx, fy, JJ, Jr, &rss);
        if (!pose_solve(JJ, Jr, step)) {
            return DIMENET_E_NO_POSE_STEP;
        }
        rodrigues(step, dR);
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

/* -- the input rules' fast tests (rectify/checks.py) ------------------------------------------ */

/* checks.clearly_spread of n points of dims 2 or 3 (row major): the sample covariance in point order. */
static int clearly_spread(size_t n, const double *p, int dims, double ratio, double absolute)
{
    double mean[3] = {0.0, 0.0, 0.0}, C[9], scale = 1.0, trace, minors;
    size_t i;
    int a, b;
    for (i = 0; i < n; i++) {
        for (a = 0; a < dims; a++) {
            double v = p[i * (size_t)dims + (size_t)a];
            mean[a] += v;
            scale = fabs(v) > scale ? fabs(v) : scale;
        }
    }
    for (a = 0; a < dims; a++) {
        mean[a] /= (double)n;
    }
    for (a = 0; a < 9; a++) {
        C[a] = 0.0;
    }
    for (i = 0; i < n; i++) {
        double d[3];
        for (a = 0; a < dims; a++) {
            d[a] = p[i * (size_t)dims + (size_t)a] - mean[a];
        }
        for (a = 0; a < dims; a++) {
            for (b = a; b < dims; b++) {
                C[a * 3 + b] += d[a] * d[b];
            }
        }
    }
    for (a = 0; a < 9; a++) {
        C[a] /= (double)n;
    }
    if (dims == 2) {
        trace = C[0] + C[4];
        minors = C[0] * C[4] - C[1] * C[1];
    } else {
        trace = C[0] + C[4] + C[8];
        minors = (C[0] * C[4] - C[1] * C[1]) + (C[0] * C[8] - C[2] * C[2]) + (C[4] * C[8] - C[5] * C[5]);
    }
    return minors > 3.0 * ratio * (trace * trace) && trace > (double)dims * absolute * (scale * scale);
}

int dimenet_frame_checks(size_t n_points, const double *points_2d_image_px, const double *points_2d_px,
                         const double *points_3d_w_mm, double width_px, double height_px, double max_coordinate,
                         double spread_ratio, double spread_absolute, unsigned *result)
{
    const double high_x = width_px - 0.5, high_y = height_px - 0.5;
    size_t i;
    unsigned out = 0u;
    if (n_points < 1 || points_2d_image_px == NULL || points_2d_px == NULL || points_3d_w_mm == NULL
        || result == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (i = 0; i < n_points && out == 0u; i++) {
        double x = points_2d_image_px[2 * i], y = points_2d_image_px[2 * i + 1];
        const double *X = points_3d_w_mm + 3 * i;
        if (!(x >= -0.5 && x <= high_x && y >= -0.5 && y <= high_y)) {
            out = DIMENET_CHECK_OUTSIDE;
        }
        if (!(X[0] >= -max_coordinate && X[0] < max_coordinate && X[1] >= -max_coordinate && X[1] < max_coordinate
              && X[2] >= -max_coordinate && X[2] < max_coordinate)) {
            out = DIMENET_CHECK_OUTSIDE;
        }
    }
    if (out == 0u && !(clearly_spread(n_points, points_3d_w_mm, 3, spread_ratio, spread_absolute)
                       && clearly_spread(n_points, points_2d_px, 2, spread_ratio, spread_absolute))) {
        out = DIMENET_CHECK_NOT_SPREAD;
    }
    *result = out;
    return DIMENET_OK;
}

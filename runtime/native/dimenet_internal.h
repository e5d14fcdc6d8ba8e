/* dimenet_internal.h: what the core's C files share with each other; not the API (dimenet_core.h is).
 * The names start with dimenet__ so that an app that links the core meets no clash. */
#ifndef DIMENET_INTERNAL_H
#define DIMENET_INTERNAL_H

#include "dimenet_core.h"

/* numpy's pairwise summation block (numpy/_core/src/umath/loops_utils.h.src). */
#define PAIRWISE_BLOCK 128

/* Where a Gram's points are: their monomials side by side (lanes, stride apart), or their raw rows. */
typedef struct {
    const double *lanes;
    size_t stride;
    const double *x, *y, *inv_z, *du, *dv;
} dimenet__gram_points;

/* numpy's pairwise sum of a contiguous float64 run (pairwise_sum_DOUBLE): what a.sum() gives. */
double dimenet__pairwise_sum(const double *a, size_t n);

/* OpenCV's Rodrigues (cv::Rodrigues, vector to matrix). */
void dimenet__rodrigues(const double rvec[3], double R[9]);

/* OpenCV's Cholesky inverse (cv::invert with DECOMP_CHOLESKY: hal::Cholesky64f on a copy, the right hand side
 * the identity) of a (n x n, row major; its lower triangle is read, then overwritten): 0 when a pivot falls below
 * DBL_EPSILON. */
int dimenet__cholesky_inverse(double *a, int n, double *inverse);

/* geometry.frame_mean_norm's sum: the norms added in OpenCV's sumElems order (four lanes, each block of four
 * summed ((l0 + l1) + l2) + l3 into the total, then the last norms one by one). */
typedef struct {
    double lanes[4], total;
    size_t n;
} dimenet__norm_sum;

/* Adds one norm (px) to the sum (started as {{0}, 0, 0}); inline: it runs once per point. */
static inline void dimenet__norm_add(dimenet__norm_sum *sum, double norm)
{
    sum->lanes[sum->n % 4] = norm;
    if (sum->n % 4 == 3) {
        sum->total += ((sum->lanes[0] + sum->lanes[1]) + sum->lanes[2]) + sum->lanes[3];
    }
    sum->n++;
}

/* np.min's running minimum of depths (mm): the smaller of depth and z, a NaN once met staying (start: HUGE_VAL). */
static inline double dimenet__depth_min(double depth, double z)
{
    return depth != depth ? depth : (z < depth || z != z) ? z : depth;
}

/* The mean of the norms added, px (their total over their count). */
double dimenet__norm_mean(const dimenet__norm_sum *sum);

/* The monomials q of one point (geometry.normal_equations._monomials), then its residuals, into q[m * stride]. */
void dimenet__monomials(double x_mm, double y_mm, double inv_z, double du_px, double dv_px, double *q, size_t stride);

/* geometry.monomial_gram of n points: the (11, 11) Gram, symmetric, by numpy's pairwise sums. */
void dimenet__gram_of(const dimenet__gram_points *p, size_t n, double G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE]);

/* geometry.gram_normal_equations: JJ (10 x 10), Jr (10) and the residuals' sum of squares from the Gram G. */
void dimenet__gram_normal_equations(const double *G, double fx, double fy, double JJ[100], double Jr[10], double *rss);

/* x^2 as the reference's Python computes it: libm's pow(x, 2.0), which is not always x * x's rounding
 * (glibc's pow is within 0.52 ulp, not correctly rounded); the exponent is read through a volatile so that
 * the compiler does not turn the call into x * x. */
double dimenet__python_square(double x);

/* geometry.normal_equations._noise_weight: 1 / max(rss / max(dof, 1), floor^2) (Python's max). */
double dimenet__noise_weight(double rss, long dof, double floor_px);

/* numpy's pairwise sum of the products x[i] y[i] (each rounded first) of n values: what (x * y).sum() gives. */
double dimenet__pairwise_dot(const double *x, const double *y, size_t n);

/* y = A x, A (n x n) row major, each row as dimenet__pairwise_dot (geometry.normal_equations.matvec). */
void dimenet__matvec(const double *A, const double *x, int n, double *y);

/* geometry.prior_posterior: dimenet_prior_posterior with a full prior precision (4 x 4 px^-2, row major). */
int dimenet__prior_posterior(const double jj[100], const double k_precision_per_px2[16], double weight_per_px2,
                             double inverse[100]);

/* geometry.prior_step: the step (10, the update of w rad, tau mm, fx, fy, cx, cy px), cov (10 x 10) and the
 * data weight 1 / s^2 (px^-2) of the normal equations JJ, Jr, rss over n_residuals residuals with the prior's
 * precision (4 x 4 px^-2), the noise floored at noise_floor_px. DIMENET_E_HESSIAN_DIAGONAL,
 * DIMENET_E_NOT_POSITIVE_DEFINITE. */
int dimenet__prior_step(const double JJ[100], const double Jr[10], double rss, long n_residuals,
                        const double k_precision_per_px2[16], double noise_floor_px, double step[10], double cov[100],
                        double *weight_per_px2);

/* geometry.normal_equations.posterior_step: cov (10 x 10), dimenet__prior_posterior's, and the step -weight cov Jr
 * (10) at a known data weight (px^-2). DIMENET_E_HESSIAN_DIAGONAL, DIMENET_E_NOT_POSITIVE_DEFINITE. */
int dimenet__posterior_step(const double JJ[100], const double Jr[10], const double k_precision_per_px2[16],
                            double weight_per_px2, double step[10], double cov[100]);

#endif

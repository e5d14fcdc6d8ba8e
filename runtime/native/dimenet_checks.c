/* dimenet_checks: the input rules' fast tests of one frame (rectify/checks.py) and the unit of its PnP
 * (geometry/pnp.py). */
#include "dimenet_internal.h"

#include <math.h>
#include <string.h>

/* -- the input rules' fast tests (rectify/checks.py) ------------------------------------------ */

/* The running sums of checks.clearly_spread for points of 2 or 3 dims (a 2D point's z is 0, which adds
 * exact zeros to the trace and the minors): the mean, then the sample covariance, in point order. */
typedef struct {
    double mean[3], c00, c01, c02, c11, c12, c22, scale;
} spread_sums;

static inline void spread_first(spread_sums *s, double x, double y, double z)
{
    s->mean[0] += x, s->mean[1] += y, s->mean[2] += z;
    s->scale = fabs(x) > s->scale ? fabs(x) : s->scale;
    s->scale = fabs(y) > s->scale ? fabs(y) : s->scale;
    s->scale = fabs(z) > s->scale ? fabs(z) : s->scale;
}

static inline void spread_second(spread_sums *s, double x, double y, double z)
{
    x -= s->mean[0], y -= s->mean[1], z -= s->mean[2];
    s->c00 += x * x, s->c01 += x * y, s->c02 += x * z, s->c11 += y * y, s->c12 += y * z, s->c22 += z * z;
}

/* geometry.covariance_invariants from the sums of n points: the trace, the sum of the principal 2 x 2 minors and
 * the determinant of their sample covariance (1 / n), as the reference groups them. */
static void spread_invariants(const spread_sums *s, size_t n, double invariants[3])
{
    double nn = (double)n, c00 = s->c00 / nn, c01 = s->c01 / nn, c02 = s->c02 / nn, c11 = s->c11 / nn;
    double c12 = s->c12 / nn, c22 = s->c22 / nn;
    invariants[0] = (c00 + c11) + c22;
    invariants[1] = ((c00 * c11 - c01 * c01) + (c00 * c22 - c02 * c02)) + (c11 * c22 - c12 * c12);
    invariants[2] = (c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02)) + c02 * (c01 * c12 - c11 * c02);
}

/* checks.clearly_spread from the trace and minors of ``dims``-dimensional points and their largest |coordinate|. */
static int clearly_spread(const double invariants[3], double scale, int dims, double ratio, double absolute)
{
    double trace = invariants[0], minors = invariants[1];
    return minors > 3.0 * ratio * (trace * trace) && trace > (double)dims * absolute * (scale * scale);
}

int dimenet_frame_checks(size_t n_points, const double *points_2d_image_px, const double *points_2d_px,
                         const double *points_3d_w_mm, double width_px, double height_px, double max_coordinate,
                         double spread_ratio, double spread_absolute, unsigned *result, double invariants_3d[3])
{
    const double high_x = width_px - 0.5, high_y = height_px - 0.5;
    spread_sums s2 = {{0.0, 0.0, 0.0}, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0};
    spread_sums s3 = s2;
    double invariants_2d[3], invariants[3];
    size_t i;
    int inside = 1;
    if (n_points < 1 || points_2d_image_px == NULL || points_2d_px == NULL || points_3d_w_mm == NULL
        || result == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (i = 0; i < n_points; i++) { /* the bounds, and the means of the two point sets side by side */
        double x = points_2d_image_px[2 * i], y = points_2d_image_px[2 * i + 1];
        const double *X = points_3d_w_mm + 3 * i, *p = points_2d_px + 2 * i;
        inside &= x >= -0.5 && x <= high_x && y >= -0.5 && y <= high_y && X[0] >= -max_coordinate
                  && X[0] < max_coordinate && X[1] >= -max_coordinate && X[1] < max_coordinate
                  && X[2] >= -max_coordinate && X[2] < max_coordinate;
        spread_first(&s2, p[0], p[1], 0.0);
        spread_first(&s3, X[0], X[1], X[2]);
    }
    if (invariants_3d != NULL) {
        invariants_3d[0] = invariants_3d[1] = invariants_3d[2] = NAN;
    }
    if (!inside) {
        *result = DIMENET_CHECK_OUTSIDE;
        return DIMENET_OK;
    }
    for (i = 0; i < 3; i++) {
        s2.mean[i] /= (double)n_points;
        s3.mean[i] /= (double)n_points;
    }
    for (i = 0; i < n_points; i++) {
        const double *X = points_3d_w_mm + 3 * i, *p = points_2d_px + 2 * i;
        spread_second(&s2, p[0], p[1], 0.0);
        spread_second(&s3, X[0], X[1], X[2]);
    }
    spread_invariants(&s3, n_points, invariants);
    spread_invariants(&s2, n_points, invariants_2d);
    *result = clearly_spread(invariants, s3.scale, 3, spread_ratio, spread_absolute)
                      && clearly_spread(invariants_2d, s2.scale, 2, spread_ratio, spread_absolute)
                  ? 0u
                  : DIMENET_CHECK_NOT_SPREAD;
    if (invariants_3d != NULL) {
        memcpy(invariants_3d, invariants, sizeof invariants);
    }
    return DIMENET_OK;
}

/* -- the PnP's unit (geometry.pnp.power_of_two_unit) ------------------------------------------ */

/* numpy's pairwise sum of (a[i] / largest)^2 over n values (np.square(a / largest).sum()): each leaf
 * block of at most PAIRWISE_BLOCK squares is written out and summed as numpy sums it. */
static double scaled_squares_sum(const double *a, size_t n, double largest)
{
    double block[PAIRWISE_BLOCK];
    size_t i;
    if (n > PAIRWISE_BLOCK) {
        size_t n2 = n / 2;
        n2 -= n2 % 8;
        return scaled_squares_sum(a, n2, largest) + scaled_squares_sum(a + n2, n - n2, largest);
    }
    for (i = 0; i < n; i++) {
        double v = a[i] / largest;
        block[i] = v * v;
    }
    return dimenet__pairwise_sum(block, n);
}

/* The largest binary exponent of a finite double (geometry.pnp.MAX_EXPONENT). */
#define MAX_EXPONENT 1023

/* Python's round() of a float to an integral value: halves to even. */
static double python_round(double x)
{
    double rounded = round(x);
    if (fabs(x - rounded) == 0.5) {
        rounded = 2.0 * round(x / 2.0);
    }
    return rounded;
}

int dimenet_power_of_two_unit(size_t n_values, const double *points_3d_w_mm, double *unit_mm)
{
    double largest = 0.0, rms;
    size_t i;
    if ((n_values > 0 && points_3d_w_mm == NULL) || unit_mm == NULL) {
        return DIMENET_E_ARGUMENT;
    }
    for (i = 0; i < n_values; i++) {
        double v = fabs(points_3d_w_mm[i]);
        if (v != v) {
            largest = v;
            break;
        }
        largest = v > largest ? v : largest;
    }
    *unit_mm = 1.0;
    if (!(largest > 0.0 && largest < HUGE_VAL)) {
        return DIMENET_OK;
    }
    rms = largest * sqrt(scaled_squares_sum(points_3d_w_mm, n_values, largest) / (double)n_values * 3.0);
    if (rms > 0.0 && rms < HUGE_VAL) { /* a denormal largest coordinate can give 0 */
        double exponent = python_round(log2(rms));
        *unit_mm = ldexp(1.0, exponent > MAX_EXPONENT ? MAX_EXPONENT : (int)exponent);
    }
    return DIMENET_OK;
}

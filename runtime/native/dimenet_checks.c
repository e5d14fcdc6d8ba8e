/* dimenet_checks: the input rules' fast tests of one frame (rectify/checks.py). */
#include "dimenet_internal.h"

#include <math.h>
#include <string.h>

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

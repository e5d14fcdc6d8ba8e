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

/* The monomials q of one point (geometry.normal_equations._monomials), then its residuals, into q[m * stride]. */
void dimenet__monomials(double x_mm, double y_mm, double inv_z, double du_px, double dv_px, double *q, size_t stride);

/* geometry.monomial_gram of n points: the (11, 11) Gram, symmetric, by numpy's pairwise sums. */
void dimenet__gram_of(const dimenet__gram_points *p, size_t n, double G[DIMENET_GRAM_SIZE * DIMENET_GRAM_SIZE]);

/* geometry.gram_normal_equations: JJ (10 x 10), Jr (10) and the residuals' sum of squares from the Gram G. */
void dimenet__gram_normal_equations(const double *G, double fx, double fy, double JJ[100], double Jr[10], double *rss);

#endif

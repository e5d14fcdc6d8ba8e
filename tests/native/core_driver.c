/* The C core's own test, without Python: every entry point of runtime/native/dimenet_core.h on valid
 * frames (against a second, plain computation of what it should give) and on hostile ones (NaN, inf,
 * huge values, no points, points behind the camera, a singular Hessian, bad arguments), where it must
 * return its error code and touch nothing outside its buffers. tests/native/test_c_core.py compiles it
 * warning-free and under AddressSanitizer and UndefinedBehaviorSanitizer and runs it; it prints one
 * line per failed check and exits 1 when one failed.
 *
 *   gcc -std=c99 -Wall -Wextra -pedantic -Werror -ffp-contract=off -I runtime/native \
 *       tests/native/core_driver.c runtime/native/dimenet_*.c -lm -o core_driver && ./core_driver */
#include "dimenet_core.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures = 0;

#define CHECK(cond, what)                                                                                              \
    do {                                                                                                               \
        if (!(cond)) {                                                                                                 \
            printf("FAIL %s:%d: %s\n", __FILE__, __LINE__, what);                                                      \
            failures++;                                                                                                \
        }                                                                                                              \
    } while (0)

/* The bundled models' feature: grid 8x6, variant A, depth_mm 500; "any-scene" adds the data step and
 * the moments. The camera: galaxy-s8's K_c on 4032 x 3024 px. */
static dimenet_feature_spec model_spec(int any_scene)
{
    dimenet_feature_spec s;
    static const double scale[5] = {0.1, 0.1, 0.01, 0.01, 500.0};
    static const double K[9] = {3059.68, 0, 2023.82, 0, 3059.68, 1508.45, 0, 0, 1};
    int c;
    memset(&s, 0, sizeof s);
    s.grid_cols = 8;
    s.grid_rows = 6;
    s.image_width_px = 4032;
    s.image_height_px = 3024;
    s.n_channels = 5;
    for (c = 0; c < 5; c++) {
        s.channels[c] = c;
        s.channel_scale[c] = scale[c];
    }
    s.depth_mm = 500.0;
    s.data_step = any_scene;
    s.moments = any_scene;
    s.pmd_scale_per_px = 0.1;
    memcpy(s.K_c_px, K, sizeof K);
    return s;
}

static void rotation(const double r[3], double R[9])
{
    double t = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]), k[3], c, s;
    int i, j;
    for (i = 0; i < 3; i++) {
        k[i] = r[i] / t;
    }
    c = cos(t), s = sin(t);
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            R[i * 3 + j] = (i == j ? c : 0.0) + (1 - c) * k[i] * k[j];
        }
    }
    R[1] -= s * k[2], R[2] += s * k[1], R[3] += s * k[2], R[5] -= s * k[0], R[6] -= s * k[1], R[7] += s * k[0];
}

/* n points on two planes of a box in {W} (mm), seen from the pose (rvec, tvec); their exact pixels
 * under spec's K_c plus offset_px in x. */
static void make_frame(const dimenet_feature_spec *spec, size_t n, const double rvec[3], const double tvec[3],
                       double offset_px, double *p2, double *p3)
{
    double R[9];
    size_t i;
    rotation(rvec, R);
    for (i = 0; i < n; i++) {
        double X = -150.0 + 300.0 * (double)(i % 17) / 16.0, Y = -110.0 + 220.0 * (double)((i / 17) % 13) / 12.0;
        double Z = (i % 2) ? 0.0 : 40.0 + 0.1 * (double)i, xc[3];
        int r;
        p3[3 * i] = X, p3[3 * i + 1] = Y, p3[3 * i + 2] = Z;
        for (r = 0; r < 3; r++) {
            xc[r] = R[r * 3] * X + R[r * 3 + 1] * Y + R[r * 3 + 2] * Z + tvec[r];
        }
        p2[2 * i] = spec->K_c_px[0] * xc[0] / xc[2] + spec->K_c_px[2] + offset_px;
        p2[2 * i + 1] = spec->K_c_px[4] * xc[1] / xc[2] + spec->K_c_px[5];
    }
}

static int near(double a, double b, double tol)
{
    return fabs(a - b) <= tol * (1.0 + fabs(b));
}

/* The grid part again, plainly: the cell means of X, Y, 1/Z in {C0} and the PMD, scaled. */
static void grid_reference(const dimenet_feature_spec *s, size_t n, const double *p2, const double *p3,
                           const double rvec[3], const double tvec[3], double *out)
{
    double R[9], z_sum = 0.0, factor, sums[48][6];
    size_t i;
    int c, k;
    rotation(rvec, R);
    memset(sums, 0, sizeof sums);
    for (i = 0; i < n; i++) {
        double xc[3], ch[5];
        int col = (int)floor(p2[2 * i] * s->grid_cols / s->image_width_px);
        int row = (int)floor(p2[2 * i + 1] * s->grid_rows / s->image_height_px);
        int r;
        col = col < 0 ? 0 : (col > s->grid_cols - 1 ? s->grid_cols - 1 : col);
        row = row < 0 ? 0 : (row > s->grid_rows - 1 ? s->grid_rows - 1 : row);
        for (r = 0; r < 3; r++) {
            xc[r] = R[r * 3] * p3[3 * i] + R[r * 3 + 1] * p3[3 * i + 1] + R[r * 3 + 2] * p3[3 * i + 2] + tvec[r];
        }
        z_sum += xc[2];
        ch[0] = s->K_c_px[0] * xc[0] / xc[2] + s->K_c_px[2] - p2[2 * i];
        ch[1] = s->K_c_px[4] * xc[1] / xc[2] + s->K_c_px[5] - p2[2 * i + 1];
        ch[2] = xc[0], ch[3] = xc[1], ch[4] = 1.0 / xc[2];
        for (k = 0; k < 5; k++) {
            sums[row * s->grid_cols + col][k] += ch[k];
        }
        sums[row * s->grid_cols + col][5] += 1.0;
    }
    factor = s->depth_mm * (double)n / z_sum;
    for (c = 0; c < s->grid_cols * s->grid_rows; c++) {
        double count = sums[c][5] > 1 ? sums[c][5] : 1;
        for (k = 0; k < 5; k++) {
            double f = k == 2 || k == 3 ? factor : (k == 4 ? 1.0 / factor : 1.0);
            out[c * 5 + k] = sums[c][k] / count * s->channel_scale[k] * f;
        }
    }
}

static void test_sizes(void)
{
    dimenet_feature_spec s = model_spec(1), bad;
    size_t n = 0, scratch = 0;
    CHECK(dimenet_feature_size(&s, &n) == DIMENET_OK && n == 240 + 8 + 64, "any-scene's feature size");
    s = model_spec(0);
    CHECK(dimenet_feature_size(&s, &n) == DIMENET_OK && n == 240, "default's feature size");
    CHECK(dimenet_scratch_doubles(&s, 320, &scratch) == DIMENET_OK && scratch == 18 * 320 + 6 * 48, "scratch size");
    CHECK(dimenet_feature_size(NULL, &n) == DIMENET_E_ARGUMENT, "NULL spec");
    CHECK(dimenet_feature_size(&s, NULL) == DIMENET_E_ARGUMENT, "NULL size");
    CHECK(dimenet_scratch_doubles(&s, (size_t)-1, &scratch) == DIMENET_E_ARGUMENT, "scratch size overflow");
    bad = s, bad.grid_cols = 0;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "0 columns");
    bad = s, bad.grid_cols = 1 << 30, bad.grid_rows = 1 << 30;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_OK || sizeof(size_t) < 8, "a 2^60-cell grid fits 64 bits");
    bad = s, bad.grid_cols = 0x7fffffff, bad.grid_rows = 0x7fffffff;
    CHECK(dimenet_scratch_doubles(&bad, 10, &scratch) == DIMENET_E_ARGUMENT, "a grid whose scratch overflows");
    bad = s, bad.n_channels = 6;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "6 channels");
    bad = s, bad.channels[4] = 7;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "channel 7");
    bad = s, bad.image_width_px = NAN;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "NaN width");
    bad = s, bad.image_height_px = -1;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "negative height");
    bad = s, bad.depth_mm = -5;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "negative depth_mm");
    bad = s, bad.depth_mm = HUGE_VAL;
    CHECK(dimenet_feature_size(&bad, &n) == DIMENET_E_ARGUMENT, "infinite depth_mm");
    CHECK(strcmp(dimenet_error_message(DIMENET_E_NOT_POSITIVE_DEFINITE),
                 "the points fix no pose: the Gauss-Newton Hessian is not positive definite")
              == 0,
          "the message of a Hessian that is not positive definite");
    CHECK(dimenet_error_message(-1) != NULL && dimenet_error_message(99) != NULL, "unknown codes have a message");
}

/* A frame seen exactly: no PMD, the grid as computed plainly, a zero data step, the moments' means. */
static void test_exact_frame(int any_scene)
{
    enum { N = 320 };
    static double p2[2 * N], p3[3 * N], rows[6 * N], feats[312], reference[240], scratch[18 * N + 6 * 48];
    static const double rvec[3] = {0.12, -0.31, 0.05}, tvec[3] = {12.0, -25.0, 610.0};
    dimenet_feature_spec s = model_spec(any_scene);
    dimenet_frame_stats st;
    size_t D, i;
    int code, k;
    double mean_a = 0.0;
    dimenet_feature_size(&s, &D);
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, DIMENET_REFUSE_BEHIND_CAMERA, feats, D, rows,
                                  scratch, sizeof scratch / sizeof scratch[0], &st);
    CHECK(code == DIMENET_OK, "an exact frame is fine");
    CHECK(st.n_used == N && st.n_behind == 0 && st.e_c_px < 1e-9, "an exact frame has no PMD");
    grid_reference(&s, N, p2, p3, rvec, tvec, reference);
    for (k = 0; k < 240; k++) {
        CHECK(near(feats[k], reference[k], 1e-9), "the grid feature is the cells' scaled means");
    }
    for (i = 0; i < N; i++) {
        CHECK(rows[5 * N + i] == 1.0 && fabs(rows[i]) < 1e-9, "point rows: the count row, the PMD");
        mean_a += rows[2 * N + i] * rows[4 * N + i] / N;
    }
    if (any_scene) {
        for (k = 0; k < 4; k++) {
            CHECK(fabs(feats[240 + k]) < 1e-6, "no PMD: no step on K");
            CHECK(feats[244 + k] <= 1e-12 && feats[244 + k] > -20, "the posterior is no wider than the prior");
        }
        CHECK(near(feats[248], mean_a, 1e-12), "the first moment is the mean of a = X / Z");
    }
    /* one pixel off in x: e_c is 1 px, and the step moves cx (its clip is 0.05 fx_c = 153 px) */
    make_frame(&s, N, rvec, tvec, 1.0, p2, p3);
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, NULL, scratch,
                                  sizeof scratch / sizeof scratch[0], &st);
    CHECK(code == DIMENET_OK && near(st.e_c_px, 1.0, 1e-9), "one pixel off: e_c 1 px");
    if (any_scene) {
        CHECK(fabs(feats[242] - 0.1) < 0.05, "one pixel off in x: the step moves cx by about +1 px (x 0.1)");
    }
}

/* Hostile frames: each call must return a code (no crash, no sanitizer report). */
static void test_hostile(void)
{
    enum { N = 64 };
    static double p2[2 * N], p3[3 * N], rows[6 * N], feats[312], scratch[18 * N + 6 * 48];
    static unsigned char mask[N];
    const double rvec[3] = {0.1, 0.2, 0.3}, tvec[3] = {0, 0, 500}, behind[3] = {0, 0, -500};
    const size_t S = sizeof scratch / sizeof scratch[0];
    dimenet_feature_spec s = model_spec(1);
    dimenet_frame_stats st;
    double jj[100], inv[100], gram[121];
    size_t D, i;
    int code;
    dimenet_feature_size(&s, &D);
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);

    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, behind, DIMENET_REFUSE_BEHIND_CAMERA, feats, D, rows,
                                  scratch, S, &st);
    CHECK(code == DIMENET_E_BEHIND_CAMERA && st.n_behind == N, "behind the camera: refused with the flag");
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, behind, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_OK && st.n_behind == N, "behind the camera: counted without the flag");

    code = dimenet_frame_features(&s, 0, NULL, NULL, NULL, rvec, tvec, 0, feats, D, NULL, scratch, S, &st);
    CHECK(code == DIMENET_E_HESSIAN_DIAGONAL && st.n_used == 0, "no points: no pose");
    memset(mask, 0, sizeof mask);
    code = dimenet_frame_features(&s, N, p2, p3, mask, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_HESSIAN_DIAGONAL && st.n_used == 0, "an empty mask: no pose");
    s.data_step = 0, s.moments = 0;
    code = dimenet_frame_features(&s, N, p2, p3, mask, rvec, tvec, 0, feats, 240, rows, scratch, S, &st);
    CHECK(code == DIMENET_OK && feats[0] == 0.0 && isnan(st.e_c_px), "the default's feature of no points is zero");
    s = model_spec(1);

    for (i = 0; i < N; i++) { /* one point repeated: the pose is not fixed */
        memcpy(p2 + 2 * i, p2, 2 * sizeof(double));
        memcpy(p3 + 3 * i, p3, 3 * sizeof(double));
    }
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_NOT_POSITIVE_DEFINITE, "one point repeated: not positive definite");

    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    p2[7] = NAN;
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_HESSIAN_DIAGONAL, "a NaN pixel: a NaN Hessian diagonal");
    p2[7] = HUGE_VAL;
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_HESSIAN_DIAGONAL, "an infinite pixel: an infinite Hessian diagonal");
    p2[7] = 1e308;
    p3[4] = -1e308;
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code != DIMENET_OK, "huge values: refused");
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    p3[2] = -tvec[2] * 2; /* not exact: one point far behind */
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, DIMENET_REFUSE_BEHIND_CAMERA, feats, D, rows,
                                  scratch, S, &st);
    CHECK(code == DIMENET_OK || code == DIMENET_E_BEHIND_CAMERA, "one point moved: a code");
    {
        const double nan_pose[3] = {NAN, 0, 0}, huge_pose[3] = {1e300, -1e300, 1e300};
        code = dimenet_frame_features(&s, N, p2, p3, NULL, nan_pose, tvec, DIMENET_REFUSE_BEHIND_CAMERA, feats, D,
                                      rows, scratch, S, &st);
        CHECK(code == DIMENET_E_HESSIAN_DIAGONAL, "a NaN rotation");
        code = dimenet_frame_features(&s, N, p2, p3, NULL, huge_pose, huge_pose, 0, feats, D, rows, scratch, S, &st);
        CHECK(code != DIMENET_OK, "a huge pose");
    }
    /* bad arguments */
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D - 1, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "a feature buffer of the wrong size");
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S - 1, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "too little scratch");
    code = dimenet_frame_features(&s, N, NULL, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "no points_2d");
    code = dimenet_frame_features(&s, N, p2, p3, NULL, NULL, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "no rvec");
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 4u, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "an unknown flag");
    code = dimenet_frame_features(NULL, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, &st);
    CHECK(code == DIMENET_E_ARGUMENT, "no spec");
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, rows, scratch, S, NULL);
    CHECK(code == DIMENET_OK, "stats are optional");

    /* the Hessian inverse and the Gram on their own */
    memset(jj, 0, sizeof jj);
    CHECK(dimenet_prior_posterior(jj, 1.0, 1.0, inv) == DIMENET_E_HESSIAN_DIAGONAL, "a zero Hessian");
    for (i = 0; i < 10; i++) {
        jj[i * 10 + i] = 1.0;
    }
    jj[1] = jj[10] = 2.0; /* [[1, 2], [2, 1]] block: indefinite */
    CHECK(dimenet_prior_posterior(jj, 1.0, 1.0, inv) == DIMENET_E_NOT_POSITIVE_DEFINITE, "an indefinite Hessian");
    jj[1] = jj[10] = 0.5;
    CHECK(dimenet_prior_posterior(jj, 0.0, 2.0, inv) == DIMENET_OK && near(inv[0], 2.0 / 3.0, 1e-14),
          "a 2 x 2 block's inverse");
    jj[0] = NAN;
    CHECK(dimenet_prior_posterior(jj, 0.0, 2.0, inv) == DIMENET_E_HESSIAN_DIAGONAL, "a NaN Hessian");
    CHECK(dimenet_prior_posterior(NULL, 0.0, 2.0, inv) == DIMENET_E_ARGUMENT, "no Hessian");
    CHECK(dimenet_monomial_gram(0, NULL, NULL, NULL, NULL, NULL, gram) == DIMENET_OK && gram[0] == 0.0,
          "the Gram of no points");
    CHECK(dimenet_monomial_gram(3, NULL, NULL, NULL, NULL, NULL, gram) == DIMENET_E_ARGUMENT, "no points given");
    {
        const double x[2] = {1, 2}, y[2] = {3, 4}, iz[2] = {0.5, 0.25}, u[2] = {1, -1}, v[2] = {0, 2};
        CHECK(dimenet_monomial_gram(2, x, y, iz, u, v, gram) == DIMENET_OK && gram[0] == 2.0
                  && gram[1] == 0.5 + 0.5 && gram[9 * 11 + 9] == 2.0 && gram[11 + 0] == gram[1],
              "the Gram of two points");
    }
}

/* Other specs: variants, a 1 x 1 and an odd grid, no depth_mm, a mask. */
static void test_other_specs(void)
{
    enum { N = 100 };
    static double p2[2 * N], p3[3 * N], feats[7 * 5 * 5 + 72], scratch[18 * N + 6 * 35];
    static unsigned char mask[N];
    const double rvec[3] = {-0.2, 0.1, 0.0}, tvec[3] = {5, 5, 700};
    dimenet_feature_spec s = model_spec(1);
    dimenet_frame_stats st;
    size_t D, i;
    int code;
    make_frame(&s, N, rvec, tvec, 0.5, p2, p3);
    for (i = 0; i < N; i++) {
        mask[i] = (unsigned char)(i % 3 != 0);
    }
    s.grid_cols = 1, s.grid_rows = 1, s.n_channels = 2, s.channels[0] = 4, s.channels[1] = 0, s.depth_mm = 0;
    dimenet_feature_size(&s, &D);
    code = dimenet_frame_features(&s, N, p2, p3, mask, rvec, tvec, 0, feats, D, NULL, scratch, 18 * N + 6, &st);
    CHECK(code == DIMENET_OK && D == 2 + 72 && st.n_used == 66, "a 1 x 1 grid of 1/Z and dx on masked points");
    CHECK(near(feats[1], -0.5 * 0.1, 1e-9), "the mean dx of a frame half a pixel off, scaled");
    s.grid_cols = 7, s.grid_rows = 5, s.n_channels = 3, s.channels[0] = 2, s.channels[1] = 3, s.channels[2] = 4;
    s.data_step = 0;
    dimenet_feature_size(&s, &D);
    code = dimenet_frame_features(&s, N, p2, p3, NULL, rvec, tvec, 0, feats, D, NULL, scratch, 18 * N + 6 * 35, &st);
    CHECK(code == DIMENET_OK && D == 105 + 64, "a 7 x 5 grid, variant E, moments");
}

/* The pose under K from a start pose: an exact frame seen under K_c from a pose, started one step
 * away, returns to it; a frame under K = K_c + 3 px in cx from its K_c pose moves; hostile frames give
 * codes, never a crash. */
static void test_pose_steps(void)
{
    enum { N = 320 };
    static double p2[2 * N], p3[3 * N], scratch[12 * N];
    static const double rvec[3] = {0.12, -0.31, 0.05}, tvec[3] = {12.0, -25.0, 610.0};
    dimenet_feature_spec s = model_spec(0);
    double k[4] = {3059.68, 3059.68, 2023.82, 1508.45}, r0[3], t0[3], r[3], t[3], e = -1.0, depth = -1.0;
    size_t P = 0, i;
    int code, c;
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    CHECK(dimenet_pose_scratch_doubles(N, &P) == DIMENET_OK && P == 12 * N, "the pose's scratch is 12 N");
    CHECK(dimenet_pose_scratch_doubles((size_t)-1, &P) == DIMENET_E_ARGUMENT, "an overflowing scratch size");
    for (c = 0; c < 3; c++) {
        r0[c] = rvec[c] + 2e-3, t0[c] = tvec[c] + 1.0;
    }
    code = dimenet_pose_steps(N, p2, p3, k, r0, t0, 4, r, t, &e, &depth, scratch, 12 * N);
    CHECK(code == DIMENET_OK, "four steps from a nearby pose");
    CHECK(e < 1e-9 && depth > 500.0 && depth < 700.0, "the exact frame's error is 0 at a depth of ~610 mm");
    for (c = 0; c < 3; c++) {
        CHECK(near(r[c], rvec[c], 1e-9) && near(t[c], tvec[c], 1e-9), "the exact frame's pose is found again");
    }
    code = dimenet_pose_steps(N, p2, p3, k, rvec, tvec, 0, r, t, &e, &depth, NULL, 0);
    CHECK(code == DIMENET_OK && r[0] == rvec[0] && t[2] == tvec[2], "no step: the start pose");
    CHECK(e < 1e-9 && depth > 500.0, "no step, no scratch: the error and depth at the start pose");
    k[2] += 3.0;
    code = dimenet_pose_steps(N, p2, p3, k, rvec, tvec, 2, r, t, NULL, NULL, scratch, 12 * N);
    CHECK(code == DIMENET_OK && fabs(r[1] - rvec[1]) > 1e-5, "3 px in cx turns the pose");
    CHECK(dimenet_pose_steps(0, NULL, NULL, k, rvec, tvec, 1, r, t, NULL, NULL, NULL, 0) == DIMENET_E_NO_POSE_STEP,
          "no points: no step");
    for (i = 0; i < N; i++) { /* every point the same: J J^T singular */
        p3[3 * i] = p3[0], p3[3 * i + 1] = p3[1], p3[3 * i + 2] = p3[2], p2[2 * i] = p2[0], p2[2 * i + 1] = p2[1];
    }
    CHECK(dimenet_pose_steps(N, p2, p3, k, rvec, tvec, 1, r, t, NULL, NULL, scratch, 12 * N) == DIMENET_E_NO_POSE_STEP,
          "one point repeated fixes no pose");
    p2[7] = NAN;
    CHECK(dimenet_pose_steps(N, p2, p3, k, rvec, tvec, 1, r, t, NULL, NULL, scratch, 12 * N) == DIMENET_E_NO_POSE_STEP,
          "a NaN pixel: no step");
    CHECK(dimenet_pose_steps(N, p2, p3, k, rvec, tvec, 1, r, t, NULL, NULL, scratch, 12 * N - 1) == DIMENET_E_ARGUMENT,
          "a short scratch is refused");
    CHECK(dimenet_pose_steps(N, p2, p3, k, rvec, tvec, -1, r, t, NULL, NULL, scratch, 12 * N) == DIMENET_E_ARGUMENT,
          "negative steps are refused");
    CHECK(dimenet_pose_steps(N, p2, NULL, k, rvec, tvec, 1, r, t, NULL, NULL, scratch, 12 * N) == DIMENET_E_ARGUMENT,
          "a NULL buffer is refused");
    CHECK(strcmp(dimenet_error_message(DIMENET_E_NO_POSE_STEP), "no Gauss-Newton step: the points fix no pose under K")
              == 0,
          "the message is the reference's");
}

/* Mode map's step: an exact frame with the prior at its K and the start at its pose stays there; a prior
 * 4 px off in cx with a vague precision is pulled back by the frame; a known noise weighs the data by
 * 1 / s^2; hostile and bad arguments give codes. */
static void test_map_step(void)
{
    enum { N = 320 };
    static double p2[2 * N], p3[3 * N], scratch[9 * N], residuals[2 * N];
    static const double rvec[3] = {0.12, -0.31, 0.05}, tvec[3] = {12.0, -25.0, 610.0};
    dimenet_feature_spec s = model_spec(0);
    double k[4] = {3059.68, 3059.68, 2023.82, 1508.45}, prior[4], prior_cov[16] = {0.0}, out_k[4], R[9], t[3];
    double cov[100], weight = 0.0, Rs[9], turn[3] = {0.0, 0.0, 0.0}, e = -1.0, depth = 0.0;
    size_t S = 0, i;
    int steps = -1, c;
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    for (c = 0; c < 4; c++) {
        prior_cov[5 * c] = 1e6, prior[c] = k[c];
    }
    CHECK(dimenet_map_scratch_doubles(N, &S) == DIMENET_OK && S == 9 * N, "the map step's scratch is 9 N");
    CHECK(dimenet_map_scratch_doubles((size_t)-1, &S) == DIMENET_E_ARGUMENT, "an overflowing scratch size");
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
              == DIMENET_OK,
          "the exact frame's step");
    rotation(rvec, Rs);
    for (c = 0; c < 4; c++) {
        CHECK(near(out_k[c], k[c], 1e-6), "the exact frame keeps its K");
    }
    for (c = 0; c < 9; c++) {
        CHECK(near(R[c], Rs[c], 1e-9), "the exact frame keeps its pose");
    }
    CHECK(near(weight, 100.0, 1e-12), "no residuals: the noise floor 0.1 px weighs the data");
    CHECK(e >= 0.0 && e < 1e-6, "no residuals: a mean error of 0 px");
    CHECK(depth > 0.0 && depth < tvec[2] + 1000.0, "the points are in front of the camera");
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, turn, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
                  == DIMENET_OK
              && near(out_k[2], k[2], 1e-6),
          "a zero turn changes nothing");
    prior[2] += 4.0;
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, 0.5, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
              == DIMENET_OK,
          "a prior 4 px off in cx");
    CHECK(steps == 1 && fabs(out_k[2] - k[2]) < 0.4, "the frame pulls cx back");
    CHECK(weight == 4.0, "a known noise of 0.5 px: weight 4");
    for (i = 0; i < 2 * N; i++) {
        CHECK(fabs(residuals[i]) < 1.0, "the residuals at the step are small");
    }
    CHECK(e > 0.0 && e < 1.0, "the mean error at the step is small");
    CHECK(cov[66] > 0.0 && cov[66] < 1e6, "the posterior of fx is tighter than the prior");
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N - 1)
              == DIMENET_E_ARGUMENT,
          "a short scratch is refused");
    CHECK(dimenet_map_step(0, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
              == DIMENET_E_ARGUMENT,
          "no points are refused");
    CHECK(dimenet_map_step(N, p2, p3, NULL, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
              == DIMENET_E_ARGUMENT,
          "a NULL prior is refused");
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, NULL, &depth, &steps, scratch, 9 * N)
              == DIMENET_E_ARGUMENT,
          "a NULL error output is refused");
    prior_cov[10] = -1.0;
    CHECK(dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                           residuals, &e, &depth, &steps, scratch, 9 * N)
              == DIMENET_E_PRIOR_COVARIANCE,
          "a prior covariance with a negative variance is refused");
    CHECK(strcmp(dimenet_error_message(DIMENET_E_PRIOR_COVARIANCE),
                 "the prior's covariance of K is not positive definite")
              == 0,
          "the prior covariance's message");
    prior_cov[10] = 1e6;
    { /* the camera 2 m behind its place: every point behind it */
        const double back[3] = {tvec[0], tvec[1], tvec[2] - 2000.0};
        c = dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, back, NULL, 0.5, 0.1, out_k, R, t, cov, &weight,
                             residuals, &e, &depth, &steps, scratch, 9 * N);
        CHECK(c != DIMENET_OK || depth < 0.0, "points behind the camera give a negative depth");
    }
    for (c = 0; c < 16; c++) { /* the widest prior a double holds: the data alone */
        prior_cov[c] = c % 5 == 0 ? 1e300 : 0.0;
    }
    for (i = 0; i < N; i++) { /* every point the same: no pose */
        p3[3 * i] = p3[0], p3[3 * i + 1] = p3[1], p3[3 * i + 2] = p3[2], p2[2 * i] = p2[0], p2[2 * i + 1] = p2[1];
    }
    c = dimenet_map_step(N, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, out_k, R, t, cov, &weight,
                         residuals, &e, &depth, &steps, scratch, 9 * N);
    CHECK(c == DIMENET_E_NOT_POSITIVE_DEFINITE || c == DIMENET_E_HESSIAN_DIAGONAL, "one point repeated fixes no pose");
}

/* The input rules' fast tests: a frame inside and spread; a pixel outside, a NaN, a coordinate at the
 * range's end; collinear points; bad arguments. */
static void test_frame_checks(void)
{
    enum { N = 64 };
    static double p2[2 * N], p3[3 * N];
    static const double rvec[3] = {0.12, -0.31, 0.05}, tvec[3] = {12.0, -25.0, 610.0};
    dimenet_feature_spec s = model_spec(0);
    unsigned r = 99u;
    double inv[3] = {0.0, 0.0, 0.0};
    size_t i;
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK && r == 0u,
          "an ordinary frame passes");
    CHECK(inv[0] > 0.0 && inv[1] > 0.0 && inv[2] > 0.0 && inv[1] <= inv[0] * inv[0] / 3.0,
          "a 3D cloud's covariance: a positive trace, minors and determinant, the minors at most T^2 / 3");
    for (i = 0; i < 4; i++) { /* four points on a square of side 2 in z = 0: covariance diag(1, 1, 0) */
        p3[3 * i] = (i % 2) ? 1.0 : -1.0, p3[3 * i + 1] = (i / 2) ? 1.0 : -1.0, p3[3 * i + 2] = 0.0;
    }
    CHECK(dimenet_frame_checks(4, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK && inv[0] == 2.0
              && inv[1] == 1.0 && inv[2] == 0.0,
          "a square's invariants by hand: trace 2, minors 1, determinant 0");
    CHECK(dimenet_frame_checks(4, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, NULL) == DIMENET_OK,
          "no invariants asked for");
    make_frame(&s, N, rvec, tvec, 0.0, p2, p3);
    p2[6] = -0.5;
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK && r == 0u,
          "on the image's edge: inside");
    p2[6] = -0.51;
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK
              && r == DIMENET_CHECK_OUTSIDE && inv[0] != inv[0],
          "beyond the edge: outside, no invariants (NaN)");
    p2[6] = NAN;
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK
              && r == DIMENET_CHECK_OUTSIDE,
          "a NaN pixel: outside");
    p2[6] = 100.0, p3[4] = 1e12;
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK
              && r == DIMENET_CHECK_OUTSIDE,
          "a coordinate at the range's end: outside");
    for (i = 0; i < N; i++) {
        p3[3 * i + 1] = 0.0, p3[3 * i + 2] = 0.0;
    }
    CHECK(dimenet_frame_checks(N, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_OK
              && r == DIMENET_CHECK_NOT_SPREAD,
          "collinear 3D points: not clearly spread");
    CHECK(dimenet_frame_checks(0, p2, p2, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_E_ARGUMENT,
          "no points are refused");
    CHECK(dimenet_frame_checks(N, p2, NULL, p3, 4032, 3024, 1e12, 1e-4, 1e-10, &r, inv) == DIMENET_E_ARGUMENT,
          "a NULL buffer is refused");
}

/* The PnP's unit: the power of two nearest the RMS norm; 1 for zero or non-finite points; bad arguments. */
/* Mode map's posterior by hand: the K block symmetrised; a correlation of 1 at r = 1/2 and s = s0 widens each
 * standard deviation by sqrt(1 + 2 (1/2) (1/2)) = sqrt(3/2); a bias b adds b_p b_q times the prior. */
static void test_map_posterior(void)
{
    double cov[100] = {0.0}, prior[16] = {0.0}, out[16], rho[4] = {0.0, 0.0, 0.0, 0.0}, bias[4] = {0.0, 0.0, 0.0, 0.0};
    int i;
    for (i = 0; i < 4; i++) {
        cov[10 * (6 + i) + 6 + i] = 2.0, prior[5 * i] = 4.0;
    }
    cov[10 * 6 + 7] = 1.0, cov[10 * 7 + 6] = 0.5; /* not symmetric: (1 + 0.5) / 2 */
    CHECK(dimenet_map_posterior(cov, prior, 2.0, rho, 2.0, bias, out) == DIMENET_OK && out[0] == 2.0
              && out[1] == 0.75 && out[4] == 0.75 && out[5] == 2.0,
          "no widening: the K block symmetrised");
    rho[0] = 1.0;
    CHECK(dimenet_map_posterior(cov, prior, 2.0, rho, 2.0, bias, out) == DIMENET_OK && near(out[0], 3.0, 1e-15)
              && near(out[1], 0.75 * sqrt(1.5), 1e-15) && out[5] == 2.0,
          "rho 1 at r = 1/2, s = s0: the variance times 3/2");
    rho[0] = 0.0, bias[2] = 0.5;
    CHECK(dimenet_map_posterior(cov, prior, 2.0, rho, 2.0, bias, out) == DIMENET_OK && out[10] == 3.0 && out[0] == 2.0,
          "a bias of 0.5 adds a quarter of the prior");
    CHECK(dimenet_map_posterior(NULL, prior, 2.0, rho, 2.0, bias, out) == DIMENET_E_ARGUMENT, "a NULL cov is refused");
}

/* The occupied cells of a grid by hand: a cell with one set channel counts, a NaN too, -0.0 does not. */
static void test_occupied_cells(void)
{
    const double grid[12] = {0.0, 0.0, 0.0, 2.5, -0.0, -0.0, 0.0, 0.0, NAN, 0.0, 0.0, -1.0};
    size_t occupied = 99;
    CHECK(dimenet_occupied_cells(6, 2, grid, &occupied) == DIMENET_OK && occupied == 3,
          "cells 1, 4 and 5 of six hold points");
    CHECK(dimenet_occupied_cells(0, 2, grid, &occupied) == DIMENET_OK && occupied == 0, "no cells, none occupied");
    CHECK(dimenet_occupied_cells(6, 0, grid, &occupied) == DIMENET_E_ARGUMENT, "no channel is refused");
    CHECK(dimenet_occupied_cells(6, 2, NULL, &occupied) == DIMENET_E_ARGUMENT, "a NULL grid is refused");
    CHECK(dimenet_occupied_cells((size_t)-1, 2, grid, &occupied) == DIMENET_E_ARGUMENT, "an overflowing size");
}

/* The network's covariance by hand: sigma_0 = exp(0.5 + log n) with one statistic (log n), the others exp of
 * their intercepts; the floors; a NaN statistic; bad columns and counts. */
static void test_network_covariance(void)
{
    const double correlation[16] = {1.0, 0.5, 0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0};
    const double coef[8] = {0.5, 1.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0};
    const unsigned char n_column[1] = {0}, pmd_column[1] = {2}, bad[1] = {4};
    double out[16];
    CHECK(dimenet_network_covariance(4.0, 3.0, 1.0, 0.1, 0.05, 1e-6, 1, n_column, coef, correlation, out) == DIMENET_OK
              && near(out[0], 16.0 * exp(1.0), 1e-14) && out[5] == 1.0 && near(out[1], 2.0 * exp(0.5), 1e-14)
              && near(out[10], exp(2.0), 1e-14) && near(out[15], exp(-2.0), 1e-15) && out[2] == 0.0,
          "sigma (4 exp(0.5), 1, e, 1 / e), correlation 0.5 between fx and fy");
    CHECK(dimenet_network_covariance(4.0, 3.0, 0.01, 0.1, 0.05, 1e-6, 1, pmd_column, coef, correlation, out)
                  == DIMENET_OK
              && near(out[0], 0.05 * 0.05 * exp(1.0), 1e-15),
          "a PMD below the floor reads as the floor");
    CHECK(dimenet_network_covariance(4.0, 3.0, NAN, 0.1, 0.05, 1e-6, 1, pmd_column, coef, correlation, out)
                  == DIMENET_OK
              && isnan(out[0]) && isnan(out[15]),
          "a NaN PMD stays NaN (Python's max), in every sigma (0 NaN is NaN)");
    CHECK(dimenet_network_covariance(4.0, 3.0, 1.0, 0.1, 0.05, 1e-6, 1, bad, coef, correlation, out)
              == DIMENET_E_ARGUMENT,
          "a column outside 0 to 3 is refused");
    CHECK(dimenet_network_covariance(0.0, 3.0, 1.0, 0.1, 0.05, 1e-6, 1, n_column, coef, correlation, out)
              == DIMENET_E_ARGUMENT,
          "no points are refused");
    CHECK(dimenet_network_covariance(4.0, 3.0, 1.0, 0.1, 0.05, 1e-6, 5, n_column, coef, correlation, out)
              == DIMENET_E_ARGUMENT,
          "more than four columns are refused");
    CHECK(dimenet_network_covariance(4.0, 3.0, 1.0, 0.1, 0.05, 1e-6, 1, n_column, NULL, correlation, out)
              == DIMENET_E_ARGUMENT,
          "a NULL coef is refused");
}

/* The stream's Kalman step by hand: a reset with equal variances gives the mean of the prior and the evidence, half
 * the variance; an innovation far beyond the limit resets first; evidence that is not positive definite leaves the
 * state carried; dt_s < 0 without a reset is refused. */
static void test_stream_step(void)
{
    const double eye[16] = {1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0};
    const double tau[4] = {30.0, 30.0, 0.6, 0.6}, k0[4] = {100.0, 100.0, 50.0, 40.0}, z[4] = {104.0, 98.0, 50.0, 46.0};
    double far[4] = {120.0, 120.0, 70.0, 60.0}, negative[16], k[4], P[16];
    int jumped = -1, updated = -1, i;
    for (i = 0; i < 16; i++) {
        negative[i] = -2.0 * eye[i];
    }
    CHECK(dimenet_stream_step(far, eye, k0, k0, z, eye, eye, tau, -1.0, 1, 30.0, k, P, &jumped, &updated) == DIMENET_OK
              && k[0] == 102.0 && k[1] == 99.0 && k[3] == 43.0 && P[0] == 0.5 && P[1] == 0.0 && !jumped && updated,
          "a reset: the mean of prior and evidence, half the variance");
    CHECK(dimenet_stream_step(far, eye, k0, k0, z, eye, eye, tau, 0.0, 0, 30.0, k, P, &jumped, &updated) == DIMENET_OK
              && jumped && updated && k[0] == 102.0 && P[5] == 0.5,
          "an innovation of 668 beyond 30: reset, then updated");
    CHECK(dimenet_stream_step(far, eye, k0, k0, z, negative, eye, tau, 0.0, 0, 30.0, k, P, &jumped, &updated)
                  == DIMENET_OK
              && !updated && !jumped && k[0] == 120.0 && P[0] == 1.0,
          "evidence that is not positive definite: the state carried");
    CHECK(dimenet_stream_step(far, eye, k0, k0, z, eye, eye, tau, -0.1, 0, 30.0, k, P, &jumped, &updated)
              == DIMENET_E_ARGUMENT,
          "dt_s < 0 without a reset is refused");
    CHECK(dimenet_stream_step(far, NULL, k0, k0, z, eye, eye, tau, 0.0, 0, 30.0, k, P, &jumped, &updated)
              == DIMENET_E_ARGUMENT,
          "a NULL P is refused");
}

static void test_power_of_two_unit(void)
{
    double p3[12] = {300.0, 0.0, 0.0, 0.0, 300.0, 0.0, 0.0, 0.0, 300.0, -300.0, 0.0, 0.0}, unit = 0.0;
    CHECK(dimenet_power_of_two_unit(12, p3, &unit) == DIMENET_OK && unit == 256.0, "RMS norm 300 mm: 256");
    p3[0] = 400.0, p3[4] = 400.0, p3[8] = 400.0, p3[9] = -400.0;
    CHECK(dimenet_power_of_two_unit(12, p3, &unit) == DIMENET_OK && unit == 512.0, "RMS norm 400 mm: 512");
    p3[5] = INFINITY;
    CHECK(dimenet_power_of_two_unit(12, p3, &unit) == DIMENET_OK && unit == 1.0, "an inf coordinate: 1");
    p3[5] = NAN;
    CHECK(dimenet_power_of_two_unit(12, p3, &unit) == DIMENET_OK && unit == 1.0, "a NaN coordinate: 1");
    CHECK(dimenet_power_of_two_unit(0, NULL, &unit) == DIMENET_OK && unit == 1.0, "no points: 1");
    CHECK(dimenet_power_of_two_unit(12, NULL, &unit) == DIMENET_E_ARGUMENT, "a NULL buffer is refused");
    CHECK(dimenet_power_of_two_unit(12, p3, NULL) == DIMENET_E_ARGUMENT, "a NULL result is refused");
}

int main(void)
{
    test_pose_steps();
    test_map_step();
    test_frame_checks();
    test_power_of_two_unit();
    test_occupied_cells();
    test_network_covariance();
    test_stream_step();
    test_map_posterior();
    test_sizes();
    test_exact_frame(0);
    test_exact_frame(1);
    test_hostile();
    test_other_specs();
    if (failures) {
        printf("%d check(s) failed\n", failures);
        return 1;
    }
    printf("core_driver: all checks passed\n");
    return 0;
}

/* A fuzz target for every entry point of dimenet_core.h (libFuzzer's LLVMFuzzerTestOneInput).
 *
 * The input bytes become a feature spec, a frame and a pose: the first bytes choose the grid, the
 * channels, the depth, the data step and moments, a mask, the flags and whether the numbers are raw
 * IEEE bit patterns (NaN, inf, subnormal, huge) or plausible values (pixels in the image, a scene in
 * front of the camera), so that both the argument checks and the deep paths (the Gram, the data step's
 * Cholesky) run. Every buffer is sized exactly, so AddressSanitizer sees any access past it; a result
 * that breaks the API's promises (an unknown code, more points used than given) aborts.
 *
 * With clang (libFuzzer):
 *   clang -std=c99 -g -O1 -fsanitize=fuzzer,address,undefined -I runtime/native \
 *       runtime/native/fuzz/fuzz_core.c runtime/native/dimenet_*.c -lm -o fuzz_core
 *   ./fuzz_core -max_total_time=60
 * With gcc only, replay.c drives it with pseudo-random inputs (tests/native/test_c_core.py). */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "dimenet_core.h"

typedef struct {
    const uint8_t *data;
    size_t size, at;
} bytes;

static unsigned take(bytes *b)
{
    return b->at < b->size ? b->data[b->at++] : 0u;
}

/* A double: raw bits (any IEEE value) or lo + (hi - lo) u for a 16-bit fraction u. */
static double number(bytes *b, int raw, double lo, double hi)
{
    if (raw) {
        uint64_t bits = 0;
        double x;
        int i;
        for (i = 0; i < 8; i++) {
            bits = bits << 8 | take(b);
        }
        memcpy(&x, &bits, sizeof x);
        return x;
    } else {
        unsigned high = take(b), u = high << 8 | take(b);
        return lo + (hi - lo) * (double)u / 65535.0;
    }
}

static void check(int ok)
{
    if (!ok) {
        abort();
    }
}

static int known(int code)
{
    return code >= DIMENET_OK && code <= DIMENET_E_PRIOR_COVARIANCE;
}

/* The paper's variants A to E (rectify/features.py VARIANTS), or (a first byte of 200 or more) any
 * channels, bad ones included. */
static const int VARIANTS[5][DIMENET_CHANNELS] = {{0, 1, 2, 3, 4}, {0, 1}, {0, 1, 4}, {0, 1, 2, 3}, {2, 3, 4}};
static const int VARIANT_SIZE[5] = {5, 2, 3, 4, 3};

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    bytes b;
    dimenet_feature_spec spec;
    dimenet_frame_stats stats;
    size_t n, i, D = 0, S = 0;
    unsigned mode, flags, variant;
    int raw, code, c, use_mask, behind;
    double *p2, *p3, *features, *rows, *scratch, rvec[3], tvec[3], jj[100], inverse[100], gram[121];
    unsigned char *mask;

    b.data = data, b.size = size, b.at = 0;
    mode = take(&b);
    raw = mode & 1u;
    use_mask = (mode >> 1) & 1u;
    flags = (mode >> 2) & 1u ? DIMENET_REFUSE_BEHIND_CAMERA : 0u;
    behind = (mode >> 3) & 1u;
    memset(&spec, 0, sizeof spec);
    spec.grid_cols = (int)(take(&b) % 17u); /* 0: a bad spec */
    spec.grid_rows = (int)(take(&b) % 13u);
    variant = take(&b);
    spec.n_channels = variant < 200u ? VARIANT_SIZE[variant % 5u] : (int)(take(&b) % 7u); /* 0 and 6: bad */
    for (c = 0; c < DIMENET_CHANNELS; c++) {
        spec.channels[c] = variant < 200u ? VARIANTS[variant % 5u][c] : (int)(take(&b) % 6u); /* 5: bad */
        spec.channel_scale[c] = number(&b, raw, 1e-3, 1e3);
    }
    spec.depth_mm = (mode >> 4) & 1u ? number(&b, raw, 0.0, 2000.0) : 0.0;
    spec.data_step = (int)((mode >> 5) & 1u);
    spec.moments = (int)((mode >> 6) & 1u);
    spec.pmd_scale_per_px = number(&b, raw, 0.01, 1.0);
    spec.image_width_px = number(&b, raw, 1.0, 8000.0);
    spec.image_height_px = number(&b, raw, 1.0, 6000.0);
    spec.K_c_px[0] = number(&b, raw, 100.0, 8000.0);
    spec.K_c_px[4] = number(&b, raw, 100.0, 8000.0);
    spec.K_c_px[2] = number(&b, raw, 0.0, 8000.0);
    spec.K_c_px[5] = number(&b, raw, 0.0, 6000.0);
    spec.K_c_px[8] = 1.0;
    for (i = 0; i < 3; i++) {
        rvec[i] = number(&b, raw, -3.2, 3.2);
        tvec[i] = number(&b, raw, -300.0, 300.0);
    }
    tvec[2] = behind ? -fabs(tvec[2]) : (raw ? tvec[2] : 400.0 + fabs(tvec[2]) * 2.0);
    n = take(&b) % 200u;
    if (n > (b.size - b.at) / 2) {
        n = (b.size - b.at) / 2;
    }

    /* the sizes: a bad spec must be refused by each of them alike */
    code = dimenet_feature_size(&spec, &D);
    check(code == DIMENET_OK || code == DIMENET_E_ARGUMENT);
    check(code == DIMENET_OK || dimenet_scratch_doubles(&spec, n, &S) == DIMENET_E_ARGUMENT);
    check(dimenet_error_message(code) != NULL && dimenet_error_message(-7) != NULL);
    if (code != DIMENET_OK || D > 100000 || dimenet_scratch_doubles(&spec, n, &S) != DIMENET_OK || S > 4000000) {
        check(dimenet_frame_features(&spec, 0, NULL, NULL, NULL, rvec, tvec, 0, jj, 1, NULL, inverse, 100, &stats)
              == DIMENET_E_ARGUMENT);
        return 0;
    }
    p2 = (double *)malloc(sizeof(double) * (2 * n + 1));
    p3 = (double *)malloc(sizeof(double) * (3 * n + 1));
    mask = (unsigned char *)malloc(n + 1);
    features = (double *)malloc(sizeof(double) * D);
    rows = (double *)malloc(sizeof(double) * (DIMENET_POINT_ROWS * n + 1));
    scratch = (double *)malloc(sizeof(double) * S);
    if (!p2 || !p3 || !mask || !features || !rows || !scratch) {
        free(p2), free(p3), free(mask), free(features), free(rows), free(scratch);
        return 0;
    }
    for (i = 0; i < n; i++) {
        unsigned k = take(&b);
        p2[2 * i] = number(&b, raw, -10.0, 8010.0);
        p2[2 * i + 1] = number(&b, raw, -10.0, 6010.0);
        p3[3 * i] = number(&b, raw, -300.0, 300.0);
        p3[3 * i + 1] = number(&b, raw, -300.0, 300.0);
        p3[3 * i + 2] = (k & 1u) ? 0.0 : number(&b, raw, -100.0, 100.0); /* planes and volumes */
        mask[i] = (unsigned char)((k >> 1) % 5u != 0u);
    }

    /* the frame kernel, with and without the point rows and the stats; the wrong sizes refused */
    memset(&stats, 0, sizeof stats);
    code = dimenet_frame_features(&spec, n, p2, p3, use_mask ? mask : NULL, rvec, tvec, flags, features, D, rows,
                                  scratch, S, &stats);
    check(known(code) && code != DIMENET_E_ARGUMENT);
    check(stats.n_used <= n && stats.n_behind <= stats.n_used);
    check(flags != 0u || code != DIMENET_E_BEHIND_CAMERA);
    code = dimenet_frame_features(&spec, n, p2, p3, use_mask ? mask : NULL, rvec, tvec, flags, features, D, NULL,
                                  scratch, S, NULL);
    check(known(code) && code != DIMENET_E_ARGUMENT);
    check(dimenet_frame_features(&spec, n, p2, p3, NULL, rvec, tvec, 0, features, D, NULL, scratch, S - 1, NULL)
          == DIMENET_E_ARGUMENT);
    check(dimenet_frame_features(&spec, n, p2, p3, NULL, rvec, tvec, 0, features, D + 1, NULL, scratch, S, NULL)
          == DIMENET_E_ARGUMENT);
    check(dimenet_frame_features(&spec, n, p2, p3, NULL, rvec, tvec, 8u, features, D, NULL, scratch, S, NULL)
          == DIMENET_E_ARGUMENT);

    /* the Gram of the point rows, and the Hessian inverse of a matrix made of the input */
    check(dimenet_monomial_gram(n, rows + 2 * n, rows + 3 * n, rows + 4 * n, rows, rows + n, gram) == DIMENET_OK);
    for (i = 0; i < 100; i++) {
        jj[i] = gram[(i * 7) % 121];
    }
    for (i = 0; i < 10; i++) {
        jj[i * 10 + i] = fabs(jj[i * 10 + i]);
    }
    code = dimenet_prior_posterior(jj, spec.pmd_scale_per_px, spec.channel_scale[0], inverse);
    check(known(code) && code != DIMENET_E_ARGUMENT && code != DIMENET_E_BEHIND_CAMERA);

    /* the pose under a K near K_c from the input's pose (scratch: 18 n >= the pose's 12 n), 0 to 3 steps;
     * a failed call leaves its outputs as they were, a bad argument is refused */
    {
        double k[4], r_out[3], t_out[3], before[6], e = -1.0, depth = -1.0;
        size_t P = 0;
        int steps = (int)(take(&b) % 4u);
        k[0] = spec.K_c_px[0] + number(&b, raw, -50.0, 50.0);
        k[1] = spec.K_c_px[4] + number(&b, raw, -50.0, 50.0);
        k[2] = spec.K_c_px[2] + number(&b, raw, -50.0, 50.0);
        k[3] = spec.K_c_px[5] + number(&b, raw, -50.0, 50.0);
        check(dimenet_pose_scratch_doubles(n, &P) == DIMENET_OK && P <= S);
        for (i = 0; i < 3; i++) {
            r_out[i] = before[i] = -1.0, t_out[i] = before[3 + i] = -2.0;
        }
        code = dimenet_pose_steps(n, p2, p3, k, rvec, tvec, steps, r_out, t_out, &e, &depth, scratch, P);
        check(code == DIMENET_OK || code == DIMENET_E_NO_POSE_STEP);
        for (i = 0; i < 3 && code != DIMENET_OK; i++) {
            check(r_out[i] == before[i] && t_out[i] == before[3 + i]);
        }
        for (i = 0; i < 3 && code == DIMENET_OK && steps > 0; i++) {
            check(isfinite(r_out[i]) && isfinite(t_out[i]));
        }
        check(code == DIMENET_OK || (e == -1.0 && depth == -1.0));
        check(code != DIMENET_OK || n == 0 || !(e < 0.0));
        check(dimenet_pose_steps(n, p2, p3, k, rvec, tvec, DIMENET_MAX_POSE_STEPS + 1, r_out, t_out, NULL, NULL, scratch, P)
              == DIMENET_E_ARGUMENT);
        check(n == 0 || dimenet_pose_steps(n, p2, p3, k, rvec, tvec, 1, r_out, t_out, NULL, NULL, scratch, P - 1)
                            == DIMENET_E_ARGUMENT);
        check(dimenet_pose_steps(n, p2, p3, NULL, rvec, tvec, 1, r_out, t_out, NULL, NULL, scratch, P) == DIMENET_E_ARGUMENT);
        code = dimenet_pose_steps(n, p2, p3, k, rvec, tvec, 0, r_out, t_out, &e, &depth, NULL, 0);
        check(code == DIMENET_OK); /* no step cannot fail */
    }
    /* mode map's step from a prior near K_c (a covariance made of the input, possibly not positive definite)
     * and the input's pose, turned or not, with a known or estimated noise; exact buffers; any values give a
     * known code, no points or a short scratch are refused */
    {
        double prior[4], prior_cov[16], turn[3], k_out[4], R[9], t_out[3], cov[100], weight = 0.0, noise;
        double e_out = 0.0, depth = 0.0;
        double *residuals = (double *)malloc(sizeof(double) * (2 * n + 1));
        size_t M = 0;
        int steps = -1;
        prior[0] = spec.K_c_px[0] + number(&b, raw, -50.0, 50.0);
        prior[1] = spec.K_c_px[4] + number(&b, raw, -50.0, 50.0);
        prior[2] = spec.K_c_px[2] + number(&b, raw, -50.0, 50.0);
        prior[3] = spec.K_c_px[5] + number(&b, raw, -50.0, 50.0);
        for (i = 0; i < 16; i++) {
            prior_cov[i] = i % 5 == 0 ? number(&b, raw, 0.0, 1e4) : number(&b, raw, -10.0, 10.0);
        }
        for (i = 0; i < 3; i++) {
            turn[i] = number(&b, raw, -0.01, 0.01);
        }
        noise = take(&b) % 2u ? -1.0 : number(&b, raw, 0.0, 3.0);
        check(residuals != NULL && dimenet_map_scratch_doubles(n, &M) == DIMENET_OK && M <= S);
        code = dimenet_map_step(n, p2, p3, prior, prior_cov, rvec, tvec, take(&b) % 2u ? turn : NULL, noise, 0.1,
                                k_out, R, t_out, cov, &weight, residuals, &e_out, &depth, &steps, scratch, M);
        check(n == 0 ? code == DIMENET_E_ARGUMENT
                     : (code == DIMENET_OK || code == DIMENET_E_PRIOR_COVARIANCE || code == DIMENET_E_HESSIAN_DIAGONAL
                        || code == DIMENET_E_NOT_POSITIVE_DEFINITE));
        check(code != DIMENET_OK || steps == 0 || steps == 1);
        check(n == 0 || dimenet_map_step(n, p2, p3, prior, prior_cov, rvec, tvec, NULL, -1.0, 0.1, k_out, R, t_out,
                                         cov, &weight, residuals, &e_out, &depth, &steps, scratch, M - 1)
                            == DIMENET_E_ARGUMENT);
        { /* its posterior from the step's cov (or, without a step, the input's values) for any widening */
            double k_cov[16], rho[4], bias[4];
            for (i = 0; i < 4; i++) {
                rho[i] = take(&b) % 2u ? number(&b, raw, 0.0, 1.0) : 0.0;
                bias[i] = take(&b) % 2u ? number(&b, raw, 0.0, 3.0) : 0.0;
            }
            if (code != DIMENET_OK) {
                for (i = 0; i < 100; i++) {
                    cov[i] = number(&b, raw, -1e3, 1e3);
                }
            }
            check(dimenet_map_posterior(cov, prior_cov, number(&b, raw, 0.0, 5.0), rho, number(&b, raw, 0.01, 5.0),
                                        bias, k_cov)
                  == DIMENET_OK);
        }
        free(residuals);
    }
    /* the input rules' fast tests: a verdict for any values, a refusal of no points */
    {
        unsigned verdict = 99u;
        double invariants[3];
        code = dimenet_frame_checks(n, p2, p2, p3, spec.image_width_px, spec.image_height_px, 1e12, 1e-4, 1e-10,
                                    &verdict, invariants);
        check(n == 0 ? code == DIMENET_E_ARGUMENT : (code == DIMENET_OK && verdict <= DIMENET_CHECK_NOT_SPREAD));
    }
    /* the PnP's unit: a power of two (1 for no or non-finite points) for any values */
    {
        double unit = 0.0;
        int exponent;
        check(dimenet_power_of_two_unit(3 * n, p3, &unit) == DIMENET_OK);
        check(frexp(unit, &exponent) == 0.5 && unit > 0.0 && isfinite(unit));
    }
    /* the occupied cells of the input's values read as a grid of 1 to 5 channels: at most every cell */
    {
        size_t channels = 1u + take(&b) % 5u, occupied = 0;
        check(dimenet_occupied_cells(3 * n / channels, channels, p3, &occupied) == DIMENET_OK
              && occupied <= 3 * n / channels);
        check(dimenet_occupied_cells(n, 0, p3, &occupied) == DIMENET_E_ARGUMENT);
    }
    /* the network's covariance for any statistics, floors and weights: a result, or a refusal of a bad count or
     * column, never a crash */
    {
        double coef[20], correlation[16], k_cov[16], stats[6];
        unsigned char columns[5];
        size_t n_columns = take(&b) % 6u;
        int refused = 0;
        for (i = 0; i < 20; i++) {
            coef[i] = number(&b, raw, -50.0, 50.0);
        }
        for (i = 0; i < 16; i++) {
            correlation[i] = number(&b, raw, -1.0, 1.0);
        }
        for (i = 0; i < 6; i++) {
            stats[i] = number(&b, raw, -10.0, 1e6);
        }
        for (i = 0; i < n_columns; i++) {
            columns[i] = (unsigned char)(take(&b) % 5u);
            refused |= columns[i] > 3;
        }
        refused |= n_columns > 4 || !(stats[0] >= 1.0) || !(stats[1] >= 1.0);
        code = dimenet_network_covariance(stats[0], stats[1], stats[2], stats[3], stats[4], stats[5], n_columns,
                                          columns, coef, correlation, k_cov);
        check(code == (refused ? DIMENET_E_ARGUMENT : DIMENET_OK));
    }
    /* the stream's Kalman step for any state and evidence: a result, or the refusal of dt_s < 0 without a reset */
    {
        double v[5][4], M[3][16], k_out[4], P_out[16], dt = number(&b, raw, -1.0, 10.0);
        int reset = (int)(take(&b) % 2u), jumped = 0, updated = 0;
        for (i = 0; i < 5; i++) {
            size_t j;
            for (j = 0; j < 4; j++) {
                v[i][j] = number(&b, raw, 1e-3, 5000.0);
            }
        }
        for (i = 0; i < 3; i++) {
            size_t j;
            for (j = 0; j < 16; j++) {
                M[i][j] = number(&b, raw, -100.0, 100.0);
            }
        }
        code = dimenet_stream_step(v[0], M[0], v[1], v[2], v[3], M[1], M[2], v[4], dt, reset,
                                   number(&b, raw, 0.0, 100.0), k_out, P_out, &jumped, &updated);
        check(code == (reset || dt >= 0.0 ? DIMENET_OK : DIMENET_E_ARGUMENT));
        check(code != DIMENET_OK || ((jumped == 0 || jumped == 1) && (updated == 0 || updated == 1)));
    }
    free(p2), free(p3), free(mask), free(features), free(rows), free(scratch);
    return 0;
}

/* The stream's Kalman filter step over k = (fx, fy, cx, cy) px: rectify.stream_filter.stream_step_reference to
 * the bit (every sum left to right, S = P + R by Cholesky of its lower triangle, libm's exp). */
#include "dimenet_core.h"

#include <math.h>

/* L (lower, row major) with L L^T = S from S's lower triangle, column by column; 0 unless every pivot is > 0. */
static int cholesky4(const double S[16], double L[16])
{
    int i, j, m;
    for (i = 0; i < 16; i++) {
        L[i] = 0.0;
    }
    for (j = 0; j < 4; j++) {
        double d = S[5 * j];
        for (m = 0; m < j; m++) {
            d = d - L[4 * j + m] * L[4 * j + m];
        }
        if (!(d > 0.0)) {
            return 0;
        }
        L[5 * j] = sqrt(d);
        for (i = j + 1; i < 4; i++) {
            double s = S[4 * i + j];
            for (m = 0; m < j; m++) {
                s = s - L[4 * i + m] * L[4 * j + m];
            }
            L[4 * i + j] = s / L[5 * j];
        }
    }
    return 1;
}

/* x with L L^T x = b: forward, then back substitution. */
static void solve4(const double L[16], const double b[4], double x[4])
{
    double y[4];
    int i, m;
    for (i = 0; i < 4; i++) {
        double s = b[i];
        for (m = 0; m < i; m++) {
            s = s - L[4 * i + m] * y[m];
        }
        y[i] = s / L[5 * i];
    }
    for (i = 3; i >= 0; i--) {
        double s = y[i];
        for (m = i + 1; m < 4; m++) {
            s = s - L[4 * m + i] * x[m];
        }
        x[i] = s / L[5 * i];
    }
}

static double dot4(const double x[4], const double y[4])
{
    double acc = x[0] * y[0];
    int m;
    for (m = 1; m < 4; m++) {
        acc = acc + x[m] * y[m];
    }
    return acc;
}

/* The state reset: k_prior and Q. */
static void reset_state(const double k_prior[4], const double Q[16], double k[4], double P[16])
{
    int i;
    for (i = 0; i < 4; i++) {
        k[i] = k_prior[i];
    }
    for (i = 0; i < 16; i++) {
        P[i] = Q[i];
    }
}

/* S = P + R, factored; the innovation z - k. */
static int factored(const double P[16], const double R[16], const double k[4], const double z[4], double L[16],
                    double innovation[4])
{
    double S[16];
    int i;
    for (i = 0; i < 16; i++) {
        S[i] = P[i] + R[i];
    }
    for (i = 0; i < 4; i++) {
        innovation[i] = z[i] - k[i];
    }
    return cholesky4(S, L);
}

int dimenet_stream_step(const double k[4], const double P[16], const double k_prior_last[4], const double k_prior[4],
                        const double z[4], const double R[16], const double Q[16], const double tau_s[4], double dt_s,
                        int reset, double chi2_limit, double k_out[4], double P_out[16], int *jumped, int *updated)
{
    double L[16], innovation[4], x[4], gain[16], column[4], row[4], P_new[16];
    int i, j, m;
    if (k == NULL || P == NULL || k_prior_last == NULL || k_prior == NULL || z == NULL || R == NULL || Q == NULL
        || tau_s == NULL || k_out == NULL || P_out == NULL || jumped == NULL || updated == NULL
        || !(reset || dt_s >= 0.0)) {
        return DIMENET_E_ARGUMENT;
    }
    *jumped = 0;
    *updated = 0;
    if (reset) {
        reset_state(k_prior, Q, k_out, P_out);
    } else { /* the AR(1) about the priors */
        double a[4];
        for (i = 0; i < 4; i++) {
            a[i] = exp(-dt_s / tau_s[i]);
            k_out[i] = k_prior[i] + a[i] * (k[i] - k_prior_last[i]);
        }
        for (i = 0; i < 4; i++) {
            for (j = 0; j < 4; j++) {
                double A = a[i] * a[j];
                P_out[4 * i + j] = A * P[4 * i + j] + (1.0 - A) * Q[4 * i + j];
            }
        }
    }
    if (!factored(P_out, R, k_out, z, L, innovation)) {
        return DIMENET_OK;
    }
    if (!reset) {
        solve4(L, innovation, x);
        if (dot4(innovation, x) > chi2_limit) { /* a jump: the state reset, then updated */
            *jumped = 1;
            reset_state(k_prior, Q, k_out, P_out);
            if (!factored(P_out, R, k_out, z, L, innovation)) {
                return DIMENET_OK;
            }
        }
    }
    for (i = 0; i < 4; i++) { /* the rows of P S^-1 (S symmetric) */
        solve4(L, P_out + 4 * i, gain + 4 * i);
    }
    for (i = 0; i < 4; i++) {
        k_out[i] = k_out[i] + dot4(gain + 4 * i, innovation);
    }
    for (i = 0; i < 4; i++) { /* (I - gain) P, then symmetrised */
        for (m = 0; m < 4; m++) {
            row[m] = (i == m ? 1.0 : 0.0) - gain[4 * i + m];
        }
        for (j = 0; j < 4; j++) {
            for (m = 0; m < 4; m++) {
                column[m] = P_out[4 * m + j];
            }
            P_new[4 * i + j] = dot4(row, column);
        }
    }
    for (i = 0; i < 4; i++) {
        for (j = 0; j < 4; j++) {
            P_out[4 * i + j] = (P_new[4 * i + j] + P_new[4 * j + i]) / 2.0;
        }
    }
    *updated = 1;
    return DIMENET_OK;
}

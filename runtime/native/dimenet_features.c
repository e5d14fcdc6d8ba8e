/* dimenet_features: the feature stage (rectify/features.py and rectify/encoders): the grid, the data
 * step and the moments of one frame at its C0 pose, and the sizes of their buffers.
 *
 * Each function names the numpy code it follows; the comments say where the operation order is the
 * reference's and where it cannot be (numpy's matrix products go through BLAS, whose summation order
 * and fused multiply-adds are its own: those sums are taken here in point order). */
#include "dimenet_internal.h"

#include <math.h>
#include <string.h>

/* The data step's constants (rectify/features.py): the prior's 1 sigma over fx_c, the clip of its
 * Delta K over fx_c, the noise floor of its data weight (px), the floor of a variance ratio. */
#define STEP_PRIOR_REL 0.1
#define STEP_CLIP_REL 0.05
#define STEP_NOISE_FLOOR_PX 0.1
#define STEP_VARIANCE_FLOOR 1e-30
/* Scratch doubles per point: the point rows (6), its depth (1), its monomials (11). */
#define SCRATCH_PER_POINT 18
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

int dimenet_occupied_cells(size_t n_cells, size_t n_channels, const double *grid, size_t *occupied)
{
    size_t cell, c, count = 0;
    if (grid == NULL || occupied == NULL || n_channels < 1 || n_cells > ((size_t)-1) / n_channels) {
        return DIMENET_E_ARGUMENT;
    }
    for (cell = 0; cell < n_cells; cell++) {
        for (c = 0; c < n_channels && grid[cell * n_channels + c] == 0.0; c++) {
        }
        count += c < n_channels;
    }
    *occupied = count;
    return DIMENET_OK;
}

int dimenet_network_covariance(double n_points, double occupied_cells, double mean_pmd_px, double thickness_3d,
                               double d_floor_px, double t_floor, size_t n_columns, const unsigned char *columns,
                               const double *coef, const double correlation[16], double k_cov_px2[16])
{
    double z[4], sigma[4];
    size_t p, q, j;
    if (columns == NULL || coef == NULL || correlation == NULL || k_cov_px2 == NULL || n_columns > 4
        || !(n_points >= 1.0) || !(occupied_cells >= 1.0)) {
        return DIMENET_E_ARGUMENT;
    }
    for (j = 0; j < n_columns; j++) {
        if (columns[j] > 3) {
            return DIMENET_E_ARGUMENT;
        }
    }
    z[0] = log(n_points);
    z[1] = log(occupied_cells);
    z[2] = log(d_floor_px > mean_pmd_px ? d_floor_px : mean_pmd_px);
    z[3] = log(t_floor > thickness_3d ? t_floor : thickness_3d);
    for (p = 0; p < 4; p++) {
        const double *row = coef + p * (1 + n_columns);
        double acc = row[0];
        for (j = 0; j < n_columns; j++) {
            acc = acc + row[1 + j] * z[columns[j]];
        }
        sigma[p] = exp(acc);
    }
    for (p = 0; p < 4; p++) {
        for (q = 0; q < 4; q++) {
            k_cov_px2[4 * p + q] = (sigma[p] * sigma[q]) * correlation[4 * p + q];
        }
    }
    return DIMENET_OK;
}

/* -- numpy's sums ----------------------------------------------------------------------------- */

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
        res += dimenet__pairwise_sum(a + i, j - i);
        i = j;
    }
    return res;
}

/* rectify.features.gram_inputs' data step for one frame: geometry.prior_step, then _step_inputs. */
static int data_step(const double *G, size_t n, double fx_c, double fy_c, double pmd_scale, double out[8])
{
    double prior_var = dimenet__python_square(STEP_PRIOR_REL * fx_c);
    double clip_px = STEP_CLIP_REL * fx_c, precision[16] = {0.0};
    double JJ[100], Jr[10], rss, inv[100], step[10], weight;
    int code, k;
    for (k = 0; k < 4; k++) { /* np.eye(4) / prior_var */
        precision[5 * k] = 1.0 / prior_var;
    }
    dimenet__gram_normal_equations(G, fx_c, fy_c, JJ, Jr, &rss);
    code = dimenet__prior_step(JJ, Jr, rss, (long)(2 * n), precision, STEP_NOISE_FLOOR_PX, step, inv, &weight);
    if (code != DIMENET_OK) {
        return code;
    }
    for (k = 0; k < 4; k++) { /* _step_inputs: the clipped Delta K times the PMD's scale (Python's min, max) */
        double d = step[6 + k];
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
    dimenet__rodrigues(rvec_w_to_c0_rad, R);
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
            dimenet__monomials(rows[2 * N + i], rows[3 * N + i], inv_z, du, dv, lanes + n_used, N);
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
            sums[k] = mask == NULL ? dimenet__pairwise_sum(row, N) : masked_sum(row, mask, N);
        }
        counts[0] = (double)n_used;
    }

    /* the cell means times the channels' scales (with depth_mm: times depth factor ^ exponent) */
    if (spec->depth_mm > 0.0) {
        double z_sum = dimenet__pairwise_sum(depths, N); /* the unused points' depths are 0 (np.where) */
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
        dimenet__gram_points p;
        memset(&p, 0, sizeof p);
        p.lanes = lanes, p.stride = N;
        dimenet__gram_of(&p, n_used, G);
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

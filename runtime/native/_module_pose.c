/* dimenet.runtime.native._core, the pose and checks half of the binding (_module.c has the module and the
 * feature stage): pose_steps (dimenet_pose_steps), frame_checks (dimenet_frame_checks), power_of_two_unit
 * (dimenet_power_of_two_unit), occupied_cells (dimenet_occupied_cells), network_covariance
 * (dimenet_network_covariance), stream_step (dimenet_stream_step), map_step (dimenet_map_step) and map_posterior
 * (dimenet_map_posterior), under the same rules as _module.c's (buffers checked, the GIL released in the kernels
 * that loop over points, no static mutable state). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "_binding.h"

PyDoc_STRVAR(pose_steps_doc,
             "pose_steps(points_2d, points_3d, K, rvec, tvec, steps, rvec_out, tvec_out)\n--\n\n"
             "The pose under the pinhole K (3, 3) px (no skew) after ``steps`` Gauss-Newton steps from the pose "
             "rvec, tvec (3,) into rvec_out, tvec_out (3,) float64, the GIL released; returns (e px, smallest depth "
             "mm) at that pose (geometry.pose_step.pose_under_k to the bit): points_2d (N, 2) px, points_3d (N, 3) "
             "mm in {W}. With no outputs (rvec_out and tvec_out None) and steps 0: geometry.frame_error_and_depth. "
             "InputError when a step has no solution or the pose is not finite; TypeError or ValueError for "
             "arrays of the wrong type or shape, or a K with skew.");

static PyObject *pose_steps(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *const names[] = {"points_2d", "points_3d", "K", "rvec", "tvec", "rvec_out", "tvec_out"};
    static const char ndims[7] = {2, 2, 2, 1, 1, 1, 1};
    Py_buffer views[7];
    int n_views = 0, code = DIMENET_OK, i, outputs;
    long steps;
    Py_ssize_t N;
    size_t n_scratch = 0;
    double e = 0.0, depth = 0.0, k[4], r_out[3], t_out[3];
    const double *K;
    double *scratch = NULL;
    PyObject *result = NULL;

    if (nargs != 8) {
        PyErr_Format(PyExc_TypeError, "pose_steps takes 8 arguments, got %zd", nargs);
        return NULL;
    }
    steps = PyLong_AsLong(args[5]);
    if (steps == -1 && PyErr_Occurred()) {
        return NULL;
    }
    outputs = !(args[6] == Py_None && args[7] == Py_None);
    if (steps < 0 || steps > DIMENET_MAX_POSE_STEPS || (!outputs && steps != 0)) {
        PyErr_Format(PyExc_ValueError, "pose_steps: steps must be 0 to %d (0 without outputs), got %ld",
                     DIMENET_MAX_POSE_STEPS, steps);
        return NULL;
    }
    for (i = 0; i < (outputs ? 7 : 5); i++) {
        Py_ssize_t any[2] = {-1, -1};
        if (dimenet_py_get_view(args[i < 5 ? i : i + 1], &views[i], names[i], 'd', ndims[i], any, i >= 5) != 0) {
            goto done;
        }
        n_views++;
    }
    N = views[0].shape[0];
    if (views[0].shape[1] != 2 || views[1].shape[0] != N || views[1].shape[1] != 3 || views[2].shape[0] != 3
        || views[2].shape[1] != 3 || views[3].shape[0] != 3 || views[4].shape[0] != 3
        || (outputs && (views[5].shape[0] != 3 || views[6].shape[0] != 3))) {
        PyErr_SetString(PyExc_ValueError, "pose_steps: points_2d (N, 2), points_3d (N, 3), K (3, 3), rvec, tvec, "
                                          "rvec_out and tvec_out (3,) expected");
        goto done;
    }
    K = (const double *)views[2].buf;
    if (K[1] != 0.0) {
        PyErr_SetString(PyExc_ValueError, "pose_steps: K must have no skew (K[0, 1] == 0)");
        goto done;
    }
    k[0] = K[0], k[1] = K[4], k[2] = K[2], k[3] = K[5];
    if (dimenet_pose_scratch_doubles((size_t)N, &n_scratch) != DIMENET_OK) {
        PyErr_NoMemory();
        goto done;
    }
    if (steps > 0) {
        scratch = (double *)PyMem_RawMalloc(n_scratch * sizeof(double) + 1);
        if (scratch == NULL) {
            PyErr_NoMemory();
            goto done;
        }
    } else {
        n_scratch = 0; /* no step reads it */
    }
    Py_BEGIN_ALLOW_THREADS
    code = dimenet_pose_steps((size_t)N, (const double *)views[0].buf, (const double *)views[1].buf, k,
                              (const double *)views[3].buf, (const double *)views[4].buf, (int)steps,
                              outputs ? (double *)views[5].buf : r_out, outputs ? (double *)views[6].buf : t_out, &e,
                              &depth, scratch, n_scratch);
    Py_END_ALLOW_THREADS
    if (code != DIMENET_OK) {
        PyErr_SetString(code == DIMENET_E_NO_POSE_STEP ? dimenet_py_state_of(module)->input_error : PyExc_ValueError,
                        dimenet_error_message(code));
        goto done;
    }
    result = Py_BuildValue("(dd)", e, depth);
done:
    PyMem_RawFree(scratch);
    dimenet_py_release_views(views, n_views);
    return result;
}

PyDoc_STRVAR(frame_checks_doc,
             "frame_checks(points_2d_image, points_2d, points_3d, width_px, height_px, max_coordinate, spread_ratio, "
             "spread_absolute)\n--\n\n"
             "The input rules' fast tests on one frame (dimenet_frame_checks), the GIL released: points_2d_image "
             "and points_2d (N, 2) px (as given; in the model's pixels), points_3d (N, 3) mm, N >= 1. Returns (the "
             "verdict: 0, or 1 (a point not finite or outside the image or the coordinate range), or 2 (not clearly "
             "spread); the 3D points' geometry.covariance_invariants to the bit, NaN with the verdict 1).");

static PyObject *frame_checks(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const int ARRAY_ARGS[3] = {0, 1, 2};
    static const char *const names[3] = {"points_2d_image", "points_2d", "points_3d"};
    static const Py_ssize_t shapes[3][2] = {{-1, -1}, {-1, -1}, {-1, -1}};
    static const char ndims[3] = {2, 2, 2};
    Py_buffer views[3];
    int code, i;
    double numbers[5], invariants[3];
    unsigned flags = 0u;
    PyObject *result = NULL;
    (void)module;
    if (nargs != 8) {
        PyErr_Format(PyExc_TypeError, "frame_checks takes 8 arguments, got %zd", nargs);
        return NULL;
    }
    for (i = 0; i < 5; i++) {
        numbers[i] = PyFloat_AsDouble(args[3 + i]);
        if (numbers[i] == -1.0 && PyErr_Occurred()) {
            return NULL;
        }
    }
    if (dimenet_py_get_views(args, ARRAY_ARGS, names, ndims, shapes, 3, 3, views) != 0) {
        return NULL;
    }
    if (views[0].shape[1] != 2 || views[1].shape[1] != 2 || views[2].shape[1] != 3 || views[0].shape[0] < 1
        || views[1].shape[0] != views[0].shape[0] || views[2].shape[0] != views[0].shape[0]) {
        PyErr_SetString(PyExc_ValueError, "frame_checks: points_2d_image and points_2d (N, 2), points_3d (N, 3), "
                                          "N >= 1 expected");
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    code = dimenet_frame_checks((size_t)views[0].shape[0], (const double *)views[0].buf,
                                (const double *)views[1].buf, (const double *)views[2].buf, numbers[0], numbers[1],
                                numbers[2], numbers[3], numbers[4], &flags, invariants);
    Py_END_ALLOW_THREADS
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, dimenet_error_message(code));
        goto done;
    }
    result = Py_BuildValue("(k(ddd))", (unsigned long)flags, invariants[0], invariants[1], invariants[2]);
done:
    dimenet_py_release_views(views, 3);
    return result;
}

PyDoc_STRVAR(power_of_two_unit_doc,
             "power_of_two_unit(points_3d)\n--\n\n"
             "geometry.pnp.power_of_two_unit to the bit (dimenet_power_of_two_unit), the GIL released: the power of "
             "two nearest the RMS norm of points_3d (N, 3) float64 mm, C contiguous; 1.0 when that is 0 or not "
             "finite.");

static PyObject *power_of_two_unit(PyObject *module, PyObject *points_3d)
{
    static const Py_ssize_t rows_of_three[2] = {-1, 3};
    Py_buffer view;
    double unit = 1.0;
    int code;
    (void)module;
    if (dimenet_py_get_view(points_3d, &view, "points_3d", 'd', 2, rows_of_three, 0) != 0) {
        return NULL;
    }
    Py_BEGIN_ALLOW_THREADS
    code = dimenet_power_of_two_unit((size_t)view.shape[0] * 3u, (const double *)view.buf, &unit);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&view);
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, dimenet_error_message(code));
        return NULL;
    }
    return PyFloat_FromDouble(unit);
}

PyDoc_STRVAR(occupied_cells_doc,
             "occupied_cells(grid, n_channels)\n--\n\n"
             "rectify.uncertainty.occupied_cells of one frame (dimenet_occupied_cells): the cells of grid (cells x "
             "n_channels,) float64, C contiguous, with a channel that is not 0.");

static PyObject *occupied_cells(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const Py_ssize_t any[1] = {-1};
    Py_buffer view;
    Py_ssize_t n_channels;
    size_t occupied = 0;
    int code = DIMENET_E_ARGUMENT;
    (void)module;
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "occupied_cells takes 2 arguments, got %zd", nargs);
        return NULL;
    }
    n_channels = PyLong_AsSsize_t(args[1]);
    if (n_channels == -1 && PyErr_Occurred()) {
        return NULL;
    }
    if (dimenet_py_get_view(args[0], &view, "grid", 'd', 1, any, 0) != 0) {
        return NULL;
    }
    if (n_channels >= 1 && view.shape[0] % n_channels == 0) {
        Py_BEGIN_ALLOW_THREADS
        code = dimenet_occupied_cells((size_t)(view.shape[0] / n_channels), (size_t)n_channels,
                                      (const double *)view.buf, &occupied);
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&view);
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, "occupied_cells: n_channels >= 1 dividing the grid's length expected");
        return NULL;
    }
    return PyLong_FromSize_t(occupied);
}

PyDoc_STRVAR(network_covariance_doc,
             "network_covariance(n_points, occupied_cells, mean_pmd_px, thickness_3d, d_floor_px, t_floor, columns, "
             "coef, correlation, k_cov_out)\n--\n\n"
             "The network's covariance of Delta K of one frame (dimenet_network_covariance; "
             "Uncertainty.frame_covariance to the bit) into k_cov_out (4, 4) px^2 from the frame's four statistics "
             "(numbers), their floors, columns (bytes: the statistics coef weighs, 0 to 3), coef (4, 1 + "
             "len(columns)) and correlation (4, 4), all float64 C contiguous. ValueError for a count below 1 or a "
             "column outside 0 to 3.");

static PyObject *network_covariance(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const int ARRAY_ARGS[3] = {7, 8, 9};
    static const char *const names[3] = {"coef", "correlation", "k_cov_out"};
    static const Py_ssize_t shapes[3][2] = {{4, -1}, {4, 4}, {4, 4}};
    static const char ndims[3] = {2, 2, 2};
    Py_buffer views[3];
    int code = DIMENET_OK, i;
    double numbers[6];
    char *columns;
    Py_ssize_t n_columns;
    PyObject *result = NULL;
    (void)module;
    if (nargs != 10) {
        PyErr_Format(PyExc_TypeError, "network_covariance takes 10 arguments, got %zd", nargs);
        return NULL;
    }
    for (i = 0; i < 6; i++) {
        numbers[i] = PyFloat_AsDouble(args[i]);
    }
    if (PyErr_Occurred() || PyBytes_AsStringAndSize(args[6], &columns, &n_columns) != 0) {
        return NULL;
    }
    if (dimenet_py_get_views(args, ARRAY_ARGS, names, ndims, shapes, 3, 2, views) != 0) {
        return NULL;
    }
    if (views[0].shape[1] != 1 + n_columns) {
        PyErr_SetString(PyExc_ValueError, "network_covariance: coef must be (4, 1 + len(columns))");
        goto done;
    }
    code = dimenet_network_covariance(numbers[0], numbers[1], numbers[2], numbers[3], numbers[4], numbers[5],
                                      (size_t)n_columns, (const unsigned char *)columns,
                                      (const double *)views[0].buf, (const double *)views[1].buf,
                                      (double *)views[2].buf);
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, "network_covariance: counts >= 1 and at most four columns, each 0 to 3, "
                                          "expected");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    dimenet_py_release_views(views, 3);
    return result;
}

PyDoc_STRVAR(stream_step_doc,
             "stream_step(k, P, k_prior_last, k_prior, z, R, Q, tau_s, dt_s, reset, chi2_limit, k_out, P_out)\n--\n\n"
             "One frame of the stream's Kalman filter (dimenet_stream_step; rectify.stream_filter's reference to the "
             "bit) into k_out (4,) px and P_out (4, 4) px^2: k, k_prior_last, k_prior, z, tau_s (4,) and P, R, Q (4, "
             "4), all float64 C contiguous; returns (jumped, updated). ValueError for dt_s < 0 unless reset.");

static PyObject *stream_step(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const int ARRAY_ARGS[10] = {0, 1, 2, 3, 4, 5, 6, 7, 11, 12};
    static const char *const names[10] = {"k", "P", "k_prior_last", "k_prior", "z", "R", "Q", "tau_s", "k_out", "P_out"};
    static const Py_ssize_t shapes[10][2] = {{4, -1}, {4, 4}, {4, -1}, {4, -1}, {4, -1},
                                             {4, 4},  {4, 4}, {4, -1}, {4, -1}, {4, 4}};
    static const char ndims[10] = {1, 2, 1, 1, 1, 2, 2, 1, 1, 2};
    Py_buffer views[10];
    const double *b[10];
    int code = DIMENET_OK, i, reset, jumped = 0, updated = 0;
    double dt_s, chi2_limit;
    PyObject *result = NULL;
    (void)module;
    if (nargs != 13) {
        PyErr_Format(PyExc_TypeError, "stream_step takes 13 arguments, got %zd", nargs);
        return NULL;
    }
    dt_s = PyFloat_AsDouble(args[8]);
    chi2_limit = PyFloat_AsDouble(args[10]);
    if (PyErr_Occurred()) {
        return NULL;
    }
    reset = PyObject_IsTrue(args[9]);
    if (reset < 0) {
        return NULL;
    }
    if (dimenet_py_get_views(args, ARRAY_ARGS, names, ndims, shapes, 10, 8, views) != 0) {
        return NULL;
    }
    for (i = 0; i < 10; i++) {
        b[i] = (const double *)views[i].buf;
    }
    code = dimenet_stream_step(b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], dt_s, reset, chi2_limit,
                               (double *)views[8].buf, (double *)views[9].buf, &jumped, &updated);
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, "stream_step: dt_s >= 0 unless reset expected");
        goto done;
    }
    result = Py_BuildValue("(OO)", jumped ? Py_True : Py_False, updated ? Py_True : Py_False);
done:
    dimenet_py_release_views(views, 10);
    return result;
}

PyDoc_STRVAR(map_posterior_doc,
             "map_posterior(cov, k_cov_prior, noise_px, data_correlation, noise_scale_px, data_bias, k_cov_out)\n--\n\n"
             "Mode map's posterior of K (dimenet_map_posterior; map_fit's K_cov to the bit): the K block of cov (10, "
             "10) symmetrised, widened by the uncertainty model's data_correlation (4,), noise_scale_px and "
             "data_bias (4,) against the network's k_cov_prior (4, 4) px^2 at the frame's 2D noise noise_px, into "
             "k_cov_out (4, 4), all float64 C contiguous.");

static PyObject *map_posterior(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const int ARRAY_ARGS[5] = {0, 1, 3, 5, 6};
    static const char *const names[5] = {"cov", "k_cov_prior", "data_correlation", "data_bias", "k_cov_out"};
    static const Py_ssize_t shapes[5][2] = {{10, 10}, {4, 4}, {4, -1}, {4, -1}, {4, 4}};
    static const char ndims[5] = {2, 2, 1, 1, 2};
    Py_buffer views[5];
    int code = DIMENET_OK;
    double noise_px, noise_scale_px;
    PyObject *result = NULL;
    (void)module;
    if (nargs != 7) {
        PyErr_Format(PyExc_TypeError, "map_posterior takes 7 arguments, got %zd", nargs);
        return NULL;
    }
    noise_px = PyFloat_AsDouble(args[2]);
    noise_scale_px = PyFloat_AsDouble(args[4]);
    if (PyErr_Occurred()) {
        return NULL;
    }
    if (dimenet_py_get_views(args, ARRAY_ARGS, names, ndims, shapes, 5, 4, views) != 0) {
        return NULL;
    }
    code = dimenet_map_posterior((const double *)views[0].buf, (const double *)views[1].buf, noise_px,
                                 (const double *)views[2].buf, noise_scale_px, (const double *)views[3].buf,
                                 (double *)views[4].buf);
    if (code != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, dimenet_error_message(code));
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    dimenet_py_release_views(views, 5);
    return result;
}

PyDoc_STRVAR(map_step_doc,
             "map_step(points_2d, points_3d, k_prior, k_cov_prior, rvec, tvec, turn, noise_px, noise_floor_px, k_out, "
             "R_out, tvec_out, cov_out, residuals_out)\n--\n\n"
             "Mode map's Gauss-Newton step (dimenet_map_step; geometry.map_step.map_steps with one step, to the bit), "
             "the GIL released: points_2d (N, 2) px, points_3d (N, 3) mm in {W}, N >= 1; k_prior (4,) px and "
             "k_cov_prior (4, 4) px^2 the prior on K; rvec, tvec (3,) the start pose, turned first by turn (3,) rad "
             "(None: not turned); noise_px the 2D noise std (< 0: the frame's estimate), floored at noise_floor_px. "
             "Writes k_out (4,), R_out (3, 3), tvec_out (3,), cov_out (10, 10) and residuals_out (N, 2), all "
             "float64; returns (weight 1 / s^2 px^-2, e px the residuals' mean norm and the smallest depth mm at the "
             "result, steps 0 or 1). InputError when the prior's covariance is not positive definite or the points "
             "fix no pose; TypeError or ValueError for arrays of the wrong type or shape.");

static PyObject *map_step(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    /* the arrays, in argument order; turn (6) may be None; 7 and 8 are the two floats */
    static const int ARRAY_ARGS[12] = {0, 1, 2, 3, 4, 5, 6, 9, 10, 11, 12, 13};
    static const char *const names[12] = {"points_2d", "points_3d", "k_prior", "k_cov_prior", "rvec", "tvec",
                                          "turn",      "k_out",     "R_out",   "tvec_out",  "cov_out", "residuals_out"};
    static const char ndims[12] = {2, 2, 1, 2, 1, 1, 1, 1, 2, 1, 2, 2};
    Py_buffer views[12];
    int held[12] = {0}, code = DIMENET_OK, i, steps = 0;
    double noise_px, noise_floor_px, weight = 0.0, e = 0.0, depth = 0.0, *scratch = NULL;
    size_t n_scratch = 0;
    Py_ssize_t N;
    PyObject *result = NULL;

    if (nargs != 14) {
        PyErr_Format(PyExc_TypeError, "map_step takes 14 arguments, got %zd", nargs);
        return NULL;
    }
    noise_px = PyFloat_AsDouble(args[7]);
    noise_floor_px = PyFloat_AsDouble(args[8]);
    if (PyErr_Occurred()) {
        return NULL;
    }
    for (i = 0; i < 12; i++) {
        Py_ssize_t any[2] = {-1, -1};
        if (i == 6 && args[6] == Py_None) {
            continue;
        }
        if (dimenet_py_get_view(args[ARRAY_ARGS[i]], &views[i], names[i], 'd', ndims[i], any, i >= 7) != 0) {
            goto done;
        }
        held[i] = 1;
    }
    N = views[0].shape[0];
    if (N < 1 || views[0].shape[1] != 2 || views[1].shape[0] != N || views[1].shape[1] != 3
        || views[2].shape[0] != 4 || views[3].shape[0] != 4 || views[3].shape[1] != 4 || views[4].shape[0] != 3
        || views[5].shape[0] != 3 || (held[6] && views[6].shape[0] != 3) || views[7].shape[0] != 4
        || views[8].shape[0] != 3 || views[8].shape[1] != 3 || views[9].shape[0] != 3 || views[10].shape[0] != 10
        || views[10].shape[1] != 10 || views[11].shape[0] != N || views[11].shape[1] != 2) {
        PyErr_SetString(PyExc_ValueError, "map_step: points_2d (N, 2) with N >= 1, points_3d (N, 3), k_prior (4,), "
                                          "k_cov_prior (4, 4), rvec, tvec, turn (3,), k_out (4,), R_out (3, 3), "
                                          "tvec_out (3,), cov_out (10, 10) and residuals_out (N, 2) expected");
        goto done;
    }
    if (dimenet_map_scratch_doubles((size_t)N, &n_scratch) != DIMENET_OK
        || (scratch = (double *)PyMem_RawMalloc(n_scratch * sizeof(double))) == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    code = dimenet_map_step((size_t)N, (const double *)views[0].buf, (const double *)views[1].buf,
                            (const double *)views[2].buf, (const double *)views[3].buf, (const double *)views[4].buf,
                            (const double *)views[5].buf, held[6] ? (const double *)views[6].buf : NULL, noise_px,
                            noise_floor_px, (double *)views[7].buf, (double *)views[8].buf, (double *)views[9].buf,
                            (double *)views[10].buf, &weight, (double *)views[11].buf, &e, &depth, &steps, scratch,
                            n_scratch);
    Py_END_ALLOW_THREADS
    if (code != DIMENET_OK) {
        PyErr_SetString(code == DIMENET_E_ARGUMENT ? PyExc_ValueError : dimenet_py_state_of(module)->input_error,
                        dimenet_error_message(code));
        goto done;
    }
    result = Py_BuildValue("(dddi)", weight, e, depth, steps);
done:
    PyMem_RawFree(scratch);
    for (i = 11; i >= 0; i--) {
        if (held[i]) {
            PyBuffer_Release(&views[i]);
        }
    }
    return result;
}

PyMethodDef dimenet_py_pose_methods[] = {
    {"map_step", (PyCFunction)(void (*)(void))map_step, METH_FASTCALL, map_step_doc},
    {"map_posterior", (PyCFunction)(void (*)(void))map_posterior, METH_FASTCALL, map_posterior_doc},
    {"pose_steps", (PyCFunction)(void (*)(void))pose_steps, METH_FASTCALL, pose_steps_doc},
    {"frame_checks", (PyCFunction)(void (*)(void))frame_checks, METH_FASTCALL, frame_checks_doc},
    {"power_of_two_unit", (PyCFunction)power_of_two_unit, METH_O, power_of_two_unit_doc},
    {"occupied_cells", (PyCFunction)(void (*)(void))occupied_cells, METH_FASTCALL, occupied_cells_doc},
    {"network_covariance", (PyCFunction)(void (*)(void))network_covariance, METH_FASTCALL, network_covariance_doc},
    {"stream_step", (PyCFunction)(void (*)(void))stream_step, METH_FASTCALL, stream_step_doc},
    {NULL, NULL, 0, NULL},
};

/* dimenet.runtime.native._core: the thin CPython binding of dimenet_core (dimenet_core.h).
 *
 * No numpy headers: arrays come in through the buffer protocol, each checked for its type (float64
 * 'd' or bool '?'), shape and C contiguity; the caller (rectify/features.py) allocates the outputs.
 * The kernel runs with the GIL released; its error codes become the InputError messages of the numpy
 * reference (dimenet.runtime.errors). No static mutable state: the InputError class is held in the
 * module's state, every call has its own scratch, so threads may call at once. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <string.h>

#include "_binding.h"

/* The packed FeatureSpec (features.py FeatureSpec._native): grid cols, rows, channel count, the five
 * channel indices, the five scales, depth_mm (0: none), data_step, moments, the PMD's scale. */
#define LAYOUT_SIZE 17

dimenet_py_state *dimenet_py_state_of(PyObject *module)
{
    return (dimenet_py_state *)PyModule_GetState(module);
}

static void raise_frame_error(PyObject *module, int code, const dimenet_frame_stats *st, Py_ssize_t n_points);

void dimenet_py_release_views(Py_buffer *views, int n_views)
{
    while (n_views > 0) {
        PyBuffer_Release(&views[--n_views]);
    }
}

int dimenet_py_get_views(PyObject *const *args, const int *arg_index, const char *const *names, const char *ndims,
                         const Py_ssize_t (*shapes)[2], int n, int first_writable, Py_buffer *views)
{
    int i;
    for (i = 0; i < n; i++) {
        if (dimenet_py_get_view(args[arg_index[i]], &views[i], names[i], 'd', ndims[i], shapes[i], i >= first_writable)
            != 0) {
            dimenet_py_release_views(views, i);
            return -1;
        }
    }
    return 0;
}

int dimenet_py_get_view(PyObject *obj, Py_buffer *view, const char *name, char kind, int ndim,
                        const Py_ssize_t *shape, int writable)
{
    const char *fmt;
    int i;
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0) {
        PyErr_Format(PyExc_TypeError, "%s must be a C-contiguous%s array", name, writable ? " writable" : "");
        return -1;
    }
    fmt = view->format == NULL ? "B" : view->format;
    if (fmt[0] == '@' || fmt[0] == '=' || (fmt[0] == '<' && kind == '?')) {
        fmt++;
    }
#if PY_BIG_ENDIAN
    if (fmt[0] == '>') {
        fmt++;
    }
#else
    if (fmt[0] == '<') {
        fmt++;
    }
#endif
    if (fmt[0] != kind || fmt[1] != '\0' || view->ndim != ndim) {
        PyErr_Format(PyExc_TypeError, "%s must be a %d-d %s array, got format '%s' with %d dimension(s)", name, ndim,
                     kind == 'd' ? "float64" : "bool", view->format == NULL ? "B" : view->format, view->ndim);
        PyBuffer_Release(view);
        return -1;
    }
    for (i = 0; i < ndim; i++) {
        if (shape[i] >= 0 && view->shape[i] != shape[i]) {
            PyErr_Format(PyExc_ValueError, "%s: dimension %d is %zd, expected %zd", name, i, view->shape[i], shape[i]);
            PyBuffer_Release(view);
            return -1;
        }
    }
    return 0;
}

static int spec_from_layout(const double *layout, const double *K_c, double width_px, double height_px,
                            dimenet_feature_spec *spec)
{
    int c;
    for (c = 0; c < LAYOUT_SIZE; c++) {
        if (!(layout[c] - layout[c] == 0.0)) {
            return -1;
        }
    }
    if (layout[0] < 1 || layout[0] > 2147483647.0 || layout[1] < 1 || layout[1] > 2147483647.0 || layout[2] < 1
        || layout[2] > DIMENET_CHANNELS) {
        return -1;
    }
    memset(spec, 0, sizeof *spec);
    spec->grid_cols = (int)layout[0];
    spec->grid_rows = (int)layout[1];
    spec->n_channels = (int)layout[2];
    for (c = 0; c < DIMENET_CHANNELS; c++) {
        if (layout[3 + c] < 0 || layout[3 + c] >= DIMENET_CHANNELS) {
            return -1;
        }
        spec->channels[c] = (int)layout[3 + c];
        spec->channel_scale[c] = layout[8 + c];
    }
    spec->depth_mm = layout[13];
    spec->data_step = layout[14] != 0.0;
    spec->moments = layout[15] != 0.0;
    spec->pmd_scale_per_px = layout[16];
    spec->image_width_px = width_px;
    spec->image_height_px = height_px;
    memcpy(spec->K_c_px, K_c, sizeof spec->K_c_px);
    return 0;
}

PyDoc_STRVAR(grid_features_doc,
             "grid_features(points_2d, points_3d, mask, rvecs, tvecs, K_c, width_px, height_px, layout, features, "
             "point_rows, stats, refuse_behind)\n--\n\n"
             "The feature of F frames of N points into ``features`` (F, D) float64 (dimenet_frame_features frame by "
             "frame, the GIL released): points_2d (F, N, 2) px, points_3d (F, N, 3) mm in {W}, mask (F, N) bool or "
             "None, rvecs and tvecs (F, 3) the C0 poses, K_c (3, 3) px, the image's width and height px, layout "
             "(17,) the packed FeatureSpec; point_rows (F, 6, N) float64 or None the raw point rows; stats (F, 3) "
             "float64 or None: e_c px, used points, points behind the camera. With refuse_behind, a frame whose "
             "points are not all in front of the camera is an InputError. InputError as the numpy reference's "
             "(the data step on points that fix no pose, the first such frame); TypeError or ValueError for "
             "arrays of the wrong type or shape.");

static PyObject *grid_features(PyObject *module, PyObject *args)
{
    PyObject *o_p2, *o_p3, *o_mask, *o_rvecs, *o_tvecs, *o_K, *o_layout, *o_feats, *o_rows, *o_stats;
    double width_px, height_px;
    int refuse_behind;
    Py_buffer p2, p3, mask, rvecs, tvecs, K, layout, feats, rows, stats;
    Py_buffer *views[10] = {NULL};
    int n_views = 0, code = DIMENET_OK, failed = 0;
    Py_ssize_t F, N, f;
    Py_ssize_t shape[3];
    dimenet_feature_spec spec;
    dimenet_frame_stats st;
    size_t D = 0, n_scratch = 0;
    double *scratch = NULL;
    PyObject *result = NULL;

    if (!PyArg_ParseTuple(args, "OOOOOOddOOOOp:grid_features", &o_p2, &o_p3, &o_mask, &o_rvecs, &o_tvecs, &o_K,
                          &width_px, &height_px, &o_layout, &o_feats, &o_rows, &o_stats, &refuse_behind)) {
        return NULL;
    }
#define VIEW(obj, view, name, kind, nd, writable)                                                                      \
    do {                                                                                                               \
        if (dimenet_py_get_view(obj, &view, name, kind, nd, shape, writable) != 0) {                                   \
            goto done;                                                                                                 \
        }                                                                                                              \
        views[n_views++] = &view;                                                                                      \
    } while (0)
    shape[0] = -1, shape[1] = -1, shape[2] = 2;
    VIEW(o_p2, p2, "points_2d", 'd', 3, 0);
    F = p2.shape[0], N = p2.shape[1];
    shape[0] = F, shape[1] = N, shape[2] = 3;
    VIEW(o_p3, p3, "points_3d", 'd', 3, 0);
    if (o_mask != Py_None) {
        VIEW(o_mask, mask, "mask", '?', 2, 0);
    }
    shape[1] = 3;
    VIEW(o_rvecs, rvecs, "rvecs", 'd', 2, 0);
    VIEW(o_tvecs, tvecs, "tvecs", 'd', 2, 0);
    shape[0] = 3;
    VIEW(o_K, K, "K_c", 'd', 2, 0);
    shape[0] = LAYOUT_SIZE;
    VIEW(o_layout, layout, "layout", 'd', 1, 0);
    if (spec_from_layout((const double *)layout.buf, (const double *)K.buf, width_px, height_px, &spec) != 0
        || dimenet_feature_size(&spec, &D) != DIMENET_OK
        || dimenet_scratch_doubles(&spec, (size_t)N, &n_scratch) != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, "grid_features: the layout, image size or grid is not a valid feature spec");
        goto done;
    }
    shape[0] = F, shape[1] = (Py_ssize_t)D;
    VIEW(o_feats, feats, "features", 'd', 2, 1);
    if (o_rows != Py_None) {
        shape[1] = DIMENET_POINT_ROWS, shape[2] = N;
        VIEW(o_rows, rows, "point_rows", 'd', 3, 1);
    }
    if (o_stats != Py_None) {
        shape[1] = 3;
        VIEW(o_stats, stats, "stats", 'd', 2, 1);
    }
    scratch = (double *)PyMem_RawMalloc(n_scratch * sizeof(double) + 1);
    if (scratch == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    for (f = 0; f < F; f++) {
        memset(&st, 0, sizeof st);
        code = dimenet_frame_features(
            &spec, (size_t)N, (const double *)p2.buf + f * N * 2, (const double *)p3.buf + f * N * 3,
            o_mask == Py_None ? NULL : (const unsigned char *)mask.buf + f * N, (const double *)rvecs.buf + f * 3,
            (const double *)tvecs.buf + f * 3, refuse_behind ? DIMENET_REFUSE_BEHIND_CAMERA : 0u,
            (double *)feats.buf + f * (Py_ssize_t)D, D,
            o_rows == Py_None ? NULL : (double *)rows.buf + f * DIMENET_POINT_ROWS * N, scratch, n_scratch, &st);
        if (o_stats != Py_None) {
            double *s = (double *)stats.buf + f * 3;
            s[0] = st.e_c_px, s[1] = (double)st.n_used, s[2] = (double)st.n_behind;
        }
        if (code != DIMENET_OK) {
            failed = 1;
            break;
        }
    }
    Py_END_ALLOW_THREADS
    if (failed) {
        raise_frame_error(module, code, &st, N);
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_RawFree(scratch);
    while (n_views > 0) {
        PyBuffer_Release(views[--n_views]);
    }
    return result;
#undef VIEW
}

/* The InputError of a failed frame (the numpy path's messages) or the ValueError of a bad argument. */
static void raise_frame_error(PyObject *module, int code, const dimenet_frame_stats *st, Py_ssize_t n_points)
{
    if (code == DIMENET_E_BEHIND_CAMERA) { /* rectify.checks.behind_camera_error's message */
        PyErr_Format(dimenet_py_state_of(module)->input_error,
                     "%zu of %zd points lie behind the camera at the best pose under K_c: "
                     "the correspondences do not fit one pinhole camera",
                     st->n_behind, n_points);
    } else if (code == DIMENET_E_ARGUMENT) {
        PyErr_SetString(PyExc_ValueError, dimenet_error_message(code));
    } else {
        PyErr_SetString(dimenet_py_state_of(module)->input_error, dimenet_error_message(code));
    }
}

PyDoc_STRVAR(frame_features_doc,
             "frame_features(points_2d, points_3d, rvec, tvec, K_c, image_size, layout, features) -> e_c\n--\n\n"
             "One frame's feature into ``features`` (1, D) float64 at its C0 pose (the rectifier's hot path, "
             "rectify.stages.frame_features), the GIL released: points_2d (N, 2) px, points_3d (N, 3) mm in {W}, "
             "rvec and tvec (3,), K_c (3, 3) px, image_size (width, height) px, layout (17,) the packed "
             "FeatureSpec. Returns e_c (px), the mean norm of the PMD. InputError as the numpy path's: a point "
             "behind the camera, the data step on points that fix no pose.");

static PyObject *frame_features(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    static const char *const names[] = {"points_2d", "points_3d", "rvec", "tvec", "K_c", "layout", "features"};
    Py_buffer views[7];
    int n_views = 0, code = DIMENET_OK;
    Py_ssize_t N = 0;
    double width_px, height_px;
    dimenet_feature_spec spec;
    dimenet_frame_stats st;
    size_t D = 0, n_scratch = 0;
    double *scratch = NULL;
    PyObject *result = NULL, *size;
    const char kinds_nd[7] = {2, 2, 1, 1, 2, 1, 2};
    int i;

    if (nargs != 8) {
        PyErr_Format(PyExc_TypeError, "frame_features takes 8 arguments, got %zd", nargs);
        return NULL;
    }
    size = args[5];
    if (!PyTuple_Check(size) || PyTuple_GET_SIZE(size) != 2) {
        PyErr_SetString(PyExc_TypeError, "image_size must be a tuple (width, height)");
        return NULL;
    }
    width_px = PyFloat_AsDouble(PyTuple_GET_ITEM(size, 0));
    height_px = PyFloat_AsDouble(PyTuple_GET_ITEM(size, 1));
    if (PyErr_Occurred()) {
        return NULL;
    }
    for (i = 0; i < 7; i++) {
        PyObject *obj = args[i < 5 ? i : i + 1];
        Py_ssize_t any[2] = {-1, -1};
        if (dimenet_py_get_view(obj, &views[i], names[i], 'd', kinds_nd[i], any, i == 6) != 0) {
            goto done;
        }
        n_views++;
    }
    N = views[0].shape[0];
    if (views[0].shape[1] != 2 || views[1].shape[0] != N || views[1].shape[1] != 3 || views[2].shape[0] != 3
        || views[3].shape[0] != 3 || views[4].shape[0] != 3 || views[4].shape[1] != 3
        || views[5].shape[0] != LAYOUT_SIZE) {
        PyErr_SetString(PyExc_ValueError, "frame_features: points_2d (N, 2), points_3d (N, 3), rvec and tvec (3,), "
                                          "K_c (3, 3) and layout (17,) expected");
        goto done;
    }
    if (spec_from_layout((const double *)views[5].buf, (const double *)views[4].buf, width_px, height_px, &spec) != 0
        || dimenet_feature_size(&spec, &D) != DIMENET_OK
        || dimenet_scratch_doubles(&spec, (size_t)N, &n_scratch) != DIMENET_OK) {
        PyErr_SetString(PyExc_ValueError, "frame_features: the layout, image size or grid is not a valid feature spec");
        goto done;
    }
    if (views[6].shape[0] != 1 || views[6].shape[1] != (Py_ssize_t)D) {
        PyErr_Format(PyExc_ValueError, "features must be (1, %zu)", D);
        goto done;
    }
    scratch = (double *)PyMem_RawMalloc(n_scratch * sizeof(double) + 1);
    if (scratch == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    memset(&st, 0, sizeof st);
    Py_BEGIN_ALLOW_THREADS
    code = dimenet_frame_features(&spec, (size_t)N, (const double *)views[0].buf, (const double *)views[1].buf, NULL,
                                  (const double *)views[2].buf, (const double *)views[3].buf,
                                  DIMENET_REFUSE_BEHIND_CAMERA, (double *)views[6].buf, D, NULL, scratch, n_scratch,
                                  &st);
    Py_END_ALLOW_THREADS
    if (code != DIMENET_OK) {
        raise_frame_error(module, code, &st, N);
        goto done;
    }
    result = PyFloat_FromDouble(st.e_c_px);
done:
    PyMem_RawFree(scratch);
    dimenet_py_release_views(views, n_views);
    return result;
}

static PyMethodDef methods[] = {
    {"grid_features", grid_features, METH_VARARGS, grid_features_doc},
    {"frame_features", (PyCFunction)(void (*)(void))frame_features, METH_FASTCALL, frame_features_doc},
    {NULL, NULL, 0, NULL},
};

static int module_traverse(PyObject *module, visitproc visit, void *arg)
{
    Py_VISIT(dimenet_py_state_of(module)->input_error);
    return 0;
}

static int module_clear(PyObject *module)
{
    Py_CLEAR(dimenet_py_state_of(module)->input_error);
    return 0;
}

static void module_free(void *module)
{
    module_clear((PyObject *)module);
}

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT,
    "_core",
    "The compiled core of the DIME-Net runtime (dimenet_core.h): the feature stage of every encoder.",
    sizeof(dimenet_py_state),
    methods,
    NULL,
    module_traverse,
    module_clear,
    module_free,
};

PyMODINIT_FUNC PyInit__core(void)
{
    PyObject *module, *errors;
    module = PyModule_Create(&module_def);
    if (module == NULL) {
        return NULL;
    }
    errors = PyImport_ImportModule("dimenet.runtime.errors");
    if (errors == NULL) {
        Py_DECREF(module);
        return NULL;
    }
    dimenet_py_state_of(module)->input_error = PyObject_GetAttrString(errors, "InputError");
    Py_DECREF(errors);
    if (dimenet_py_state_of(module)->input_error == NULL || PyModule_AddFunctions(module, dimenet_py_pose_methods) != 0
        || PyModule_AddIntConstant(module, "LAYOUT_SIZE", LAYOUT_SIZE) != 0
        || PyModule_AddIntConstant(module, "POINT_ROWS", DIMENET_POINT_ROWS) != 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}

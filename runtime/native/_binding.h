/* _binding.h: what the two files of the CPython binding (_module.c, _module_pose.c) share; the module's
 * own names, not exported from the extension. Include after Python.h. */
#ifndef DIMENET_BINDING_H
#define DIMENET_BINDING_H

#include "dimenet_core.h"

/* The module's state: the InputError class (dimenet.runtime.errors), held per module, not in a static. */
typedef struct {
    PyObject *input_error;
} dimenet_py_state;

dimenet_py_state *dimenet_py_state_of(PyObject *module);

/* A buffer of ``kind`` ('d' float64, '?' bool) with ndim dimensions, C contiguous; shape[i] < 0: any.
 * 0, or -1 with a TypeError or ValueError set (and nothing held). */
int dimenet_py_get_view(PyObject *obj, Py_buffer *view, const char *name, char kind, int ndim,
                        const Py_ssize_t *shape, int writable);

/* views[i] (float64, dimenet_py_get_view's) of args[arg_index[i]] for i < n: names[i], ndims[i], shapes[i], writable
 * from index first_writable on. 0 with all n held, or -1 with a TypeError or ValueError set and nothing held. */
int dimenet_py_get_views(PyObject *const *args, const int *arg_index, const char *const *names, const char *ndims,
                         const Py_ssize_t (*shapes)[2], int n, int first_writable, Py_buffer *views);

/* Releases views[0 .. n_views - 1], the last first. */
void dimenet_py_release_views(Py_buffer *views, int n_views);

/* pose_steps and frame_checks (_module_pose.c), added to the module at its creation. */
extern PyMethodDef dimenet_py_pose_methods[];

#endif

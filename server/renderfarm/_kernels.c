/* Fused per-pixel loops of the progressive merge (merge.py): one pass over a tile's arrays
 * instead of a dozen numpy passes. merge.py's docstring states the statistics; the tests in
 * server/tests/test_merge.py check these loops against numpy (relative_error(), and the
 * statistics of all samples computed at once).
 *
 * Every array is a C-contiguous buffer (numpy arrays, bytes); float64 unless said otherwise.
 * Batch arrays come off the wire as float32 or float64, told apart by their byte length.
 * The GIL stays held: the loops take microseconds, and on a busy single-core server giving the
 * GIL away for that long only invites a thread switch in the middle of a merge.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Rec. 709 luminance weights. */
static const double kLumR = 0.2126, kLumG = 0.7152, kLumB = 0.0722;

typedef struct {
    Py_buffer view;
    int held;
} Buffer;

static int get_buffer(PyObject *obj, Buffer *b, int writable, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &b->view, flags) != 0) {
        PyErr_Format(PyExc_TypeError, "%s: a C-contiguous%s buffer is required", name,
                     writable ? " writable" : "");
        return -1;
    }
    b->held = 1;
    return 0;
}

static void release(Buffer *b, size_t count) {
    for (size_t i = 0; i < count; ++i) {
        if (b[i].held) {
            PyBuffer_Release(&b[i].view);
            b[i].held = 0;
        }
    }
}

/* The element size (4 or 8) of a batch array of `count` values, or 0 when it fits neither. */
static int batch_itemsize(const Buffer *b, Py_ssize_t count) {
    if (b->view.len == 4 * count) return 4;
    if (b->view.len == 8 * count) return 8;
    return 0;
}

static inline double load(const void *data, int itemsize, Py_ssize_t i) {
    return itemsize == 4 ? (double)((const float *)data)[i] : ((const double *)data)[i];
}

PyDoc_STRVAR(merge_doc,
             "merge(pixels, n_a, n_b, rgb_sum, lum_mean, m2_within, m2_between, batch_rgb,\n"
             "      batch_m2, out_rgb_sum, out_lum_mean, out_m2_within, out_m2_between)\n"
             "--\n\n"
             "Merge one batch of n_b samples per pixel into statistics of n_a samples (Chan et\n"
             "al.), writing the merged statistics to the out_ arrays (which may be the inputs).");

static PyObject *merge(PyObject *self, PyObject *args) {
    (void)self;
    Py_ssize_t pixels;
    double n_a, n_b;
    PyObject *objs[10];
    if (!PyArg_ParseTuple(args, "nddOOOOOOOOOO", &pixels, &n_a, &n_b, &objs[0], &objs[1],
                          &objs[2], &objs[3], &objs[4], &objs[5], &objs[6], &objs[7], &objs[8],
                          &objs[9])) {
        return NULL;
    }
    static const char *names[10] = {"rgb_sum",      "lum_mean",      "m2_within",
                                    "m2_between",   "batch_rgb",     "batch_m2",
                                    "out_rgb_sum",  "out_lum_mean",  "out_m2_within",
                                    "out_m2_between"};
    if (pixels <= 0 || !(n_b > 0) || !(n_a >= 0)) {
        PyErr_SetString(PyExc_ValueError, "merge: pixels > 0, n_a >= 0 and n_b > 0 are required");
        return NULL;
    }
    Buffer b[10];
    memset(b, 0, sizeof b);
    for (int i = 0; i < 10; ++i) {
        if (get_buffer(objs[i], &b[i], i >= 6, names[i]) != 0) {
            release(b, 10);
            return NULL;
        }
    }
    const Py_ssize_t expected[10] = {24, 8, 8, 8, 0, 0, 24, 8, 8, 8};
    for (int i = 0; i < 10; ++i) {
        if (expected[i] && b[i].view.len != expected[i] * pixels) {
            PyErr_Format(PyExc_ValueError, "merge: %s has %zd bytes, expected %zd", names[i],
                         b[i].view.len, expected[i] * pixels);
            release(b, 10);
            return NULL;
        }
    }
    const int rgb_size = batch_itemsize(&b[4], 3 * pixels);
    const int m2_size = batch_itemsize(&b[5], pixels);
    if (!rgb_size || !m2_size) {
        PyErr_SetString(PyExc_ValueError,
                        "merge: batch arrays must hold float32 or float64 values, one (m2) or "
                        "three (rgb) per pixel");
        release(b, 10);
        return NULL;
    }
    const double *rgb = b[0].view.buf, *mean = b[1].view.buf, *within = b[2].view.buf,
                 *between = b[3].view.buf;
    const void *batch_rgb = b[4].view.buf, *batch_m2 = b[5].view.buf;
    double *out_rgb = b[6].view.buf, *out_mean = b[7].view.buf, *out_within = b[8].view.buf,
           *out_between = b[9].view.buf;
    const double inv_b = 1.0 / n_b, n = n_a + n_b;
    const double gain = n_a * n_b / n, step = n_b / n;
    const int has_between = n_a > 0;
    for (Py_ssize_t p = 0; p < pixels; ++p) {
        const double r = load(batch_rgb, rgb_size, 3 * p), g = load(batch_rgb, rgb_size, 3 * p + 1),
                     bl = load(batch_rgb, rgb_size, 3 * p + 2);
        const double delta = (kLumR * r + kLumG * g + kLumB * bl) * inv_b - mean[p];
        out_between[p] = has_between ? between[p] + delta * delta * gain : between[p];
        out_mean[p] = mean[p] + delta * step;
        out_within[p] = within[p] + load(batch_m2, m2_size, p);
        out_rgb[3 * p] = rgb[3 * p] + r;
        out_rgb[3 * p + 1] = rgb[3 * p + 1] + g;
        out_rgb[3 * p + 2] = rgb[3 * p + 2] + bl;
    }
    release(b, 10);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(squared_relative_error_doc,
             "squared_relative_error(pixels, lum_mean, m2, m2_extra, k, floor) -> float\n"
             "--\n\n"
             "Sum over pixels of (s / max(mean - s, floor))^2 with s = sqrt((m2 + m2_extra) * k);\n"
             "m2_extra may be None.");

static PyObject *squared_relative_error(PyObject *self, PyObject *args) {
    (void)self;
    Py_ssize_t pixels;
    PyObject *mean_obj, *m2_obj, *extra_obj;
    double k, floor_value;
    if (!PyArg_ParseTuple(args, "nOOOdd", &pixels, &mean_obj, &m2_obj, &extra_obj, &k,
                          &floor_value)) {
        return NULL;
    }
    Buffer b[3];
    memset(b, 0, sizeof b);
    if (get_buffer(mean_obj, &b[0], 0, "lum_mean") != 0 || get_buffer(m2_obj, &b[1], 0, "m2") != 0 ||
        (extra_obj != Py_None && get_buffer(extra_obj, &b[2], 0, "m2_extra") != 0)) {
        release(b, 3);
        return NULL;
    }
    for (int i = 0; i < 3; ++i) {
        if (b[i].held && b[i].view.len != 8 * pixels) {
            PyErr_Format(PyExc_ValueError, "squared_relative_error: array %d has %zd bytes, "
                         "expected %zd", i, b[i].view.len, 8 * pixels);
            release(b, 3);
            return NULL;
        }
    }
    const double *mean = b[0].view.buf, *m2 = b[1].view.buf;
    const double *extra = b[2].held ? b[2].view.buf : NULL;
    double total = 0.0;
    for (Py_ssize_t p = 0; p < pixels; ++p) {
        const double v = (extra ? m2[p] + extra[p] : m2[p]) * k;
        const double s = sqrt(v);
        const double bound = mean[p] - s;
        const double rel = s / (bound > floor_value ? bound : floor_value);
        total += rel * rel;
    }
    release(b, 3);
    return PyFloat_FromDouble(total);
}

static PyMethodDef methods[] = {
    {"merge", merge, METH_VARARGS, merge_doc},
    {"squared_relative_error", squared_relative_error, METH_VARARGS, squared_relative_error_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "renderfarm._kernels",
    "Fused per-pixel loops of the progressive merge (see merge.py).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }

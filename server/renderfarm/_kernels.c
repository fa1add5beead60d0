/* Fused per-pixel loops of the progressive merge (merge.py), and of downscaled previews
 * (images.py): one pass over a tile's arrays instead of a dozen numpy passes. merge.py's docstring states the statistics; the tests in
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
             "      batch_m2, out_rgb_sum, out_lum_mean, out_m2_within, out_m2_between,\n"
             "      error_terms=0, k=0.0, floor=0.0) -> float\n"
             "--\n\n"
             "Merge one batch of n_b samples per pixel into statistics of n_a samples (Chan et\n"
             "al.), writing the merged statistics to the out_ arrays (which may be the inputs).\n"
             "In the same pass, the sum over pixels of the squared relative error of the merged\n"
             "statistics (squared_relative_error's), with the variance of the mean\n"
             "(m2_within + m2_between) * k for error_terms 1, m2_between * k for 2, m2_within * k\n"
             "for 3; error_terms 0 returns inf (no estimate yet).");

/* The error terms of merge(): which M2 arrays make the variance of the mean. */
enum { kErrorNone = 0, kErrorBoth = 1, kErrorBetween = 2, kErrorWithin = 3 };

/* One pixel of merge(): the merged statistics, and its squared relative error (or 0). */
#define MERGE_PIXEL(r, g, bl, batch_m2_value)                                                   \
    do {                                                                                      \
        const double delta = (kLumR * (r) + kLumG * (g) + kLumB * (bl)) * inv_b - mean[p];   \
        const double nb = has_between ? between[p] + delta * delta * gain : between[p];       \
        const double nm = mean[p] + delta * step;                                            \
        const double nw = within[p] + (batch_m2_value);                                      \
        out_between[p] = nb;                                                                  \
        out_mean[p] = nm;                                                                     \
        out_within[p] = nw;                                                                   \
        out_rgb[3 * p] = rgb[3 * p] + (r);                                                    \
        out_rgb[3 * p + 1] = rgb[3 * p + 1] + (g);                                            \
        out_rgb[3 * p + 2] = rgb[3 * p + 2] + (bl);                                           \
        if (terms != kErrorNone) {                                                            \
            const double v = (terms == kErrorBoth ? nw + nb : terms == kErrorBetween ? nb : nw) \
                             * k;                                                             \
            const double s = sqrt(v);                                                         \
            const double bound = nm - s;                                                      \
            const double rel = s / (bound > floor_value ? bound : floor_value);               \
            total += rel * rel;                                                               \
        }                                                                                     \
    } while (0)

static PyObject *merge(PyObject *self, PyObject *args) {
    (void)self;
    Py_ssize_t pixels;
    double n_a, n_b, k = 0.0, floor_value = 0.0;
    int terms = kErrorNone;
    PyObject *objs[10];
    if (!PyArg_ParseTuple(args, "nddOOOOOOOOOO|idd", &pixels, &n_a, &n_b, &objs[0], &objs[1],
                          &objs[2], &objs[3], &objs[4], &objs[5], &objs[6], &objs[7], &objs[8],
                          &objs[9], &terms, &k, &floor_value)) {
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
    if (terms < kErrorNone || terms > kErrorWithin) {
        PyErr_SetString(PyExc_ValueError, "merge: error_terms is 0, 1, 2 or 3");
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
    double total = 0.0;
    if (rgb_size == 4 && m2_size == 4) {  /* what workers send: a loop of its own */
        const float *in = batch_rgb, *in_m2 = batch_m2;
        for (Py_ssize_t p = 0; p < pixels; ++p) {
            MERGE_PIXEL((double)in[3 * p], (double)in[3 * p + 1], (double)in[3 * p + 2],
                        (double)in_m2[p]);
        }
    } else {
        for (Py_ssize_t p = 0; p < pixels; ++p) {
            MERGE_PIXEL(load(batch_rgb, rgb_size, 3 * p), load(batch_rgb, rgb_size, 3 * p + 1),
                        load(batch_rgb, rgb_size, 3 * p + 2), load(batch_m2, m2_size, p));
        }
    }
    release(b, 10);
    return PyFloat_FromDouble(terms == kErrorNone ? INFINITY : total);
}

#undef MERGE_PIXEL

PyDoc_STRVAR(all_finite_doc,
             "all_finite(values) -> bool\n"
             "--\n\n"
             "Whether every value of a float32 or float64 array is finite; one pass, no\n"
             "temporaries.");

static PyObject *all_finite(PyObject *self, PyObject *arg) {
    (void)self;
    Buffer b;
    memset(&b, 0, sizeof b);
    if (PyObject_GetBuffer(arg, &b.view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
        PyErr_SetString(PyExc_TypeError, "all_finite: a C-contiguous buffer is required");
        return NULL;
    }
    b.held = 1;
    const Py_ssize_t itemsize = b.view.itemsize;
    const char *format = b.view.format ? b.view.format : "B";
    if (format[0] == '<' || format[0] == '=') ++format;
    if (!((itemsize == 4 && strcmp(format, "f") == 0) ||
          (itemsize == 8 && strcmp(format, "d") == 0))) {
        release(&b, 1);
        PyErr_SetString(PyExc_TypeError, "all_finite: float32 or float64 values are required");
        return NULL;
    }
    int finite = 1;
    const Py_ssize_t count = b.view.len / itemsize;
    /* A value is finite when its exponent bits are not all ones: an integer test the
     * compiler vectorises, OR-reduced so that the loop has no early exit. */
    if (itemsize == 4) {
        const uint32_t *bits = b.view.buf;
        uint32_t bad = 0;
        for (Py_ssize_t i = 0; i < count; ++i) {
            uint32_t v;
            memcpy(&v, bits + i, 4);
            bad |= (uint32_t)((v & 0x7f800000u) == 0x7f800000u);
        }
        finite = !bad;
    } else {
        const uint64_t *bits = b.view.buf;
        uint64_t bad = 0;
        for (Py_ssize_t i = 0; i < count; ++i) {
            uint64_t v;
            memcpy(&v, bits + i, 8);
            bad |= (uint64_t)((v & 0x7ff0000000000000ull) == 0x7ff0000000000000ull);
        }
        finite = !bad;
    }
    release(&b, 1);
    return PyBool_FromLong(finite);
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

PyDoc_STRVAR(block_means_doc,
             "block_means(values, height, width, channels, factor, divisor, out)\n"
             "--\n\n"
             "Means of the factor x factor blocks of float64 values (height, width, channels),\n"
             "divided by divisor, into out (ceil(height / factor), ceil(width / factor),\n"
             "channels); blocks at the right and bottom edges may be partial. For downscaled\n"
             "previews (images.py): one pass instead of a dozen numpy passes per tile.");

static PyObject *block_means(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *values_obj, *out_obj;
    Py_ssize_t h, w, c, f;
    double divisor;
    if (!PyArg_ParseTuple(args, "OnnnndO", &values_obj, &h, &w, &c, &f, &divisor, &out_obj)) {
        return NULL;
    }
    if (h <= 0 || w <= 0 || c <= 0 || f <= 0 || !(divisor > 0)) {
        PyErr_SetString(PyExc_ValueError, "block_means: positive sizes and divisor required");
        return NULL;
    }
    Buffer b[2];
    memset(b, 0, sizeof b);
    if (get_buffer(values_obj, &b[0], 0, "values") != 0 ||
        get_buffer(out_obj, &b[1], 1, "out") != 0) {
        release(b, 2);
        return NULL;
    }
    const Py_ssize_t oh = (h + f - 1) / f, ow = (w + f - 1) / f;
    if (b[0].view.len != 8 * h * w * c || b[1].view.len != 8 * oh * ow * c) {
        PyErr_SetString(PyExc_ValueError, "block_means: array sizes do not match the shape");
        release(b, 2);
        return NULL;
    }
    const double *in = b[0].view.buf;
    double *out = b[1].view.buf;
    memset(out, 0, (size_t)b[1].view.len);
    for (Py_ssize_t y = 0; y < h; ++y) {
        double *row = out + (y / f) * ow * c;
        const double *src = in + y * w * c;
        for (Py_ssize_t bx = 0; bx < ow; ++bx) {
            const Py_ssize_t x1 = (bx + 1) * f <= w ? (bx + 1) * f : w;
            double *dst = row + bx * c;
            if (c == 3) {  /* RGB: the sums in registers */
                double r = 0.0, g = 0.0, bl = 0.0;
                for (Py_ssize_t x = bx * f; x < x1; ++x) {
                    r += src[3 * x];
                    g += src[3 * x + 1];
                    bl += src[3 * x + 2];
                }
                dst[0] += r;
                dst[1] += g;
                dst[2] += bl;
                continue;
            }
            for (Py_ssize_t x = bx * f; x < x1; ++x) {
                for (Py_ssize_t k = 0; k < c; ++k) dst[k] += src[x * c + k];
            }
        }
    }
    for (Py_ssize_t by = 0; by < oh; ++by) {
        const Py_ssize_t rows = (by + 1) * f <= h ? f : h - by * f;
        for (Py_ssize_t bx = 0; bx < ow; ++bx) {
            const Py_ssize_t cols = (bx + 1) * f <= w ? f : w - bx * f;
            const double scale = 1.0 / ((double)(rows * cols) * divisor);
            double *dst = out + (by * ow + bx) * c;
            for (Py_ssize_t k = 0; k < c; ++k) dst[k] *= scale;
        }
    }
    release(b, 2);
    Py_RETURN_NONE;
}

#define EXR_CHANNEL_COUNT 13

PyDoc_STRVAR(exr_tile_doc,
             "exr_tile(rgb_sum, lum_mean, m2, m2_extra, albedo_sum, normal_sum, coverage_sum,\n"
             "         height, width, samples, aov_samples, k, floor, out, out_width, x0)\n"
             "--\n\n"
             "A tile's 13 EXR channels (images.EXR_CHANNELS) as float32 into a band `out` of\n"
             "out_width pixels a row, from column x0: the mean RGB, the variance of the mean\n"
             "luminance (m2 + m2_extra) * k (m2_extra may be None; m2 None: unknown, inf), the\n"
             "spp, the relative error sqrt(v) / max(mean - sqrt(v), floor), and the albedo and\n"
             "normal means (float32 sums over aov_samples, divided in float32), and the alpha\n"
             "coverage_sum / samples (float32 counts). The same\n"
             "arithmetic as merge.py's numpy, rounded once to float32.");

static PyObject *exr_tile(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *objs[8];
    Py_ssize_t h, w, samples, aov_samples, out_width, x0;
    double k, floor_value;
    if (!PyArg_ParseTuple(args, "OOOOOOOnnnnddOnn", &objs[0], &objs[1], &objs[2], &objs[3],
                          &objs[4], &objs[5], &objs[7], &h, &w, &samples, &aov_samples, &k,
                          &floor_value, &objs[6], &out_width, &x0)) {
        return NULL;
    }
    static const char *names[8] = {"rgb_sum",    "lum_mean",   "m2",  "m2_extra",
                                   "albedo_sum", "normal_sum", "out", "coverage_sum"};
    if (h <= 0 || w <= 0 || samples <= 0 || aov_samples <= 0 || x0 < 0 || x0 + w > out_width) {
        PyErr_SetString(PyExc_ValueError, "exr_tile: sizes out of range");
        return NULL;
    }
    Buffer b[8];
    memset(b, 0, sizeof b);
    for (int i = 0; i < 8; ++i) {
        if ((i == 2 || i == 3) && objs[i] == Py_None) continue;
        if (get_buffer(objs[i], &b[i], i == 6, names[i]) != 0) {
            release(b, 8);
            return NULL;
        }
    }
    const Py_ssize_t pixels = h * w;
    const Py_ssize_t expected[8] = {24, 8, 8, 8, 12, 12, 0, 4};
    for (int i = 0; i < 8; ++i) {
        if (i != 6 && b[i].held && b[i].view.len != expected[i] * pixels) {
            PyErr_Format(PyExc_ValueError, "exr_tile: %s has %zd bytes, expected %zd", names[i],
                         b[i].view.len, expected[i] * pixels);
            release(b, 8);
            return NULL;
        }
    }
    if (b[6].view.len != 4 * EXR_CHANNEL_COUNT * out_width * h) {
        PyErr_SetString(PyExc_ValueError, "exr_tile: out is not height x out_width x 13 floats");
        release(b, 8);
        return NULL;
    }
    const double *rgb = b[0].view.buf, *mean = b[1].view.buf;
    const double *m2 = b[2].held ? b[2].view.buf : NULL, *extra = b[3].held ? b[3].view.buf : NULL;
    const float *albedo = b[4].view.buf, *normal = b[5].view.buf;
    const float *coverage = b[7].view.buf;
    float *out = b[6].view.buf;
    const double n = (double)samples;
    const float aov_n = (float)aov_samples;
    for (Py_ssize_t y = 0; y < h; ++y) {
        for (Py_ssize_t x = 0; x < w; ++x) {
            const Py_ssize_t p = y * w + x;
            float *o = out + (y * out_width + x0 + x) * EXR_CHANNEL_COUNT;
            o[0] = (float)(rgb[3 * p] / n);
            o[1] = (float)(rgb[3 * p + 1] / n);
            o[2] = (float)(rgb[3 * p + 2] / n);
            if (m2) {
                const double v = (extra ? m2[p] + extra[p] : m2[p]) * k;
                const double s = sqrt(v);
                const double bound = mean[p] - s;
                o[3] = (float)v;
                o[5] = (float)(s / (bound > floor_value ? bound : floor_value));
            } else {
                o[3] = (float)INFINITY;
                o[5] = (float)INFINITY;
            }
            o[4] = (float)n;
            for (int c = 0; c < 3; ++c) {
                o[6 + c] = albedo[3 * p + c] / aov_n;
                o[9 + c] = normal[3 * p + c] / aov_n;
            }
            o[12] = (float)((double)coverage[p] / n);
        }
    }
    release(b, 8);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(merge_ranked_doc,
"merge_ranked(stored, batch, out, pixels, ranks)\n\n"
"Cryptomatte's ranked rows (domain/cryptomatte.py): per pixel, `ranks` (label, count) uint32\n"
"pairs of `stored` and of `batch` (label 0: an empty slot; each set holds a label at most\n"
"once) merged into `out`: the counts of equal labels added (saturating at 2^32 - 1), the\n"
"`ranks` largest kept, by count descending then label ascending, empty slots (0, 0) last.");

#define MAX_RANKS 16

static PyObject *merge_ranked(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *stored_obj, *batch_obj, *out_obj;
    Py_ssize_t pixels, ranks;
    if (!PyArg_ParseTuple(args, "OOOnn", &stored_obj, &batch_obj, &out_obj, &pixels, &ranks)) {
        return NULL;
    }
    if (pixels < 0 || ranks <= 0 || ranks > MAX_RANKS) {
        PyErr_SetString(PyExc_ValueError, "merge_ranked: 0 < ranks <= 16 and pixels >= 0");
        return NULL;
    }
    Buffer b[3];
    memset(b, 0, sizeof b);
    if (get_buffer(stored_obj, &b[0], 0, "stored") != 0 ||
        get_buffer(batch_obj, &b[1], 0, "batch") != 0 ||
        get_buffer(out_obj, &b[2], 1, "out") != 0) {
        release(b, 3);
        return NULL;
    }
    const Py_ssize_t bytes = 4 * 2 * ranks * pixels;
    if (b[0].view.len != bytes || b[1].view.len != bytes || b[2].view.len != bytes) {
        PyErr_SetString(PyExc_ValueError, "merge_ranked: array sizes do not match the shape");
        release(b, 3);
        return NULL;
    }
    const uint32_t *stored = b[0].view.buf, *batch = b[1].view.buf;
    uint32_t *out = b[2].view.buf;
    for (Py_ssize_t p = 0; p < pixels; ++p) {
        const uint32_t *s = stored + 2 * ranks * p, *t = batch + 2 * ranks * p;
        uint32_t label[2 * MAX_RANKS];
        uint64_t count[2 * MAX_RANKS];
        int n = 0;
        for (Py_ssize_t r = 0; r < ranks; ++r) {
            if (s[2 * r] == 0) continue;
            label[n] = s[2 * r];
            count[n++] = s[2 * r + 1];
        }
        const int stored_n = n;
        for (Py_ssize_t r = 0; r < ranks; ++r) {
            const uint32_t l = t[2 * r];
            if (l == 0) continue;
            int i = 0;
            while (i < stored_n && label[i] != l) ++i;
            if (i < stored_n) {
                count[i] += t[2 * r + 1];
            } else {
                label[n] = l;
                count[n++] = t[2 * r + 1];
            }
        }
        /* Insertion sort (n <= 2 ranks): count descending, then label ascending. */
        for (int i = 1; i < n; ++i) {
            const uint32_t l = label[i];
            const uint64_t c = count[i];
            int j = i - 1;
            while (j >= 0 && (count[j] < c || (count[j] == c && label[j] > l))) {
                label[j + 1] = label[j];
                count[j + 1] = count[j];
                --j;
            }
            label[j + 1] = l;
            count[j + 1] = c;
        }
        uint32_t *o = out + 2 * ranks * p;
        for (Py_ssize_t r = 0; r < ranks; ++r) {
            const int kept = r < n;
            o[2 * r] = kept ? label[r] : 0;
            o[2 * r + 1] = kept ? (count[r] > UINT32_MAX ? UINT32_MAX : (uint32_t)count[r]) : 0;
        }
    }
    release(b, 3);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"merge", merge, METH_VARARGS, merge_doc},
    {"all_finite", all_finite, METH_O, all_finite_doc},
    {"squared_relative_error", squared_relative_error, METH_VARARGS, squared_relative_error_doc},
    {"block_means", block_means, METH_VARARGS, block_means_doc},
    {"exr_tile", exr_tile, METH_VARARGS, exr_tile_doc},
    {"merge_ranked", merge_ranked, METH_VARARGS, merge_ranked_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "renderfarm._kernels",
    "Fused per-pixel loops of the progressive merge (see merge.py).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }

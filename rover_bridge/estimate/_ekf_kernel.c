/*
 * rover_bridge.estimate._ekf_kernel: the EKF's covariance arithmetic in C (optional, built at install).
 *
 * The filter's logic (models, gating, slip, trapezoids) stays in Python, once: rover_bridge.estimate.ekf.
 * These functions are only the linear algebra it runs per measurement, on the same Python lists of
 * floats, with the same operations in the same order as the pure-Python kernel there (PythonKernel),
 * which is the reference: a property test holds the two equal bit for bit. So the build must not
 * contract a * b + c into a fused multiply-add (-ffp-contract=off, set in pyproject.toml; GCC fuses by
 * default on Arm), nor reassociate (no -ffast-math); C evaluates a + b + c as (a + b) + c, as Python.
 *
 * Why C: inside the running bridge each of these list comprehensions runs cold after a wake-up, and
 * together they were the largest single piece of the bridge's own CPU (README, Performance).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#define NMAX 8 /* the filter's states: IX IY IYAW IV IW IB IKT IKR */
#define IV 3
#define IW 4
#define IKT 6
#define IKR 7

/* The first `len` numbers of a list into out[]; the list must hold exactly `len` unless `longer`. */
static int load_first(PyObject *obj, double *out, Py_ssize_t len, const char *name, int longer)
{
    Py_ssize_t have = PyList_CheckExact(obj) ? PyList_GET_SIZE(obj) : -1;
    if (have < len || (have > len && !longer)) {
        PyErr_Format(PyExc_TypeError, "%s: expected a list of %s%zd floats", name, longer ? "at least " : "", len);
        return -1;
    }
    for (Py_ssize_t i = 0; i < len; i++) {
        double v = PyFloat_AsDouble(PyList_GET_ITEM(obj, i));
        if (v == -1.0 && PyErr_Occurred())
            return -1;
        out[i] = v;
    }
    return 0;
}

static int load(PyObject *obj, double *out, Py_ssize_t len, const char *name)
{
    return load_first(obj, out, len, name, 0);
}

/* list[i] = v (a new float; the old item is released). */
static int put(PyObject *list, Py_ssize_t i, double v)
{
    PyObject *f = PyFloat_FromDouble(v);
    if (f == NULL)
        return -1;
    PyList_SET_ITEM(list, i, f);
    return 0;
}

static PyObject *new_list(const double *v, Py_ssize_t len)
{
    PyObject *list = PyList_New(len);
    if (list == NULL)
        return NULL;
    for (Py_ssize_t i = 0; i < len; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL) {
            Py_DECREF(list);
            return NULL;
        }
        PyList_SET_ITEM(list, i, f);
    }
    return list;
}

/* Replace the items of an exactly-`len` list in place. */
static int put_all(PyObject *list, const double *v, Py_ssize_t len)
{
    for (Py_ssize_t i = 0; i < len; i++) {
        PyObject *old = PyList_GET_ITEM(list, i);
        if (put(list, i, v[i]) < 0)
            return -1;
        Py_DECREF(old);
    }
    return 0;
}

static int get_double(PyObject *obj, double *out)
{
    *out = PyFloat_AsDouble(obj);
    return (*out == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

static int get_size(PyObject *obj, Py_ssize_t *n, Py_ssize_t lo, Py_ssize_t hi, const char *name)
{
    *n = PyLong_AsSsize_t(obj);
    if (*n == -1 && PyErr_Occurred())
        return -1;
    if (*n < lo || *n > hi) {
        PyErr_Format(PyExc_ValueError, "%s must be %zd to %zd, got %zd", name, lo, hi, *n);
        return -1;
    }
    return 0;
}

#define NARGS(want, name)                                                               \
    if (nargs != (want)) {                                                              \
        PyErr_Format(PyExc_TypeError, name "() takes %d arguments (%zd given)", (want), nargs); \
        return NULL;                                                                    \
    }

/* propagate_cov(p, n, f02, f12, f03, f13, f04, f14, dt_s, q): P = F P F' + diag(q[:n]), in place (PythonKernel). */
static PyObject *propagate_cov(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    NARGS(10, "propagate_cov");
    Py_ssize_t n;
    double f[6], dt, p[NMAX * NMAX], q[NMAX];
    if (get_size(args[1], &n, 5, NMAX, "n") < 0)
        return NULL;
    for (int i = 0; i < 6; i++)
        if (get_double(args[2 + i], &f[i]) < 0)
            return NULL;
    if (get_double(args[8], &dt) < 0 || load(args[0], p, n * n, "p") < 0 || load_first(args[9], q, n, "q", 1) < 0)
        return NULL;
    const double f02 = f[0], f12 = f[1], f03 = f[2], f13 = f[3], f04 = f[4], f14 = f[5];
    const double *r0 = p, *r1 = p + n, *r2 = p + 2 * n, *r3 = p + 3 * n, *r4 = p + 4 * n;
    double t0[NMAX], t1[NMAX], t2[NMAX];
    for (Py_ssize_t j = 0; j < n; j++) {
        t0[j] = r0[j] + f02 * r2[j] + f03 * r3[j] + f04 * r4[j];
        t1[j] = r1[j] + f12 * r2[j] + f13 * r3[j] + f14 * r4[j];
        t2[j] = r2[j] + dt * r4[j];
    }
    const double n01 = t0[1] + f12 * t0[2] + f13 * t0[3] + f14 * t0[4];
    const double n02 = t0[2] + dt * t0[4];
    const double n12 = t1[2] + dt * t1[4];
    t0[0] = t0[0] + (f02 * t0[2] + f03 * t0[3] + f04 * t0[4] + q[0]);
    t1[1] = t1[1] + (f12 * t1[2] + f13 * t1[3] + f14 * t1[4] + q[1]);
    t2[2] = t2[2] + (dt * t2[4] + q[2]);
    t0[1] = n01; t0[2] = n02; t1[0] = n01; t1[2] = n12; t2[0] = n02; t2[1] = n12;
    PyObject *list = args[0];
    for (Py_ssize_t j = 0; j < n; j++) {
        p[j] = t0[j];
        p[n + j] = t1[j];
        p[2 * n + j] = t2[j];
    }
    for (Py_ssize_t i = 3; i < n; i++) {
        Py_ssize_t k = n * i;
        p[k] = t0[i];
        p[k + 1] = t1[i];
        p[k + 2] = t2[i];
        p[k + i] = p[k + i] + q[i];
    }
    if (put_all(list, p, n * n) < 0)
        return NULL;
    Py_RETURN_NONE;
}

/* Python's float division refuses a zero divisor; so do these, alike. */
static int nonzero(double c)
{
    if (c == 0.0) {
        PyErr_SetString(PyExc_ZeroDivisionError, "float division by zero");
        return -1;
    }
    return 0;
}

/* column_sum(p, n, i, j, c): [(P[k, i] + P[k, j]) / c for each row k] (the gyro's P H' / sqrt(S)). */
static PyObject *column_sum(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    NARGS(5, "column_sum");
    Py_ssize_t n, i, j;
    double c, p[NMAX * NMAX], out[NMAX];
    if (get_size(args[1], &n, 1, NMAX, "n") < 0 || get_size(args[2], &i, 0, n - 1, "i") < 0 ||
        get_size(args[3], &j, 0, n - 1, "j") < 0 || get_double(args[4], &c) < 0 || load(args[0], p, n * n, "p") < 0 || nonzero(c) < 0)
        return NULL;
    for (Py_ssize_t k = 0; k < n; k++)
        out[k] = (p[n * k + i] + p[n * k + j]) / c;
    return new_list(out, n);
}

/* wheel_columns(p, hv3, hv4, hv6, hv7, hw3, hw4, hw6, hw7): (u, w) = the two columns of P H' for H's
   rows that are zero but at v, omega and the geometry states (8 states). */
static PyObject *wheel_columns(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    NARGS(9, "wheel_columns");
    double h[8], p[NMAX * NMAX], u[NMAX], w[NMAX];
    for (int i = 0; i < 8; i++)
        if (get_double(args[1 + i], &h[i]) < 0)
            return NULL;
    if (load(args[0], p, NMAX * NMAX, "p") < 0)
        return NULL;
    for (Py_ssize_t k = 0; k < NMAX * NMAX; k += NMAX) {
        u[k / NMAX] = p[k + IV] * h[0] + p[k + IW] * h[1] + p[k + IKT] * h[2] + p[k + IKR] * h[3];
        w[k / NMAX] = p[k + IV] * h[4] + p[k + IW] * h[5] + p[k + IKT] * h[6] + p[k + IKR] * h[7];
    }
    PyObject *lu = new_list(u, NMAX), *lw = lu ? new_list(w, NMAX) : NULL;
    if (lw == NULL) {
        Py_XDECREF(lu);
        return NULL;
    }
    return Py_BuildValue("(NN)", lu, lw);
}

/* whiten(u, w, c00, c10, c11): (a, b) = the columns [u w] times C^-T, C = [[c00, 0], [c10, c11]]. */
static PyObject *whiten(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    NARGS(5, "whiten");
    double u[NMAX], w[NMAX], a[NMAX], b[NMAX], c00, c10, c11;
    Py_ssize_t n = PyList_Check(args[0]) ? PyList_GET_SIZE(args[0]) : -1;
    if (n < 1 || n > NMAX) {
        PyErr_SetString(PyExc_TypeError, "u: expected a list of 1 to 8 floats");
        return NULL;
    }
    if (load(args[0], u, n, "u") < 0 || load(args[1], w, n, "w") < 0 || get_double(args[2], &c00) < 0 ||
        get_double(args[3], &c10) < 0 || get_double(args[4], &c11) < 0 || nonzero(c00) < 0 || nonzero(c11) < 0)
        return NULL;
    for (Py_ssize_t k = 0; k < n; k++) {
        a[k] = u[k] / c00;
        b[k] = (w[k] - c10 * a[k]) / c11;
    }
    PyObject *la = new_list(a, n), *lb = la ? new_list(b, n) : NULL;
    if (lb == NULL) {
        Py_XDECREF(la);
        return NULL;
    }
    return Py_BuildValue("(NN)", la, lb);
}

/* fuse(x, p, mask, fixed, a, e0, b, e1): the update of x and P from whitened columns (PythonKernel.fuse),
   in place; returns (x, p). b is None for a one-row measurement. */
static PyObject *fuse(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    NARGS(8, "fuse");
    PyObject *lx = args[0], *lp = args[1], *lfixed = args[3], *lb = args[6];
    Py_ssize_t n = PyList_CheckExact(lx) ? PyList_GET_SIZE(lx) : -1;
    if (n < 1 || n > NMAX) {
        PyErr_SetString(PyExc_TypeError, "x: expected a list of 1 to 8 floats");
        return NULL;
    }
    double x[NMAX], p[NMAX * NMAX], m[NMAX], a[NMAX], b[NMAX], e0, e1, out[NMAX * NMAX];
    int two = lb != Py_None;
    if (load(lx, x, n, "x") < 0 || load(lp, p, n * n, "p") < 0 || load(args[2], m, n, "mask") < 0 ||
        load(args[4], a, n, "a") < 0 || get_double(args[5], &e0) < 0 || get_double(args[7], &e1) < 0 ||
        (two && load(lb, b, n, "b") < 0))
        return NULL;
    if (!PyList_CheckExact(lfixed)) {
        PyErr_SetString(PyExc_TypeError, "fixed: expected a list of indices");
        return NULL;
    }
    if (two) {
        for (Py_ssize_t i = 0; i < n; i++)
            x[i] = x[i] + m[i] * (a[i] * e0 + b[i] * e1);
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = 0; j < n; j++)
                out[n * i + j] = p[n * i + j] - (a[i] * a[j] + b[i] * b[j]);
    } else {
        for (Py_ssize_t i = 0; i < n; i++)
            x[i] = x[i] + m[i] * a[i] * e0;
        for (Py_ssize_t i = 0; i < n; i++)
            for (Py_ssize_t j = 0; j < n; j++)
                out[n * i + j] = p[n * i + j] - a[i] * a[j];
    }
    for (Py_ssize_t f = 0; f < PyList_GET_SIZE(lfixed); f++) {
        Py_ssize_t k = PyLong_AsSsize_t(PyList_GET_ITEM(lfixed, f));
        if (k == -1 && PyErr_Occurred())
            return NULL;
        if (k < 0 || k >= n * n) {
            PyErr_Format(PyExc_IndexError, "fixed: index %zd out of range", k);
            return NULL;
        }
        out[k] = p[k];
    }
    if (put_all(lx, x, n) < 0 || put_all(lp, out, n * n) < 0)
        return NULL;
    return PyTuple_Pack(2, lx, lp);
}

static PyMethodDef methods[] = {
    {"propagate_cov", (PyCFunction)(void (*)(void))propagate_cov, METH_FASTCALL,
     "P = F P F' + diag(q) in place, F the identity but for the pose rows."},
    {"column_sum", (PyCFunction)(void (*)(void))column_sum, METH_FASTCALL,
     "(P[:, i] + P[:, j]) / c as a list."},
    {"wheel_columns", (PyCFunction)(void (*)(void))wheel_columns, METH_FASTCALL,
     "The two columns of P H' of the wheel measurement."},
    {"whiten", (PyCFunction)(void (*)(void))whiten, METH_FASTCALL,
     "(a, b): the columns [u w] times C^-T, C lower triangular."},
    {"fuse", (PyCFunction)(void (*)(void))fuse, METH_FASTCALL,
     "The EKF update of x and P from whitened columns, in place; returns (x, p)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "_ekf_kernel",
    .m_doc = "The EKF's covariance arithmetic in C (rover_bridge.estimate.ekf's PythonKernel is the reference).",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC PyInit__ekf_kernel(void)
{
    return PyModule_Create(&module);
}

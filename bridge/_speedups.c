/*
 * bridge._speedups -- the per-frame hot path in C (optional; pure Python is the reference).
 *
 * Why this exists: at 100 Hz the daemon's reader thread runs every frame "cold" (the
 * CPU halts between frames and the caches are cold when the next one arrives), so the
 * cost of a frame is the amount of interpreter code it runs, not the arithmetic. Two
 * pieces of that path are pure computation on a handful of numbers and are moved here:
 *
 *   decode_attitude_lines(data)   == bridge.protocol.gmr._decode_attitude_lines
 *   solve(consts, mx, my, mz, ax, ay, az)
 *                                 == the arithmetic of AttitudeEngine._finish/_assemble
 *
 * Each function is a line-by-line transcription of its Python twin and gives bit-identical
 * results: the same operations in the same order on IEEE doubles, the same libm calls that
 * CPython's math module makes, and no contraction of a*b+c into a fused multiply-add
 * (setup.py compiles with -ffp-contract=off; on aarch64 FMA would otherwise change the
 * last bit). tests/test_speedups.py checks the two against each other with hypothesis.
 * When this module is missing (no compiler at install time, or COMPASS_BRIDGE_PURE_PYTHON
 * set), the Python twins run instead.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

/* ------------------------------------------------------------------ $PGMRA decode */

/* Bound once by bind_attitude_frame(): the classes the Python fast path uses. */
static PyObject *slots_cls = NULL;   /* _AttitudeSlots: AttitudeFrame's layout, settable */
static PyObject *frame_cls = NULL;   /* AttitudeFrame */
static PyObject *flags_table = NULL; /* tuple: flags value -> Flags member */
static unsigned long seq_max = 0;

/* Attribute names, interned once. */
static PyObject *s_seq, *s_heading, *s_pitch, *s_roll, *s_mx, *s_my, *s_mz, *s_ax, *s_ay,
    *s_az, *s_flags, *s_class;
static PyObject *s_true, *s_magnetic;

static PyObject *
bind_attitude_frame(PyObject *self, PyObject *args)
{
    PyObject *slots, *frame, *table;
    unsigned long smax;
    if (!PyArg_ParseTuple(args, "OOO!k", &slots, &frame, &PyTuple_Type, &table, &smax))
        return NULL;
    Py_XSETREF(slots_cls, Py_NewRef(slots));
    Py_XSETREF(frame_cls, Py_NewRef(frame));
    Py_XSETREF(flags_table, Py_NewRef(table));
    seq_max = smax;
    Py_RETURN_NONE;
}

/* [0-9]{1,maxd} at *p (advanced); returns the value, -1 when the shape does not match. */
static long
digits(const char **p, const char *end, int maxd)
{
    const char *q = *p;
    long v = 0;
    int n = 0;
    while (q < end && *q >= '0' && *q <= '9') {
        if (++n > maxd)
            return -1;
        v = v * 10 + (*q - '0');
        q++;
    }
    if (n == 0)
        return -1;
    *p = q;
    return v;
}

/* (-)?[0-9]{1,maxd}\.[0-9] (minus only when signed) as a value in tenths; 0 on mismatch. */
static int
tenths(const char **p, const char *end, int maxd, int is_signed, long *out, int *negative)
{
    const char *q = *p;
    *negative = 0;
    if (is_signed && q < end && *q == '-') {
        *negative = 1;
        q++;
    }
    long whole = digits(&q, end, maxd);
    if (whole < 0 || q + 2 > end || q[0] != '.' || q[1] < '0' || q[1] > '9')
        return 0;
    *out = whole * 10 + (q[1] - '0');
    *p = q + 2;
    return 1;
}

static int
hexdigit(char c)
{
    if (c >= '0' && c <= '9')
        return c - '0';
    if (c >= 'A' && c <= 'F')
        return c - 'A' + 10;
    return -1;
}

/* A decimal with one fractional digit, as float() reads it: tenths / 10.0 is the correctly
 * rounded value of the exact decimal (both operands are exact doubles), which is what
 * float("12.3") returns too. The sign is applied after rounding, as float("-12.3") does. */
static double
tenths_value(long t, int negative)
{
    double v = (double)t / 10.0;
    return negative ? -v : v;
}

/* One line at [p, end): 1 and the frame's values on success, 0 when it is not a valid
 * fast-shape $PGMRA line (the caller then returns None). */
typedef struct {
    long seq, mx, my, mz, ax, ay, az;
    double heading, pitch, roll;
    int flags;
} attitude_t;

static int
parse_line(const char **pp, const char *end, attitude_t *f)
{
    const char *p = *pp;
    if (end - p < 7 || memcmp(p, "$PGMRA,", 7) != 0)
        return 0;
    const char *body = p + 1;
    p += 7;
    long t;
    int neg;
    if ((f->seq = digits(&p, end, 5)) < 0 || p >= end || *p++ != ',')
        return 0;
    if (!tenths(&p, end, 3, 0, &t, &neg) || p >= end || *p++ != ',')
        return 0;
    f->heading = tenths_value(t, neg);
    if (!tenths(&p, end, 2, 1, &t, &neg) || p >= end || *p++ != ',')
        return 0;
    f->pitch = tenths_value(t, neg) + 0.0; /* "+ 0.0": -0.0 -> 0.0, as the Python twin */
    if (!tenths(&p, end, 3, 1, &t, &neg))
        return 0;
    f->roll = tenths_value(t, neg) + 0.0;
    long *adc[6] = {&f->mx, &f->my, &f->mz, &f->ax, &f->ay, &f->az};
    for (int i = 0; i < 6; i++) {
        if (p >= end || *p++ != ',')
            return 0;
        if ((*adc[i] = digits(&p, end, 4)) < 0)
            return 0;
    }
    /* ,[01][0-9A-F]\*[0-9A-F]{2}\r?\n */
    if (end - p < 7 || p[0] != ',' || (p[1] != '0' && p[1] != '1'))
        return 0;
    int lo = hexdigit(p[2]);
    if (lo < 0 || p[3] != '*')
        return 0;
    f->flags = (p[1] - '0') * 16 + lo;
    const char *body_end = p + 3;
    int c1 = hexdigit(p[4]), c2 = hexdigit(p[5]);
    if (c1 < 0 || c2 < 0)
        return 0;
    p += 6;
    if (*p == '\r')
        p++;
    if (p >= end || *p != '\n')
        return 0;
    p++;
    /* The received checksum XORed with every body byte must cancel to 0. */
    int x = c1 * 16 + c2;
    for (const char *b = body; b < body_end; b++)
        x ^= (unsigned char)*b;
    if (f->heading >= 360.0) {
        if (f->heading != 360.0)
            return 0;
        f->heading = 0.0; /* tolerated rounding artefact, as in _decode_attitude */
    }
    if (!(x == 0 && (unsigned long)f->seq <= seq_max && -90.0 <= f->pitch && f->pitch <= 90.0 &&
          -180.0 <= f->roll && f->roll <= 180.0 &&
          (f->mx | f->my | f->mz | f->ax | f->ay | f->az) <= 0xFFF))
        return 0;
    *pp = p;
    return 1;
}

/* obj.name = value, taking the new reference ``value`` (NULL: the error is already set). */
static int
set_new(PyObject *o, PyObject *name, PyObject *value)
{
    if (value == NULL)
        return -1;
    int r = PyObject_SetAttr(o, name, value);
    Py_DECREF(value);
    return r;
}

static PyObject *
make_frame(const attitude_t *f)
{
    if (f->flags >= PyTuple_GET_SIZE(flags_table)) {
        PyErr_SetString(PyExc_ValueError, "flags value outside the bound flags table");
        return NULL;
    }
    PyObject *o = PyObject_CallNoArgs(slots_cls);
    if (o == NULL)
        return NULL;
    if (set_new(o, s_seq, PyLong_FromLong(f->seq)) < 0 ||
        set_new(o, s_heading, PyFloat_FromDouble(f->heading)) < 0 ||
        set_new(o, s_pitch, PyFloat_FromDouble(f->pitch)) < 0 ||
        set_new(o, s_roll, PyFloat_FromDouble(f->roll)) < 0 ||
        set_new(o, s_mx, PyLong_FromLong(f->mx)) < 0 ||
        set_new(o, s_my, PyLong_FromLong(f->my)) < 0 ||
        set_new(o, s_mz, PyLong_FromLong(f->mz)) < 0 ||
        set_new(o, s_ax, PyLong_FromLong(f->ax)) < 0 ||
        set_new(o, s_ay, PyLong_FromLong(f->ay)) < 0 ||
        set_new(o, s_az, PyLong_FromLong(f->az)) < 0 ||
        PyObject_SetAttr(o, s_flags, PyTuple_GET_ITEM(flags_table, f->flags)) < 0 ||
        PyObject_SetAttr(o, s_class, frame_cls) < 0) {
        Py_DECREF(o);
        return NULL;
    }
    return o;
}

static PyObject *
decode_attitude_lines(PyObject *self, PyObject *arg)
{
    if (slots_cls == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "bind_attitude_frame() was not called");
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0)
        return NULL;
    const char *p = view.buf;
    const char *end = p + view.len;
    PyObject *frames = PyList_New(0);
    attitude_t f;
    while (frames != NULL && p < end) {
        if (!parse_line(&p, end, &f)) {
            /* Not the fast case: None, as the Python twin (the frames so far are dropped). */
            Py_SETREF(frames, Py_NewRef(Py_None));
            break;
        }
        PyObject *frame = make_frame(&f);
        if (frame == NULL || PyList_Append(frames, frame) < 0)
            Py_CLEAR(frames);
        Py_XDECREF(frame);
    }
    PyBuffer_Release(&view);
    return frames;
}

/* ------------------------------------------------------------------ attitude */

/* CPython's math.degrees/radians constants (Modules/mathmodule.c); Py_MATH_PI is the
 * double math.pi holds. attitude.py's _DEG is 180.0 / math.pi: the same division. */
static const double DEG = 180.0 / Py_MATH_PI;
static const double RAD = Py_MATH_PI / 180.0;
static const double TWO_PI = 2.0 * Py_MATH_PI;

/* attitude._fold_360 */
static double
fold_360(double a)
{
    a = fmod(a, 360.0);
    if (a < 0.0)
        a += 360.0;
    return a >= 360.0 ? 0.0 : a;
}

/* Python's min(hi, v) and max(lo, v): the first argument unless the second compares
 * strictly less (greater), which is also what they do with a NaN. */
static double
clamp_unit(double v)
{
    double m = v < 1.0 ? v : 1.0;
    return m > -1.0 ? m : -1.0;
}

#define N_CONSTS 27

static PyObject *
tuple3(double a, double b, double c)
{
    return Py_BuildValue("(ddd)", a, b, c);
}

/* solve(consts, mx, my, mz, ax, ay, az) -> tuple | None
 *
 * consts: AttitudeEngine._State.consts, 27 entries:
 *   mo[3], mm[9], ao[3], am[9], sin_degraded, declination_deg (float or None), publish_true.
 * Returns None for non-finite vectors (the caller raises its ValueError), else
 *   (roll, pitch, yaw, heading_mag, heading_true | None, declination_deg | None, label,
 *    (qw, qx, qy, qz), (hx, hy, hz), (gx, gy, gz), bn, dip, degraded, gn):
 * AttitudeSolution's first 13 fields in order, then |g| for the quality flags.
 */
static PyObject *
solve(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "solve() takes consts and six counts");
        return NULL;
    }
    PyObject *consts = args[0];
    if (!PyTuple_Check(consts) || PyTuple_GET_SIZE(consts) != N_CONSTS) {
        PyErr_SetString(PyExc_TypeError, "solve(): consts must be a 27-tuple");
        return NULL;
    }
    double c[25];
    for (int i = 0; i < 25; i++) {
        c[i] = PyFloat_AsDouble(PyTuple_GET_ITEM(consts, i));
        if (c[i] == -1.0 && PyErr_Occurred())
            return NULL;
    }
    PyObject *decl_obj = PyTuple_GET_ITEM(consts, 25);
    int publish_true = PyObject_IsTrue(PyTuple_GET_ITEM(consts, 26));
    if (publish_true < 0)
        return NULL;
    double in[6];
    for (int i = 0; i < 6; i++) {
        in[i] = PyFloat_AsDouble(args[i + 1]);
        if (in[i] == -1.0 && PyErr_Occurred())
            return NULL;
    }
    const double *mo = c, *m = c + 3, *ao = c + 12, *a = c + 15;
    double sin_degraded = c[24];

    /* solve_counts */
    double dx = in[0] - mo[0], dy = in[1] - mo[1], dz = in[2] - mo[2];
    double hx = m[0] * dx + m[1] * dy + m[2] * dz;
    double hy = m[3] * dx + m[4] * dy + m[5] * dz;
    double hz = m[6] * dx + m[7] * dy + m[8] * dz;
    double ex = in[3] - ao[0], ey = in[4] - ao[1], ez = in[5] - ao[2];
    double gx = a[0] * ex + a[1] * ey + a[2] * ez;
    double gy = a[3] * ex + a[4] * ey + a[5] * ez;
    double gz = a[6] * ex + a[7] * ey + a[8] * ez;
    if (!isfinite(hx + hy + hz + gx + gy + gz))
        Py_RETURN_NONE;

    /* _finish */
    double gn = sqrt(gx * gx + gy * gy + gz * gz);
    double bn = sqrt(hx * hx + hy * hy + hz * hz);
    int degraded = 0;
    double pitch, roll, sp, cp, sr, cr, dip;
    if (gn > 1e-6) {
        sp = -gx / gn;
        if (sp > 1.0)
            sp = 1.0;
        else if (sp < -1.0)
            sp = -1.0;
        pitch = asin(sp);
        double ryz = sqrt(gy * gy + gz * gz);
        if (ryz > 0.0) {
            roll = atan2(gy, gz);
            sr = gy / ryz;
            cr = gz / ryz;
        }
        else {
            roll = 0.0;
            sr = 0.0;
            cr = 1.0;
        }
        cp = ryz / gn;
        dip = bn > 0.0 ? asin(clamp_unit((hx * gx + hy * gy + hz * gz) / (gn * bn))) * DEG : 0.0;
        if (fabs(sp) > sin_degraded || gn < 0.2)
            degraded = 1;
    }
    else {
        pitch = roll = 0.0;
        sp = 0.0;
        cp = 1.0;
        sr = 0.0;
        cr = 1.0;
        dip = 0.0;
        degraded = 1;
    }
    double xh = hx * cp + hy * sp * sr + hz * sp * cr;
    double yh = hy * cr - hz * sr;
    double horizontal_min = 0.02 * bn;
    if (bn == 0.0 || (xh * xh + yh * yh) < horizontal_min * horizontal_min)
        degraded = 1;
    double heading_mag = atan2(-yh, xh) * DEG;
    if (heading_mag < 0.0) {
        heading_mag += 360.0;
        if (heading_mag >= 360.0)
            heading_mag = 0.0;
    }

    /* _assemble (all but the quality flags) */
    int have_true = 0;
    double heading_true = 0.0;
    if (decl_obj != Py_None) {
        double decl = PyFloat_AsDouble(decl_obj);
        if (decl == -1.0 && PyErr_Occurred())
            return NULL;
        have_true = 1;
        heading_true = heading_mag + decl;
        if (heading_true >= 360.0)
            heading_true -= 360.0;
        else if (heading_true < 0.0)
            heading_true += 360.0;
        if (!(0.0 <= heading_true && heading_true < 360.0))
            heading_true = fold_360(heading_true);
    }
    double published;
    PyObject *label;
    if (publish_true && have_true) {
        published = heading_true;
        label = s_true;
    }
    else {
        published = heading_mag;
        label = s_magnetic;
    }
    double yaw = published * RAD;
    if (yaw > Py_MATH_PI)
        yaw -= TWO_PI;
    double hr = 0.5 * roll, hp = 0.5 * pitch, hyw = 0.5 * yaw;
    double cr2 = cos(hr), sr2 = sin(hr);
    double cp2 = cos(hp), sp2 = sin(hp);
    double cy2 = cos(hyw), sy2 = sin(hyw);
    double qw = cr2 * cp2 * cy2 + sr2 * sp2 * sy2;
    double qx = sr2 * cp2 * cy2 - cr2 * sp2 * sy2;
    double qy = cr2 * sp2 * cy2 + sr2 * cp2 * sy2;
    double qz = cr2 * cp2 * sy2 - sr2 * sp2 * cy2;
    if (qw < 0.0) {
        qw = -qw;
        qx = -qx;
        qy = -qy;
        qz = -qz;
    }

    PyObject *ht = have_true ? PyFloat_FromDouble(heading_true) : Py_NewRef(Py_None);
    PyObject *q = Py_BuildValue("(dddd)", qw, qx, qy, qz);
    PyObject *h = tuple3(hx, hy, hz);
    PyObject *g = tuple3(gx, gy, gz);
    PyObject *out = NULL;
    if (ht != NULL && q != NULL && h != NULL && g != NULL)
        out = Py_BuildValue("(ddddOOONNNddNd)", roll, pitch, yaw, heading_mag, ht, decl_obj,
                            label, q, h, g, bn, dip, PyBool_FromLong(degraded), gn);
    else {
        Py_XDECREF(q);
        Py_XDECREF(h);
        Py_XDECREF(g);
    }
    /* "N" stole q, h, g and the bool (also on failure); "O" did not take ht. */
    Py_XDECREF(ht);
    return out;
}

/* ------------------------------------------------------------------ module */

static PyMethodDef methods[] = {
    {"bind_attitude_frame", bind_attitude_frame, METH_VARARGS,
     "bind_attitude_frame(slots_cls, frame_cls, flags_table, seq_max): the classes "
     "decode_attitude_lines builds frames with."},
    {"decode_attitude_lines", decode_attitude_lines, METH_O,
     "decode_attitude_lines(data) -> list | None: bridge.protocol.gmr._decode_attitude_lines."},
    {"solve", (PyCFunction)(void (*)(void))solve, METH_FASTCALL,
     "solve(consts, mx, my, mz, ax, ay, az) -> tuple | None: the arithmetic of "
     "AttitudeEngine._finish and _assemble."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "bridge._speedups",
    .m_doc = "The per-frame hot path in C; pure-Python twins in bridge.protocol.gmr and "
             "bridge.core.attitude are the reference.",
    .m_size = -1,
    .m_methods = methods,
};

PyMODINIT_FUNC
PyInit__speedups(void)
{
    struct {
        PyObject **slot;
        const char *name;
    } names[] = {
        {&s_seq, "seq"},     {&s_heading, "heading"}, {&s_pitch, "pitch"}, {&s_roll, "roll"},
        {&s_mx, "mx"},       {&s_my, "my"},           {&s_mz, "mz"},       {&s_ax, "ax"},
        {&s_ay, "ay"},       {&s_az, "az"},           {&s_flags, "flags"}, {&s_class, "__class__"},
        {&s_true, "true"},   {&s_magnetic, "magnetic"},
    };
    for (size_t i = 0; i < sizeof(names) / sizeof(names[0]); i++) {
        *names[i].slot = PyUnicode_InternFromString(names[i].name);
        if (*names[i].slot == NULL)
            return NULL;
    }
    return PyModule_Create(&module);
}

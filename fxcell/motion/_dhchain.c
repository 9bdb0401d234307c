/* fxcell.motion._dhchain: the calibrated UR arm's DH chain in C (hatch_build.py builds it).
 *
 * The same computations as fxcell.motion.kinematics.DHChain, in the same order of floating
 * operations (built with -ffp-contract=off, so no fused multiply-adds): forward kinematics,
 * the geometric Jacobian, Newton steps with a damped fallback, Marquardt's
 * Levenberg-Marquardt and the search along the wrist's self-motion (`valley`), plus
 * `nearest`, which refines a list of nominal starts and returns the solution nearest a seed
 * (each joint 2π-shifted toward it within the limits) in one call. DHChain in Python is the fallback where this extension is not built;
 * tests/test_native.py checks that both give the same results.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

/* The calibrated inverse's hot path (Chain.hot_path sets it; see Chain.fast): the nominal
 * model's closed form for the starts and the settings of the refinement. */
typedef struct {
    int ready, tcp_identity;
    double geom[6]; /* nominal d1, d4, d5, d6, a2, a3 */
    double tcp[12], tcp_inv[12];
    double start_lower[6], start_upper[6], lower[6], upper[6];
    long newton_iterations, settle_iterations;
    double converged, rounding, stationary, accepted, factor, near, singular_move;
    double lenient_h2, lenient_c3, edge_c3, lenient_wrist, wrist_eps;
    int branches;
} Hot;

typedef struct {
    PyObject_HEAD
    double theta[6], a[6], d[6], ca[6], sa[6], tcp[12];
    Hot hot;
} Chain;

static const double TWO_PI = 6.283185307179586;
static const double INV_TWO_PI = 0.15915494309189535;
static const double LIMIT_EPS = 1e-12;  /* as kinematics._LIMIT_EPS */
static const double FINAL_STEP = 1e-7;  /* as kinematics._FINAL_STEP */
static const double WRIST_MOVE = 0.1;   /* as kinematics._WRIST_MOVE */
#define VALLEY_POINTS 12                /* as kinematics._VALLEY_POINTS */
static const int VALLEY_PROJECTIONS = 1;  /* as kinematics._VALLEY_PROJECTIONS */
static const int VALLEY_STEPS = 30;       /* as kinematics._VALLEY_STEPS */
static const int VALLEY_HALVINGS = 5;    /* as kinematics._VALLEY_HALVINGS */
static const double VALLEY_NEAR = 0.05;    /* as kinematics._VALLEY_NEAR */
static const double VALLEY_FINISH = 1e-5; /* as kinematics._VALLEY_FINISH */
static const double VALLEY_FLOOR = 1e-2;  /* as kinematics._VALLEY_FLOOR */
static const double VALLEY_PREDICT = 0.3; /* as kinematics._VALLEY_PREDICT */
static const double VALLEY_SAME = 0.25;   /* as kinematics._VALLEY_SAME */
static const long VALLEY_TRIES = 6;       /* as kinematics._VALLEY_TRIES */
static const double VALLEY_ON = 0.1;      /* as kinematics._VALLEY_ON */
#define MAX_WALKED 16                    /* as kinematics._MAX_WALKED */
#define STALL_STEPS 8                    /* as kinematics._STALL_STEPS */
#define QUICK_STALL 3                    /* as kinematics._QUICK_STALL */
static const double STALL_GAIN = 1e-3;    /* as kinematics._STALL_GAIN */
static const double STALL_FLOOR = 1e-7;   /* as kinematics._STALL_FLOOR */
static const double STALL_DONE = 1e-10;   /* as kinematics._STALL_DONE */
static const long VALLEY_REJECTIONS = 3;  /* as kinematics._VALLEY_REJECTIONS */
static const int VALLEY_OFF = 2;          /* as kinematics._VALLEY_OFF */
static const double VALLEY_CUTS = 0.01;   /* as kinematics._VALLEY_CUTS */

/* ------------------------------------------------------------------ conversions */

static int
read_floats(PyObject *obj, double *out, Py_ssize_t n, const char *what)
{
    PyObject *seq = PySequence_Fast(obj, what);
    if (seq == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(seq) != n) {
        PyErr_Format(PyExc_ValueError, "%s: %zd values expected, got %zd", what, n,
                     PySequence_Fast_GET_SIZE(seq));
        Py_DECREF(seq);
        return -1;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (Py_ssize_t i = 0; i < n; i++) {
        double v = PyFloat_AsDouble(items[i]);
        if (v == -1.0 && PyErr_Occurred()) {
            Py_DECREF(seq);
            return -1;
        }
        out[i] = v;
    }
    Py_DECREF(seq);
    return 0;
}

static PyObject *
float_list(const double *v, Py_ssize_t n)
{
    PyObject *out = PyList_New(n);
    if (out == NULL)
        return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *f = PyFloat_FromDouble(v[i]);
        if (f == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, f);
    }
    return out;
}

/* ------------------------------------------------------------------ the chain */

static void
evaluate(const Chain *c, const double *q, double *out, double *jac)
{
    double xx = 1.0, xy = 0.0, xz = 0.0;
    double yx = 0.0, yy = 1.0, yz = 0.0;
    double zx = 0.0, zy = 0.0, zz = 1.0;
    double ox = 0.0, oy = 0.0, oz = 0.0;
    double axes[36];
    for (int j = 0; j < 6; j++) {
        int k = 6 * j;
        axes[k] = zx;
        axes[k + 1] = zy;
        axes[k + 2] = zz;
        axes[k + 3] = ox;
        axes[k + 4] = oy;
        axes[k + 5] = oz;
        double t = q[j] + c->theta[j];
        double ct = cos(t), st = sin(t);
        double ca = c->ca[j], sa = c->sa[j], a = c->a[j], d = c->d[j];
        double ux = ct * xx + st * yx, uy = ct * xy + st * yy, uz = ct * xz + st * yz;
        double vx = ct * yx - st * xx, vy = ct * yy - st * xy, vz = ct * yz - st * xz;
        ox = ox + a * ux + d * zx;
        oy = oy + a * uy + d * zy;
        oz = oz + a * uz + d * zz;
        xx = ux;
        xy = uy;
        xz = uz;
        double nyx = ca * vx + sa * zx, nyy = ca * vy + sa * zy, nyz = ca * vz + sa * zz;
        double nzx = ca * zx - sa * vx, nzy = ca * zy - sa * vy, nzz = ca * zz - sa * vz;
        yx = nyx;
        yy = nyy;
        yz = nyz;
        zx = nzx;
        zy = nzy;
        zz = nzz;
    }
    const double *T = c->tcp;
    double px = ox + xx * T[9] + yx * T[10] + zx * T[11];
    double py = oy + xy * T[9] + yy * T[10] + zy * T[11];
    double pz = oz + xz * T[9] + yz * T[10] + zz * T[11];
    out[0] = xx * T[0] + yx * T[3] + zx * T[6];
    out[1] = xx * T[1] + yx * T[4] + zx * T[7];
    out[2] = xx * T[2] + yx * T[5] + zx * T[8];
    out[3] = xy * T[0] + yy * T[3] + zy * T[6];
    out[4] = xy * T[1] + yy * T[4] + zy * T[7];
    out[5] = xy * T[2] + yy * T[5] + zy * T[8];
    out[6] = xz * T[0] + yz * T[3] + zz * T[6];
    out[7] = xz * T[1] + yz * T[4] + zz * T[7];
    out[8] = xz * T[2] + yz * T[5] + zz * T[8];
    out[9] = px;
    out[10] = py;
    out[11] = pz;
    if (jac != NULL) {
        for (int j = 0; j < 6; j++) {
            int k = 6 * j;
            double ax = axes[k], ay = axes[k + 1], az = axes[k + 2];
            double rx = px - axes[k + 3], ry = py - axes[k + 4], rz = pz - axes[k + 5];
            jac[j] = ay * rz - az * ry;
            jac[6 + j] = az * rx - ax * rz;
            jac[12 + j] = ax * ry - ay * rx;
            jac[18 + j] = ax;
            jac[24 + j] = ay;
            jac[30 + j] = az;
        }
    }
}

static void
twist_to(const double *f, const double *t, double *e)
{
    double a00 = f[0], a01 = f[1], a02 = f[2], a10 = f[3], a11 = f[4], a12 = f[5];
    double a20 = f[6], a21 = f[7], a22 = f[8];
    double b00 = t[0], b01 = t[1], b02 = t[2], b10 = t[3], b11 = t[4], b12 = t[5];
    double b20 = t[6], b21 = t[7], b22 = t[8];
    double e01 = b00 * a10 + b01 * a11 + b02 * a12;
    double e02 = b00 * a20 + b01 * a21 + b02 * a22;
    double e10 = b10 * a00 + b11 * a01 + b12 * a02;
    double e12 = b10 * a20 + b11 * a21 + b12 * a22;
    double e20 = b20 * a00 + b21 * a01 + b22 * a02;
    double e21 = b20 * a10 + b21 * a11 + b22 * a12;
    double trace = b00 * a00 + b01 * a01 + b02 * a02 + b10 * a10 + b11 * a11 + b12 * a12 +
                   b20 * a20 + b21 * a21 + b22 * a22;
    double wx = 0.5 * (e21 - e12), wy = 0.5 * (e02 - e20), wz = 0.5 * (e10 - e01);
    double s = sqrt(wx * wx + wy * wy + wz * wz);
    double scale = s > 1e-300 ? atan2(s, 0.5 * (trace - 1.0)) / s : 1.0;
    e[0] = t[9] - f[9];
    e[1] = t[10] - f[10];
    e[2] = t[11] - f[11];
    e[3] = scale * wx;
    e[4] = scale * wy;
    e[5] = scale * wz;
}

static double
norm6(const double *v)
{
    return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3] + v[4] * v[4] +
                v[5] * v[5]);
}

/* J x = rhs (lam 0), or the damped least squares (JᵀJ + lam·I) x = Jᵀ rhs (scaled:
 * Marquardt's lam·(diag(JᵀJ) + 1e-12)); 0 if singular to rounding. */
static int
solve6(const double *jac, const double *rhs, double lam, int scaled, double *x)
{
    double m[42];
    if (lam == 0.0 && !scaled) {
        for (int i = 0; i < 6; i++) {
            for (int k = 0; k < 6; k++)
                m[7 * i + k] = jac[6 * i + k];
            m[7 * i + 6] = rhs[i];
        }
    }
    else {
        for (int i = 0; i < 6; i++) {
            for (int k = i; k < 6; k++) {
                double acc = 0.0;
                for (int r = 0; r < 6; r++)
                    acc += jac[6 * r + i] * jac[6 * r + k];
                m[7 * i + k] = acc;
                m[7 * k + i] = acc;
            }
            m[7 * i + i] += scaled ? lam * (m[7 * i + i] + 1e-12) : lam;
            double acc = 0.0;
            for (int r = 0; r < 6; r++)
                acc += jac[6 * r + i] * rhs[r];
            m[7 * i + 6] = acc;
        }
    }
    for (int c = 0; c < 6; c++) {
        int p = c;
        double big = fabs(m[7 * c + c]);
        for (int r = c + 1; r < 6; r++) {
            double v = fabs(m[7 * r + c]);
            if (v > big) {
                p = r;
                big = v;
            }
        }
        if (big < 1e-300)
            return 0;
        if (p != c) {
            for (int k = c; k < 7; k++) {
                double tmp = m[7 * c + k];
                m[7 * c + k] = m[7 * p + k];
                m[7 * p + k] = tmp;
            }
        }
        double inv_p = 1.0 / m[7 * c + c];
        for (int r = c + 1; r < 6; r++) {
            double f = m[7 * r + c] * inv_p;
            if (f != 0.0)
                for (int k = c + 1; k < 7; k++)
                    m[7 * r + k] -= f * m[7 * c + k];
        }
    }
    for (int c = 5; c >= 0; c--) {
        double acc = m[7 * c + 6];
        for (int k = c + 1; k < 6; k++)
            acc -= m[7 * c + k] * x[k];
        double v = acc / m[7 * c + c];
        if (v - v != 0.0)
            return 0;
        x[c] = v;
    }
    return 1;
}

static double
gradient_ratio(const double *jac, const double *err, double norm)
{
    double grad = 0.0, size = 0.0;
    for (int k = 0; k < 6; k++) {
        double acc = 0.0;
        for (int r = 0; r < 6; r++) {
            double v = jac[6 * r + k];
            acc += v * err[r];
            size += v * v;
        }
        grad += acc * acc;
    }
    double scale = sqrt(size) * norm;
    return scale > 0.0 ? sqrt(grad) / scale : 0.0;
}

/* Newton's steps from q (updated in place) toward target; the error norm left (after a
 * final step shorter than FINAL_STEP, the step's length squared); with rejections > 0 the
 * steps stop at that many rejected ones (DHChain.newton). */
static double
newton(const Chain *c, double *q, const double *target, long iterations, double converged,
       double rounding, long rejections)
{
    long rejected = 0;
    double frame[12], jac[36], err[6], step[6], trial[6], tjac[36], terr[6];
    evaluate(c, q, frame, jac);
    twist_to(frame, target, err);
    double norm = norm6(err), lam = 0.0;
    for (long it = 0; it < iterations; it++) {
        if (norm < converged)
            break;
        if (!solve6(jac, err, lam, 0, step)) {
            lam = lam > 1e-9 ? lam : 1e-9;
            continue;
        }
        double size = norm6(step);
        if (lam == 0.0 && size < FINAL_STEP) {
            /* a full Newton step this short leaves an error of its square's order, far
             * below converged: taken without evaluating the chain again */
            for (int k = 0; k < 6; k++)
                q[k] += step[k];
            return size * size;
        }
        for (int k = 0; k < 6; k++)
            trial[k] = q[k] + step[k];
        evaluate(c, trial, frame, tjac);
        twist_to(frame, target, terr);
        double tnorm = norm6(terr);
        if (tnorm < norm) {
            memcpy(q, trial, sizeof trial);
            memcpy(jac, tjac, sizeof tjac);
            memcpy(err, terr, sizeof terr);
            norm = tnorm;
            lam = lam > 1e-9 ? lam * 0.1 : 0.0;
        }
        else {
            if (norm < rounding)
                break;
            if (++rejected == rejections)
                break;
            lam = lam == 0.0 ? 1e-6 : lam * 10.0;
            if (lam > 1.0)
                break;
        }
    }
    return norm;
}

/* The gain ratio of Marquardt's step (kinematics._gain_ratio). */
static double
gain_ratio(const double *jac, const double *err, const double *step, double lam, double norm,
           double tnorm)
{
    double predicted = 0.0;
    for (int i = 0; i < 6; i++) {
        double g = 0.0, dd = 0.0;
        for (int r = 0; r < 6; r++) {
            double v = jac[6 * r + i];
            g += v * err[r];
            dd += v * v;
        }
        predicted += step[i] * (g + lam * (dd + 1e-12) * step[i]);
    }
    predicted *= 0.5;
    double actual = 0.5 * (norm * norm - tnorm * tnorm);
    return predicted > 0.0 ? actual / predicted : -1.0;
}

/* Marquardt's Levenberg-Marquardt from q (in place), a stall judged over window steps, the
 * damping updated by Nielsen's rule if adaptive (DHChain.settle); the error norm left, and the
 * stationarity ratio in *gradient. */
static double
settle(const Chain *c, double *q, const double *target, long iterations, double converged,
       double stationary, int window, int adaptive, double *gradient)
{
    double frame[12], jac[36], err[6], step[6], trial[6], tjac[36], terr[6];
    evaluate(c, q, frame, jac);
    twist_to(frame, target, err);
    double norm = norm6(err);
    double g = gradient_ratio(jac, err, norm);
    double lam = 1e-3, grow = 2.0, mark = norm;
    for (long it = 0; it < iterations; it++) {
        if (norm < converged || g < stationary)
            break;
        if (stationary > 0.0 && it > 0 && it % window == 0) {
            if (norm > STALL_FLOOR && norm > (1.0 - STALL_GAIN) * mark) {
                g = 0.0; /* stalled far from a root: a local minimum's basin */
                break;
            }
            if (norm < STALL_DONE && norm > 0.5 * mark)
                break; /* crawling into a singular root: close enough */
            mark = norm;
        }
        if (!solve6(jac, err, lam, 1, step)) {
            lam *= 5.0;
            if (lam > 1e9)
                break;
            continue;
        }
        for (int k = 0; k < 6; k++)
            trial[k] = q[k] + step[k];
        evaluate(c, trial, frame, tjac);
        twist_to(frame, target, terr);
        double tnorm = norm6(terr);
        if (tnorm < norm) {
            if (adaptive) {
                double t = 2.0 * gain_ratio(jac, err, step, lam, norm, tnorm) - 1.0;
                double f = 1.0 - t * t * t;
                if (f < 1.0 / 3.0)
                    f = 1.0 / 3.0;
                lam = lam * f > 1e-9 ? lam * f : 1e-9;
                grow = 2.0;
            }
            else
                lam = lam * 0.2 > 1e-9 ? lam * 0.2 : 1e-9;
            memcpy(q, trial, sizeof trial);
            memcpy(jac, tjac, sizeof tjac);
            memcpy(err, terr, sizeof terr);
            norm = tnorm;
            g = gradient_ratio(jac, err, norm);
        }
        else {
            if (adaptive) {
                lam *= grow;
                grow *= 2.0;
            }
            else
                lam *= 5.0;
            if (lam > 1e9)
                break;
        }
    }
    *gradient = g;
    return norm;
}

/* q (in place) toward the valley's floor: Gauss-Newton steps on θ1..θ5 with θ6 held
 * (DHChain._project); jac, err and the returned norm are those at q. */
static double
project(const Chain *c, double *q, const double *target, double *jac, double *err)
{
    double frame[12], held[36], x[6], trial[6], tjac[36], terr[6];
    evaluate(c, q, frame, jac);
    twist_to(frame, target, err);
    double norm = norm6(err);
    for (int p = 0; p < VALLEY_PROJECTIONS; p++) {
        memcpy(held, jac, sizeof held);
        for (int r = 0; r < 6; r++)
            held[6 * r + 5] = 0.0;
        if (!solve6(held, err, 1e-12, 0, x))
            break;
        for (int k = 0; k < 6; k++)
            trial[k] = q[k] + x[k];
        evaluate(c, trial, frame, tjac);
        twist_to(frame, target, terr);
        double tnorm = norm6(terr);
        if (!(tnorm < norm))
            break;
        memcpy(q, trial, sizeof trial);
        memcpy(jac, tjac, sizeof tjac);
        memcpy(err, terr, sizeof terr);
        norm = tnorm;
    }
    return norm;
}

/* The root of the valley between points lower and upper (θ6 increasing) into q
 * (DHChain._close); its error norm. */
static double
close_root(const Chain *c, const double *lower, const double *upper, const double *target,
           double converged, double *q)
{
    double jac[36], err[6], step[6];
    double lo = lower[5], hi = upper[5];
    int halved = 0;
    memcpy(q, lower, 6 * sizeof(double));
    double norm = project(c, q, target, jac, err);
    for (int it = 0; it < VALLEY_STEPS; it++) {
        if (norm < converged)
            break;
        if (!solve6(jac, err, 0.0, 0, step))
            break;
        if (step[5] > 0.0)
            lo = q[5];
        else
            hi = q[5];
        double t = q[5] + step[5];
        if (lo < t && t < hi) { /* Newton's step: near the root it needs no projection */
            for (int k = 0; k < 6; k++)
                q[k] = q[k] + step[k];
            double size = norm6(step);
            if (size < FINAL_STEP)
                return size * size; /* as in newton: an error of the step's square */
            double frame[12];
            evaluate(c, q, frame, jac);
            twist_to(frame, target, err);
            norm = norm6(err);
        }
        else {
            if (++halved > VALLEY_HALVINGS)
                break; /* a minimum of the error between the points, not a root */
            q[5] = 0.5 * (lo + hi);
            norm = project(c, q, target, jac, err);
        }
    }
    if (converged <= norm && norm < VALLEY_FINISH) /* a step's sign misled the bracket */
        norm = newton(c, q, target, VALLEY_STEPS, converged, converged, 0);
    return norm;
}

/* Squared distance from seed with each joint's difference wrapped into [-π, π]. */
static double
free_distance(const double *q, const double *seed)
{
    double d = 0.0;
    for (int k = 0; k < 6; k++) {
        double w = q[k] - seed[k];
        w -= TWO_PI * nearbyint(w * INV_TWO_PI);
        d += w * w;
    }
    return d;
}

/* Euclidean distance of joints a and b, each joint's difference wrapped into [-π, π]
 * (kinematics._wrapped_distance). */
static double
wrapped_distance(const double *a, const double *b)
{
    return sqrt(free_distance(a, b));
}

/* A lower bound of the wrapped distance from seed of any point on the segment between a and
 * b (kinematics._chord_bound). */
static double
chord_bound(const double *a, const double *b, const double *seed)
{
    return 0.5 *
           (wrapped_distance(a, seed) + wrapped_distance(b, seed) - wrapped_distance(a, b));
}

#define MAX_SAMPLES (VALLEY_POINTS + 2)
#define MAX_ROOTS (VALLEY_POINTS + 3 + MAX_SAMPLES)

#define HALF (VALLEY_POINTS / 2)

/* The solutions along the wrist's self-motion through q (DHChain._walk): up to MAX_ROOTS
 * joints into roots and their error norms into norms; their number. With pts not NULL, the
 * points on the floor by their turn from the origin (-HALF..HALF) into it, and *whole set to
 * whether every one was on the floor (the valley not cut). Roots that cannot be nearer seed
 * than bound are not looked for (as in DHChain._walk); next to the singularity (VALLEY_CUTS)
 * a side stops where it leaves the floor and the other goes on past HALF to that point. */
static int
valley(const Chain *c, const double *q, const double *target, double converged,
       const double *seed, double bound, double roots[][6], double *norms, double pts[][6],
       int *whole)
{
    int on_floor = 0;
    double h = TWO_PI / VALLEY_POINTS;
    double origin[6], origin_jac[36], origin_err[6];
    double qq[6], below[6], jac[36], err[6], step[6], held[36], column[6], tangent[6];
    double samples[MAX_SAMPLES][6], predicted[MAX_SAMPLES]; /* points on the floor, θ6's step */
    int n = 0, n_samples = 0;
    memcpy(origin, q, sizeof origin);
    double origin_norm = project(c, origin, target, origin_jac, origin_err);
    if (origin_norm < converged) {
        memcpy(roots[n], origin, sizeof origin);
        norms[n++] = origin_norm;
    }
    int last = HALF; /* the - side's last point: beyond HALF where the + side left the floor */
    int cuts = fabs(sin(q[4])) < VALLEY_CUTS; /* whether a side stops where it leaves the floor */
    for (int side = 0; side < 2; side++) {
        double sign = side ? -1.0 : 1.0, previous = 0.0, norm = origin_norm;
        int been_on = 0, off = 0; /* off: points off the floor in a row */
        memcpy(qq, origin, sizeof qq);
        memcpy(jac, origin_jac, sizeof jac);
        memcpy(err, origin_err, sizeof err);
        memcpy(below, qq, sizeof below);
        for (int point = 0; point <= (side ? last : HALF); point++) {
            if (point) {
                memcpy(held, jac, sizeof held);
                for (int r = 0; r < 6; r++) {
                    column[r] = -jac[6 * r + 5];
                    held[6 * r + 5] = 0.0;
                }
                if (!solve6(held, column, 1e-12, 0, tangent))
                    for (int k = 0; k < 6; k++)
                        tangent[k] = 0.0;
                tangent[5] = 1.0;
                for (int k = 0; k < 6; k++)
                    qq[k] = qq[k] + sign * h * tangent[k];
                norm = project(c, qq, target, jac, err);
                if (norm < converged) {
                    memcpy(roots[n], qq, sizeof qq);
                    norms[n++] = norm;
                    previous = 0.0;
                    been_on = 1;
                    off = 0;
                    continue;
                }
            }
            int ok = solve6(jac, err, 0.0, 0, step);
            if (norm > VALLEY_FLOOR || !ok) {
                previous = 0.0; /* off the floor (out of reach there): no bracket across */
                if (cuts && been_on && ++off == VALLEY_OFF) {
                    /* left the floor: the rest of this side is walked from the other */
                    if (!side)
                        last = VALLEY_POINTS - point;
                    break;
                }
                continue;
            }
            been_on = 1;
            off = 0;
            if ((point || sign > 0.0) && point <= HALF) {
                memcpy(samples[n_samples], qq, sizeof qq);
                predicted[n_samples++] = step[5];
                if (pts != NULL)
                    memcpy(pts[HALF + (sign > 0.0 ? point : -point)], qq, sizeof qq);
                on_floor++;
            }
            else if (point) {
                memcpy(samples[n_samples], qq, sizeof qq);
                predicted[n_samples++] = step[5];
            }
            if (sign * previous > 0.0 && sign * step[5] < 0.0 &&
                !(chord_bound(below, qq, seed) - WRIST_MOVE > bound)) {
                if (sign > 0.0)
                    norms[n] = close_root(c, below, qq, target, converged, roots[n]);
                else
                    norms[n] = close_root(c, qq, below, target, converged, roots[n]);
                n++;
            }
            previous = step[5];
            memcpy(below, qq, sizeof below);
        }
    }
    /* roots closer together than the points leave no sign change between them: a point whose
     * Newton step of θ6 predicts a root within VALLEY_PREDICT of the spacing, where no root
     * found is, gets VALLEY_TRIES Newton's steps */
    for (int i = 0; i < n_samples; i++) {
        double t = predicted[i];
        if (!(fabs(t) < VALLEY_PREDICT * h))
            continue;
        if (wrapped_distance(samples[i], seed) - 2.0 * fabs(t) - WRIST_MOVE > bound)
            continue; /* the predicted root cannot be nearer the seed than the best */
        double aim = samples[i][5] + t;
        int known = 0;
        for (int k = 0; k < n && !known; k++) {
            if (!(norms[k] < converged))
                continue;
            double w = roots[k][5] - aim;
            known = fabs(w - TWO_PI * nearbyint(w * INV_TWO_PI)) < VALLEY_SAME * h;
        }
        if (known)
            continue;
        memcpy(roots[n], samples[i], 6 * sizeof(double));
        norms[n] = newton(c, roots[n], target, VALLEY_TRIES, converged, converged, 0);
        if (norms[n] < converged)
            n++;
    }
    if (whole != NULL)
        *whole = on_floor == 2 * HALF + 1 && last == HALF;
    return n;
}

/* Whether q lies on the valley whose points pts are (a whole turn of θ6 on the floor):
 * θ1..θ5 within VALLEY_ON of the line between the two points whose θ6 enclose its own
 * (kinematics._on_walked). */
static int
on_walked(const double *q, double pts[][6])
{
    double h = TWO_PI / VALLEY_POINTS;
    double w = q[5] - pts[HALF][5];
    w -= TWO_PI * nearbyint(w * INV_TWO_PI);
    double u = w / h;
    double kf = floor(u);
    if (kf < -HALF || kf >= HALF)
        return 0;
    int k = (int)kf;
    const double *a = pts[HALF + k], *b = pts[HALF + k + 1];
    double f = u - kf;
    for (int j = 0; j < 5; j++) {
        double step = b[j] - a[j];
        step -= TWO_PI * nearbyint(step * INV_TWO_PI);
        double off = q[j] - (a[j] + f * step);
        off -= TWO_PI * nearbyint(off * INV_TWO_PI);
        if (!(fabs(off) < VALLEY_ON))
            return 0;
    }
    return 1;
}

/* The 2π-equivalent of v nearest s within [lo, hi], or NaN (kinematics._near). */
static double
near_angle(double v, double s, double lo, double hi)
{
    v += TWO_PI * nearbyint((s - v) * INV_TWO_PI);
    if (v > hi) {
        v = v - hi < LIMIT_EPS ? hi : v - TWO_PI * ceil((v - hi) * INV_TWO_PI);
        if (v < lo)
            return NAN;
    }
    else if (v < lo) {
        v = lo - v < LIMIT_EPS ? lo : v + TWO_PI * ceil((lo - v) * INV_TWO_PI);
        if (v > hi)
            return NAN;
    }
    return v;
}

/* ------------------------------------------------------------------ the Python type */

static int
Chain_init(Chain *self, PyObject *args, PyObject *kwds)
{
    PyObject *theta, *a, *d, *alpha, *tcp;
    double al[6];
    if (!PyArg_ParseTuple(args, "OOOOO:Chain", &theta, &a, &d, &alpha, &tcp))
        return -1;
    if (read_floats(theta, self->theta, 6, "theta") || read_floats(a, self->a, 6, "a") ||
        read_floats(d, self->d, 6, "d") || read_floats(alpha, al, 6, "alpha") ||
        read_floats(tcp, self->tcp, 12, "tcp"))
        return -1;
    for (int j = 0; j < 6; j++) {
        self->ca[j] = cos(al[j]);
        self->sa[j] = sin(al[j]);
    }
    return 0;
}

static PyObject *
Chain_frame(Chain *self, PyObject *arg)
{
    double q[6], f[12];
    if (read_floats(arg, q, 6, "q"))
        return NULL;
    evaluate(self, q, f, NULL);
    return float_list(f, 12);
}

static PyObject *
Chain_frame_and_jacobian(Chain *self, PyObject *arg)
{
    double q[6], f[12], jac[36];
    if (read_floats(arg, q, 6, "q"))
        return NULL;
    evaluate(self, q, f, jac);
    PyObject *frame = float_list(f, 12);
    if (frame == NULL)
        return NULL;
    PyObject *j = float_list(jac, 36);
    if (j == NULL) {
        Py_DECREF(frame);
        return NULL;
    }
    return Py_BuildValue("(NN)", frame, j);
}

static PyObject *
Chain_newton(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    double q[6], target[12];
    long iterations = 20;
    double converged = 1e-12, rounding = 1e-11;
    long rejections = 0;
    if (nargs < 2 || nargs > 6) {
        PyErr_SetString(PyExc_TypeError,
                        "newton(q, target, iterations, converged, rounding, rejections)");
        return NULL;
    }
    if (read_floats(args[0], q, 6, "q") || read_floats(args[1], target, 12, "target"))
        return NULL;
    if (nargs > 2 && (iterations = PyLong_AsLong(args[2])) == -1 && PyErr_Occurred())
        return NULL;
    if (nargs > 3 && (converged = PyFloat_AsDouble(args[3])) == -1.0 && PyErr_Occurred())
        return NULL;
    if (nargs > 4 && (rounding = PyFloat_AsDouble(args[4])) == -1.0 && PyErr_Occurred())
        return NULL;
    if (nargs > 5 && (rejections = PyLong_AsLong(args[5])) == -1 && PyErr_Occurred())
        return NULL;
    double norm = newton(self, q, target, iterations, converged, rounding, rejections);
    PyObject *out = float_list(q, 6);
    return out == NULL ? NULL : Py_BuildValue("(Nd)", out, norm);
}

static PyObject *
Chain_valley(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    double q[6], target[12], converged = 1e-12, roots[MAX_ROOTS][6], norms[MAX_ROOTS];
    if (nargs < 2 || nargs > 3) {
        PyErr_SetString(PyExc_TypeError, "valley(q, target, converged)");
        return NULL;
    }
    if (read_floats(args[0], q, 6, "q") || read_floats(args[1], target, 12, "target"))
        return NULL;
    if (nargs > 2 && (converged = PyFloat_AsDouble(args[2])) == -1.0 && PyErr_Occurred())
        return NULL;
    int n = valley(self, q, target, converged, q, INFINITY, roots, norms, NULL, NULL);
    PyObject *out = PyList_New(n);
    if (out == NULL)
        return NULL;
    for (int i = 0; i < n; i++) {
        PyObject *joints = float_list(roots[i], 6);
        PyObject *pair = joints == NULL ? NULL : Py_BuildValue("(Nd)", joints, norms[i]);
        if (pair == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, pair);
    }
    return out;
}

static PyObject *
Chain_settle(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    double q[6], target[12];
    long iterations = 60;
    double converged = 1e-12, stationary = 1e-6, gradient = 0.0;
    if (nargs < 2 || nargs > 5) {
        PyErr_SetString(PyExc_TypeError, "settle(q, target, iterations, converged, stationary)");
        return NULL;
    }
    if (read_floats(args[0], q, 6, "q") || read_floats(args[1], target, 12, "target"))
        return NULL;
    if (nargs > 2 && (iterations = PyLong_AsLong(args[2])) == -1 && PyErr_Occurred())
        return NULL;
    if (nargs > 3 && (converged = PyFloat_AsDouble(args[3])) == -1.0 && PyErr_Occurred())
        return NULL;
    if (nargs > 4 && (stationary = PyFloat_AsDouble(args[4])) == -1.0 && PyErr_Occurred())
        return NULL;
    double norm =
        settle(self, q, target, iterations, converged, stationary, STALL_STEPS, 0, &gradient);
    PyObject *out = float_list(q, 6);
    return out == NULL ? NULL : Py_BuildValue("(Ndd)", out, norm, gradient);
}

/* Next to which singularities target g is, whatever the joints (with the chain's own d4, d6
 * and TCP): 1 if its wrist centre is within near·d4 of the shoulder singularity (h² below
 * (near·d4)², h its distance from the plane of axes 1 and 2), 2 if the wrist is (|sin θ5|
 * below near) for either shoulder, 3 both, 0 neither. */
static int
singular_target(const Chain *c, const double *g, double near)
{
    const double *T = c->tcp;
    /* flange = goal · tcp⁻¹: R_f = R_g·R_tᵀ, p_f = p_g - R_f·p_t */
    double f[9], pf[3];
    for (int r = 0; r < 3; r++) {
        const double *row = g + 3 * r;
        f[3 * r] = row[0] * T[0] + row[1] * T[1] + row[2] * T[2];
        f[3 * r + 1] = row[0] * T[3] + row[1] * T[4] + row[2] * T[5];
        f[3 * r + 2] = row[0] * T[6] + row[1] * T[7] + row[2] * T[8];
        pf[r] = g[9 + r] - (f[3 * r] * T[9] + f[3 * r + 1] * T[10] + f[3 * r + 2] * T[11]);
    }
    double d4 = c->d[3];
    double x = pf[0] - c->d[5] * f[2], y = pf[1] - c->d[5] * f[5];
    double rho2 = x * x + y * y;
    double h2 = rho2 - d4 * d4;
    int out = h2 < near * near * d4 * d4 ? 1 : 0;
    double h = h2 > 0.0 ? sqrt(h2) : 0.0;
    if (rho2 > 0.0) {
        for (int side = 0; side < 2; side++) {
            double hs = side ? -h : h;
            double c1 = (x * hs - y * d4) / rho2, s1 = (y * hs + x * d4) / rho2;
            double zx = f[0] * s1 - f[3] * c1, zy = f[1] * s1 - f[4] * c1;
            if (zx * zx + zy * zy < near * near)
                out |= 2;
        }
    }
    return out;
}

/* Next to the wrist singularity (sin θ5 ≈ 0) refinement can turn θ2, θ3, θ4 and θ6 far
 * (the arm's self-motion there), but θ1 and θ5 only by the deltas' order: a lower bound of the
 * distance from seed of any solution it reaches, with WRIST_MOVE rad for those moves. */
static double
wrist_bound(const double *start, const double *seed)
{
    double w1 = start[0] - seed[0], w5 = start[4] - seed[4];
    w1 -= TWO_PI * nearbyint(w1 * INV_TWO_PI);
    w5 -= TWO_PI * nearbyint(w5 * INV_TWO_PI);
    return sqrt(w1 * w1 + w5 * w5) - WRIST_MOVE;
}

#define MAX_STARTS 64

/* DHChain.nearest on starts[0..n) (joints only): the best joints into best (returns whether
 * any), their distance² into *best_d, the largest move, the smallest distance of a start that
 * neither converged nor reached a local minimum, and singular_target's flags. */
static int
nearest_core(const Chain *self, double starts[][6], Py_ssize_t n, const double *target,
             const double *seed, const double *lower, const double *upper, long n_newton,
             long n_settle, double converged, double rounding, double stationary,
             double accepted, double factor, double near, double *best, double *best_d_out,
             double *moved_out, double *unrefined_out, int *singular_out)
{
    double distance[MAX_STARTS];
    int order[MAX_STARTS];
    for (Py_ssize_t i = 0; i < n; i++) {
        distance[i] = sqrt(free_distance(starts[i], seed));
        /* insertion sort by distance (stable: ties keep the caller's order) */
        Py_ssize_t k = i;
        while (k > 0 && distance[order[k - 1]] > distance[i]) {
            order[k] = order[k - 1];
            k--;
        }
        order[k] = (int)i;
    }
    int singular_at = singular_target(self, target, near);
    int shoulder = singular_at & 1;
    double best_d = INFINITY, moved = 0.0, regular = 0.0, unrefined = INFINITY;
    int found_any = 0;
    int missed[MAX_STARTS]; /* starts whose valley walk found no root */
    double walked[MAX_WALKED][2 * HALF + 1][6]; /* the points of the valleys walked whole */
    int n_walked = 0;
    Py_ssize_t n_missed = 0, n_pending = n;
    const int *pending = order;
    int retry = 0;
    for (;;) {
        for (Py_ssize_t r = 0; r < n_pending; r++) {
            int i = pending[r];
            const double *start = starts[i];
            int singular =
                shoulder || fabs(sin(start[2])) < near || fabs(sin(start[4])) < near;
            double q[6];
            double found[MAX_ROOTS + 1][6], norms[MAX_ROOTS];
            int n_found = 0;
            memcpy(q, start, sizeof q);
            if (!retry) {
                if (found_any && !singular &&
                    distance[i] > sqrt(best_d) + factor * regular + 1e-9)
                    continue; /* it cannot come nearer */
                if (found_any && shoulder &&
                    !(fabs(sin(start[2])) < near || fabs(sin(start[4])) < near) &&
                    distance[i] > sqrt(best_d) + factor * moved + 1e-9)
                    continue; /* next to the shoulder singularity alone: by the largest move */
                if (found_any && !shoulder && fabs(sin(start[4])) < near &&
                    wrist_bound(start, seed) > sqrt(best_d) + 1e-9)
                    continue; /* next to the wrist singularity, but θ1 and θ5 alone are too far */
                int on_valley = !shoulder && fabs(sin(start[4])) < VALLEY_NEAR;
                if (on_valley) {
                    int known = 0;
                    for (int w = 0; w < n_walked && !known; w++)
                        known = on_walked(start, walked[w]);
                    if (known)
                        continue; /* on a valley walked already */
                }
                double err = newton(self, q, target, n_newton, converged, rounding,
                                    on_valley ? VALLEY_REJECTIONS : 0);
                if (err <= accepted) {
                    memcpy(found[n_found++], q, sizeof q);
                }
                else if (on_valley) {
                    /* along the wrist's self-motion: every solution on this branch's valley */
                    double roots[MAX_ROOTS][6];
                    int whole = 0;
                    int n_roots = valley(self, start, target, converged, seed, sqrt(best_d),
                                         roots, norms,
                                         n_walked < MAX_WALKED ? walked[n_walked] : NULL,
                                         &whole);
                    if (whole && n_walked < MAX_WALKED)
                        n_walked++;
                    for (int k = 0; k < n_roots; k++)
                        if (norms[k] <= accepted)
                            memcpy(found[n_found++], roots[k], sizeof q);
                    if (!n_found) {
                        missed[n_missed++] = i;
                        continue;
                    }
                }
            }
            if (!n_found) { /* damped steps, on from where Newton's left off */
                double gradient;
                int window = fabs(sin(start[4])) >= near ? QUICK_STALL : STALL_STEPS;
                double err =
                    settle(self, q, target, n_settle, converged, stationary, window, 1, &gradient);
                if (err > accepted) {
                    if (!(gradient <= stationary) && distance[i] < unrefined)
                        unrefined = distance[i];
                    continue;
                }
                memcpy(found[n_found++], q, sizeof q);
            }
            for (int f = 0; f < n_found; f++) {
                const double *sol = found[f];
                double m = 0.0, d = 0.0, shifted[6];
                for (int k = 0; k < 6; k++)
                    m += (sol[k] - start[k]) * (sol[k] - start[k]);
                m = sqrt(m);
                if (m > moved)
                    moved = m;
                if (!singular && m > regular)
                    regular = m;
                int inside = 1;
                for (int k = 0; k < 6; k++) {
                    shifted[k] = near_angle(sol[k], seed[k], lower[k], upper[k]);
                    if (shifted[k] != shifted[k]) {
                        inside = 0;
                        break;
                    }
                    d += (shifted[k] - seed[k]) * (shifted[k] - seed[k]);
                }
                if (inside && d < best_d) {
                    memcpy(best, shifted, 6 * sizeof(double));
                    best_d = d;
                    found_any = 1;
                }
            }
        }
        if (retry || found_any || !n_missed)
            break;
        /* nothing found: where the valley is cut (the arm stretched or folded) its walk can
         * miss a root that damped steps reach */
        pending = missed;
        n_pending = n_missed;
        retry = 1;
    }
    *best_d_out = best_d;
    *moved_out = moved;
    *unrefined_out = unrefined;
    *singular_out = singular_at;
    return found_any;
}

/* nearest(starts, target, seed, lower, upper, newton_iterations, settle_iterations,
 *         converged, rounding, stationary, accepted, factor, near): DHChain.nearest in C. */
static PyObject *
Chain_nearest(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 13) {
        PyErr_SetString(PyExc_TypeError, "nearest() takes 13 arguments");
        return NULL;
    }
    double target[12], seed[6], lower[6], upper[6];
    if (read_floats(args[1], target, 12, "target") || read_floats(args[2], seed, 6, "seed") ||
        read_floats(args[3], lower, 6, "lower") || read_floats(args[4], upper, 6, "upper"))
        return NULL;
    long n_newton = PyLong_AsLong(args[5]);
    long n_settle = PyLong_AsLong(args[6]);
    double converged = PyFloat_AsDouble(args[7]);
    double rounding = PyFloat_AsDouble(args[8]);
    double stationary = PyFloat_AsDouble(args[9]);
    double accepted = PyFloat_AsDouble(args[10]);
    double factor = PyFloat_AsDouble(args[11]);
    double near = PyFloat_AsDouble(args[12]);
    if (PyErr_Occurred())
        return NULL;
    PyObject *seq = PySequence_Fast(args[0], "starts");
    if (seq == NULL)
        return NULL;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    if (n > MAX_STARTS) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "at most %d starts", MAX_STARTS);
        return NULL;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    double starts[MAX_STARTS][6];
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *pair = items[i];
        if (!PyTuple_Check(pair) || PyTuple_GET_SIZE(pair) != 2) {
            Py_DECREF(seq);
            PyErr_SetString(PyExc_TypeError, "starts: (distance², joints) pairs expected");
            return NULL;
        }
        if (read_floats(PyTuple_GET_ITEM(pair, 1), starts[i], 6, "start")) {
            Py_DECREF(seq);
            return NULL;
        }
    }
    Py_DECREF(seq);
    double best[6], best_d, moved, unrefined;
    int singular_at;
    int found_any = nearest_core(self, starts, n, target, seed, lower, upper, n_newton, n_settle,
                                 converged, rounding, stationary, accepted, factor, near, best,
                                 &best_d, &moved, &unrefined, &singular_at);
    PyObject *q_out;
    if (found_any) {
        q_out = float_list(best, 6);
        if (q_out == NULL)
            return NULL;
    }
    else {
        q_out = Py_NewRef(Py_None);
    }
    return Py_BuildValue("(Ndddi)", q_out, best_d, moved, unrefined, singular_at);
}

/* ------------------------------------------------------------------ the hot path */

/* Product of two transforms given as 12 floats (kinematics._compose). */
static void
compose(const double *a, const double *b, double *out)
{
    double r[12];
    for (int i = 0; i < 3; i++) {
        const double *row = a + 3 * i;
        for (int j = 0; j < 3; j++)
            r[3 * i + j] = row[0] * b[j] + row[1] * b[3 + j] + row[2] * b[6 + j];
        r[9 + i] = row[0] * b[9] + row[1] * b[10] + row[2] * b[11] + a[9 + i];
    }
    memcpy(out, r, sizeof r);
}

/* The inverse of a rigid transform given as 12 floats (calibration._inverse_rows). */
static void
inverse_rows(const double *f, double *out)
{
    double x = f[9], y = f[10], z = f[11];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            out[3 * i + j] = f[3 * j + i];
    out[9] = -(f[0] * x + f[3] * y + f[6] * z);
    out[10] = -(f[1] * x + f[4] * y + f[7] * z);
    out[11] = -(f[2] * x + f[5] * y + f[8] * z);
}

/* The nominal model's TCP frame at q (Kinematics.forward_rows: _flange, then the TCP). */
static void
nominal_frame(const Hot *h, const double *q, double *out)
{
    double d1 = h->geom[0], d4 = h->geom[1], d5 = h->geom[2], d6 = h->geom[3];
    double a2 = h->geom[4], a3 = h->geom[5];
    double c1 = cos(q[0]), s1 = sin(q[0]);
    double q23 = q[1] + q[2];
    double q234 = q23 + q[3];
    double c2 = cos(q[1]), s2 = sin(q[1]);
    double c23 = cos(q23), s23 = sin(q23);
    double c234 = cos(q234), s234 = sin(q234);
    double c5 = cos(q[4]), s5 = sin(q[4]);
    double c6 = cos(q[5]), s6 = sin(q[5]);
    double x4x = c234 * c1, x4y = c234 * s1, x4z = s234;
    double z4x = s234 * c1, z4y = s234 * s1, z4z = -c234;
    double x5x = c5 * x4x + s5 * s1, x5y = c5 * x4y - s5 * c1, x5z = c5 * x4z;
    double z5x = -s5 * x4x + c5 * s1, z5y = -s5 * x4y - c5 * c1, z5z = -s5 * x4z;
    double x6x = c6 * x5x - s6 * z4x, x6y = c6 * x5y - s6 * z4y, x6z = c6 * x5z - s6 * z4z;
    double y6x = -s6 * x5x - c6 * z4x, y6y = -s6 * x5y - c6 * z4y, y6z = -s6 * x5z - c6 * z4z;
    double reach = a2 * c2 + a3 * c23;
    double f[12] = {
        x6x, y6x, z5x, x6y, y6y, z5y, x6z, y6z, z5z,
        reach * c1 + d4 * s1 + d5 * z4x + d6 * z5x,
        reach * s1 - d4 * c1 + d5 * z4y + d6 * z5y,
        d1 + a2 * s2 + a3 * s23 + d5 * z4z + d6 * z5z,
    };
    if (h->tcp_identity)
        memcpy(out, f, sizeof f);
    else
        compose(f, h->tcp, out);
}

/* v's 2π-equivalent nearest s, as Kinematics.nearest_within writes it inline: NaN if none
 * within [lo, hi]. */
static double
toward(double v, double s, double lo, double hi)
{
    double w = v + TWO_PI * floor((s - v) * INV_TWO_PI + 0.5);
    if (!(lo <= w && w <= hi))
        w = near_angle(v, s, lo, hi);
    return w;
}

#define MAX_CANDIDATES 16

/* Kinematics._arm with elbow 0 (both elbows) and no rough list: the nominal arm's solutions
 * for θ1 (t1, its sine and cosine), θ5 (sine, cosine) and θ6 into out; their number. */
static int
nominal_arm(const Hot *H, const double *f, double p5x, double p5y, double p5z, double t1,
            double s1, double c1, double s5, double c5, double t6, double out[][6])
{
    double r00 = f[0], r01 = f[1], r02 = f[2], r10 = f[3], r11 = f[4], r12 = f[5];
    double r20 = f[6], r21 = f[7], r22 = f[8];
    double d1 = H->geom[0], d5 = H->geom[2], a2 = H->geom[4], a3 = H->geom[5];
    double s6 = sin(t6), c6 = cos(t6);
    double z4x = -(s6 * r00 + c6 * r01);
    double z4y = -(s6 * r10 + c6 * r11);
    double z4z = -(s6 * r20 + c6 * r21);
    double u = c5 * c6, v = -c5 * s6, w = -s5;
    double x4x = r00 * u + r01 * v + r02 * w;
    double x4y = r10 * u + r11 * v + r12 * w;
    double x4z = r20 * u + r21 * v + r22 * w;
    double t234 = atan2(x4z, c1 * x4x + s1 * x4y);
    double o4x = p5x - d5 * z4x, o4y = p5y - d5 * z4y, o4z = p5z - d5 * z4z;
    double X = c1 * o4x + s1 * o4y;
    double Y = o4z - d1;
    double c3 = (X * X + Y * Y - a2 * a2 - a3 * a3) / (2.0 * a2 * a3);
    if (c3 > 1.0 || c3 < -1.0) {
        if (fabs(c3) > 1.0 + 1e-12) /* _CLIP_EPS */
            return 0;
        c3 = c3 > 0.0 ? 1.0 : -1.0;
    }
    double s3a = sqrt(1.0 - c3 * c3);
    double t5 = atan2(s5, c5);
    double base = atan2(Y, X);
    int n = 0;
    for (int k = 0; k < (s3a > 0.0 ? 2 : 1); k++) {
        double s3 = (k ? -1.0 : 1.0) * s3a;
        double t3 = atan2(s3, c3);
        double t2 = base - atan2(a3 * s3, a2 + a3 * c3);
        double sol[6] = {t1, t2, t3, t234 - t2 - t3, t5, t6};
        memcpy(out[n++], sol, sizeof sol);
    }
    return n;
}

/* Kinematics._continuum_starts: wrist singular (θ5 = 0 or π, cosine c5), the members of the
 * continuum the refinement starts from, both elbows, one per interval of reach (its
 * middle; the seed's θ6 on the whole circle) into out; their number (at most 4). */
static int
continuum_starts(const Hot *H, const double *f, double p5x, double p5y, double p5z, double t1,
                 double s1, double c1, double c5, const double *seed, double out[][6])
{
    double r00 = f[0], r01 = f[1], r10 = f[3], r11 = f[4], r20 = f[6], r21 = f[7];
    double d1 = H->geom[0], d5 = H->geom[2], a2 = H->geom[4], a3 = H->geom[5];
    double X5 = c1 * p5x + s1 * p5y, Y5 = p5z - d1;
    double ax = c1 * r00 + s1 * r10, ay = r20;
    double bx = c1 * r01 + s1 * r11, by = r21;
    double A = ax * X5 + ay * Y5;
    double B = bx * X5 + by * Y5;
    double kD = sqrt(A * A + B * B), gamma = atan2(A, B);
    double den = 2.0 * d5 * kD;
    double D2 = X5 * X5 + Y5 * Y5;
    double mids[2];
    int n_mids = 0;
    if (den < 1e-15) {
        mids[n_mids++] = seed[5];
    }
    else {
        double lo_c = ((a2 - a3) * (a2 - a3) - D2 - d5 * d5) / den;
        double hi_c = ((a2 + a3) * (a2 + a3) - D2 - d5 * d5) / den;
        if (lo_c > 1.0 + 1e-12 || hi_c < -1.0 - 1e-12) /* _CLIP_EPS */
            return 0;
        double near = acos(fmin(fmax(hi_c, -1.0), 1.0));
        double far = acos(fmin(fmax(lo_c, -1.0), 1.0));
        if (hi_c >= 1.0 && lo_c <= -1.0)
            mids[n_mids++] = seed[5];
        else if (hi_c >= 1.0)
            mids[n_mids++] = gamma;
        else if (lo_c <= -1.0)
            mids[n_mids++] = gamma + M_PI;
        else {
            mids[n_mids++] = gamma + 0.5 * (near + far);
            mids[n_mids++] = gamma - 0.5 * (near + far);
        }
    }
    int n = 0;
    for (int i = 0; i < n_mids; i++)
        n += nominal_arm(H, f, p5x, p5y, p5z, t1, s1, c1, 0.0, c5, mids[i], out + n);
    return n;
}

/* A candidate inserted into q[0..*n), es its distances², sorted as Python sorts
 * (distance², joints) pairs. */
static void
insert_candidate(double q[][6], double *es, int *n, double e, const double *sol)
{
    int at = *n;
    while (at > 0) {
        const double *prev = q[at - 1];
        int after = es[at - 1] < e;
        if (es[at - 1] == e) {
            int j = 0;
            while (j < 6 && prev[j] == sol[j])
                j++;
            after = j == 6 || prev[j] < sol[j];
        }
        if (after)
            break;
        es[at] = es[at - 1];
        memcpy(q[at], q[at - 1], 6 * sizeof(double));
        at--;
    }
    es[at] = e;
    memcpy(q[at], sol, 6 * sizeof(double));
    (*n)++;
}

/* Kinematics.nearest_within(g, seed, inf, lenient=True) on the nominal model with the
 * starts' limits: the candidates' joints into q (sorted as Python sorts (distance², joints)
 * pairs), their number; where a shoulder branch is within lenient_wrist of the wrist
 * singularity, the continuum's members of Kinematics._continuum_starts too. */
static int
nominal_starts(const Hot *H, const double *g, const double *seed, double q[][6])
{
    double r00 = g[0], r01 = g[1], r02 = g[2], r10 = g[3], r11 = g[4], r12 = g[5];
    double r20 = g[6], r21 = g[7], r22 = g[8], px = g[9], py = g[10], pz = g[11];
    if (!H->tcp_identity) { /* flange = target · tcp⁻¹, written out */
        const double *b = H->tcp_inv;
        double nx = r00 * b[9] + r01 * b[10] + r02 * b[11] + px;
        double ny = r10 * b[9] + r11 * b[10] + r12 * b[11] + py;
        double nz = r20 * b[9] + r21 * b[10] + r22 * b[11] + pz;
        px = nx, py = ny, pz = nz;
        double m[9];
        const double rr[9] = {r00, r01, r02, r10, r11, r12, r20, r21, r22};
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 3; j++)
                m[3 * i + j] =
                    rr[3 * i] * b[j] + rr[3 * i + 1] * b[3 + j] + rr[3 * i + 2] * b[6 + j];
        r00 = m[0], r01 = m[1], r02 = m[2], r10 = m[3], r11 = m[4], r12 = m[5];
        r20 = m[6], r21 = m[7], r22 = m[8];
    }
    double d1 = H->geom[0], d4 = H->geom[1], d5 = H->geom[2], d6 = H->geom[3];
    double a2 = H->geom[4], a3 = H->geom[5];
    const double *lo = H->start_lower, *hi = H->start_upper;
    double p5x = px - d6 * r02, p5y = py - d6 * r12, p5z = pz - d6 * r22;
    double rho2 = p5x * p5x + p5y * p5y;
    double h2 = rho2 - d4 * d4;
    int clamped = 0;
    if (h2 < H->lenient_h2 * d4 * d4) {
        if (h2 < -H->edge_c3 * d4 * d4 || rho2 == 0.0)
            return 0;
        h2 = H->lenient_h2 * d4 * d4;
        clamped = 1;
    }
    if (h2 < 0.0) {
        if (h2 < -1e-12 * d4 * d4) /* _CLIP_EPS */
            return 0;
        h2 = 0.0;
    }
    double h = sqrt(h2);
    double norm = h2 > 1e-12 && !clamped ? rho2 : sqrt(rho2 * (h2 + d4 * d4));
    double k3 = 1.0 / (2.0 * a2 * a3);
    double l3 = a2 * a2 + a3 * a3;
    /* shoulders: e1, v1, c1, sn1, t1 */
    double sh[2][5];
    int n_sh = 0;
    for (int side = 0; side < (h > 0.0 ? 2 : 1); side++) {
        double hs = side ? -h : h;
        double c1 = (p5x * hs - p5y * d4) / norm;
        double sn1 = (p5y * hs + p5x * d4) / norm;
        double t = atan2(sn1, c1);
        double v1 = toward(t, seed[0], lo[0], hi[0]);
        if (v1 != v1)
            continue;
        sh[n_sh][0] = (v1 - seed[0]) * (v1 - seed[0]);
        sh[n_sh][1] = v1;
        sh[n_sh][2] = c1;
        sh[n_sh][3] = sn1;
        sh[n_sh][4] = t;
        n_sh++;
    }
    if (n_sh == 2 && sh[1][0] < sh[0][0]) {
        double tmp[5];
        memcpy(tmp, sh[0], sizeof tmp);
        memcpy(sh[0], sh[1], sizeof tmp);
        memcpy(sh[1], tmp, sizeof tmp);
    }
    double es[MAX_CANDIDATES];
    int n = 0;
    double singular[2][4]; /* t1, c1, sn1, c5 */
    int n_singular = 0;
    for (int i = 0; i < n_sh; i++) {
        double e1 = sh[i][0], v1 = sh[i][1], c1 = sh[i][2], sn1 = sh[i][3];
        double zx = r00 * sn1 - r10 * c1;
        double zy = r01 * sn1 - r11 * c1;
        double zz = r02 * sn1 - r12 * c1;
        double s5a = sqrt(zx * zx + zy * zy);
        if (s5a <= H->wrist_eps || s5a < H->lenient_wrist) {
            /* exactly singular; or close enough that the deltas can put the calibrated
             * solutions anywhere along the continuum */
            singular[n_singular][0] = sh[i][4];
            singular[n_singular][1] = c1;
            singular[n_singular][2] = sn1;
            singular[n_singular][3] = zz >= 0.0 ? 1.0 : -1.0;
            n_singular++;
            if (s5a <= H->wrist_eps)
                continue;
        }
        double c6 = zx / s5a, sn6 = -zy / s5a;
        double t6 = atan2(-zy, zx);
        double t5 = atan2(s5a, zz);
        double z4x = -(sn6 * r00 + c6 * r01);
        double z4y = -(sn6 * r10 + c6 * r11);
        double z4z = -(sn6 * r20 + c6 * r21);
        double u = zz * c6, v = -zz * sn6, w = -s5a;
        double x4x = r00 * u + r01 * v + r02 * w;
        double x4y = r10 * u + r11 * v + r12 * w;
        double x4z = r20 * u + r21 * v + r22 * w;
        double x4p = c1 * x4x + sn1 * x4y;
        double wr[2][4]; /* e6, sign, v5, v6 */
        int n_wr = 0;
        for (int flip = 0; flip < 2; flip++) {
            double sign = flip ? -1.0 : 1.0;
            double t5w = flip ? -t5 : t5, t6w = flip ? t6 + M_PI : t6;
            double v5 = toward(t5w, seed[4], lo[4], hi[4]);
            if (v5 != v5)
                continue;
            double v6 = toward(t6w, seed[5], lo[5], hi[5]);
            if (v6 != v6)
                continue;
            wr[n_wr][0] = e1 + (v5 - seed[4]) * (v5 - seed[4]) + (v6 - seed[5]) * (v6 - seed[5]);
            wr[n_wr][1] = sign;
            wr[n_wr][2] = v5;
            wr[n_wr][3] = v6;
            n_wr++;
        }
        if (n_wr == 2 && wr[1][0] < wr[0][0]) {
            double tmp[4];
            memcpy(tmp, wr[0], sizeof tmp);
            memcpy(wr[0], wr[1], sizeof tmp);
            memcpy(wr[1], tmp, sizeof tmp);
        }
        for (int k = 0; k < n_wr; k++) {
            double e6 = wr[k][0], sign = wr[k][1], v5 = wr[k][2], v6 = wr[k][3];
            double t234 = atan2(sign * x4z, sign * x4p);
            double sd5 = sign * d5;
            double ox = p5x - sd5 * z4x, oy = p5y - sd5 * z4y, oz = p5z - sd5 * z4z;
            double X = c1 * ox + sn1 * oy;
            double Y = oz - d1;
            double c3 = (X * X + Y * Y - l3) * k3;
            if (fabs(c3) > H->lenient_c3) {
                if (fabs(c3) >= 1.0 + H->edge_c3)
                    continue;
                c3 = c3 > 0.0 ? H->lenient_c3 : -H->lenient_c3;
            }
            double s3a = sqrt(1.0 - c3 * c3);
            double base = atan2(Y, X);
            double gg = atan2(a3 * s3a, a2 + a3 * c3);
            double t3 = atan2(s3a, c3);
            for (int elbow = 0; elbow < 2; elbow++) {
                double t2 = elbow ? base + gg : base - gg, t3e = elbow ? -t3 : t3;
                double v2 = toward(t2, seed[1], lo[1], hi[1]);
                if (v2 != v2)
                    continue;
                double e = e6 + (v2 - seed[1]) * (v2 - seed[1]);
                double v3 = toward(t3e, seed[2], lo[2], hi[2]);
                if (v3 != v3)
                    continue;
                double t4 = t234 - t2 - t3e;
                double v4 = toward(t4, seed[3], lo[3], hi[3]);
                if (v4 != v4)
                    continue;
                e += (v3 - seed[2]) * (v3 - seed[2]) + (v4 - seed[3]) * (v4 - seed[3]);
                double sol[6] = {v1, v2, v3, v4, v5, v6};
                insert_candidate(q, es, &n, e, sol);
            }
        }
    }
    /* the wrist-singular shoulders' continuum members, last */
    double f[12] = {r00, r01, r02, r10, r11, r12, r20, r21, r22, px, py, pz};
    for (int i = 0; i < n_singular; i++) {
        double c5 = singular[i][3];
        double v5 = near_angle(c5 > 0.0 ? 0.0 : M_PI, seed[4], lo[4], hi[4]);
        if (v5 != v5)
            continue;
        double members[4][6];
        int m = continuum_starts(H, f, p5x, p5y, p5z, singular[i][0], singular[i][2],
                                 singular[i][1], c5, seed, members);
        for (int k = 0; k < m; k++) {
            /* Kinematics._nearest: each joint's equivalent nearest the seed */
            double total = 0.0, sol[6];
            int inside = 1;
            for (int j = 0; j < 6; j++) {
                sol[j] = near_angle(members[k][j], seed[j], lo[j], hi[j]);
                if (sol[j] != sol[j]) {
                    inside = 0;
                    break;
                }
                total += (sol[j] - seed[j]) * (sol[j] - seed[j]);
            }
            if (inside)
                insert_candidate(q, es, &n, total, sol);
        }
    }
    return n;
}

/* hot_path(geom, tcp, tcp_inv, tcp_identity, start_lower, start_upper, lower, upper,
 *          newton_iterations, settle_iterations, converged, rounding, stationary, accepted,
 *          factor, near, singular_move, lenient_h2, lenient_c3, edge_c3, lenient_wrist,
 *          wrist_eps, branches): the settings of fast(). */
static PyObject *
Chain_hot_path(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 23) {
        PyErr_SetString(PyExc_TypeError, "hot_path() takes 23 arguments");
        return NULL;
    }
    Hot H;
    if (read_floats(args[0], H.geom, 6, "geom") || read_floats(args[1], H.tcp, 12, "tcp") ||
        read_floats(args[2], H.tcp_inv, 12, "tcp_inv") ||
        read_floats(args[4], H.start_lower, 6, "start_lower") ||
        read_floats(args[5], H.start_upper, 6, "start_upper") ||
        read_floats(args[6], H.lower, 6, "lower") || read_floats(args[7], H.upper, 6, "upper"))
        return NULL;
    H.tcp_identity = PyObject_IsTrue(args[3]);
    H.newton_iterations = PyLong_AsLong(args[8]);
    H.settle_iterations = PyLong_AsLong(args[9]);
    double *v[] = {&H.converged, &H.rounding, &H.stationary, &H.accepted, &H.factor, &H.near,
                   &H.singular_move, &H.lenient_h2, &H.lenient_c3, &H.edge_c3,
                   &H.lenient_wrist, &H.wrist_eps};
    for (int i = 0; i < 12; i++)
        *v[i] = PyFloat_AsDouble(args[10 + i]);
    H.branches = (int)PyLong_AsLong(args[22]);
    if (H.tcp_identity < 0 || PyErr_Occurred())
        return NULL;
    H.ready = 1;
    self->hot = H;
    Py_RETURN_NONE;
}

/* fast(target, seed): CalibratedKinematics._nearest_python in one call: the joints, or None
 * where the general path decides. */
static PyObject *
Chain_fast(Chain *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "fast() takes 2 arguments");
        return NULL;
    }
    const Hot *H = &self->hot;
    if (!H->ready) {
        PyErr_SetString(PyExc_RuntimeError, "fast() before hot_path()");
        return NULL;
    }
    double goal[12], seed[6];
    if (read_floats(args[0], goal, 12, "target") || read_floats(args[1], seed, 6, "seed"))
        return NULL;
    double starts[MAX_CANDIDATES][6];
    int n = nominal_starts(H, goal, seed, starts);
    if (n == 0)
        Py_RETURN_NONE;
    double best[6], best_d, moved, unrefined;
    int singular;
    int found = nearest_core(self, starts, n, goal, seed, H->lower, H->upper,
                             H->newton_iterations, H->settle_iterations, H->converged,
                             H->rounding, H->stationary, H->accepted, H->factor, H->near, best,
                             &best_d, &moved, &unrefined, &singular);
    if (!found || unrefined <= sqrt(best_d) + H->factor * moved)
        Py_RETURN_NONE;
    if (n < H->branches && (singular || moved > H->singular_move)) {
        /* the branches of the target corrected by the offset at the seed too */
        double nominal[12], calibrated[12], inv[12], corrected[12];
        nominal_frame(H, seed, nominal);
        evaluate(self, seed, calibrated, NULL);
        inverse_rows(calibrated, inv);
        compose(nominal, inv, corrected);
        compose(corrected, goal, corrected);
        n = nominal_starts(H, corrected, seed, starts);
        if (n > 0) {
            double own[6], own_d, m, u;
            int s;
            if (nearest_core(self, starts, n, goal, seed, H->lower, H->upper,
                             H->newton_iterations, H->settle_iterations, H->converged,
                             H->rounding, H->stationary, H->accepted, H->factor, H->near, own,
                             &own_d, &m, &u, &s) &&
                own_d < best_d)
                memcpy(best, own, sizeof best);
        }
    }
    return float_list(best, 6);
}

static PyMethodDef Chain_methods[] = {
    {"frame", (PyCFunction)Chain_frame, METH_O,
     "The TCP frame at q as 12 floats (rotation row-major, then position)."},
    {"frame_and_jacobian", (PyCFunction)Chain_frame_and_jacobian, METH_O,
     "The TCP frame and the geometric Jacobian (36 floats row-major)."},
    {"newton", (PyCFunction)(void (*)(void))Chain_newton, METH_FASTCALL,
     "Newton's steps toward target: (joints, error norm)."},
    {"settle", (PyCFunction)(void (*)(void))Chain_settle, METH_FASTCALL,
     "Levenberg-Marquardt toward target: (joints, error norm, stationarity)."},
    {"valley", (PyCFunction)(void (*)(void))Chain_valley, METH_FASTCALL,
     "The solutions along the wrist's self-motion through q: (joints, error norm) pairs."},
    {"nearest", (PyCFunction)(void (*)(void))Chain_nearest, METH_FASTCALL,
     "Each start refined; the solution nearest the seed (see the C source)."},
    {"hot_path", (PyCFunction)(void (*)(void))Chain_hot_path, METH_FASTCALL,
     "The settings of fast(): the nominal model's closed form and the refinement's."},
    {"fast", (PyCFunction)(void (*)(void))Chain_fast, METH_FASTCALL,
     "The calibrated inverse's hot path in one call: the joints, or None."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject ChainType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "fxcell.motion._dhchain.Chain",
    .tp_basicsize = sizeof(Chain),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "A 6R arm's DH chain with per-joint theta offsets and a TCP (as DHChain).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Chain_init,
    .tp_methods = Chain_methods,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_dhchain",
    "The calibrated arm's DH chain in C (see fxcell.motion.kinematics.DHChain).", -1, NULL,
};

PyMODINIT_FUNC
PyInit__dhchain(void)
{
    if (PyType_Ready(&ChainType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddObjectRef(m, "Chain", (PyObject *)&ChainType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}

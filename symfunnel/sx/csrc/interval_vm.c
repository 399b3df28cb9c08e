/* The batched interval rules of symfunnel/sx/batch_rules.py in C: one interpreter for every SX tape, many boxes
 * per call, each rule the same sequence of IEEE operations as its numpy twin (round to nearest, then one ulp
 * outward; libm's transcendental functions widened by TRANSCENDENTAL_ULPS ulps first). numpy's minimum / maximum
 * propagate NaN, so nmin / nmax do too. Compiled with -std=c99 -ffp-contract=off: no fused multiply-add, no
 * reassociation, so +, -, *, / and sqrt give numpy's doubles bit for bit.
 *
 * The tape is an int32 array of 5 per instruction: op (interval_vm_ops.h), argument slots a0 and a1, result slot,
 * and aux (INPUT: flat input column; CONST: index into consts; OUTPUT: flat output index; an operation with a
 * domain: its number among those, the culprit a box reports; else -1). Boxes run in chunks of B, each chunk through
 * the whole tape, so a chunk's work slots stay in cache. An instruction's result slot may be one of its arguments:
 * each loop reads a box's arguments before it writes its results. */
#include <fenv.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "interval_vm_ops.h"

static const double REL = VM_TRANSCENDENTAL_ULPS * 0x1p-52;     /* batch_rules._REL */
static const double PI = 3.141592653589793;
static const double TWO_PI = 6.283185307179586;     /* 2.0 * math.pi in double */

static inline double nmin(double a, double b) { return a != a ? a : (b != b ? b : (a < b ? a : b)); }
static inline double nmax(double a, double b) { return a != a ? a : (b != b ? b : (a > b ? a : b)); }

/* min(min(p, q), min(r, s)) and the max as numpy computes them; without a NaN among the four (the usual case) the
 * NaN tests of nmin / nmax are all false, so their plain comparisons alone give the same doubles */
static inline void minmax4(double p, double q, double r, double s, double *lo, double *hi) {
    if (p == p && q == q && r == r && s == s) {
        double a = p < q ? p : q, b = r < s ? r : s, c = p > q ? p : q, d = r > s ? r : s;
        *lo = a < b ? a : b;
        *hi = c > d ? c : d;
    } else {
        *lo = nmin(nmin(p, q), nmin(r, s));
        *hi = nmax(nmax(p, q), nmax(r, s));
    }
}

/* nextafter(x, +inf) and nextafter(x, -inf) by the bits, C99's results: a finite nonzero x (the usual case) moves
 * one unit of its magnitude, +-0 goes to the smallest subnormal of the direction's sign, an infinity of the other
 * sign to the largest finite double, an infinity of the direction's sign and NaN stay */
static inline double up(double x) {
    uint64_t u, m;
    memcpy(&u, &x, 8);
    m = u & 0x7FFFFFFFFFFFFFFFull;
    if (m - 1 < 0x7FEFFFFFFFFFFFFFull) u += 1 - ((u >> 63) << 1);
    else if (m == 0) u = 1;
    else if (u == 0xFFF0000000000000ull) u -= 1;
    memcpy(&x, &u, 8);
    return x;
}
static inline double dn(double x) {
    uint64_t u, m;
    memcpy(&u, &x, 8);
    m = u & 0x7FFFFFFFFFFFFFFFull;
    if (m - 1 < 0x7FEFFFFFFFFFFFFFull) u += ((u >> 63) << 1) - 1;
    else if (m == 0) u = 0x8000000000000001ull;
    else if (u == 0x7FF0000000000000ull) u -= 1;
    memcpy(&x, &u, 8);
    return x;
}
static inline double wdn(double x) { return dn(x - fabs(x) * REL); }
static inline double wup(double x) { return up(x + fabs(x) * REL); }

static inline void absint(double al, double ah, double *lo, double *hi) {
    int pos = al >= 0, neg = ah <= 0;
    *lo = pos ? al : (neg ? -ah : 0.0);
    *hi = pos ? ah : (neg ? -al : nmax(-al, ah));
}

static inline int contains_point(double al, double ah, double phase, double period) {
    double tol = 1e-12 * nmax(1.0, nmax(fabs(al), fabs(ah)));
    double k_lo = ceil((al - tol - phase) / period);
    double k_hi = floor((ah + tol - phase) / period);
    return k_lo <= k_hi;
}

static inline void periodic(int cosine, double al, double ah, double *plo, double *phi) {
    double max_phase = cosine ? 0.0 : 0.5 * PI, min_phase = cosine ? PI : -0.5 * PI;
    int wide = !(ah - al < 6.0) || !(fabs(al) < 1e15) || !(fabs(ah) < 1e15);
    double a = wide ? 0.0 : al, b = wide ? 0.0 : ah;
    double fa = cosine ? cos(a) : sin(a), fb = cosine ? cos(b) : sin(b);
    double lo = nmin(fa, fb), hi = nmax(fa, fb);
    hi = contains_point(a, b, max_phase, TWO_PI) ? 1.0 : wup(hi);
    lo = contains_point(a, b, min_phase, TWO_PI) ? -1.0 : wdn(lo);
    *plo = wide ? -1.0 : nmax(lo, -1.0);
    *phi = wide ? 1.0 : nmin(hi, 1.0);
}

static inline double sgn(double x) { return x > 0 ? 1.0 : (x < 0 ? -1.0 : (x == 0 ? 0.0 : x)); }

static inline void power(double al, double ah, double bl, double bh, double *plo, double *phi, int *bad) {
    if (bl == bh && floor(bl) == bl && fabs(bl) < 1024) {
        double n = bl, pl, ph;
        int k = (int)fabs(n);
        if (k == 0) { *plo = 1.0; *phi = 1.0; *bad = 0; return; }
        if (k % 2) { pl = pow(al, (double)k); ph = pow(ah, (double)k); }
        else { double l, h; absint(al, ah, &l, &h); pl = pow(l, (double)k); ph = pow(h, (double)k); }
        if (n < 0) {
            int z = al <= 0 && ah >= 0;
            double ql, qh;
            if (z) { pl = 1.0; ph = 1.0; }
            ql = 1.0 / ph; qh = 1.0 / pl;
            pl = nmin(ql, qh); ph = nmax(ql, qh);
            *bad = z;
        } else {
            *bad = 0;
        }
        *plo = wdn(pl); *phi = wup(ph);
        return;
    }
    if (al > 0 || (al >= 0 && bl > 0)) {
        double c0 = pow(al, bl), c1 = pow(al, bh), c2 = pow(ah, bl), c3 = pow(ah, bh);
        *plo = nmax(wdn(nmin(nmin(nmin(c0, c1), c2), c3)), 0.0);
        *phi = wup(nmax(nmax(nmax(c0, c1), c2), c3));
        *bad = 0;
        return;
    }
    *plo = -INFINITY; *phi = INFINITY; *bad = 1;
}

/* Runs the tape over K boxes. LO/HI: (K, n_in) row-major; Lo/Hi: (K, n_out); Bad: the outputs' domain flags;
 * sw: a switching operation switched on the box; culprit: the first failing operation's number (-1: none).
 * wl/wh/wb: scratch of n_work * B. Returns 0, or -1 when the rounding mode is not round-to-nearest. */
int sfi_eval(const int32_t *code, int n_code, const double *consts, int n_work, int n_in, int n_out,
             const double *LO, const double *HI, long K, int B, double *Lo, double *Hi,
             uint8_t *Bad, uint8_t *sw, int64_t *culprit, double *wl, double *wh, uint8_t *wb) {
    if (fegetround() != FE_TONEAREST) return -1;
    for (long k = 0; k < K * n_out; k++) { Lo[k] = 0.0; Hi[k] = 0.0; Bad[k] = 0; }
    for (long k = 0; k < K; k++) { sw[k] = 0; culprit[k] = -1; }
    for (long k0 = 0; k0 < K; k0 += B) {
        int nb = (int)((K - k0) < B ? (K - k0) : B);
        for (int i = 0; i < n_code; i++) {
            const int32_t *c = code + 5 * i;
            int op = c[0], a0 = c[1], a1 = c[2], aux = c[4];
            double *rl = wl + (long)c[3] * B, *rh = wh + (long)c[3] * B;
            uint8_t *rb = wb + (long)c[3] * B;
            const double *xl = wl + (long)a0 * B, *xh = wh + (long)a0 * B;
            const double *yl = wl + (long)a1 * B, *yh = wh + (long)a1 * B;
            const uint8_t *xb = wb + (long)a0 * B, *yb = wb + (long)a1 * B;
            uint8_t *s = sw + k0;
            int64_t *cu = culprit + k0;
            int b;
            switch (op) {
            case VM_INPUT:
                for (b = 0; b < nb; b++) {
                    rl[b] = LO[(k0 + b) * n_in + aux]; rh[b] = HI[(k0 + b) * n_in + aux]; rb[b] = 0;
                }
                break;
            case VM_CONST: {
                double v = consts[aux];
                uint8_t f = !isfinite(v);
                for (b = 0; b < nb; b++) { rl[b] = v; rh[b] = v; rb[b] = f; }
                break;
            }
            case VM_OUTPUT: {
                const double *ol = wl + (long)a0 * B, *oh = wh + (long)a0 * B;
                for (b = 0; b < nb; b++) {
                    Lo[(k0 + b) * n_out + aux] = ol[b]; Hi[(k0 + b) * n_out + aux] = oh[b];
                    Bad[(k0 + b) * n_out + aux] = xb[b];
                }
                break;
            }
            case VM_ASSIGN:
                for (b = 0; b < nb; b++) { rl[b] = xl[b]; rh[b] = xh[b]; rb[b] = xb[b]; }
                break;
            case VM_ADD:
                for (b = 0; b < nb; b++) {
                    double al = xl[b], ah = xh[b], bl = yl[b], bh = yh[b];
                    rl[b] = dn(al + bl); rh[b] = up(ah + bh); rb[b] = xb[b] | yb[b];
                }
                break;
            case VM_SUB:
                for (b = 0; b < nb; b++) {
                    double al = xl[b], ah = xh[b], bl = yl[b], bh = yh[b];      /* the result may be an argument */
                    rl[b] = dn(al - bh); rh[b] = up(ah - bl); rb[b] = xb[b] | yb[b];
                }
                break;
            case VM_MUL:
                for (b = 0; b < nb; b++) {
                    double p1 = xl[b] * yl[b], p2 = xl[b] * yh[b], p3 = xh[b] * yl[b], p4 = xh[b] * yh[b], lo, hi;
                    minmax4(p1, p2, p3, p4, &lo, &hi);
                    rl[b] = dn(lo); rh[b] = up(hi); rb[b] = xb[b] | yb[b];
                }
                break;
            case VM_DIV:
                for (b = 0; b < nb; b++) {
                    int e = yl[b] <= 0 && yh[b] >= 0;
                    double bl = e ? 1.0 : yl[b], bh = e ? 1.0 : yh[b];
                    double q1 = xl[b] / bl, q2 = xl[b] / bh, q3 = xh[b] / bl, q4 = xh[b] / bh, lo, hi;
                    minmax4(q1, q2, q3, q4, &lo, &hi);
                    rl[b] = dn(lo); rh[b] = up(hi); rb[b] = xb[b] | yb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_NEG:
                for (b = 0; b < nb; b++) { double l = xl[b]; rl[b] = -xh[b]; rh[b] = -l; rb[b] = xb[b]; }
                break;
            case VM_TWICE:
                for (b = 0; b < nb; b++) { rl[b] = 2.0 * xl[b]; rh[b] = 2.0 * xh[b]; rb[b] = xb[b]; }
                break;
            case VM_FABS:
                for (b = 0; b < nb; b++) { absint(xl[b], xh[b], rl + b, rh + b); rb[b] = xb[b]; }
                break;
            case VM_SQ:
                for (b = 0; b < nb; b++) {
                    double l, h;
                    absint(xl[b], xh[b], &l, &h);
                    rl[b] = nmax(dn(l * l), 0.0); rh[b] = up(h * h); rb[b] = xb[b];
                }
                break;
            case VM_INV:
                for (b = 0; b < nb; b++) {
                    int e = xl[b] <= 0 && xh[b] >= 0;
                    double l = e ? 1.0 : xl[b], h = e ? 1.0 : xh[b];
                    rl[b] = dn(1.0 / h); rh[b] = up(1.0 / l); rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_EXP:
                for (b = 0; b < nb; b++) { double l = xl[b]; rl[b] = nmax(wdn(exp(l)), 0.0); rh[b] = wup(exp(xh[b])); rb[b] = xb[b]; }
                break;
            case VM_LOG:
                for (b = 0; b < nb; b++) {
                    int e = xl[b] <= 0;
                    double l = e ? 1.0 : xl[b], h = e ? 1.0 : xh[b];
                    rl[b] = wdn(log(l)); rh[b] = wup(log(h)); rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_SQRT:
                for (b = 0; b < nb; b++) {
                    int e = xl[b] < 0;
                    double l = e ? 0.0 : xl[b], h = e ? 0.0 : xh[b];
                    rl[b] = nmax(dn(sqrt(l)), 0.0); rh[b] = up(sqrt(h)); rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_SIN:
            case VM_COS:
                for (b = 0; b < nb; b++) { periodic(op == VM_COS, xl[b], xh[b], rl + b, rh + b); rb[b] = xb[b]; }
                break;
            case VM_TAN:
                for (b = 0; b < nb; b++) {
                    double al = xl[b], ah = xh[b];
                    int e = !(ah - al < 3.0) || contains_point(al, ah, 0.5 * PI, PI) || !(fabs(al) < 1e15)
                            || !(fabs(ah) < 1e15);
                    if (e) { al = 0.0; ah = 0.0; }
                    rl[b] = wdn(tan(al)); rh[b] = wup(tan(ah)); rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_ASIN:
            case VM_ACOS:
                for (b = 0; b < nb; b++) {
                    int e = xl[b] < -1 || xh[b] > 1;
                    double l = e ? 0.0 : xl[b], h = e ? 0.0 : xh[b];
                    if (op == VM_ASIN) { rl[b] = wdn(asin(l)); rh[b] = wup(asin(h)); }
                    else { rl[b] = nmax(wdn(acos(h)), 0.0); rh[b] = wup(acos(l)); }
                    rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_ATAN:
                for (b = 0; b < nb; b++) { double l = xl[b]; rl[b] = wdn(atan(l)); rh[b] = wup(atan(xh[b])); rb[b] = xb[b]; }
                break;
            case VM_SINH:
                for (b = 0; b < nb; b++) { double l = xl[b]; rl[b] = wdn(sinh(l)); rh[b] = wup(sinh(xh[b])); rb[b] = xb[b]; }
                break;
            case VM_COSH:
                for (b = 0; b < nb; b++) {
                    double l, h;
                    absint(xl[b], xh[b], &l, &h);
                    rl[b] = nmax(wdn(cosh(l)), 1.0); rh[b] = wup(cosh(h)); rb[b] = xb[b];
                }
                break;
            case VM_TANH:
                for (b = 0; b < nb; b++) {
                    double l = xl[b];
                    rl[b] = nmax(wdn(tanh(l)), -1.0); rh[b] = nmin(wup(tanh(xh[b])), 1.0); rb[b] = xb[b];
                }
                break;
            case VM_ATANH:
                for (b = 0; b < nb; b++) {
                    int e = xl[b] <= -1 || xh[b] >= 1;
                    double l = e ? 0.0 : xl[b], h = e ? 0.0 : xh[b];
                    rl[b] = wdn(atanh(l)); rh[b] = wup(atanh(h)); rb[b] = xb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_POW:
            case VM_CONSTPOW:
                for (b = 0; b < nb; b++) {
                    int e;
                    double l, h;
                    power(xl[b], xh[b], yl[b], yh[b], &l, &h, &e);
                    rl[b] = l; rh[b] = h; rb[b] = xb[b] | yb[b] | e;
                    if (e && cu[b] < 0) cu[b] = aux;
                }
                break;
            case VM_SIGN:
            case VM_FLOOR:
            case VM_CEIL:
                for (b = 0; b < nb; b++) {
                    double l = op == VM_SIGN ? sgn(xl[b]) : (op == VM_FLOOR ? floor(xl[b]) : ceil(xl[b]));
                    double h = op == VM_SIGN ? sgn(xh[b]) : (op == VM_FLOOR ? floor(xh[b]) : ceil(xh[b]));
                    rl[b] = l; rh[b] = h; rb[b] = xb[b];
                    s[b] |= l != h;
                }
                break;
            case VM_FMIN:
                for (b = 0; b < nb; b++) { double l = nmin(xl[b], yl[b]); rh[b] = nmin(xh[b], yh[b]); rl[b] = l; rb[b] = xb[b] | yb[b]; }
                break;
            case VM_FMAX:
                for (b = 0; b < nb; b++) { double l = nmax(xl[b], yl[b]); rh[b] = nmax(xh[b], yh[b]); rl[b] = l; rb[b] = xb[b] | yb[b]; }
                break;
            case VM_LT: case VM_LE: case VM_EQ: case VM_NE: case VM_NOT: case VM_AND: case VM_OR:
                for (b = 0; b < nb; b++) {
                    double al = xl[b], ah = xh[b], bl = yl[b], bh = yh[b];
                    int t, f;
                    if (op == VM_LT) { t = ah < bl; f = al >= bh; }
                    else if (op == VM_LE) { t = ah <= bl; f = al > bh; }
                    else if (op == VM_EQ || op == VM_NE) {
                        int same = al == ah && bl == bh && al == bl, apart = ah < bl || bh < al;
                        t = op == VM_EQ ? same : apart; f = op == VM_EQ ? apart : same;
                    } else {
                        int ta = al > 0 || ah < 0, fa = al == 0 && ah == 0;
                        if (op == VM_NOT) { t = fa; f = ta; }
                        else {
                            int tb = bl > 0 || bh < 0, fb = bl == 0 && bh == 0;
                            t = op == VM_AND ? (ta && tb) : (ta || tb);
                            f = op == VM_AND ? (fa || fb) : (fa && fb);
                        }
                    }
                    rl[b] = t ? 1.0 : 0.0; rh[b] = f ? 0.0 : 1.0;
                    rb[b] = op == VM_NOT ? xb[b] : (xb[b] | yb[b]);
                    s[b] |= !(t || f);
                }
                break;
            case VM_IF_ELSE_ZERO:
                for (b = 0; b < nb; b++) {
                    double cl = xl[b], ch = xh[b], vl = yl[b], vh = yh[b];
                    int t = cl > 0 || ch < 0, f = cl == 0 && ch == 0;
                    uint8_t cb = xb[b], vb = yb[b];
                    rl[b] = f ? 0.0 : (t ? vl : nmin(vl, 0.0));
                    rh[b] = f ? 0.0 : (t ? vh : nmax(vh, 0.0));
                    /* the condition's domain errors count; the branch's only where it is not certainly dead */
                    rb[b] = cb | (vb & !f);
                    s[b] |= !(t || f);
                }
                break;
            default:
                return -2 - op;
            }
        }
    }
    return 0;
}

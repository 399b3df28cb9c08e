"""The batched interval rules: one per SX tape operation, each on numpy arrays of lower and upper bounds (one entry
per box), for the tape compiler `batch`.

Rounding. Every result is pushed one ulp outward (`numpy.nextafter`) after being computed in round-to-nearest:
IEEE 754 +, -, *, / and sqrt are correctly rounded, so the exact result lies within half an ulp and one ulp outward
encloses it. numpy's exp, log, sin, cos, tan, asin, acos, atan, sinh, cosh, tanh, atanh and pow are not correctly
rounded (libm or SIMD code within a few ulps): their results are widened by TRANSCENDENTAL_ULPS ulps first.
Endpoint arithmetic is exact for wide boxes (no midpoint-radius overestimation: the product of two positive
intervals stays positive), which the branch and bound's first, wide boxes need.

Domain errors (division by an interval containing 0, log of one reaching <= 0, sqrt below 0, atanh outside (-1, 1),
asin/acos outside [-1, 1], tan across a pole, pow outside its domain) and non-finite values mark the box's output
invalid: (-inf, inf). A discontinuous operation (sign, floor, ceil, a comparison, a logic operation, an undecided
if-else) that switches on a box sets its `switched` flag, so the mean-value form is not applied there.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["TRANSCENDENTAL_ULPS", "BATCH_OPS"]

#: ulps by which results of numpy's (not correctly rounded) transcendental functions are widened
TRANSCENDENTAL_ULPS = 8
_REL = TRANSCENDENTAL_ULPS * 2.0 ** -52
_INF = np.inf
_PI_LO = math.pi                     # the double nearest pi is below pi
_PI_HI = math.nextafter(math.pi, 4)


#: the directions of nextafter as 0-d arrays: a Python float there is converted to an array at every call (about
#: a third of nextafter's cost on a small batch); the same direction, so the same bits
_TO_NEG = np.array(-np.inf)
_TO_POS = np.array(np.inf)
_next = np.nextafter


def _dn(x):
    return _next(x, _TO_NEG)


def _up(x):
    return _next(x, _TO_POS)


def _wdn(x):
    """Down, widened for a transcendental function's error."""
    return _next(x - np.abs(x) * _REL, _TO_NEG)


def _wup(x):
    return _next(x + np.abs(x) * _REL, _TO_POS)


def _bad_of(*arrays):
    out = np.zeros(np.shape(arrays[0]), dtype=bool)
    for a in arrays:
        out |= ~np.isfinite(a)
    return out


# --- rules: each takes (lo, hi) pairs and returns (lo, hi, bad) or (lo, hi, bad, switched) ------------------

def ADD(al, ah, bl, bh):
    return _next(al + bl, _TO_NEG), _next(ah + bh, _TO_POS), None


def SUB(al, ah, bl, bh):
    return _next(al - bh, _TO_NEG), _next(ah - bl, _TO_POS), None


def MUL(al, ah, bl, bh):
    p1, p2, p3, p4 = al * bl, al * bh, ah * bl, ah * bh
    lo = np.minimum(np.minimum(p1, p2), np.minimum(p3, p4))
    hi = np.maximum(np.maximum(p1, p2), np.maximum(p3, p4))
    return _next(lo, _TO_NEG), _next(hi, _TO_POS), None


def _mulc(al, ah, c):
    """MUL with a constant factor c (bl = bh = c): of its four products two pairs are equal, so two are enough;
    the same values bit for bit, NaN and infinities included (np.minimum(p, p) is p)."""
    p, q = al * c, ah * c
    return _next(np.minimum(p, q), _TO_NEG), _next(np.maximum(p, q), _TO_POS)


def DIV(al, ah, bl, bh):
    bad = (bl <= 0) & (bh >= 0)
    bl = np.where(bad, 1.0, bl)
    bh = np.where(bad, 1.0, bh)
    q1, q2, q3, q4 = al / bl, al / bh, ah / bl, ah / bh
    lo = np.minimum(np.minimum(q1, q2), np.minimum(q3, q4))
    hi = np.maximum(np.maximum(q1, q2), np.maximum(q3, q4))
    return _dn(lo), _up(hi), bad


def NEG(al, ah):
    return -ah, -al, None


def TWICE(al, ah):
    return 2.0 * al, 2.0 * ah, None


def _abs(al, ah):
    pos = al >= 0
    neg = ah <= 0
    lo = np.where(pos, al, np.where(neg, -ah, 0.0))
    hi = np.where(pos, ah, np.where(neg, -al, np.maximum(-al, ah)))
    return lo, hi


def FABS(al, ah):
    lo, hi = _abs(al, ah)
    return lo, hi, None


def SQ(al, ah):
    lo, hi = _abs(al, ah)
    return np.maximum(_dn(lo * lo), 0.0), _up(hi * hi), None


def INV(al, ah):
    bad = (al <= 0) & (ah >= 0)
    al = np.where(bad, 1.0, al)
    ah = np.where(bad, 1.0, ah)
    return _dn(1.0 / ah), _up(1.0 / al), bad


def EXP(al, ah):
    return np.maximum(_wdn(np.exp(al)), 0.0), _wup(np.exp(ah)), None


def LOG(al, ah):
    bad = al <= 0
    al = np.where(bad, 1.0, al)
    ah = np.where(bad, 1.0, ah)
    return _wdn(np.log(al)), _wup(np.log(ah)), bad


def SQRT(al, ah):
    bad = al < 0
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return np.maximum(_dn(np.sqrt(al)), 0.0), _up(np.sqrt(ah)), bad


def _contains_point(al, ah, phase, period):
    """Whether some phase + k period (k integer) may lie in [al, ah] (conservative: the interval is widened)."""
    tol = 1e-12 * np.maximum(1.0, np.maximum(np.abs(al), np.abs(ah)))
    k_lo = np.ceil((al - tol - phase) / period)
    k_hi = np.floor((ah + tol - phase) / period)
    return k_lo <= k_hi


def _periodic(fn, al, ah, max_phase, min_phase):
    """sin or cos on intervals: values at the ends, +1 / -1 where a maximum / minimum lies inside."""
    wide = ~(ah - al < 6.0) | ~(np.abs(al) < 1e15) | ~(np.abs(ah) < 1e15)
    a = np.where(wide, 0.0, al)
    b = np.where(wide, 0.0, ah)
    fa, fb = fn(a), fn(b)
    lo = np.minimum(fa, fb)
    hi = np.maximum(fa, fb)
    two_pi = 2.0 * math.pi
    hi = np.where(_contains_point(a, b, max_phase, two_pi), 1.0, _wup(hi))
    lo = np.where(_contains_point(a, b, min_phase, two_pi), -1.0, _wdn(lo))
    lo = np.where(wide, -1.0, np.maximum(lo, -1.0))
    hi = np.where(wide, 1.0, np.minimum(hi, 1.0))
    return lo, hi


def SIN(al, ah):
    lo, hi = _periodic(np.sin, al, ah, 0.5 * math.pi, -0.5 * math.pi)
    return lo, hi, None


def COS(al, ah):
    lo, hi = _periodic(np.cos, al, ah, 0.0, math.pi)
    return lo, hi, None


def TAN(al, ah):
    bad = ~(ah - al < 3.0) | _contains_point(al, ah, 0.5 * math.pi, math.pi) | ~(np.abs(al) < 1e15) \
        | ~(np.abs(ah) < 1e15)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.tan(al)), _wup(np.tan(ah)), bad


def ASIN(al, ah):
    bad = (al < -1) | (ah > 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.arcsin(al)), _wup(np.arcsin(ah)), bad


def ACOS(al, ah):
    bad = (al < -1) | (ah > 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return np.maximum(_wdn(np.arccos(ah)), 0.0), _wup(np.arccos(al)), bad


def ATAN(al, ah):
    return _wdn(np.arctan(al)), _wup(np.arctan(ah)), None


def SINH(al, ah):
    return _wdn(np.sinh(al)), _wup(np.sinh(ah)), None


def COSH(al, ah):
    lo, hi = _abs(al, ah)
    return np.maximum(_wdn(np.cosh(lo)), 1.0), _wup(np.cosh(hi)), None


def TANH(al, ah):
    return np.maximum(_wdn(np.tanh(al)), -1.0), np.minimum(_wup(np.tanh(ah)), 1.0), None


def ATANH(al, ah):
    bad = (al <= -1) | (ah >= 1)
    al = np.where(bad, 0.0, al)
    ah = np.where(bad, 0.0, ah)
    return _wdn(np.arctanh(al)), _wup(np.arctanh(ah)), bad


def _ipow(al, ah, n):
    """x^n for an integer n >= 1 (monotone for odd n; in |x| for even n), before widening."""
    if n % 2:
        return np.power(al, n), np.power(ah, n)
    lo, hi = _abs(al, ah)
    return np.power(lo, n), np.power(hi, n)


def POW(al, ah, bl, bh):
    shape = np.broadcast(al, bl).shape
    lo = np.full(shape, -_INF)
    hi = np.full(shape, _INF)
    bad = np.ones(shape, dtype=bool)
    al, ah, bl, bh = (np.broadcast_to(v, shape) for v in (al, ah, bl, bh))
    point = (bl == bh) & (np.floor(bl) == bl) & (np.abs(bl) < 1024)
    for n in np.unique(bl[point]) if point.any() else []:
        sel = point & (bl == n)
        a, b = al[sel], ah[sel]
        k = int(abs(n))
        if k == 0:
            lo[sel], hi[sel], bad[sel] = 1.0, 1.0, False
            continue
        pl, ph = _ipow(a, b, k)
        if n < 0:
            z = (a <= 0) & (b >= 0)
            pl, ph = np.where(z, 1.0, pl), np.where(z, 1.0, ph)
            # 1/x^k: x^k has one sign on the box (0 excluded)
            ql, qh = 1.0 / ph, 1.0 / pl
            pl, ph = np.minimum(ql, qh), np.maximum(ql, qh)
            bad[sel] = z
        else:
            bad[sel] = False
        lo[sel], hi[sel] = _wdn(pl), _wup(ph)
    real = ~point
    ok = real & ((al > 0) | ((al >= 0) & (bl > 0)))
    if ok.any():
        a, b, c, d = al[ok], ah[ok], bl[ok], bh[ok]
        corners = [np.power(x, y) for x in (a, b) for y in (c, d)]
        lo[ok] = np.maximum(_wdn(np.minimum.reduce(corners)), 0.0)
        hi[ok] = _wup(np.maximum.reduce(corners))
        bad[ok] = False
    return lo, hi, bad


CONSTPOW = POW


def SIGN(al, ah):
    lo, hi = np.sign(al), np.sign(ah)
    return lo, hi, None, lo != hi


def FLOOR(al, ah):
    lo, hi = np.floor(al), np.floor(ah)
    return lo, hi, None, lo != hi


def CEIL(al, ah):
    lo, hi = np.ceil(al), np.ceil(ah)
    return lo, hi, None, lo != hi


def FMIN(al, ah, bl, bh):
    return np.minimum(al, bl), np.minimum(ah, bh), None


def FMAX(al, ah, bl, bh):
    return np.maximum(al, bl), np.maximum(ah, bh), None


def _decided(true, false):
    lo = np.where(true, 1.0, 0.0)
    hi = np.where(false, 0.0, 1.0)
    return lo, hi, None, ~(true | false)


def LT(al, ah, bl, bh):
    return _decided(ah < bl, al >= bh)


def LE(al, ah, bl, bh):
    return _decided(ah <= bl, al > bh)


def EQ(al, ah, bl, bh):
    return _decided((al == ah) & (bl == bh) & (al == bl), (ah < bl) | (bh < al))


def NE(al, ah, bl, bh):
    return _decided((ah < bl) | (bh < al), (al == ah) & (bl == bh) & (al == bl))


def _truth(al, ah):
    """(certainly nonzero, certainly zero)."""
    return (al > 0) | (ah < 0), (al == 0) & (ah == 0)


def NOT(al, ah):
    t, f = _truth(al, ah)
    return _decided(f, t)


def AND(al, ah, bl, bh):
    ta, fa = _truth(al, ah)
    tb, fb = _truth(bl, bh)
    return _decided(ta & tb, fa | fb)


def OR(al, ah, bl, bh):
    ta, fa = _truth(al, ah)
    tb, fb = _truth(bl, bh)
    return _decided(ta | tb, fa & fb)


def IF_ELSE_ZERO(cl, ch, xl, xh):
    t, f = _truth(cl, ch)
    lo = np.where(f, 0.0, np.where(t, xl, np.minimum(xl, 0.0)))
    hi = np.where(f, 0.0, np.where(t, xh, np.maximum(xh, 0.0)))
    # a certainly false condition masks its branch (also a domain error there, as CasADi's double evaluation does)
    return lo, hi, None, ~(t | f), f


def ASSIGN(al, ah):
    return al, ah, None


_RULES = {name: fn for name, fn in globals().items() if name.isupper() and callable(fn)
          and name not in ("TRANSCENDENTAL_ULPS",)}
_UNARY = frozenset(("ASSIGN", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN",
                    "ACOS", "ATAN", "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL", "NOT"))
_SWITCHING = frozenset(("SIGN", "FLOOR", "CEIL", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR", "IF_ELSE_ZERO"))
#: the operations with a domain: an error there makes the box's culprit (the first failing one)
_FAILING = frozenset(("DIV", "INV", "LOG", "SQRT", "TAN", "ASIN", "ACOS", "ATANH", "POW", "CONSTPOW"))
#: the tape operations this backend has a rule for (the same set as codac's and arb's)
BATCH_OPS = frozenset(_RULES)


def rule_name(tape, op: int, rules) -> str:
    """The name of operation `op` of `tape` (without OP_), which `rules` must have: an IntervalError naming the
    function for a free SX variable or an operation without a rule (both backends refuse the same tapes). Imported
    here: the rules module itself stays numpy only, imported early and cheaply."""
    import casadi

    from .interval import IntervalError
    from .tape import OP_NAMES
    if op == casadi.OP_PARAMETER:
        raise IntervalError(f"function {tape.function.name()!r} has free SX variables; interval evaluation needs "
                            "every symbol as an input")
    name = OP_NAMES.get(op, f"<{op}>")
    if name not in rules:
        raise IntervalError(f"no interval rule for OP_{name} in function {tape.function.name()!r}")
    return name

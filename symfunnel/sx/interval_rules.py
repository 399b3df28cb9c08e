"""The interval rules of the two independent arithmetics the tape evaluator (`interval`) runs on: codac 2
Intervals and python-flint arb balls, one rule per SX tape operation.

Domain errors. A division or INV by an interval containing 0, LOG of an interval reaching <= 0, SQRT below 0,
ATANH outside (-1, 1), ASIN/ACOS outside [-1, 1], TAN across a pole, POW outside its domain make the instruction's
value an *error* (codac: the empty interval; arb: a NaN ball), which every rule propagates. IF_ELSE_ZERO(c, x) with c
certainly 0 is 0 whatever x is (CasADi's double evaluation does the same). An output that is an error, or whose
bounds are not finite, is returned as lo = -inf, hi = +inf: no invalid result can pass for a bound, and
`Enclosure.valid` says which entries are real enclosures.

Comparisons and logic give [0, 0], [1, 1] or [0, 1] (undecided); IF_ELSE_ZERO(c, x) is x when 0 is not in c, 0 when
c is [0, 0], hull(0, x) otherwise; SIGN of an interval with 0 inside is [-1, 1] (of [0, a] it is [0, 1]).

Outward rounding: codac's Interval operations round outward themselves (its sinh, tanh and atanh are widened by
SLOPPY_ULPS more, see there); arb balls carry rigorous error radii, an input [lo, hi] becomes a ball whose radius
python-flint rounds up (by ~2^-30 relative: arb's [0, 1] is [-9.3e-10, 1 + 9.3e-10]), and a ball is read back as
[mid - rad, mid + rad] one ulp outward after the double subtraction.

The codac backend does not use codac's `AnalyticFunction`: it evaluates expression *trees* (a node shared k times
is evaluated k times, exponential in the depth of CasADi's CSE'd DAG) and carries a Jacobian per node, which made
the paper's `tau` take 60 ms per box against ~0.2 ms for this tape walk.
"""

from __future__ import annotations

import contextlib
import math
import operator
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from . import rounding

_INF = math.inf


#: ulps by which the codac backend widens sinh, tanh and atanh: codac 2.1.2 returns bounds up to 1 ulp inside the
#: exact value for ~1-2 % of arguments (measured against arb at 200 bits; tests/test_interval.py keeps checking)
SLOPPY_ULPS = 2

#: tape operations whose rules take the evaluation's `ctx` list and append to it where the operation is not
#: continuous on the box (the mean-value form is only sound where none is)
DISCONTINUOUS = frozenset({"SIGN", "FLOOR", "CEIL", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR", "IF_ELSE_ZERO"})


@dataclass
class Backend:
    """One interval arithmetic: how to make intervals and points, read bounds back, and a rule per tape operation."""

    name: str
    interval: Callable[[float, float], Any]       # outward enclosure of [lo, hi]
    point: Callable[[float], Any]                  # the exact double
    bounds: Callable[[Any], tuple[float, float]]   # outward (lo, hi); (-inf, inf) for an error / unbounded value
    rules: dict[str, Callable]
    error: Callable[[], Any]                       # a fresh error value
    #: the rounding mode every evaluation runs in (codac is outward only under upward rounding)
    mode: Callable[[], Any] = contextlib.nullcontext


def _codac_backend() -> Backend:
    """codac 2 Intervals through the `*Op.fwd` interval functions: in codac 2.1.2 `codac.acos` and `codac.sinh`
    called on an Interval build an expression node instead (the overloads resolve to the symbolic ones)."""
    with rounding.keeping_mode():            # importing codac sets the process's rounding upward
        import codac
    I = codac.Interval  # noqa: E741
    empty = I.empty
    ZERO, ONE, UNDEC = I(0.0), I(1.0), I(0.0, 1.0)

    def bounds(x):
        if x.is_empty():
            return -_INF, _INF
        lo, hi = x.lb(), x.ub()
        if lo == -_INF or hi == _INF or lo != lo:
            return -_INF, _INF
        return lo, hi

    def straddles0(b):            # False for the empty interval too (its bounds are NaN)
        return b.lb() <= 0.0 <= b.ub()

    def div(a, b):
        if b.is_empty() or straddles0(b):
            return empty()
        return a / b

    def inv(a):
        if a.is_empty() or straddles0(a):
            return empty()
        return ONE / a

    def log(a):
        return codac.LogOp.fwd(a) if a.lb() > 0.0 else empty()

    def sqrt(a):
        return codac.SqrtOp.fwd(a) if a.lb() >= 0.0 else empty()

    nextafter = math.nextafter

    def widened(r, ulps: int = SLOPPY_ULPS):
        if r.is_empty():
            return r
        lo, hi = r.lb(), r.ub()
        for _ in range(ulps):
            lo, hi = nextafter(lo, -_INF), nextafter(hi, _INF)
        return I(lo, hi)

    def atanh(a):
        return widened(codac.atanh(a)) if -1.0 < a.lb() and a.ub() < 1.0 else empty()

    def sinh(a):
        return widened(codac.SinhOp.fwd(a))

    def tanh(a):
        r = widened(codac.TanhOp.fwd(a))
        return r if r.is_empty() else I(max(r.lb(), -1.0), min(r.ub(), 1.0))

    def asin(a):
        return codac.AsinOp.fwd(a) if -1.0 <= a.lb() and a.ub() <= 1.0 else empty()

    def acos(a):
        return codac.AcosOp.fwd(a) if -1.0 <= a.lb() and a.ub() <= 1.0 else empty()

    def tan(a):
        r = codac.TanOp.fwd(a)
        return empty() if r.is_unbounded() else r

    def power(a, b):
        if a.is_empty() or b.is_empty():
            return empty()
        if b.is_degenerated() and float(b.lb()).is_integer():
            n = b.lb()
            if n < 0 and straddles0(a):
                return empty()
            return codac.PowOp.fwd(a, I(n))
        # a real exponent: pow is exp(b log a), defined for a > 0 (and a >= 0 when b > 0)
        if a.lb() > 0.0 or (a.lb() == 0.0 and b.lb() > 0.0):
            r = codac.PowOp.fwd(a, b)
            return empty() if r.is_unbounded() else r
        return empty()

    def sign(a, ctx):
        if a.is_empty():
            return empty()
        lo, hi = a.lb(), a.ub()
        if lo > 0.0:
            return I(1.0)
        if hi < 0.0:
            return I(-1.0)
        if lo == 0.0 and hi == 0.0:
            return I(0.0)
        ctx.append("SIGN")
        return I(0.0 if lo == 0.0 else -1.0, 0.0 if hi == 0.0 else 1.0)

    def floor(a, ctx):
        r = codac.FloorOp.fwd(a)
        if not r.is_empty() and not r.is_degenerated():
            ctx.append("FLOOR")
        return r

    def ceil(a, ctx):
        r = codac.CeilOp.fwd(a)
        if not r.is_empty() and not r.is_degenerated():
            ctx.append("CEIL")
        return r

    def lt(a, b, ctx):
        if a.is_empty() or b.is_empty():
            return empty()
        if a.ub() < b.lb():
            return ONE
        if a.lb() >= b.ub():
            return ZERO
        ctx.append("LT")
        return UNDEC

    def le(a, b, ctx):
        if a.is_empty() or b.is_empty():
            return empty()
        if a.ub() <= b.lb():
            return ONE
        if a.lb() > b.ub():
            return ZERO
        ctx.append("LE")
        return UNDEC

    def eq(a, b, ctx):
        if a.is_empty() or b.is_empty():
            return empty()
        if a.ub() < b.lb() or b.ub() < a.lb():
            return ZERO
        if a.lb() == a.ub() == b.lb() == b.ub():
            return ONE
        ctx.append("EQ")
        return UNDEC

    def truth(a):                 # 0, 1 or None (undecided) of CasADi's "a != 0"; a is not empty
        if a.lb() == 0.0 and a.ub() == 0.0:
            return 0
        if a.lb() > 0.0 or a.ub() < 0.0:
            return 1
        return None

    def ne(a, b, ctx):
        r = eq(a, b, ctx)
        return r if r.is_empty() else ONE - r

    def not_(a, ctx):
        if a.is_empty():
            return empty()
        t = truth(a)
        if t is None:
            ctx.append("NOT")
            return UNDEC
        return ZERO if t else ONE

    def and_(a, b, ctx):
        if a.is_empty() or b.is_empty():
            return empty()
        ta, tb = truth(a), truth(b)
        if ta == 0 or tb == 0:
            return ZERO
        if ta == 1 and tb == 1:
            return ONE
        ctx.append("AND")
        return UNDEC

    def or_(a, b, ctx):
        if a.is_empty() or b.is_empty():
            return empty()
        ta, tb = truth(a), truth(b)
        if ta == 1 or tb == 1:
            return ONE
        if ta == 0 and tb == 0:
            return ZERO
        ctx.append("OR")
        return UNDEC

    def if_else_zero(c, x, ctx):
        if c.is_empty():
            return empty()
        t = truth(c)
        if t == 0:
            return ZERO
        if t == 1 or x.is_empty():
            return x
        ctx.append("IF_ELSE_ZERO")
        return I(min(x.lb(), 0.0), max(x.ub(), 0.0))

    def fmin(a, b):
        return empty() if a.is_empty() or b.is_empty() else codac.MinOp.fwd(a, b)

    def fmax(a, b):
        return empty() if a.is_empty() or b.is_empty() else codac.MaxOp.fwd(a, b)

    rules = {
        "ASSIGN": lambda a: a,
        "ADD": operator.add, "SUB": operator.sub, "MUL": operator.mul, "DIV": div, "NEG": operator.neg,
        "SQ": codac.SqrOp.fwd, "TWICE": lambda a: a * 2.0, "INV": inv,
        "EXP": codac.ExpOp.fwd, "LOG": log, "SQRT": sqrt, "POW": power, "CONSTPOW": power,
        "SIN": codac.SinOp.fwd, "COS": codac.CosOp.fwd, "TAN": tan, "ASIN": asin, "ACOS": acos, "ATAN": codac.AtanOp.fwd,
        "SINH": sinh, "COSH": codac.CoshOp.fwd, "TANH": tanh, "ATANH": atanh,
        "FABS": codac.AbsOp.fwd, "SIGN": sign, "FLOOR": floor, "CEIL": ceil, "FMIN": fmin, "FMAX": fmax,
        "LT": lt, "LE": le, "EQ": eq, "NE": ne, "NOT": not_, "AND": and_, "OR": or_,
        "IF_ELSE_ZERO": if_else_zero,
    }
    return Backend("codac", lambda lo, hi: I(lo, hi), lambda c: I(c), bounds, rules, empty, rounding.upward)


def _arb_backend() -> Backend:
    from flint import arb

    nan = arb.nan
    ZERO, ONE = arb(0), arb(1)
    UNDEC = arb(0.5, 0.5)         # [0, 1] exactly: 0.5 is exact as midpoint and as radius
    nextafter = math.nextafter

    def interval(lo, hi):
        if lo == hi:
            return arb(lo)
        mid = 0.5 * lo + 0.5 * hi                # inside [lo, hi]; the radius covers the rounding of mid
        rad = nextafter(max(hi - mid, mid - lo), _INF)
        return arb(mid, rad)                     # arb rounds the radius up to its 30-bit magnitude

    def bounds(x):
        if not x.is_finite():
            return -_INF, _INF
        # at 53 bits of precision the midpoint is a double (or rounds to one with < 1 ulp error, out of range):
        # one ulp outward after the nearest-rounded subtraction covers both roundings
        m, r = float(x.mid()), float(x.rad())
        if r == 0.0:
            lo = hi = m
            if arb(m) != x.mid():
                lo, hi = nextafter(m, -_INF), nextafter(m, _INF)
        else:
            lo, hi = nextafter(m - r, -_INF), nextafter(m + r, _INF)
        if not (-_INF < lo and hi < _INF):
            return -_INF, _INF
        return lo, hi

    def finite(*xs):
        return all(x.is_finite() for x in xs)

    def sq(a):
        if not a.is_finite():
            return nan()
        lo, hi = a.abs_lower(), a.abs_upper()
        return (lo * lo).union(hi * hi)

    def fabs(a):
        if not a.is_finite():
            return nan()
        return a.abs_lower().union(a.abs_upper())

    def sqrt(a):
        if not (a.is_finite() and a >= 0):
            return nan()
        return a.lower().sqrt().union(a.upper().sqrt())

    def power(a, b):
        if not finite(a, b):
            return nan()
        if b.is_exact() and b.is_integer():
            if b < 0 and a.contains(0):
                return nan()
            return a ** b                        # arb_pow with an exact integer exponent: defined for a < 0
        if a > 0 or (a >= 0 and b > 0):
            return a ** b                        # NaN where arb cannot bound it (e.g. a touching 0)
        return nan()

    def sign(a, ctx):
        if not a.is_finite():
            return nan()
        if a > 0:
            return arb(1)
        if a < 0:
            return arb(-1)
        if a.is_zero():
            return arb(0)
        ctx.append("SIGN")
        if a >= 0:
            return UNDEC
        if a <= 0:
            return arb(-0.5, 0.5)
        return arb(0, 1)

    def floor(a, ctx):
        if not a.is_finite():
            return nan()
        r = a.floor()
        if not r.is_exact():
            ctx.append("FLOOR")
        return r

    def ceil(a, ctx):
        if not a.is_finite():
            return nan()
        r = a.ceil()
        if not r.is_exact():
            ctx.append("CEIL")
        return r

    def lt(a, b, ctx):
        if not finite(a, b):
            return nan()
        if a < b:
            return ONE
        if a >= b:
            return ZERO
        ctx.append("LT")
        return UNDEC

    def le(a, b, ctx):
        if not finite(a, b):
            return nan()
        if a <= b:
            return ONE
        if a > b:
            return ZERO
        ctx.append("LE")
        return UNDEC

    def eq(a, b, ctx):
        if not finite(a, b):
            return nan()
        if a == b:                                # arb: both exact and equal
            return ONE
        if a != b:                                # arb: disjoint
            return ZERO
        ctx.append("EQ")
        return UNDEC

    def truth(a):
        if a.is_zero():
            return 0
        if a != 0:
            return 1
        return None

    def ne(a, b, ctx):
        r = eq(a, b, ctx)
        return r if not r.is_finite() else ONE - r

    def not_(a, ctx):
        if not a.is_finite():
            return nan()
        t = truth(a)
        if t is None:
            ctx.append("NOT")
            return UNDEC
        return ZERO if t else ONE

    def and_(a, b, ctx):
        if not finite(a, b):
            return nan()
        ta, tb = truth(a), truth(b)
        if ta == 0 or tb == 0:
            return ZERO
        if ta == 1 and tb == 1:
            return ONE
        ctx.append("AND")
        return UNDEC

    def or_(a, b, ctx):
        if not finite(a, b):
            return nan()
        ta, tb = truth(a), truth(b)
        if ta == 1 or tb == 1:
            return ONE
        if ta == 0 and tb == 0:
            return ZERO
        ctx.append("OR")
        return UNDEC

    def if_else_zero(c, x, ctx):
        if not c.is_finite():
            return nan()
        t = truth(c)
        if t == 0:
            return ZERO
        if t == 1 or not x.is_finite():
            return x
        ctx.append("IF_ELSE_ZERO")
        return x.union(ZERO)

    def fmin(a, b):
        return a.min(b) if finite(a, b) else nan()

    def fmax(a, b):
        return a.max(b) if finite(a, b) else nan()

    rules = {
        "ASSIGN": lambda a: a,
        # arb's own operations return NaN (indeterminate) for division by a ball containing 0, log/atanh/asin/acos
        # outside their domain and tan across a pole; NaN propagates through every arithmetic operation
        "ADD": operator.add, "SUB": operator.sub, "MUL": operator.mul, "DIV": operator.truediv,
        "NEG": operator.neg, "SQ": sq, "TWICE": lambda a: a * 2, "INV": lambda a: ONE / a,
        "EXP": arb.exp, "LOG": arb.log, "SQRT": sqrt, "POW": power, "CONSTPOW": power,
        "SIN": arb.sin, "COS": arb.cos, "TAN": arb.tan, "ASIN": arb.asin, "ACOS": arb.acos, "ATAN": arb.atan,
        "SINH": arb.sinh, "COSH": arb.cosh, "TANH": arb.tanh, "ATANH": arb.atanh,
        "FABS": fabs, "SIGN": sign, "FLOOR": floor, "CEIL": ceil, "FMIN": fmin, "FMAX": fmax,
        "LT": lt, "LE": le, "EQ": eq, "NE": ne, "NOT": not_, "AND": and_, "OR": or_,
        "IF_ELSE_ZERO": if_else_zero,
    }
    return Backend("arb", interval, lambda c: arb(c), bounds, rules, nan)


BACKENDS = ("codac", "arb")
_BACKENDS: dict[str, Backend] = {}


def get_backend(name: str) -> Backend:
    """The named backend (built once; its `rules` dict is what compiled functions call, e.g. for a test to patch)."""
    if name not in BACKENDS:
        raise ValueError(f"unknown interval backend {name!r} (expected one of {', '.join(BACKENDS)})")
    if name not in _BACKENDS:
        _BACKENDS[name] = _codac_backend() if name == "codac" else _arb_backend()
    return _BACKENDS[name]


#: every tape operation that has an interval rule (besides INPUT, OUTPUT and CONST)
RULE_OPS = frozenset(
    ("ASSIGN", "ADD", "SUB", "MUL", "DIV", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "POW", "CONSTPOW",
     "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN", "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL",
     "FMIN", "FMAX", "LT", "LE", "EQ", "NE", "NOT", "AND", "OR", "IF_ELSE_ZERO"))

#: the operations whose rule takes one argument
UNARY = frozenset(
    ("ASSIGN", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN",
     "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL", "NOT"))

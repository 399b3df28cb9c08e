"""Outward-rounded interval evaluation of an SX casadi.Function's instruction tape, with two independent backends.

`IntervalFunction(f, backend="codac" | "arb")` compiles the tape of `f` once into straight-line Python that calls
one rule per instruction: codac 2 `Interval`s (outward-rounded interval arithmetic) or python-flint `arb` balls
(midpoint-radius arithmetic with rigorous error radii). Neither backend uses the other's results.

What an enclosure means: for every point x of the input box, the exact real value of the tape's expression at x
lies in [lo, hi] (and so does CasADi's double result, for ops that IEEE rounds correctly).

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

`eval_point` is CasADi's own double evaluation of the function (what branch and bound tests midpoints with).
Compiled functions keep the previous box's intervals (rebuilding only the inputs that changed), so one
IntervalFunction is not to be shared between threads.

The codac backend does not use codac's `AnalyticFunction`: it evaluates expression *trees* (a node shared k times
is evaluated k times, exponential in the depth of CasADi's CSE'd DAG) and carries a Jacobian per node, which made
the paper's `tau` take 60 ms per box against ~0.2 ms for this tape walk.
"""

from __future__ import annotations

import contextlib
import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import casadi
import numpy as np

from ..core.errors import SymfunnelError
from ..core.pycode import compile_source
from . import rounding
from .tape import OP_NAMES, Tape, as_sx_function, read_tape

__all__ = ["IntervalError", "IntervalFunction", "Enclosure", "BACKENDS", "get_backend", "RULE_OPS"]

_INF = math.inf


class IntervalError(SymfunnelError):
    """An SX function the interval evaluator cannot take: an operation without an interval rule, or free symbols."""


class Enclosure(NamedTuple):
    """Rigorous bounds of one output in its dense shape; entries that are not enclosures are (-inf, +inf)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """Where the bounds are a real (finite) enclosure, i.e. no domain error and no overflow."""
        return np.isfinite(self.lo) & np.isfinite(self.hi)

    @property
    def all_valid(self) -> bool:
        """Whether every entry is a finite enclosure."""
        return bool(np.all(self.valid))

    def contains(self, value) -> np.ndarray:
        """Elementwise lo <= value <= hi."""
        v = np.asarray(value, dtype=float).reshape(self.lo.shape)
        return (self.lo <= v) & (v <= self.hi)


# --- backends ---------------------------------------------------------------------------------------------------

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


# --- compiling a tape -------------------------------------------------------------------------------------------

def _compile(tape: Tape, be: Backend, in_off: list[int], out_off: list[int]) -> Callable:
    """Straight-line Python for the tape: run(x, ctx) -> tuple of backend values, one per output nonzero."""
    name = tape.function.name()
    ns: dict[str, Any] = {}
    lines = ["def run(x, ctx):"]
    n_out = out_off[-1]
    outs = [None] * n_out
    consts: dict[float, str] = {}
    O = casadi  # noqa: E741
    for ins in tape.instructions:
        op, a, r = ins.op, ins.args, ins.res
        if op == O.OP_INPUT:
            lines.append(f"    w{r[0]} = x[{in_off[a[0]] + a[1]}]")
        elif op == O.OP_OUTPUT:
            k = out_off[r[0]] + r[1]
            lines.append(f"    o{k} = w{a[0]}")
            outs[k] = f"o{k}"
        elif op == O.OP_CONST:
            c = float(ins.constant)
            key = math.copysign(1.0, c) if c == 0 else c   # keep -0.0 apart from 0.0 (1/-0 differs)
            cname = consts.get(key)
            if cname is None:
                cname = consts[key] = f"C{len(consts)}"
                ns[cname] = be.point(c)
            lines.append(f"    w{r[0]} = {cname}")
        elif op == O.OP_PARAMETER:
            raise IntervalError(f"function {name!r} has free SX variables; interval evaluation needs every symbol "
                                "as an input")
        else:
            opname = OP_NAMES.get(op, f"<{op}>")
            rule = be.rules.get(opname)
            if rule is None:
                raise IntervalError(f"no interval rule for OP_{opname} in function {name!r}")
            ns.setdefault(opname, rule)
            n_args = 1 if opname in _UNARY else 2
            args = ", ".join(f"w{j}" for j in a[:n_args])
            if opname in DISCONTINUOUS:
                args += ", ctx"
            lines.append(f"    w{r[0]} = {opname}({args})")
    zero = "ZERO__"
    ns[zero] = be.point(0.0)
    lines.append("    return (" + "".join(f"{o or zero}, " for o in outs) + ")")
    code = compile_source("\n".join(lines), f"<interval tape of {name} ({be.name})>")
    exec(code, ns)
    return ns["run"]


_UNARY = frozenset(
    ("ASSIGN", "NEG", "SQ", "TWICE", "INV", "EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN",
     "SINH", "COSH", "TANH", "ATANH", "FABS", "SIGN", "FLOOR", "CEIL", "NOT"))

Box = Any   # (lo, hi) pair of arrays of the input's shape, or one array of shape (..., 2)


def read_layout(obj, function: casadi.Function):
    """The tape of an SX Function, with its inputs' and outputs' names, shapes, nonzeros and offsets set on `obj`
    (shared by the interval evaluators); IntervalError when it has free symbols."""
    tape = read_tape(function)
    if tape.free:
        raise IntervalError(f"function {function.name()!r} has free SX variables "
                            f"({', '.join(v.name() for v in tape.free)}); interval evaluation needs every symbol "
                            "as an input")
    obj.name = function.name()
    obj.in_names, obj.out_names = tape.in_names, tape.out_names
    obj.in_sx_shapes, obj.out_sx_shapes = tape.in_shapes, tape.out_shapes
    obj.in_nz, obj.out_nz = tape.in_nz, tape.out_nz
    obj.in_off = [0, *np.cumsum([len(nz) for nz in tape.in_nz]).tolist()]
    obj.out_off = [0, *np.cumsum([len(nz) for nz in tape.out_nz]).tolist()]
    return tape


class IntervalFunction:
    """Interval extension of an SX casadi.Function, compiled once from its tape, on one backend.

    `form="natural"` evaluates every instruction on intervals. `form="mean_value"` also encloses
    f(X) in f(m) + J(X) (X - m) with m the box midpoint and J CasADi's AD Jacobian (itself interval-evaluated), and
    returns the intersection with the natural enclosure: it pays off on narrow boxes, where its overestimation
    shrinks with the square of the width against linearly for the natural form (the dependency effect), and it is
    skipped on boxes where a discontinuous operation (sign, a comparison, an undecided if-else, floor) switches,
    where the mean-value theorem does not hold.

    Usage::

        F = IntervalFunction(d.function("tau"), backend="codac")
        lo, hi = F.eval([(t_lo, t_hi), (q_lo, q_hi), ...])[0]      # rigorous bounds of tau over the box
        F.eval_point([t, q, ...])                                  # the same function in double (CasADi)
    """

    def __init__(self, f: casadi.Function, backend: str = "codac", form: str = "natural"):
        if form not in ("natural", "mean_value"):
            raise ValueError(f"unknown form {form!r} (expected 'natural' or 'mean_value')")
        self.function = as_sx_function(f)
        self.backend = get_backend(backend)
        self.form = form
        tape = read_layout(self, self.function)
        self._run = _compile(tape, self.backend, self.in_off, self.out_off)
        self._jac: tuple[IntervalFunction, list[tuple[int, int]]] | None = None
        self._last: tuple | None = None
        if form == "mean_value":
            self._jac = self._jacobian()

    # --- shapes ----------------------------------------------------------------------------------------------
    @staticmethod
    def _np_shape(shape: tuple[int, int]) -> tuple[int, ...]:
        return (shape[0],) if shape[1] == 1 else shape

    @property
    def in_shapes(self) -> list[tuple[int, ...]]:
        """Numpy shape of each input: (n,) for a column vector (scalars (1,)), (r, c) for a matrix."""
        return [self._np_shape(s) for s in self.in_sx_shapes]

    @property
    def out_shapes(self) -> list[tuple[int, ...]]:
        """Numpy shape of each output, the same convention as `in_shapes`."""
        return [self._np_shape(s) for s in self.out_sx_shapes]

    @property
    def n_in_nz(self) -> int:
        """Number of scalar input nonzeros (the flat layout of `eval_flat`)."""
        return self.in_off[-1]

    @property
    def n_out_nz(self) -> int:
        """Number of scalar output nonzeros."""
        return self.out_off[-1]

    def _input_nz(self, i: int, value) -> np.ndarray:
        """The nonzeros (column-major structural order) of input i given as a scalar, vector or matrix."""
        r, c = self.in_sx_shapes[i]
        a = np.asarray(value, dtype=float)
        if a.shape == (r, c) or (c == 1 and a.size == r) or (r == 1 and a.size == c):
            flat = a.reshape((r, c), order="F" if a.shape != (r, c) else "C").ravel(order="F")
            return flat[list(self.in_nz[i])]
        if a.size == 1:
            return np.full(len(self.in_nz[i]), float(a.reshape(())))
        raise ValueError(f"input {i} ({self.in_names[i]!r}) of {self.name!r} is {r}x{c}; got shape {a.shape}")

    def _ordered(self, values) -> list:
        if isinstance(values, Mapping):
            missing = [k for k in self.in_names if k not in values]
            if missing:
                raise ValueError(f"{self.name!r} needs inputs {', '.join(missing)}")
            return [values[k] for k in self.in_names]
        values = list(values)
        if len(values) != len(self.in_names):
            raise ValueError(f"{self.name!r} has {len(self.in_names)} inputs ({', '.join(self.in_names)}); "
                             f"got {len(values)}")
        return values

    def flatten_box(self, boxes) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) flat vectors over all input nonzeros from per-input boxes (sequence in input order, or dict)."""
        los, his = [], []
        for i, b in enumerate(self._ordered(boxes)):
            if isinstance(b, tuple) and len(b) == 2:
                lo, hi = b
            else:
                a = np.asarray(b, dtype=float)
                if a.shape[-1:] != (2,):
                    raise ValueError(f"box of input {self.in_names[i]!r}: give (lo, hi) or an array of shape (..., 2)")
                lo, hi = a[..., 0], a[..., 1]
            los.append(self._input_nz(i, lo))
            his.append(self._input_nz(i, hi))
        lo = np.concatenate(los) if los else np.zeros(0)
        hi = np.concatenate(his) if his else np.zeros(0)
        if np.isnan(lo).any() or np.isnan(hi).any():
            raise ValueError(f"box of {self.name!r} has NaN bounds")
        if (lo > hi).any():
            j = int(np.argmax(lo > hi))
            raise ValueError(f"box of {self.name!r} has lo > hi at flat input {j} ({lo[j]} > {hi[j]})")
        return lo, hi

    def flatten_point(self, values) -> np.ndarray:
        """The flat vector over all input nonzeros of one point (sequence in input order, or dict)."""
        parts = [self._input_nz(i, v) for i, v in enumerate(self._ordered(values))]
        return np.concatenate(parts) if parts else np.zeros(0)

    def unflatten_point(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Per-input arrays (dense, numpy shapes of `in_shapes`) from a flat nonzero vector."""
        out = {}
        for i, name in enumerate(self.in_names):
            r, c = self.in_sx_shapes[i]
            dense = np.zeros(r * c)
            dense[list(self.in_nz[i])] = x[self.in_off[i]:self.in_off[i + 1]]
            out[name] = dense.reshape((r, c), order="F").reshape(self._np_shape((r, c)))
        return out

    def _dense_outputs(self, lo: np.ndarray, hi: np.ndarray) -> list[Enclosure]:
        out = []
        for k, (r, c) in enumerate(self.out_sx_shapes):
            L, H = np.zeros(r * c), np.zeros(r * c)
            nz = list(self.out_nz[k])
            L[nz] = lo[self.out_off[k]:self.out_off[k + 1]]
            H[nz] = hi[self.out_off[k]:self.out_off[k + 1]]
            shape = self._np_shape((r, c))
            out.append(Enclosure(L.reshape((r, c), order="F").reshape(shape),
                                 H.reshape((r, c), order="F").reshape(shape)))
        return out

    # --- evaluation ------------------------------------------------------------------------------------------
    def eval(self, boxes) -> list[Enclosure]:
        """Rigorous enclosures of every output over the box (one box per input: (lo, hi) or an (..., 2) array)."""
        lo, hi = self.flatten_box(boxes)
        return self._dense_outputs(*self.eval_flat(lo, hi))

    def eval_flat(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Enclosures of the output nonzeros (flat, output after output) over a box given by flat nonzero bounds."""
        be = self.backend
        ctx: list = []
        with be.mode():
            vals = self._run(self._inputs(lo, hi), ctx)
            bounds = be.bounds
            L = np.empty(len(vals))
            H = np.empty(len(vals))
            for k, v in enumerate(vals):
                L[k], H[k] = bounds(v)
            if self._jac is not None and not ctx:
                L, H = self._mean_value(lo, hi, L, H)
        return L, H

    def _inputs(self, lo: np.ndarray, hi: np.ndarray) -> list:
        """Backend intervals of the flat box, rebuilding only the entries that differ from the previous call's box
        (branch and bound changes one variable from box to box, and making an interval costs about an operation)."""
        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        make = self.backend.interval
        last = self._last
        if last is not None and last[0].shape == lo.shape:
            changed = np.flatnonzero((last[0] != lo) | (last[1] != hi)).tolist()
            xs = list(last[2])
            for j in changed:
                xs[j] = make(float(lo[j]), float(hi[j]))
        else:
            xs = [make(a, b) for a, b in zip(lo.tolist(), hi.tolist())]
        self._last = (lo.copy(), hi.copy(), xs)
        return xs

    def eval_values(self, lo: np.ndarray, hi: np.ndarray) -> tuple[tuple, bool]:
        """The backend's raw values of the output nonzeros over a flat box, and whether no discontinuity switched."""
        ctx: list = []
        with self.backend.mode():
            vals = self._run(self._inputs(lo, hi), ctx)
        return vals, not ctx

    def eval_point(self, values) -> list[np.ndarray]:
        """The outputs in double at one point, by the CasADi Function itself (the midpoint test of branch and bound)."""
        res = self.function(*[np.asarray(v, dtype=float) for v in self._ordered(values)])
        res = [res] if self.function.n_out() == 1 else list(res)
        return [np.asarray(casadi.DM(v).full(), dtype=float).reshape(s) for v, s in zip(res, self.out_shapes)]

    def eval_point_flat(self, x: np.ndarray) -> np.ndarray:
        """The output nonzeros in double at a flat input point (CasADi's double evaluation)."""
        args = []
        for i, (r, c) in enumerate(self.in_sx_shapes):
            args.append(casadi.DM(casadi.Sparsity(self.function.sparsity_in(i)), x[self.in_off[i]:self.in_off[i + 1]]))
        res = self.function.call(args)
        return np.concatenate([np.asarray(casadi.DM(v).nonzeros(), dtype=float) for v in res]) if res else np.zeros(0)

    # --- the mean-value form ---------------------------------------------------------------------------------
    def _jacobian(self) -> tuple[IntervalFunction, list[tuple[int, int]]]:
        f = self.function
        xin = f.sx_in()
        outs = f.call(xin)
        y = casadi.vertcat(casadi.SX(0, 1), *[casadi.SX(o).nz[:] for o in outs])
        x = casadi.vertcat(casadi.SX(0, 1), *[v.nz[:] for v in xin])
        J = casadi.jacobian(y, x)
        rows, cols = J.sparsity().get_triplet()
        jf = casadi.Function(f.name() + "_jac", xin, [J], {"cse": True})
        jif = IntervalFunction(jf, backend=self.backend.name, form="natural")
        # the jacobian's output nonzeros are column-major: entry k is (rows[k], cols[k])
        return jif, list(zip(rows, cols))

    def _mean_value(self, lo, hi, L, H):
        jf, entries = self._jac
        be = self.backend
        mid = np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
        fm = self._run([be.point(v) for v in mid.tolist()], [])
        J, _ = jf.eval_values(lo, hi)
        make = be.interval
        sub = be.rules["SUB"]
        mul = be.rules["MUL"]
        add = be.rules["ADD"]
        wide = {j for j in range(len(lo)) if lo[j] < hi[j]}
        dx = {j: sub(make(lo[j], hi[j]), be.point(mid[j])) for j in wide}
        acc = list(fm)
        for k, (i, j) in enumerate(entries):
            if j in wide:
                acc[i] = add(acc[i], mul(J[k], dx[j]))
        for i, v in enumerate(acc):
            a, b = be.bounds(v)
            # only a valid natural enclosure is tightened: a domain error stays an error
            if a > -_INF and L[i] > -_INF:
                L[i], H[i] = max(L[i], a), min(H[i], b)
                if L[i] > H[i]:
                    raise IntervalError(f"{self.name!r}: the mean-value and natural enclosures of output nonzero "
                                        f"{i} are disjoint ({a}, {b}) -- an interval rule is wrong")
        return L, H

    def __repr__(self) -> str:
        return (f"IntervalFunction({self.name!r}, backend={self.backend.name!r}, form={self.form!r}, "
                f"inputs={list(self.in_names)}, outputs={list(self.out_names)})")

"""A first-order bound of the round-off in an SX function's double evaluation, by running error analysis on its tape.

Every instruction r = op(a, b) of the tape is evaluated with an error |dr| <= |dr/da| |da| + |dr/db| |db| + u |r|
(u = 2^-53, the unit round-off; the last term is the rounding of op itself, absent for the exact operations: negation,
|x|, 2x, min, max, sign, copysign, comparisons, logic, floor, ceil, if-else). Writing |dx| <= u m(x), the magnitudes
follow the same recursion, m(r) = |dr/da| m(a) + |dr/db| m(b) + |r|, with m = 0 for the inputs and the constants (the
function is evaluated at them as they are). u m of an output bounds its round-off to first order in u: it is large
exactly where large terms cancel, e.g. the 1e12 Coriolis torque a controller cancels in the joint acceleration of a
funnel of width 1e6, and stays near u |r| where nothing cancels. libm's functions are faithful to about one ulp, not
half a one, so callers multiply by a few (`ROUNDOFF_SAFETY`).

`RoundoffBound(f)` compiles the tape once into straight-line numpy (values and magnitudes side by side, vectorised
over a trailing axis of points); an operation without a rule gives m = inf (the bound then says nothing).
"""

from __future__ import annotations

import math
import re

import casadi
import numpy as np

from ..core.pycode import compile_source
from .tape import OP_NAMES, read_tape

#: the unit round-off of IEEE double precision
UNIT_ROUNDOFF = 2.0 ** -53
#: the factor callers apply to u m: libm's functions are faithful to about 1 ulp (2 u), plus second-order terms;
#: it also covers the generated C's vectorised tanh (templates/sf_tanh.h: <= 1.8 ulp of the exact tanh, <= 3.6 u)
ROUNDOFF_SAFETY = 4.0

# value of r = op(a, b): {0}, {1} the arguments
_VALUE = {
    "ASSIGN": "{0}", "ADD": "{0} + {1}", "SUB": "{0} - {1}", "MUL": "{0} * {1}", "DIV": "{0} / {1}", "NEG": "-{0}",
    "TWICE": "{0} + {0}", "SQ": "{0} * {0}", "INV": "1.0 / {0}", "SQRT": "np.sqrt({0})", "EXP": "np.exp({0})",
    "LOG": "np.log({0})", "POW": "np.power({0}, {1})", "CONSTPOW": "np.power({0}, {1})", "SIN": "np.sin({0})",
    "COS": "np.cos({0})", "TAN": "np.tan({0})", "ASIN": "np.arcsin({0})", "ACOS": "np.arccos({0})",
    "ATAN": "np.arctan({0})", "SINH": "np.sinh({0})", "COSH": "np.cosh({0})", "TANH": "np.tanh({0})",
    "ASINH": "np.arcsinh({0})", "ACOSH": "np.arccosh({0})", "ATANH": "np.arctanh({0})",
    "ATAN2": "np.arctan2({0}, {1})", "LOG1P": "np.log1p({0})", "EXPM1": "np.expm1({0})", "HYPOT": "np.hypot({0}, {1})",
    "ERF": "_erf({0})", "FABS": "np.fabs({0})", "SIGN": "np.sign({0})", "COPYSIGN": "np.copysign({0}, {1})",
    "FMIN": "np.fmin({0}, {1})", "FMAX": "np.fmax({0}, {1})", "FLOOR": "np.floor({0})", "CEIL": "np.ceil({0})",
    "LT": "({0} < {1}) * 1.0", "LE": "({0} <= {1}) * 1.0", "EQ": "({0} == {1}) * 1.0", "NE": "({0} != {1}) * 1.0",
    "NOT": "({0} == 0.0) * 1.0", "AND": "np.logical_and({0}, {1}) * 1.0", "OR": "np.logical_or({0}, {1}) * 1.0",
    "IF_ELSE_ZERO": "np.where({0} != 0.0, {1}, 0.0)",
}

# |dr/da| and |dr/db| in terms of a = {0}, b = {1}, r = {2}; None: the argument does not move r (to first order)
_PARTIALS = {
    "ASSIGN": ("1.0", None), "ADD": ("1.0", "1.0"), "SUB": ("1.0", "1.0"), "NEG": ("1.0", None),
    "MUL": ("np.fabs({1})", "np.fabs({0})"), "DIV": ("1.0 / np.fabs({1})", "np.fabs({2} / {1})"),
    "TWICE": ("2.0", None), "SQ": ("2.0 * np.fabs({0})", None), "INV": ("{2} * {2}", None),
    "SQRT": ("0.5 / {2}", None), "EXP": ("{2}", None), "LOG": ("1.0 / np.fabs({0})", None),
    "POW": ("np.fabs({1} * {2} / {0})", "np.fabs({2} * np.log(np.fabs({0})))"),
    "CONSTPOW": ("np.fabs({1} * {2} / {0})", None),
    "SIN": ("np.fabs(np.cos({0}))", None), "COS": ("np.fabs(np.sin({0}))", None), "TAN": ("1.0 + {2} * {2}", None),
    "ASIN": ("1.0 / np.sqrt(1.0 - {0} * {0})", None), "ACOS": ("1.0 / np.sqrt(1.0 - {0} * {0})", None),
    "ATAN": ("1.0 / (1.0 + {0} * {0})", None), "SINH": ("np.cosh({0})", None), "COSH": ("np.fabs(np.sinh({0}))", None),
    "TANH": ("1.0 - {2} * {2}", None), "ASINH": ("1.0 / np.sqrt(1.0 + {0} * {0})", None),
    "ACOSH": ("1.0 / np.sqrt({0} * {0} - 1.0)", None), "ATANH": ("1.0 / np.fabs(1.0 - {0} * {0})", None),
    "ATAN2": ("np.fabs({1}) / ({0} * {0} + {1} * {1})", "np.fabs({0}) / ({0} * {0} + {1} * {1})"),
    "LOG1P": ("1.0 / np.fabs(1.0 + {0})", None), "EXPM1": ("{2} + 1.0", None),
    "HYPOT": ("np.fabs({0}) / {2}", "np.fabs({1}) / {2}"), "ERF": ("1.1283791670955126 * np.exp(-{0} * {0})", None),
    "FABS": ("1.0", None), "COPYSIGN": ("1.0", None), "SIGN": (None, None), "FLOOR": (None, None),
    "CEIL": (None, None), "LT": (None, None), "LE": (None, None), "EQ": (None, None), "NE": (None, None),
    "NOT": (None, None), "AND": (None, None), "OR": (None, None),
}

#: operations whose double result is exact given their arguments (no rounding term of their own)
EXACT_OPS = frozenset(("ASSIGN", "NEG", "FABS", "TWICE", "SIGN", "COPYSIGN", "FMIN", "FMAX", "IF_ELSE_ZERO", "LT",
                       "LE", "EQ", "NE", "NOT", "AND", "OR", "FLOOR", "CEIL"))

#: operations the bound has a rule for (others make it infinite)
RULE_OPS = frozenset(_VALUE)


class RoundoffBound:
    """Values and round-off magnitudes m of an SX function's outputs at many points (module docstring).

    Call with one array per input, shape (nnz_in, K) (column-major nonzeros, K points); returns (values, m): one
    (nnz_out, K) array each per output. The round-off of CasADi's double evaluation is at most about u m.
    """

    def __init__(self, f: casadi.Function):
        self.tape = read_tape(f)
        self.function = self.tape.function
        if self.tape.free:
            raise ValueError(f"function {self.function.name()!r} has free SX variables; the round-off bound needs "
                             "them as inputs")
        self._run = _compile(self.tape)

    def __call__(self, args: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
        g = self.function
        if len(args) != g.n_in():
            raise ValueError(f"expected {g.n_in()} inputs, got {len(args)}")
        arrays = [np.asarray(a, dtype=float) for a in args]
        K = max([a.size // g.nnz_in(i) for i, a in enumerate(arrays) if g.nnz_in(i) and a.size] or [1])
        rows = [a.reshape(g.nnz_in(i), K if not g.nnz_in(i) else -1) for i, a in enumerate(arrays)]
        with np.errstate(all="ignore"):
            vals, mags = self._run(rows, np.zeros(K))
            mags = [np.where(np.isnan(m), np.inf, m) for m in mags]
        return vals, mags


#: numpy's functions the rules use, bound by their bare names in the generated code (fewer tokens to parse)
_NUMPY_NAMES = frozenset(re.findall(r"np\.(\w+)", " ".join([*_VALUE.values(), *(d for pair in _PARTIALS.values()
                                                                                for d in pair if d)])))


def _bare(expr: str) -> str:
    return expr.replace("np.", "")


def _compile(tape):
    """Straight-line numpy for the tape: run(inputs, zero) -> (values, magnitudes), lists of (nnz_out, K) arrays.

    CPython's parser is most of the cost of building it (a tape is often evaluated once: an identity's residual
    per mutant), so the code is kept short: numpy's functions by bare name, the value written straight into its
    slot unless the slot is also an argument's, and parentheses only around a compound partial."""
    lines = ["def run(x, Z):"]
    zero_m: set[int] = set()          # work slots whose magnitude is known to be 0 (exact inputs, constants)
    outs: list[list[tuple[str, str]]] = [[("Z", "Z")] * n for n in (len(nz) for nz in tape.out_nz)]
    for ins in tape.instructions:
        op, a, r = ins.op, ins.args, ins.res
        name = OP_NAMES.get(op, "")
        if op == casadi.OP_INPUT:
            lines.append(f"    w{r[0]} = x[{a[0]}][{a[1]}] + Z")
            zero_m.add(r[0])
        elif op == casadi.OP_OUTPUT:
            outs[r[0]][r[1]] = (f"w{a[0]}", "Z" if a[0] in zero_m else f"m{a[0]}")
        elif op == casadi.OP_CONST:
            c = float(ins.constant)           # an overflowed constant prints as inf/nan: not a Python name
            lines.append(f"    w{r[0]} = Z + {c!r}" if math.isfinite(c) else f"    w{r[0]} = Z + float({str(c)!r})")
            zero_m.add(r[0])
        else:
            w = [f"w{j}" for j in a] + ["_"] * (2 - len(a))
            if name not in _VALUE:
                lines.append(f"    w{r[0]} = Z + nan")
                lines.append(f"    m{r[0]} = Z + inf")
                zero_m.discard(r[0])
                continue
            # the value goes into a temporary only when the result slot is an argument's slot too
            v = "v_" if r[0] in a else f"w{r[0]}"
            lines.append(f"    {v} = {_bare(_VALUE[name].format(*w))}")
            terms = []
            if name == "IF_ELSE_ZERO":
                if a[1] not in zero_m:
                    terms.append(f"where({w[0]} != 0.0, m{a[1]}, 0.0)")
            elif name in ("FMIN", "FMAX"):
                ms = [f"m{j}" for j in a if j not in zero_m]
                if ms:
                    terms.append(ms[0] if len(ms) == 1 else f"fmax({ms[0]}, {ms[1]})")
            else:
                for k, j in enumerate(a):
                    d = _PARTIALS[name][k]
                    if d is not None and j not in zero_m:
                        d = _bare(d.format(w[0], w[1], v))
                        terms.append(f"m{j}" if d == "1.0" else f"({d}) * m{j}" if " " in d else f"{d} * m{j}")
            if name not in EXACT_OPS:
                terms.append(f"fabs({v})")
            if terms:
                lines.append(f"    m{r[0]} = " + " + ".join(terms))
                zero_m.discard(r[0])
            else:
                zero_m.add(r[0])
            if v == "v_":
                lines.append(f"    w{r[0]} = v_")
    lines.append("    vals = [" + ", ".join("np.array([" + ", ".join(v for v, _ in o) + "]).reshape(-1, Z.size)"
                                          for o in outs) + "]")
    lines.append("    mags = [" + ", ".join("np.array([" + ", ".join(m for _, m in o) + "]).reshape(-1, Z.size)"
                                          for o in outs) + "]")
    lines.append("    return vals, mags")
    ns = {"np": np, "_erf": np.vectorize(math.erf, otypes=[float]), "nan": np.nan, "inf": np.inf}
    ns.update({k: getattr(np, k) for k in _NUMPY_NAMES})
    exec(compile_source("\n".join(lines), f"<round-off tape of {tape.function.name()}>"), ns)
    return ns["run"]


__all__ = ["UNIT_ROUNDOFF", "ROUNDOFF_SAFETY", "EXACT_OPS", "RULE_OPS", "RoundoffBound"]

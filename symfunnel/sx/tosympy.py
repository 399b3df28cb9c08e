"""Exact CasADi SX -> sympy conversion by walking an SX function's instruction tape, so nothing is derived twice."""

from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction

import casadi
import sympy

from .tape import OP_NAMES, count_ops, read_tape

__all__ = ["function_to_sympy", "sx_to_sympy", "count_ops", "to_sympy_number"]

#: Largest denominator for which a float is recognised as a "small-denominator" rational (e.g. 1/3, 2/7).
MAX_DENOMINATOR = 10_000
#: Floats whose shortest round-trip decimal has at most this many significant digits become exact decimals.
MAX_DECIMAL_DIGITS = 12

_O = casadi
_ONE = sympy.Integer(1)
_ZERO = sympy.Integer(0)


def to_sympy_number(x: float, rational: bool = True) -> sympy.Expr:
    """Convert a tape constant to sympy: integers exactly, short decimals / small-denominator rationals exactly when `rational`, else a 53-bit Float."""
    x = float(x)
    if math.isnan(x):
        return sympy.nan
    if math.isinf(x):
        return sympy.oo if x > 0 else -sympy.oo
    if x.is_integer():
        return sympy.Integer(int(x))
    if rational:
        q = Fraction(x).limit_denominator(MAX_DENOMINATOR)
        if float(q) == x:
            return sympy.Rational(q.numerator, q.denominator)
        text = repr(x)
        mantissa = text.lower().split("e")[0].replace("-", "").replace(".", "").lstrip("0")
        if len(mantissa) <= MAX_DECIMAL_DIGITS:
            return sympy.Rational(text)
    return sympy.Float(x, precision=53)


def _bool(e):
    """View a tape value (0/1 indicator or any number) as a sympy Boolean condition."""
    if isinstance(e, sympy.Piecewise) and len(e.args) == 2:
        (v1, c1), (v0, c0) = e.args
        if v1 == 1 and v0 == 0 and c0 == sympy.true:
            return c1
    if e.is_Number:
        return sympy.false if e == 0 else sympy.true
    return sympy.Ne(e, 0)


def _ind(c):
    """Turn a sympy Boolean into the 0/1 number CasADi stores for a comparison."""
    if c == sympy.true:
        return _ONE
    if c == sympy.false:
        return _ZERO
    return sympy.Piecewise((_ONE, c), (_ZERO, True))


def _trunc(z):
    """C trunc (round toward zero), which C fmod uses."""
    return sympy.sign(z) * sympy.floor(sympy.Abs(z))


def _round_half_even(z):
    """Round to nearest, ties to even, which C remainder uses."""
    n = sympy.floor(z + sympy.S.Half)
    tie = sympy.And(sympy.Eq(n, z + sympy.S.Half), sympy.Eq(sympy.Mod(n, 2), 1))
    return sympy.Piecewise((n - 1, tie), (n, True))


def _copysign(a, b):
    """|a| with the sign of b."""
    # C copysign keeps the sign bit of b, so b == +0 gives +|a|; -0.0 is not representable in sympy
    return sympy.Piecewise((sympy.Abs(a), b >= 0), (-sympy.Abs(a), True))


#: opcode -> sympy builder taking the argument values
_UNARY = {
    _O.OP_ASSIGN: lambda a: a,
    _O.OP_NEG: lambda a: -a,
    _O.OP_EXP: sympy.exp,
    _O.OP_LOG: sympy.log,
    _O.OP_SQRT: sympy.sqrt,
    _O.OP_SQ: lambda a: a**2,
    _O.OP_TWICE: lambda a: 2 * a,
    _O.OP_SIN: sympy.sin,
    _O.OP_COS: sympy.cos,
    _O.OP_TAN: sympy.tan,
    _O.OP_ASIN: sympy.asin,
    _O.OP_ACOS: sympy.acos,
    _O.OP_ATAN: sympy.atan,
    _O.OP_NOT: lambda a: _ind(sympy.Not(_bool(a))),
    _O.OP_FLOOR: sympy.floor,
    _O.OP_CEIL: sympy.ceiling,
    _O.OP_FABS: sympy.Abs,
    _O.OP_SIGN: sympy.sign,
    _O.OP_ERF: sympy.erf,
    _O.OP_ERFINV: sympy.erfinv,
    _O.OP_INV: lambda a: 1 / a,
    _O.OP_SINH: sympy.sinh,
    _O.OP_COSH: sympy.cosh,
    _O.OP_TANH: sympy.tanh,
    _O.OP_ASINH: sympy.asinh,
    _O.OP_ACOSH: sympy.acosh,
    _O.OP_ATANH: sympy.atanh,
    _O.OP_LOG1P: lambda a: sympy.log(1 + a),
    _O.OP_EXPM1: lambda a: sympy.exp(a) - 1,
}

_BINARY = {
    _O.OP_ADD: lambda a, b: a + b,
    _O.OP_SUB: lambda a, b: a - b,
    _O.OP_MUL: lambda a, b: a * b,
    _O.OP_DIV: lambda a, b: a / b,
    _O.OP_POW: sympy.Pow,
    _O.OP_CONSTPOW: sympy.Pow,
    _O.OP_LT: lambda a, b: _ind(sympy.Lt(a, b)),
    _O.OP_LE: lambda a, b: _ind(sympy.Le(a, b)),
    _O.OP_EQ: lambda a, b: _ind(sympy.Eq(a, b)),
    _O.OP_NE: lambda a, b: _ind(sympy.Ne(a, b)),
    _O.OP_AND: lambda a, b: _ind(sympy.And(_bool(a), _bool(b))),
    _O.OP_OR: lambda a, b: _ind(sympy.Or(_bool(a), _bool(b))),
    _O.OP_FMOD: lambda a, b: a - b * _trunc(a / b),
    _O.OP_REMAINDER: lambda a, b: a - b * _round_half_even(a / b),
    _O.OP_COPYSIGN: _copysign,
    _O.OP_IF_ELSE_ZERO: lambda c, a: sympy.Piecewise((a, _bool(c)), (_ZERO, True)),
    _O.OP_FMIN: sympy.Min,
    _O.OP_FMAX: sympy.Max,
    _O.OP_ATAN2: sympy.atan2,
    _O.OP_HYPOT: lambda a, b: sympy.sqrt(a**2 + b**2),
    # printme(x, y) and lift(x, x0) both evaluate to x
    _O.OP_PRINTME: lambda a, b: a,
    _O.OP_LIFT: lambda a, b: a,
}

#: Every opcode this module maps (besides INPUT, OUTPUT, CONST, PARAMETER), for tests and reports.
SUPPORTED_OPS = frozenset(OP_NAMES[o] for o in (*_UNARY, *_BINARY))


def _default_symbols(tape) -> list[list[sympy.Symbol]]:
    """Real sympy Symbols named after the SX input elements, one per structural nonzero."""
    f = tape.function
    out, seen = [], {}
    for i in range(f.n_in()):
        syms = []
        for k, e in enumerate(f.sx_in(i).nonzeros()):
            name = e.name() if e.is_symbolic() else f"{tape.in_names[i]}_{k}"
            if name in seen and seen[name] != (i, k):
                raise ValueError(
                    f"input element name {name!r} occurs twice in {f.name()!r}; pass `symbols` explicitly"
                )
            seen[name] = (i, k)
            syms.append(sympy.Symbol(name, real=True))
        out.append(syms)
    return out


def _given_symbols(tape, symbols) -> list[list]:
    """Map user-given symbols (a Matrix of the input's shape, or a flat column-major / nonzero sequence) to nonzeros."""
    if len(symbols) != len(tape.in_shapes):
        raise ValueError(f"`symbols` has {len(symbols)} entries, function has {len(tape.in_shapes)} inputs")
    out = []
    for i, (s, (r, c), nz) in enumerate(zip(symbols, tape.in_shapes, tape.in_nz)):
        if isinstance(s, sympy.MatrixBase) and s.shape == (r, c):
            out.append([s[j % r, j // r] for j in nz])
            continue
        flat = list(s)
        if len(flat) == r * c:
            out.append([sympy.sympify(flat[j]) for j in nz])
        elif len(flat) == len(nz):
            out.append([sympy.sympify(v) for v in flat])
        else:
            raise ValueError(
                f"symbols for input {i} ({tape.in_names[i]!r}, {r}x{c}, {len(nz)} nonzeros) have {len(flat)} entries"
            )
    return out


def function_to_sympy(
    f: casadi.Function,
    symbols: Sequence[sympy.MatrixBase | Sequence] | None = None,
    *,
    rational: bool = True,
) -> list[sympy.Matrix]:
    """Convert each output of an SX function to a sympy Matrix of the output's shape by replaying its tape (no simplification)."""
    tape = read_tape(f)
    ins = _given_symbols(tape, symbols) if symbols is not None else _default_symbols(tape)
    free = [sympy.Symbol(v.name(), real=True) for v in tape.free]
    n_param = 0
    w: list = [None] * tape.n_work
    outs = [[_ZERO] * (r * c) for r, c in tape.out_shapes]
    for ins_ in tape.instructions:
        op, a, res = ins_.op, ins_.args, ins_.res
        fn = _UNARY.get(op)
        if fn is not None:
            w[res[0]] = fn(w[a[0]])
            continue
        fn = _BINARY.get(op)
        if fn is not None:
            w[res[0]] = fn(w[a[0]], w[a[1]])
        elif op == _O.OP_CONST:
            w[res[0]] = to_sympy_number(ins_.constant, rational)
        elif op == _O.OP_INPUT:
            w[res[0]] = ins[a[0]][a[1]]
        elif op == _O.OP_OUTPUT:
            outs[res[0]][tape.out_nz[res[0]][res[1]]] = w[a[0]]
        elif op == _O.OP_PARAMETER:
            w[res[0]] = free[n_param]
            n_param += 1
        else:
            hint = " (build the SX without never_inline calls, or expand it)" if op == _O.OP_CALL else ""
            raise NotImplementedError(
                f"sx2sympy: CasADi operation OP_{ins_.name} on the tape of {tape.function.name()!r} is not supported{hint}"
            )
    return [sympy.Matrix(c, r, vals).T for vals, (r, c) in zip(outs, tape.out_shapes)]


def sx_to_sympy(
    expr: casadi.SX,
    inputs: Sequence[casadi.SX],
    symbols: Sequence[sympy.MatrixBase | Sequence] | None = None,
    *,
    rational: bool = True,
) -> sympy.Matrix:
    """Convert one SX expression of the purely symbolic `inputs` to a sympy Matrix (via a temporary Function's tape)."""
    inputs = [casadi.SX(v) for v in inputs]
    for i, v in enumerate(inputs):
        if not v.is_valid_input():
            raise ValueError(f"input {i} of sx_to_sympy is not purely symbolic: {v}")
    f = casadi.Function("sx_to_sympy", inputs, [casadi.SX(expr)])
    return function_to_sympy(f, symbols, rational=rational)[0]

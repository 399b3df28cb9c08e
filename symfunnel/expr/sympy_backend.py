"""Evaluating an expression tree on sympy, exactly where the text is exact: every function of the language by name."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Union

import sympy as sp

from .limits import check_exponent

#: the sympy implementation of each elementwise function of `tree.FUNCTIONS`
ELEMENTWISE = {"sin": sp.sin, "cos": sp.cos, "tan": sp.tan, "asin": sp.asin, "acos": sp.acos, "atan": sp.atan,
               "sinh": sp.sinh, "cosh": sp.cosh, "tanh": sp.tanh, "exp": sp.exp, "log": sp.log, "sqrt": sp.sqrt,
               "abs": sp.Abs, "sign": sp.sign, "min": sp.Min, "max": sp.Max, "atan2": sp.atan2}
#: the value of each constant of `tree.CONSTANTS`
CONSTANTS = {"pi": sp.pi}


@dataclass(frozen=True)
class _Mat:
    """A sympy value during evaluation: shape and row-major entries (scalars are 1x1)."""

    rows: int
    cols: int
    items: tuple


def sympy_float(v: float) -> sp.Basic:
    """A float as an exact Rational when its shortest decimal form has at most 15 digits, else a Float."""
    text = repr(float(v))
    mantissa = text.lstrip("-").split("e")[0].replace(".", "").strip("0")
    return sp.Rational(text) if len(mantissa) <= 15 else sp.Float(text)


def _sympy_number(v: Union[int, float]) -> sp.Basic:
    """An int literal as an Integer, a float literal as `sympy_float`."""
    return sp.Integer(v) if isinstance(v, int) else sympy_float(v)


class SympyBackend:
    """Evaluation on sympy expressions, kept as `_Mat` until the end."""

    def __init__(self, env: Mapping[str, Any]):
        self.env = env

    def number(self, v: Union[int, float]) -> _Mat:
        return _Mat(1, 1, (_sympy_number(v),))

    def constant(self, name: str) -> _Mat:
        return _Mat(1, 1, (CONSTANTS[name],))

    def lookup(self, name: str) -> _Mat:
        v = self.env[name]
        if isinstance(v, sp.MatrixBase):
            return _Mat(v.rows, v.cols, tuple(v))
        if isinstance(v, sp.Basic):
            return _Mat(1, 1, (v,))
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"symbol '{name}': cannot use a {type(v).__name__} as a sympy value")
        return self.number(v)

    def shape(self, v: _Mat) -> tuple[int, int]:
        return (v.rows, v.cols)

    def expand(self, v: _Mat, shape: tuple[int, int]) -> _Mat:
        r, c = shape
        if (v.rows, v.cols) == shape:
            return v
        return _Mat(r, c, tuple(v.items[(i % v.rows) * v.cols + (j % v.cols)]
                                for i in range(r) for j in range(c)))

    def neg(self, v: _Mat) -> _Mat:
        return _Mat(v.rows, v.cols, tuple(-x for x in v.items))

    def binary(self, op: str, a: _Mat, b: _Mat) -> _Mat:
        if op == "**":
            for x in b.items:
                if x.is_Number and x.is_finite:
                    check_exponent(float(x))
        f = {"+": lambda x, y: x + y, "-": lambda x, y: x - y, "*": lambda x, y: x * y,
             "/": lambda x, y: x / y, "**": lambda x, y: x ** y}[op]
        return _Mat(a.rows, a.cols, tuple(f(x, y) for x, y in zip(a.items, b.items)))

    def elementwise(self, fname: str, args: list[_Mat]) -> _Mat:
        f = ELEMENTWISE[fname]
        return _Mat(args[0].rows, args[0].cols, tuple(f(*xs) for xs in zip(*(a.items for a in args))))

    def linalg(self, fname: str, args: list[_Mat]) -> _Mat:
        a = args[0]
        if fname == "transpose":
            return _Mat(a.cols, a.rows, tuple(a.items[i * a.cols + j] for j in range(a.cols)
                                              for i in range(a.rows)))
        b = args[1]
        if fname == "outer":
            return _Mat(a.rows, b.rows, tuple(x * y for x in a.items for y in b.items))
        if fname == "dot":
            return _Mat(1, 1, (sp.Add(*(x * y for x, y in zip(a.items, b.items))),))
        return _Mat(a.rows, b.cols, tuple(
            sp.Add(*(a.items[i * a.cols + k] * b.items[k * b.cols + j] for k in range(a.cols)))
            for i in range(a.rows) for j in range(b.cols)))



def to_matrix(m: _Mat) -> Union[sp.Basic, sp.Matrix]:
    """A plain expression if 1x1, else a Matrix."""
    if (m.rows, m.cols) == (1, 1):
        return m.items[0]
    return sp.Matrix(m.rows, m.cols, list(m.items))

"""Evaluating an expression tree on CasADi SX: every function of the language by name, and its arithmetic."""

from __future__ import annotations

from typing import Any, Mapping

import casadi as ca

from .limits import check_exponent

#: the CasADi implementation of each elementwise function of `tree.FUNCTIONS`
ELEMENTWISE = {"sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "asin": ca.asin, "acos": ca.acos, "atan": ca.atan,
               "sinh": ca.sinh, "cosh": ca.cosh, "tanh": ca.tanh, "exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt,
               "abs": ca.fabs, "sign": ca.sign, "min": ca.fmin, "max": ca.fmax, "atan2": ca.atan2}
#: the value of each constant of `tree.CONSTANTS`
CONSTANTS = {"pi": ca.pi}


class CasadiBackend:
    """Evaluation on CasADi SX matrices."""

    def __init__(self, env: Mapping[str, Any]):
        self.env = env

    def number(self, v: float) -> ca.SX:
        return ca.SX(float(v))

    def constant(self, name: str) -> ca.SX:
        return ca.SX(CONSTANTS[name])

    def lookup(self, name: str) -> ca.SX:
        v = self.env[name]
        if isinstance(v, ca.SX):
            return v
        if isinstance(v, ca.DM):
            return ca.SX(v)
        if isinstance(v, bool) or not isinstance(v, (int, float)) and not hasattr(v, "__array__"):
            raise TypeError(f"symbol '{name}': cannot use a {type(v).__name__} as a CasADi value")
        return ca.SX(ca.DM(v))

    def shape(self, v: ca.SX) -> tuple[int, int]:
        return v.shape

    def expand(self, v: ca.SX, shape: tuple[int, int]) -> ca.SX:
        r, c = v.shape
        return v if (r, c) == shape else ca.repmat(v, shape[0] // r if r else 0, shape[1] // c if c else 0)

    def neg(self, v: ca.SX) -> ca.SX:
        return -v

    def binary(self, op: str, a: ca.SX, b: ca.SX) -> ca.SX:
        if op == "+":
            return a + b
        if op == "-":
            return a - b
        if op == "*":
            return a * b
        if op == "/":
            return a / b
        for i in range(b.numel()):
            if b[i].is_constant():
                check_exponent(float(b[i]))
        return ca.power(a, b)

    def elementwise(self, fname: str, args: list[ca.SX]) -> ca.SX:
        return ELEMENTWISE[fname](*args)

    def linalg(self, fname: str, args: list[ca.SX]) -> ca.SX:
        if fname == "outer":
            return ca.mtimes(args[0], args[1].T)
        if fname == "dot":
            return ca.dot(args[0], args[1])
        if fname == "transpose":
            return args[0].T
        return ca.mtimes(args[0], args[1])

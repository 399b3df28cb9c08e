"""The expression language itself: the whitelisted functions, the immutable tree a parse produces, the shape rules
every backend shares and `Expression`, which evaluates a tree on CasADi SX or on sympy.

Values are scalars or matrices.  ``+ - * / ^`` and the elementwise functions work elementwise with
broadcasting: equal shapes; a 1x1 value against any shape; an (r,1) column against a (1,c) row gives
(r,c).  Anything else is an error naming both shapes.  ``outer``, ``dot``, ``transpose`` and
``mtimes`` are the linear-algebra operations (see `FUNCTIONS`); each backend (`casadi_backend`,
`sympy_backend`) implements every function of the table by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Union

from ..core.errors import InputError
from ..core.validate import did_you_mean

_EXPECTED = "an expression of numbers, names, + - * / ^ and the functions " \
            "abs, acos, asin, atan, atan2, cos, cosh, dot, exp, log, max, min, mtimes, outer, " \
            "sign, sin, sinh, sqrt, tan, tanh, transpose"


@dataclass(frozen=True)
class FunctionSpec:
    """One whitelisted function: its arity, whether it acts elementwise, and what it computes."""

    arity: int
    elementwise: bool
    doc: str
    fold: Callable[..., float] | None = None      # float implementation for constant folding


def _sign(v: float) -> float:
    """Sign of a float as -1, 0 or 1 (casadi's and sympy's convention at 0)."""
    return float((v > 0) - (v < 0))


def _atan2(y: float, x: float) -> float:
    """atan2 for constant folding; undefined at the origin, where casadi and sympy disagree."""
    if x == 0 and y == 0:
        raise ValueError("atan2(0, 0)")
    return math.atan2(y, x)


def _dot_fold(a: float, b: float) -> float:
    """dot, outer and mtimes of two constants, which are always 1x1."""
    return a * b


FUNCTIONS: dict[str, FunctionSpec] = {
    "sin": FunctionSpec(1, True, "sine", math.sin),
    "cos": FunctionSpec(1, True, "cosine", math.cos),
    "tan": FunctionSpec(1, True, "tangent", math.tan),
    "asin": FunctionSpec(1, True, "arc sine", math.asin),
    "acos": FunctionSpec(1, True, "arc cosine", math.acos),
    "atan": FunctionSpec(1, True, "arc tangent", math.atan),
    "sinh": FunctionSpec(1, True, "hyperbolic sine", math.sinh),
    "cosh": FunctionSpec(1, True, "hyperbolic cosine", math.cosh),
    "tanh": FunctionSpec(1, True, "hyperbolic tangent", math.tanh),
    "exp": FunctionSpec(1, True, "exponential", math.exp),
    "log": FunctionSpec(1, True, "natural logarithm", math.log),
    "sqrt": FunctionSpec(1, True, "square root", math.sqrt),
    "abs": FunctionSpec(1, True, "absolute value", abs),
    "sign": FunctionSpec(1, True, "sign: -1, 0 or 1", _sign),
    "min": FunctionSpec(2, True, "elementwise minimum of two values", min),
    "max": FunctionSpec(2, True, "elementwise maximum of two values", max),
    "atan2": FunctionSpec(2, True, "atan2(y, x), the angle of the point (x, y)", _atan2),
    "outer": FunctionSpec(2, False, "outer(a, b) = a b^T of two column vectors", fold=_dot_fold),
    "dot": FunctionSpec(2, False, "dot(a, b) = sum of a_ij b_ij of two equal shapes (a^T b for vectors)",
                        fold=_dot_fold),
    "transpose": FunctionSpec(1, False, "transpose(a) = a^T", fold=lambda a: a),
    "mtimes": FunctionSpec(2, False, "mtimes(A, B) = the matrix product A B", fold=_dot_fold),
}

CONSTANTS: dict[str, float] = {"pi": math.pi}



@dataclass(frozen=True)
class Num:
    """A numeric literal (int or float, 0 <= value <= MAX_LITERAL; signs are `Neg` nodes)."""

    value: Union[int, float]


@dataclass(frozen=True)
class Const:
    """A named mathematical constant from `CONSTANTS`."""

    name: str


@dataclass(frozen=True)
class Name:
    """A free symbol, bound to a value at evaluation time."""

    id: str


@dataclass(frozen=True)
class Neg:
    """Unary minus."""

    operand: "Node"


@dataclass(frozen=True)
class BinOp:
    """An elementwise binary operation, op one of + - * / **."""

    op: str
    left: "Node"
    right: "Node"


@dataclass(frozen=True)
class Call:
    """A call of a whitelisted function with positional arguments of the right arity."""

    func: str
    args: tuple["Node", ...]


Node = Union[Num, Const, Name, Neg, BinOp, Call]



def clip(text: str, n: int = 40) -> str:
    """Text shortened to at most about n characters."""
    return text if len(text) <= n else text[:n] + "..."


def one_of(choices: Iterable[str], n: int = 30) -> str:
    """'one of a, b, c' (truncated), for `expected=`."""
    items = sorted(choices)
    if not items:
        return "no free symbols here (numbers, pi and functions only)"
    more = ", ..." if len(items) > n else ""
    return "one of " + ", ".join(items[:n]) + more



def _shape_text(shape: tuple[int, int]) -> str:
    """'3x1' for (3, 1)."""
    return f"{shape[0]}x{shape[1]}"


def _broadcast(what: str, a: tuple[int, int], b: tuple[int, int]) -> tuple[int, int]:
    """The result shape of an elementwise operation on shapes a and b, or an InputError."""
    if a == b or b == (1, 1):
        return a
    if a == (1, 1):
        return b
    if a[1] == 1 and b[0] == 1:
        return (a[0], b[1])
    if a[0] == 1 and b[1] == 1:
        return (b[0], a[1])
    raise InputError(f"'{what}': shapes {_shape_text(a)} and {_shape_text(b)} do not match",
                     expected="equal shapes, a 1x1 value, or an (r,1) column with a (1,c) row")


def _linalg_shape(fname: str, shapes: list[tuple[int, int]]) -> tuple[int, int]:
    """The result shape of a linear-algebra function, or an InputError naming the shapes."""
    a = shapes[0]
    if fname == "transpose":
        return (a[1], a[0])
    b = shapes[1]
    ok = {"outer": a[1] == 1 and b[1] == 1, "dot": a == b, "mtimes": a[1] == b[0]}[fname]
    if not ok:
        raise InputError(f"{fname}: shapes {_shape_text(a)} and {_shape_text(b)} do not fit",
                         expected=FUNCTIONS[fname].doc)
    return {"outer": (a[0], b[0]), "dot": (1, 1), "mtimes": (a[0], b[1])}[fname]



def evaluate(node: Node, be: Any) -> Any:
    """Evaluate a tree on a backend; shape rules are shared so both backends agree."""
    if isinstance(node, Num):
        return be.number(node.value)
    if isinstance(node, Const):
        return be.constant(node.name)
    if isinstance(node, Name):
        return be.lookup(node.id)
    if isinstance(node, Neg):
        return be.neg(evaluate(node.operand, be))
    if isinstance(node, BinOp):
        a, b = evaluate(node.left, be), evaluate(node.right, be)
        shape = _broadcast(f"{_describe(node.left)} {node.op} {_describe(node.right)}",
                           be.shape(a), be.shape(b))
        return be.binary(node.op, be.expand(a, shape), be.expand(b, shape))
    args = [evaluate(a, be) for a in node.args]
    if FUNCTIONS[node.func].elementwise:
        if len(args) == 2:
            shape = _broadcast(f"{node.func}(...)", be.shape(args[0]), be.shape(args[1]))
            args = [be.expand(a, shape) for a in args]
        return be.elementwise(node.func, args)
    _linalg_shape(node.func, [be.shape(a) for a in args])
    return be.linalg(node.func, args)


def _describe(node: Node) -> str:
    """A short name for an operand in shape errors."""
    if isinstance(node, Name):
        return node.id
    if isinstance(node, Call):
        return f"{node.func}(...)"
    if isinstance(node, (Num, Const)):
        return str(getattr(node, "value", getattr(node, "name", "")))
    return "(...)"




@dataclass(frozen=True)
class Expression:
    """A parsed, validated expression that evaluates identically to CasADi SX and to sympy."""

    text: str
    names: frozenset[str]
    functions: frozenset[str]
    tree: Node
    _size: int
    file: str | None = None     # where errors at evaluation time are located
    key: str | None = None

    def size(self) -> int:
        """Node count of the parsed tree."""
        return self._size

    def _check_env(self, env: Mapping[str, Any]) -> None:
        """Every free symbol must be bound."""
        missing = sorted(n for n in self.names if n not in env)
        if missing:
            raise InputError(f"'{clip(self.text)}': no value for symbol '{missing[0]}'"
                             f"{did_you_mean(missing[0], env)}", expected=one_of(env))

    def to_casadi(self, env: Mapping[str, Any]) -> Any:
        """The expression as CasADi SX, with names bound to SX/DM/float values from `env`."""
        from .casadi_backend import CasadiBackend
        try:
            self._check_env(env)
            return evaluate(self.tree, CasadiBackend(env))
        except InputError as e:
            raise e.at(self.file, self.key) from None

    def to_sympy(self, env: Mapping[str, Any]) -> Any:
        """The expression as sympy (a plain expression if 1x1, else a Matrix), exact where the text is; sympy is
        imported here, on first use."""
        from .sympy_backend import SympyBackend, to_matrix
        try:
            self._check_env(env)
            m = evaluate(self.tree, SympyBackend(env))
        except InputError as e:
            raise e.at(self.file, self.key) from None
        return to_matrix(m)

    def __repr__(self) -> str:
        return f"Expression({self.text!r})"

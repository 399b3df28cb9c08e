"""The safe expression language of scenario files: one whitelisted parse that feeds both CasADi and sympy.

Scenario files are user input and may be hostile, so an expression string is never handed to
``eval``, ``sympify`` or ``parse_expr``.  It is parsed with ``ast.parse(mode="eval")`` (which builds a
syntax tree and evaluates nothing), every node is checked against a whitelist and converted to a
small immutable tree of our own, and limits against CAS hangs (size, depth, literal magnitude,
constant exponents) are enforced before anything is evaluated.

Grammar::

    expr := number | name | pi | expr (+ - * / ** ^) expr | (+ -) expr | ( expr ) | f(expr, ...)

``^`` means power (with the precedence and right associativity of ``**``, so ``-x^2`` is ``-(x^2)``
and ``2*x^2`` is ``2*(x^2)``).  ``pi`` is the constant, never a free symbol.

Values are scalars or matrices.  ``+ - * / ^`` and the elementwise functions work elementwise with
broadcasting: equal shapes; a 1x1 value against any shape; an (r,1) column against a (1,c) row gives
(r,c).  Anything else is an error naming both shapes.  ``outer``, ``dot``, ``transpose`` and
``mtimes`` are the linear-algebra operations (see `FUNCTIONS`).
"""

from __future__ import annotations

import ast
import math
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Union

import casadi as ca
import sympy as sp

from ..core.errors import InputError
from ..core.validate import did_you_mean

__all__ = ["Expression", "parse_expression", "FUNCTIONS", "CONSTANTS", "MAX_LENGTH", "MAX_NODES",
           "MAX_DEPTH", "MAX_LITERAL", "MAX_EXPONENT", "MAX_EXACT_DIGITS"]

MAX_LENGTH = 10_000      # characters of expression text
MAX_NODES = 5_000        # nodes of the parsed tree (Expression.size())
MAX_DEPTH = 200          # nesting depth of the parsed tree, and of brackets in the text
MAX_LITERAL = 1e12       # largest magnitude of a number written in the text
MAX_EXPONENT = 64        # largest |exponent| of a power whose exponent is a constant
MAX_EXACT_DIGITS = 4_000  # bound on the digits of any exact sympy number (Python refuses str() past 4300)

_EXPECTED = "an expression of numbers, names, + - * / ^ and the functions " \
            "abs, acos, asin, atan, atan2, cos, cosh, dot, exp, log, max, min, mtimes, outer, " \
            "sign, sin, sinh, sqrt, tan, tanh, transpose"


@dataclass(frozen=True)
class FunctionSpec:
    """One whitelisted function: its arity, whether it acts elementwise, and what it computes."""

    arity: int
    elementwise: bool
    doc: str
    casadi: Callable[..., Any] | None = None      # elementwise scalar implementations
    sympy: Callable[..., Any] | None = None
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
    "sin": FunctionSpec(1, True, "sine", ca.sin, sp.sin, math.sin),
    "cos": FunctionSpec(1, True, "cosine", ca.cos, sp.cos, math.cos),
    "tan": FunctionSpec(1, True, "tangent", ca.tan, sp.tan, math.tan),
    "asin": FunctionSpec(1, True, "arc sine", ca.asin, sp.asin, math.asin),
    "acos": FunctionSpec(1, True, "arc cosine", ca.acos, sp.acos, math.acos),
    "atan": FunctionSpec(1, True, "arc tangent", ca.atan, sp.atan, math.atan),
    "sinh": FunctionSpec(1, True, "hyperbolic sine", ca.sinh, sp.sinh, math.sinh),
    "cosh": FunctionSpec(1, True, "hyperbolic cosine", ca.cosh, sp.cosh, math.cosh),
    "tanh": FunctionSpec(1, True, "hyperbolic tangent", ca.tanh, sp.tanh, math.tanh),
    "exp": FunctionSpec(1, True, "exponential", ca.exp, sp.exp, math.exp),
    "log": FunctionSpec(1, True, "natural logarithm", ca.log, sp.log, math.log),
    "sqrt": FunctionSpec(1, True, "square root", ca.sqrt, sp.sqrt, math.sqrt),
    "abs": FunctionSpec(1, True, "absolute value", ca.fabs, sp.Abs, abs),
    "sign": FunctionSpec(1, True, "sign: -1, 0 or 1", ca.sign, sp.sign, _sign),
    "min": FunctionSpec(2, True, "elementwise minimum of two values", ca.fmin, sp.Min, min),
    "max": FunctionSpec(2, True, "elementwise maximum of two values", ca.fmax, sp.Max, max),
    "atan2": FunctionSpec(2, True, "atan2(y, x), the angle of the point (x, y)", ca.atan2, sp.atan2,
                          _atan2),
    "outer": FunctionSpec(2, False, "outer(a, b) = a b^T of two column vectors", fold=_dot_fold),
    "dot": FunctionSpec(2, False, "dot(a, b) = sum of a_ij b_ij of two equal shapes (a^T b for vectors)",
                        fold=_dot_fold),
    "transpose": FunctionSpec(1, False, "transpose(a) = a^T", fold=lambda a: a),
    "mtimes": FunctionSpec(2, False, "mtimes(A, B) = the matrix product A B", fold=_dot_fold),
}

CONSTANTS: dict[str, tuple[float, Any]] = {"pi": (math.pi, sp.pi)}


# ---------------------------------------------------------------- the tree

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

_BINOPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}

_REFUSED = {   # AST node type -> what the user wrote, for the error message
    ast.Attribute: "attribute access", ast.Subscript: "indexing", ast.Lambda: "lambda",
    ast.ListComp: "a comprehension", ast.SetComp: "a comprehension", ast.DictComp: "a comprehension",
    ast.GeneratorExp: "a generator", ast.Compare: "a comparison", ast.BoolOp: "a boolean operator",
    ast.IfExp: "an if-expression", ast.NamedExpr: "an assignment", ast.JoinedStr: "an f-string",
    ast.FormattedValue: "an f-string", ast.Tuple: "a tuple", ast.List: "a list", ast.Dict: "a dict",
    ast.Set: "a set", ast.Starred: "argument unpacking", ast.Await: "await", ast.Yield: "yield",
    ast.YieldFrom: "yield", ast.Slice: "a slice",
}
_REFUSED_OPS = {ast.FloorDiv: "//", ast.Mod: "%", ast.MatMult: "@", ast.LShift: "<<",
                ast.RShift: ">>", ast.BitOr: "|", ast.BitAnd: "&", ast.BitXor: "^"}
_UNICODE_HINTS = {"\u2212": "-", "\u2013": "-", "\u00d7": "*", "\u00b7": "*", "\u22c5": "*",
                  "\u00f7": "/", "\u03c0": "pi"}


# ---------------------------------------------------------------- parsing

class _Parser:
    """Converts a checked Python AST into the expression tree, enforcing the whitelist and limits."""

    def __init__(self, names: frozenset[str] | None, file: str | None, key: str | None):
        self.allowed = names
        self.file = file
        self.key = key
        self.names: set[str] = set()
        self.functions: set[str] = set()

    def fail(self, message: str, expected: str = _EXPECTED) -> InputError:
        """An InputError located at this expression's file and key."""
        return InputError(message, file=self.file, key=self.key, expected=expected)

    def convert(self, node: ast.AST) -> tuple[Node, float | None, int]:
        """(tree, value if the subtree is constant else None, bound on the digits of its exact numbers)."""
        if isinstance(node, ast.Constant):
            return self.literal(node)
        if isinstance(node, ast.Name):
            return self.name(node.id)
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, (ast.USub, ast.UAdd)):
                tree, value, digits = self.convert(node.operand)
                if isinstance(node.op, ast.UAdd):
                    return tree, value, digits
                return Neg(tree), (None if value is None else -value), digits
            sym = "~" if isinstance(node.op, ast.Invert) else "not"
            raise self.fail(f"'{_snippet(node)}': operator '{sym}' is not allowed")
        if isinstance(node, ast.BinOp):
            return self.binop(node)
        if isinstance(node, ast.Call):
            return self.call(node)
        what = _REFUSED.get(type(node), f"'{type(node).__name__}'")
        raise self.fail(f"'{_snippet(node)}': {what} is not allowed")

    def literal(self, node: ast.Constant) -> tuple[Node, float | None, int]:
        """A real, finite number of moderate magnitude."""
        v = node.value
        if isinstance(v, bool) or v is None or v is Ellipsis:
            raise self.fail(f"'{v!r}' is not allowed", "a number")
        if isinstance(v, (str, bytes)):
            raise self.fail(f"the string {_clip(repr(v))} is not allowed", "a number or a name, unquoted")
        if isinstance(v, complex):
            raise self.fail(f"the complex number '{_clip(repr(v))}' is not allowed", "a real number")
        if not isinstance(v, (int, float)):
            raise self.fail(f"'{_clip(repr(v))}' is not allowed", "a number")
        if isinstance(v, float) and not math.isfinite(v) or abs(v) > MAX_LITERAL:
            raise self.fail(f"the number {_clip(str(v))} is too large",
                            f"numbers of magnitude at most {MAX_LITERAL:g}")
        exact = _sympy_number(v)
        digits = len(str(exact.p)) + len(str(exact.q)) if exact.is_Rational else 17
        return Num(v), float(v), digits

    def name(self, ident: str) -> tuple[Node, float | None, int]:
        """A constant, or a free symbol that must be one of the allowed names."""
        if ident in CONSTANTS:
            return Const(ident), CONSTANTS[ident][0], 1
        if ident in FUNCTIONS:
            raise self.fail(f"the function '{ident}' is used without arguments",
                            f"a call such as '{ident}(x)'")
        if self.allowed is not None and ident not in self.allowed:
            hint = did_you_mean(ident, self.allowed)
            raise self.fail(f"unknown symbol '{ident}'{hint}", _one_of(self.allowed))
        self.names.add(ident)
        return Name(ident), None, 0

    def binop(self, node: ast.BinOp) -> tuple[Node, float | None, int]:
        """An arithmetic operation; constant exponents and divisors are checked here."""
        op = _BINOPS.get(type(node.op))
        if op is None:
            sym = _REFUSED_OPS.get(type(node.op), type(node.op).__name__)
            raise self.fail(f"'{_snippet(node)}': operator '{sym}' is not allowed",
                            "the operators + - * / ^ (or **)")
        left, lv, ldigits = self.convert(node.left)
        right, rv, rdigits = self.convert(node.right)
        value = None
        digits = max(ldigits, rdigits) + 1 if op in "+-" else ldigits + rdigits
        if op == "**" and rv is not None:
            if abs(rv) > MAX_EXPONENT:
                raise self.fail(f"'{_snippet(node)}': the exponent {rv:.6g} is too large",
                                f"a constant exponent of magnitude at most {MAX_EXPONENT}")
            if lv is not None and (_is_power(left) or _is_power(right)):
                raise self.fail(f"'{_snippet(node)}': a tower of constant powers is not allowed",
                                "a single power of constants, e.g. 2^10 rather than 2^2^3")
            digits = max(ldigits, 1) * max(1, math.ceil(abs(rv))) + rdigits
        if digits > MAX_EXACT_DIGITS:
            raise self.fail(f"'{_snippet(node)}': its exact numbers would grow too large "
                            f"(about {digits} digits)", "smaller constants or exponents")
        if op == "/" and rv == 0:
            raise self.fail(f"'{_snippet(node)}': division by zero", "a nonzero divisor")
        if lv is not None and rv is not None:
            value = self.fold(node, op, lv, rv)
        return BinOp(op, left, right), value, digits

    def call(self, node: ast.Call) -> tuple[Node, float | None, int]:
        """A call of a whitelisted function by name, positional arguments only, right arity."""
        if not isinstance(node.func, ast.Name):
            raise self.fail(f"'{_snippet(node)}': only the whitelisted functions can be called",
                            _one_of(FUNCTIONS))
        fname = node.func.id
        spec = FUNCTIONS.get(fname)
        if spec is None:
            hint = did_you_mean(fname, FUNCTIONS)
            raise self.fail(f"unknown function '{fname}'{hint}", _one_of(FUNCTIONS))
        if node.keywords:
            raise self.fail(f"'{_snippet(node)}': keyword arguments are not allowed",
                            f"{fname} with {spec.arity} positional argument(s)")
        if any(isinstance(a, ast.Starred) for a in node.args):
            raise self.fail(f"'{_snippet(node)}': argument unpacking is not allowed",
                            f"{fname} with {spec.arity} positional argument(s)")
        if len(node.args) != spec.arity:
            raise self.fail(f"'{_snippet(node)}': {fname} takes {spec.arity} argument(s), "
                            f"got {len(node.args)}", f"{fname}: {spec.doc}")
        self.functions.add(fname)
        converted = [self.convert(a) for a in node.args]
        args = tuple(c[0] for c in converted)
        values = [c[1] for c in converted]
        digits = max(c[2] for c in converted)
        value = None
        if all(v is not None for v in values):
            value = self.fold(node, fname, *values)
        if not spec.elementwise:
            digits = sum(c[2] for c in converted)
        return Call(fname, args), value, digits

    def fold(self, node: ast.AST, op: str, *args: float) -> float:
        """Evaluate a constant subexpression in floats, rejecting overflow and non-real results."""
        try:
            if op in FUNCTIONS:
                v = FUNCTIONS[op].fold(*args)
            elif op == "+":
                v = args[0] + args[1]
            elif op == "-":
                v = args[0] - args[1]
            elif op == "*":
                v = args[0] * args[1]
            elif op == "/":
                v = args[0] / args[1]
            else:
                v = args[0] ** args[1]
        except ZeroDivisionError:
            raise self.fail(f"'{_snippet(node)}': division by zero", "a nonzero divisor") from None
        except (OverflowError, ValueError):
            v = math.nan
        if isinstance(v, complex) or not math.isfinite(v):
            raise self.fail(f"'{_snippet(node)}' does not evaluate to a finite real number",
                            "constant subexpressions with finite real values")
        return float(v)


def _is_power(node: Node) -> bool:
    """Whether a tree is a power, possibly negated (for the constant-tower rule)."""
    while isinstance(node, Neg):
        node = node.operand
    return isinstance(node, BinOp) and node.op == "**"


def _snippet(node: ast.AST) -> str:
    """The source of an AST node (clipped), for error messages; ^ shows as **."""
    try:
        return _clip(ast.unparse(node))
    except Exception:   # unparse of a valid tree should not fail; the message must never crash
        return type(node).__name__


def _clip(text: str, n: int = 40) -> str:
    """Text shortened to at most about n characters."""
    return text if len(text) <= n else text[:n] + "..."


def _one_of(choices: Iterable[str], n: int = 30) -> str:
    """'one of a, b, c' (truncated), for `expected=`."""
    items = sorted(choices)
    if not items:
        return "no free symbols here (numbers, pi and functions only)"
    more = ", ..." if len(items) > n else ""
    return "one of " + ", ".join(items[:n]) + more


def _prescan(text: str, fail: Callable[..., InputError]) -> str:
    """Reject by character, length and bracket depth what ast.parse must not see; return the text to parse."""
    if len(text) > MAX_LENGTH:
        raise fail(f"the expression is too long ({len(text)} characters)",
                   f"at most {MAX_LENGTH} characters")
    depth = 0
    for i, ch in enumerate(text):
        if ch in "([{":
            depth += 1
            if depth > MAX_DEPTH:
                raise fail(f"brackets are nested too deeply (more than {MAX_DEPTH})",
                           f"nesting depth at most {MAX_DEPTH}")
        elif ch in ")]}":
            depth -= 1
            if depth < 0:
                raise fail(f"unbalanced '{ch}' at position {i + 1}", "balanced parentheses")
        elif ch == "#":
            raise fail(f"'#' at position {i + 1} is not allowed (no comments in expressions)")
        elif ord(ch) > 126:
            hint = f"; did you mean '{_UNICODE_HINTS[ch]}'?" if ch in _UNICODE_HINTS else ""
            raise fail(f"non-ASCII character {ch!r} at position {i + 1}{hint}")
        elif ord(ch) < 32 and ch not in "\t\n\r" or ord(ch) == 127:
            raise fail(f"control character {ch!r} at position {i + 1}")
    if depth != 0:
        raise fail("unbalanced '('", "balanced parentheses")
    stripped = " ".join(text.split())   # newlines in TOML multi-line strings are plain spaces
    if not stripped:
        raise fail("the expression is empty", _EXPECTED)
    return stripped.replace("^", "**")   # ^ is power, with the precedence of **


def _measure(tree: ast.AST, fail: Callable[..., InputError]) -> None:
    """Check node count and nesting depth iteratively, before any recursive walk."""
    count = 0
    stack = [(tree, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, ast.expr):
            depth += 1
            count += 1
            if depth > MAX_DEPTH:
                raise fail(f"the expression is nested too deeply (more than {MAX_DEPTH} levels)",
                           f"nesting depth at most {MAX_DEPTH}")
            if count > 2 * MAX_NODES:
                raise fail(f"the expression is too large (more than {MAX_NODES} nodes)",
                           f"at most {MAX_NODES} nodes")
        stack.extend((child, depth) for child in ast.iter_child_nodes(node))


def _size(node: Node) -> int:
    """Number of nodes of a tree."""
    if isinstance(node, Neg):
        return 1 + _size(node.operand)
    if isinstance(node, BinOp):
        return 1 + _size(node.left) + _size(node.right)
    if isinstance(node, Call):
        return 1 + sum(_size(a) for a in node.args)
    return 1


def parse_expression(text: str, names: Iterable[str] | None = None, *, file: str | None = None,
                     key: str | None = None) -> Expression:
    """Parse and fully validate an expression from a (possibly hostile) file; every failure is an InputError.

    `names=None` allows any identifier (the caller checks `Expression.names` later); otherwise every
    identifier must be one of `names`.  `file` and `key` locate errors.
    """
    def fail(message: str, expected: str = _EXPECTED) -> InputError:
        return InputError(message, file=file, key=key, expected=expected)

    if not isinstance(text, str):
        raise fail(f"is a {type(text).__name__}", "a string holding an expression")
    allowed = None if names is None else frozenset(names)
    source = _prescan(text, fail)
    try:
        with warnings.catch_warnings():   # e.g. SyntaxWarning "invalid decimal literal" for '1if'
            warnings.simplefilter("ignore")
            tree = ast.parse(source, mode="eval")
    except SyntaxError as e:
        if "digits" in str(e.msg):
            raise fail("a number has too many digits",
                       f"numbers of magnitude at most {MAX_LITERAL:g}") from None
        raise fail(f"syntax error ({e.msg}) in '{_clip(text.strip())}'") from None
    except (RecursionError, MemoryError) as e:
        raise fail(f"the expression is nested too deeply to parse ({type(e).__name__})",
                   f"nesting depth at most {MAX_DEPTH}") from None
    except (ValueError, OverflowError) as e:
        raise fail(f"cannot be parsed ({type(e).__name__})") from None
    try:
        _measure(tree, fail)
        parser = _Parser(allowed, file, key)
        root, _, _ = parser.convert(tree.body)
        size = _size(root)
    except (RecursionError, MemoryError, OverflowError, ValueError) as e:
        raise fail(f"cannot be parsed ({type(e).__name__})") from None
    if size > MAX_NODES:
        raise fail(f"the expression is too large ({size} nodes)", f"at most {MAX_NODES} nodes")
    return Expression(text, frozenset(parser.names), frozenset(parser.functions), root, size, file, key)


# ---------------------------------------------------------------- evaluation

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


def _check_exponent(value: float | None) -> None:
    """Refuse a numeric exponent beyond MAX_EXPONENT that only became known at evaluation time."""
    if value is not None and abs(value) > MAX_EXPONENT:
        raise InputError(f"an exponent evaluates to {value:g}",
                         expected=f"exponents of magnitude at most {MAX_EXPONENT}")


class _Casadi:
    """Evaluation on CasADi SX matrices."""

    def __init__(self, env: Mapping[str, Any]):
        self.env = env

    def number(self, v: float) -> ca.SX:
        return ca.SX(float(v))

    def constant(self, name: str) -> ca.SX:
        return ca.SX(CONSTANTS[name][0])

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
                _check_exponent(float(b[i]))
        return ca.power(a, b)

    def elementwise(self, fname: str, args: list[ca.SX]) -> ca.SX:
        return FUNCTIONS[fname].casadi(*args)

    def linalg(self, fname: str, args: list[ca.SX]) -> ca.SX:
        if fname == "outer":
            return ca.mtimes(args[0], args[1].T)
        if fname == "dot":
            return ca.dot(args[0], args[1])
        if fname == "transpose":
            return args[0].T
        return ca.mtimes(args[0], args[1])


@dataclass(frozen=True)
class _Mat:
    """A sympy value during evaluation: shape and row-major entries (scalars are 1x1)."""

    rows: int
    cols: int
    items: tuple


def _sympy_float(v: float) -> sp.Basic:
    """A float as an exact Rational when its shortest decimal form has at most 15 digits, else a Float."""
    text = repr(float(v))
    mantissa = text.lstrip("-").split("e")[0].replace(".", "").strip("0")
    return sp.Rational(text) if len(mantissa) <= 15 else sp.Float(text)


def _sympy_number(v: Union[int, float]) -> sp.Basic:
    """An int literal as an Integer, a float literal as `_sympy_float`."""
    return sp.Integer(v) if isinstance(v, int) else _sympy_float(v)


class _Sympy:
    """Evaluation on sympy expressions, kept as `_Mat` until the end."""

    def __init__(self, env: Mapping[str, Any]):
        self.env = env

    def number(self, v: Union[int, float]) -> _Mat:
        return _Mat(1, 1, (_sympy_number(v),))

    def constant(self, name: str) -> _Mat:
        return _Mat(1, 1, (CONSTANTS[name][1],))

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
                    _check_exponent(float(x))
        f = {"+": lambda x, y: x + y, "-": lambda x, y: x - y, "*": lambda x, y: x * y,
             "/": lambda x, y: x / y, "**": lambda x, y: x ** y}[op]
        return _Mat(a.rows, a.cols, tuple(f(x, y) for x, y in zip(a.items, b.items)))

    def elementwise(self, fname: str, args: list[_Mat]) -> _Mat:
        f = FUNCTIONS[fname].sympy
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


def _evaluate(node: Node, be: Any) -> Any:
    """Evaluate a tree on a backend; shape rules are shared so both backends agree."""
    if isinstance(node, Num):
        return be.number(node.value)
    if isinstance(node, Const):
        return be.constant(node.name)
    if isinstance(node, Name):
        return be.lookup(node.id)
    if isinstance(node, Neg):
        return be.neg(_evaluate(node.operand, be))
    if isinstance(node, BinOp):
        a, b = _evaluate(node.left, be), _evaluate(node.right, be)
        shape = _broadcast(f"{_describe(node.left)} {node.op} {_describe(node.right)}",
                           be.shape(a), be.shape(b))
        return be.binary(node.op, be.expand(a, shape), be.expand(b, shape))
    args = [_evaluate(a, be) for a in node.args]
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
            raise InputError(f"'{_clip(self.text)}': no value for symbol '{missing[0]}'"
                             f"{did_you_mean(missing[0], env)}", expected=_one_of(env))

    def to_casadi(self, env: Mapping[str, Union[ca.SX, ca.DM, float]]) -> ca.SX:
        """The expression as CasADi SX, with names bound to SX/DM/float values from `env`."""
        try:
            self._check_env(env)
            return _evaluate(self.tree, _Casadi(env))
        except InputError as e:
            raise e.at(self.file, self.key) from None

    def to_sympy(self, env: Mapping[str, Union[sp.Basic, sp.MatrixBase, float]]
                 ) -> Union[sp.Basic, sp.Matrix]:
        """The expression as sympy (a plain expression if 1x1, else a Matrix), exact where the text is."""
        try:
            self._check_env(env)
            m = _evaluate(self.tree, _Sympy(env))
        except InputError as e:
            raise e.at(self.file, self.key) from None
        if (m.rows, m.cols) == (1, 1):
            return m.items[0]
        return sp.Matrix(m.rows, m.cols, list(m.items))

    def __repr__(self) -> str:
        return f"Expression({self.text!r})"

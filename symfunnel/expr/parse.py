"""Parsing expression text from (possibly hostile) scenario files into the tree: ``ast.parse(mode="eval")``, which
evaluates nothing, then a whitelist over every node, and the limits, before anything is evaluated."""

from __future__ import annotations

import ast
import math
import warnings
from fractions import Fraction
from typing import Callable, Iterable

from ..core.errors import InputError
from ..core.validate import did_you_mean
from .limits import (
    MAX_DEPTH,
    MAX_EXACT_DIGITS,
    MAX_EXPONENT,
    MAX_LENGTH,
    MAX_LITERAL,
    MAX_NODES,
)
from .tree import (
    CONSTANTS,
    FUNCTIONS,
    BinOp,
    Call,
    Const,
    Expression,
    Name,
    Neg,
    Node,
    Num,
    clip,
    one_of,
)

_EXPECTED = "an expression of numbers, names, + - * / ^ and the functions " \
            "abs, acos, asin, atan, atan2, cos, cosh, dot, exp, log, max, min, mtimes, outer, " \
            "sign, sin, sinh, sqrt, tan, tanh, transpose"

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
            raise self.fail(f"the string {clip(repr(v))} is not allowed", "a number or a name, unquoted")
        if isinstance(v, complex):
            raise self.fail(f"the complex number '{clip(repr(v))}' is not allowed", "a real number")
        if not isinstance(v, (int, float)):
            raise self.fail(f"'{clip(repr(v))}' is not allowed", "a number")
        if isinstance(v, float) and not math.isfinite(v) or abs(v) > MAX_LITERAL:
            raise self.fail(f"the number {clip(str(v))} is too large",
                            f"numbers of magnitude at most {MAX_LITERAL:g}")
        digits = exact_digits(v)
        return Num(v), float(v), digits

    def name(self, ident: str) -> tuple[Node, float | None, int]:
        """A constant, or a free symbol that must be one of the allowed names."""
        if ident in CONSTANTS:
            return Const(ident), CONSTANTS[ident], 1
        if ident in FUNCTIONS:
            raise self.fail(f"the function '{ident}' is used without arguments",
                            f"a call such as '{ident}(x)'")
        if self.allowed is not None and ident not in self.allowed:
            hint = did_you_mean(ident, self.allowed)
            raise self.fail(f"unknown symbol '{ident}'{hint}", one_of(self.allowed))
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
                            one_of(FUNCTIONS))
        fname = node.func.id
        spec = FUNCTIONS.get(fname)
        if spec is None:
            hint = did_you_mean(fname, FUNCTIONS)
            raise self.fail(f"unknown function '{fname}'{hint}", one_of(FUNCTIONS))
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
        return clip(ast.unparse(node))
    except Exception:   # unparse of a valid tree should not fail; the message must never crash
        return type(node).__name__


def exact_digits(v: int | float) -> int:
    """Digits of the exact number a literal stands for (numerator and denominator of the rational its shortest
    decimal form is, 17 for a float that needs more than 15 significant digits): the sympy backend's exact value."""
    if isinstance(v, int):
        return len(str(v)) + 1
    text = repr(float(v))
    mantissa = text.lstrip("-").split("e")[0].replace(".", "").strip("0")
    if len(mantissa) > 15:
        return 17
    f = Fraction(text)
    return len(str(f.numerator)) + len(str(f.denominator))


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
        from ..core.validate import a_type
        raise fail(f"is {a_type(text)}", "a string holding an expression")
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
        raise fail(f"syntax error ({e.msg}) in '{clip(text.strip())}'") from None
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


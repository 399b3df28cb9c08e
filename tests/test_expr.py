"""Tests of the safe expression language: backend agreement, broadcasting, exactness, hostile input."""

from __future__ import annotations

import random

import casadi as ca
import numpy as np
import pytest
import sympy as sp
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from symfunnel.core.errors import InputError
from symfunnel.expr import FUNCTIONS, MAX_NODES, parse_expression

SCALARS = ["x", "y", "z"]
FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ---------------------------------------------------------------- helpers

def casadi_value(expr, shapes: dict[str, tuple[int, int]], values: dict[str, np.ndarray]) -> np.ndarray:
    """Evaluate an Expression through a casadi.Function at numeric values."""
    syms = {n: ca.SX.sym(n, *shapes[n]) for n in shapes}
    out = expr.to_casadi(syms)
    f = ca.Function("f", [syms[n] for n in shapes], [out])
    return np.array(f(*[ca.DM(values[n]) for n in shapes]), dtype=float)


def sympy_value(expr, shapes: dict[str, tuple[int, int]], values: dict[str, np.ndarray]) -> np.ndarray:
    """Evaluate an Expression through sympy (entry symbols, lambdify with numpy) at numeric values."""
    env, flat_syms, flat_vals = {}, [], []
    for n, (r, c) in shapes.items():
        if (r, c) == (1, 1):
            s = sp.Symbol(n)
            env[n] = s
            flat_syms.append(s)
            flat_vals.append(float(np.asarray(values[n]).reshape(-1)[0]))
        else:
            m = sp.Matrix(r, c, lambda i, j: sp.Symbol(f"{n}_{i}_{j}"))
            env[n] = m
            flat_syms.extend(m)
            flat_vals.extend(np.asarray(values[n], dtype=float).reshape(r, c).reshape(-1))
    out = expr.to_sympy(env)
    f = sp.lambdify(flat_syms, out, modules="numpy")
    with np.errstate(all="ignore"):
        v = np.array(f(*flat_vals), dtype=complex)
    return np.atleast_2d(v)


def assert_agree(text: str, shapes, values) -> None:
    """Both backends give the same numbers (skipping points where the value is not tame)."""
    e = parse_expression(text)
    a = casadi_value(e, shapes, values)
    assume(np.all(np.isfinite(a)) and np.max(np.abs(a), initial=0.0) < 1e6)
    b = sympy_value(e, shapes, values)
    assert a.shape == b.shape, text
    assert np.allclose(b.imag, 0.0, atol=1e-9), text
    np.testing.assert_allclose(b.real, a, rtol=1e-7, atol=1e-8, err_msg=text)


def rejected(text, **kw) -> InputError:
    """The InputError parsing `text` raises (failing the test if it parses)."""
    with pytest.raises(InputError) as info:
        parse_expression(text, **kw)
    return info.value


# ---------------------------------------------------------------- expression strategies

LITERALS = st.sampled_from(["0.3", "2", "1.5", "0.25", "3", "1e-1", "0.7", "1"])


def _scalar_expr(leaves):
    """Random scalar expressions of the grammar whose values stay tame on [-2, 2]."""
    def extend(e):
        two = st.tuples(e, e)
        return st.one_of(
            two.map(lambda p: f"({p[0]}) + ({p[1]})"),
            two.map(lambda p: f"({p[0]}) - ({p[1]})"),
            two.map(lambda p: f"({p[0]})*({p[1]})"),
            two.map(lambda p: f"({p[0]})/(1.5 + sin({p[1]}))"),
            st.tuples(e, st.sampled_from(["^", "**"]), st.sampled_from(["2", "3", "-1", "0.5"])).map(
                lambda p: f"(1.25 + tanh({p[0]})){p[1]}{p[2]}"),
            st.tuples(e, st.sampled_from(["^2", "**2", "^3"])).map(lambda p: f"tanh({p[0]}){p[1]}"),
            st.tuples(e, e).map(lambda p: f"(2 + cos({p[0]}))^tanh({p[1]})"),
            e.map(lambda a: f"-({a})"),
            e.map(lambda a: f"+({a})"),
            st.tuples(st.sampled_from(["sin", "cos", "tanh", "atan", "abs"]), e).map(
                lambda p: f"{p[0]}({p[1]})"),
            e.map(lambda a: f"exp(sin({a}))"),
            e.map(lambda a: f"log(1 + abs({a}))"),
            # sqrt's condition number is unbounded at 0: sympy's exact sin(pi) = 0 against CasADi's 1.2e-16 makes
            # sqrt(abs(sqrt(abs(sin(pi))))) 0 against 1.05e-4; away from 0 both must agree to rounding
            e.map(lambda a: f"sqrt(0.01 + abs({a}))"),
            e.map(lambda a: f"tan(tanh({a}))"),
            e.map(lambda a: f"asin(tanh({a}))"),
            e.map(lambda a: f"acos(0.9*tanh({a}))"),
            e.map(lambda a: f"sinh(tanh({a})) + cosh(tanh({a}))"),
            st.tuples(st.sampled_from(["min", "max"]), e, e).map(lambda p: f"{p[0]}({p[1]}, {p[2]})"),
            two.map(lambda p: f"atan2({p[0]}, 2 + cos({p[1]}))"),
        )
    return st.recursive(st.one_of(leaves, LITERALS), extend, max_leaves=12)


SCALAR_EXPR = _scalar_expr(st.sampled_from(SCALARS + ["sign(x)", "pi"]))
POINT = st.floats(-2.0, 2.0, allow_nan=False).map(lambda v: round(v, 6))


# ---------------------------------------------------------------- backend agreement

@FAST
@given(SCALAR_EXPR, POINT, POINT, POINT)
def test_backends_agree_on_random_scalar_expressions(text, x, y, z):
    shapes = {n: (1, 1) for n in SCALARS}
    assert_agree(text, shapes, {"x": x, "y": y, "z": z})


def _vector_expr():
    """Random 3x1 expressions mixing vectors, scalars (broadcast) and the linear-algebra functions."""
    scalar = _scalar_expr(st.sampled_from(["s"]))

    def extend(e):
        return st.one_of(
            st.tuples(e, st.sampled_from(["+", "-", "*"]), e).map(lambda p: f"({p[0]}) {p[1]} ({p[2]})"),
            st.tuples(scalar, e).map(lambda p: f"({p[0]})*({p[1]})"),
            st.tuples(e, scalar).map(lambda p: f"({p[0]}) + {p[1]}"),
            e.map(lambda a: f"sin({a})"),
            e.map(lambda a: f"tanh({a})^2"),
            st.tuples(e, e).map(lambda p: f"max({p[0]}, {p[1]})"),
            e.map(lambda a: f"mtimes(A, {a})"),
            e.map(lambda a: f"transpose(mtimes(transpose({a}), A))"),
            st.tuples(e, e, e).map(lambda p: f"mtimes(outer({p[0]}, {p[1]}), {p[2]})"),
            st.tuples(e, e, e).map(lambda p: f"dot({p[0]}, {p[1]})*({p[2]})"),
            st.tuples(e, e).map(lambda p: f"({p[0]})/(2 + cos({p[1]}))"),
        )
    return st.recursive(st.sampled_from(["u", "v", "0.5*u"]), extend, max_leaves=6)


VEC = st.lists(POINT, min_size=3, max_size=3).map(lambda l: np.array(l).reshape(3, 1))
MAT = st.lists(POINT, min_size=9, max_size=9).map(lambda l: np.array(l).reshape(3, 3) / 3)


@FAST
@given(_vector_expr(), VEC, VEC, POINT, MAT)
def test_backends_agree_on_random_vector_expressions(text, u, v, s, A):
    shapes = {"u": (3, 1), "v": (3, 1), "s": (1, 1), "A": (3, 3)}
    assert_agree(text, shapes, {"u": u, "v": v, "s": s, "A": A})


def test_paper_style_expressions():
    e = parse_expression("-Gamma*(outer(Phi, zeta2*z2) - sigma*w_hat)")
    assert e.names == {"Gamma", "Phi", "zeta2", "z2", "sigma", "w_hat"}
    assert e.functions == {"outer"}
    shapes = {"Gamma": (1, 1), "Phi": (4, 1), "zeta2": (1, 1), "z2": (2, 1), "sigma": (1, 1),
              "w_hat": (4, 2)}
    rng = np.random.default_rng(0)
    values = {n: rng.uniform(-1, 1, s) for n, s in shapes.items()}
    a = casadi_value(e, shapes, values)
    expected = -values["Gamma"] * (values["Phi"] @ (values["zeta2"] * values["z2"]).T
                                   - values["sigma"] * values["w_hat"])
    np.testing.assert_allclose(a, expected, rtol=1e-12)
    np.testing.assert_allclose(sympy_value(e, shapes, values).real, expected, rtol=1e-12)
    e = parse_expression("beta*l2^2 + gamma*l1*l2*cos(q2)")
    b, g, l1, l2, q2 = sp.symbols("beta gamma l1 l2 q2")
    got = e.to_sympy({"beta": b, "gamma": g, "l1": l1, "l2": l2, "q2": q2})
    assert sp.simplify(got - (b * l2**2 + g * l1 * l2 * sp.cos(q2))) == 0


# ---------------------------------------------------------------- semantics

def test_caret_is_power_with_power_precedence():
    x = sp.Symbol("x")
    assert parse_expression("x^2").to_sympy({"x": x}) == x**2
    assert parse_expression("2*x^2 + 1").to_sympy({"x": x}) == 2 * x**2 + 1
    assert parse_expression("-x^2").to_sympy({"x": x}) == -(x**2)
    assert parse_expression("x^3^2").to_sympy({"x": x}) == x**9            # right associative
    assert parse_expression("x^-1").to_sympy({"x": x}) == 1 / x
    sx = ca.SX.sym("x")
    f = ca.Function("f", [sx], [parse_expression("3*x^2").to_casadi({"x": sx})])
    assert float(f(2.0)) == 12.0


def test_sympy_literals_are_exact():
    x = sp.Symbol("x")
    assert parse_expression("0.3*x").to_sympy({"x": x}) == sp.Rational(3, 10) * x
    assert parse_expression("0.1*x + 0.2*x - 0.3*x").to_sympy({"x": x}) == 0
    assert parse_expression("1e-3").to_sympy({}) == sp.Rational(1, 1000)
    two = parse_expression("2").to_sympy({})
    assert isinstance(two, sp.Integer) and two == 2
    assert parse_expression("1/3").to_sympy({}) == sp.Rational(1, 3)
    assert parse_expression("2*pi").to_sympy({}) == 2 * sp.pi
    assert parse_expression("x").to_sympy({"x": 0.25}) == sp.Rational(1, 4)   # env floats too
    long = parse_expression("0.12345678901234567").to_sympy({})
    assert isinstance(long, sp.Float)


def test_sympy_scalar_results_are_plain_expressions():
    u = sp.Matrix(sp.symbols("u0:3"))
    out = parse_expression("dot(u, u)").to_sympy({"u": u})
    assert isinstance(out, sp.Expr) and not isinstance(out, sp.MatrixBase)
    assert isinstance(parse_expression("x + 1").to_sympy({"x": sp.Symbol("x")}), sp.Expr)
    assert isinstance(parse_expression("2*u").to_sympy({"u": u}), sp.MatrixBase)


@pytest.mark.parametrize("text, shapes, result", [
    ("s + u", {"s": (1, 1), "u": (3, 1)}, (3, 1)),
    ("u*s", {"s": (1, 1), "u": (3, 1)}, (3, 1)),
    ("u*v", {"u": (3, 1), "v": (3, 1)}, (3, 1)),
    ("W - 2", {"W": (2, 3)}, (2, 3)),
    ("u + w", {"u": (3, 1), "w": (1, 2)}, (3, 2)),
    ("w * u", {"u": (3, 1), "w": (1, 2)}, (3, 2)),
    ("max(u, w)", {"u": (3, 1), "w": (1, 2)}, (3, 2)),
    ("u^s", {"s": (1, 1), "u": (3, 1)}, (3, 1)),
    ("outer(u, v)", {"u": (3, 1), "v": (2, 1)}, (3, 2)),
    ("dot(u, v)", {"u": (3, 1), "v": (3, 1)}, (1, 1)),
    ("transpose(W)", {"W": (2, 3)}, (3, 2)),
    ("mtimes(W, u)", {"W": (2, 3), "u": (3, 1)}, (2, 1)),
])
def test_broadcasting_and_linear_algebra_shapes(text, shapes, result):
    rng = np.random.default_rng(1)
    values = {n: rng.uniform(0.5, 1.5, s) for n, s in shapes.items()}
    a = casadi_value(parse_expression(text), shapes, values)
    assert a.shape == result
    np.testing.assert_allclose(sympy_value(parse_expression(text), shapes, values).real, a, rtol=1e-12)
    # the (r,1) with (1,c) rule is the numpy outer broadcast
    if text == "u + w":
        np.testing.assert_allclose(a, values["u"] + values["w"])


@pytest.mark.parametrize("text, shapes, named", [
    ("u + v", {"u": (3, 1), "v": (2, 1)}, "3x1 and 2x1"),
    ("W * u", {"W": (2, 3), "u": (3, 1)}, "2x3 and 3x1"),
    ("min(u, w)", {"u": (3, 1), "w": (1, 3)}, None),   # allowed: outer broadcast
    ("outer(w, u)", {"w": (1, 3), "u": (3, 1)}, "1x3 and 3x1"),
    ("dot(u, v)", {"u": (3, 1), "v": (2, 1)}, "3x1 and 2x1"),
    ("mtimes(u, v)", {"u": (3, 1), "v": (3, 1)}, "3x1 and 3x1"),
])
def test_shape_mismatch_is_an_input_error_naming_the_shapes(text, shapes, named):
    e = parse_expression(text, file="s.toml", key="design.k")
    cenv = {n: ca.SX.sym(n, *s) for n, s in shapes.items()}
    senv = {n: sp.zeros(*s) if s != (1, 1) else sp.Symbol(n) for n, s in shapes.items()}
    if named is None:
        e.to_casadi(cenv)
        e.to_sympy(senv)
        return
    for convert, env in ((e.to_casadi, cenv), (e.to_sympy, senv)):
        with pytest.raises(InputError) as info:
            convert(env)
        assert named in str(info.value) and "s.toml" in str(info.value)


def test_missing_name_at_evaluation():
    e = parse_expression("x1 + x2", file="s.toml", key="k")
    with pytest.raises(InputError, match="x2"):
        e.to_casadi({"x1": ca.SX.sym("x1")})
    with pytest.raises(InputError, match="x2"):
        e.to_sympy({"x1": sp.Symbol("x1")})


def test_exponent_known_only_at_evaluation_is_limited():
    e = parse_expression("x^n")
    with pytest.raises(InputError, match="exponent"):
        e.to_sympy({"x": sp.Integer(9), "n": sp.Integer(10**6)})
    with pytest.raises(InputError, match="exponent"):
        e.to_casadi({"x": 9.0, "n": 1e6})
    assert e.to_sympy({"x": sp.Integer(2), "n": 10}) == 1024


def test_api_attributes():
    e = parse_expression("0.3*sin(t) + max(q1, pi)", names=["t", "q1"])
    assert e.text == "0.3*sin(t) + max(q1, pi)"
    assert e.names == frozenset({"t", "q1"})
    assert e.functions == frozenset({"sin", "max"})
    assert e.size() == 8
    assert set(FUNCTIONS) >= {"sin", "cos", "tan", "exp", "log", "sqrt", "abs", "sign", "tanh", "min",
                              "max", "outer", "dot", "transpose", "mtimes"}
    assert all(spec.doc for spec in FUNCTIONS.values())
    multi = parse_expression("q1 +\n  2*t")     # TOML multi-line strings
    assert multi.names == {"q1", "t"}


# ---------------------------------------------------------------- hostile input

HOSTILE = [
    "__import__('os').system('ls')", "().__class__.__bases__", "q1.real", "q[0]", "lambda x: x",
    "[x for x in y]", "open('f')", "sin(x=1)", "sin(*a)", "'abc'", "1j", "True", "q1 if q2 else t",
    "q1 < 2", "9**9**9", "2**1000", "q1**100000", "1e300", "10000000000000000000000", "(" * 100000,
    "sin" * 5000, "q1" + "+q1" * 20000, "\x00", "", "   ", "sin(sin)", "sin()", "min(q1)", "f(q1)",
    "q1 and q2", "{1:2}", "(1,2)", "q1 @ q2", "q1 // 2", "q1 % 2", "~q1", "1/0",
    # further cases
    "-" * 9000 + "x", "not " * 2000 + "x", "x**" * 2000 + "x", "+".join(["x"] * 3000), "1" * 5000,
    "(" * 300 + "x" + ")" * 300, "sin(" * 250 + "x" + ")" * 250, "x # comment", "q1 \u2212 q2",
    "x + 1)", "(x", "None", "...", "b'x'", "f'{x}'", "(y := 2)", "{x}", "x[1:2]", "sin(x)(y)",
    "x.y(z)", "2^2^2", "(2^3)^2", "1e400", "x/(1-1)", "0^-1", "sqrt(-1)", "log(0)", "exp(1e4)",
    "(-8)^(1/3)", "x^(2^7)", "x^exp(10)", "atan2(0, 0)", "x ^^ 2", "x | y", "x & y", "x << 2",
    "not x", "x;y", "import os", "x = 1", "await x", "(yield)", "*x", "x if y", "sin(1, 2)",
    "outer(x)", "q1\x07", "\ufeffx", 5, None, b"x",
    "((x*1.000000000001)^64)^64", "1e-300^64", "-(2^3)^2", "2^-3^2",   # exact numbers too large, towers
]


@pytest.mark.parametrize("text", HOSTILE, ids=lambda t: repr(t)[:30])
def test_hostile_strings_are_rejected(text):
    err = rejected(text, file="scenario.toml", key="plant.disturbance")
    assert "scenario.toml" in str(err) and "plant.disturbance" in str(err)
    assert err.expected


def test_limits_are_not_too_tight():
    parse_expression("sin(" * 150 + "x" + ")" * 150)
    parse_expression("+".join(["x"] * 150))
    parse_expression("1e12 + 2^64 + x^-64 + 1e-300")
    parse_expression("(((((x)))))")
    parse_expression("(1.25 + tanh(tanh(pi)^2))^2 + x^(2^3)")   # powers inside functions are no towers
    assert len(str(parse_expression("(0.1 + 1e-12)^64").to_sympy({}))) < 4300
    err = rejected("+".join(["sin(x)*cos(y)"] * 400))   # a left-deep chain of 400 sums
    assert "deeply" in str(err)


def test_node_limit(monkeypatch):
    import symfunnel.expr.parse as expr
    text = "(" + "+".join(["x"] * 30) + ")*(" + "+".join(["y"] * 30) + ")"
    assert parse_expression(text).size() == 2 * 59 + 1
    monkeypatch.setattr(expr, "MAX_NODES", 100)
    assert "too large" in str(rejected(text))
    assert MAX_NODES == 5000


def test_unknown_names_get_a_hint():
    err = rejected("x + t", names=["x1", "t", "q1"], file="a.toml", key="initial.q")
    assert "unknown symbol 'x'" in str(err) and "did you mean 'x1'" in str(err)
    assert "a.toml" in str(err) and "initial.q" in str(err) and "x1" in err.expected
    err = rejected("sinh(x) + coss(x)")
    assert "did you mean 'cos'" in str(err)
    parse_expression("x1 + 2*t + pi", names=["x1", "t"])   # pi is a constant, not a name


# ---------------------------------------------------------------- fuzzing

def _only_input_errors(text: str) -> None:
    """Parsing and evaluating arbitrary text raises nothing but InputError."""
    try:
        e = parse_expression(text, file="f.toml", key="k")
    except InputError as err:
        assert "f.toml" in str(err)
        return
    try:
        e.to_casadi({n: ca.SX.sym(n) for n in e.names})
        e.to_sympy({n: sp.Symbol(n) for n in e.names})
    except InputError:
        pass


ALPHABET = "xyqt0123456789.e+-*/^() ,sincoexpmaqrtlgbd_[]{}'\"=<>!@#%&|~:;\n\\"


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=60))
def test_fuzz_arbitrary_text(text):
    _only_input_errors(text)


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=ALPHABET, max_size=40))
def test_fuzz_grammar_alphabet(text):
    _only_input_errors(text)


VALID = ["0.3*sin(t)", "beta*l2^2 + gamma*l1*l2*cos(q2)", "-Gamma*(outer(Phi, zeta2) - sigma*w)",
         "max(x, 2)^3 / (1 + exp(-y))", "atan2(y, x) + sqrt(abs(x))", "x^-2 + 1e-3*log(1 + x^2)"]


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(VALID), st.lists(st.tuples(st.integers(0, 200), st.sampled_from(
    ["del", "ins", "rep", "dup"]), st.sampled_from(list(ALPHABET) + ["**", "sin(", "9^9", "1e99"])),
    min_size=1, max_size=4))
def test_fuzz_mutated_valid_strings(base, edits):
    text = base
    for pos, kind, piece in edits:
        i = pos % (len(text) + 1)
        if kind == "del":
            text = text[:i] + text[i + 1:]
        elif kind == "ins":
            text = text[:i] + piece + text[i:]
        elif kind == "rep":
            text = text[:i] + piece + text[i + 1:]
        else:
            text = text[:i] + text[i:i + 5] + text[i:]
    _only_input_errors(text)


def test_random_deep_and_wide_inputs_stay_input_errors():
    rng = random.Random(7)
    pieces = ["(", ")", "sin(", "x", "+", "-", "*", "^", "2", ",", "9", "e"]
    for _ in range(200):
        _only_input_errors("".join(rng.choice(pieces) for _ in range(rng.randint(1, 3000))))


def test_both_backends_implement_every_function_and_constant_of_the_language():
    from symfunnel.expr import casadi_backend, sympy_backend
    from symfunnel.expr.tree import CONSTANTS
    elementwise = {k for k, spec in FUNCTIONS.items() if spec.elementwise}
    assert set(casadi_backend.ELEMENTWISE) == elementwise == set(sympy_backend.ELEMENTWISE)
    assert set(casadi_backend.CONSTANTS) == set(CONSTANTS) == set(sympy_backend.CONSTANTS)


def test_parsing_and_casadi_evaluation_do_not_import_sympy():
    import subprocess
    import sys
    code = ("import sys, casadi as ca\nfrom symfunnel.expr import parse_expression\n"
            "e = parse_expression('sin(q1)^2 + max(t, 2*pi) + 0.1', {'q1', 't'})\n"
            "e.to_casadi({'q1': ca.SX.sym('q1'), 't': ca.SX.sym('t')})\nprint('sympy' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"

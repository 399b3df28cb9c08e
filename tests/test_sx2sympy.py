"""Tests for the exact SX -> sympy conversion through the instruction tape."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from symfunnel.sx.tape import OP_NAMES, read_tape
from symfunnel.sx.tosympy import SUPPORTED_OPS, count_ops, function_to_sympy, sx_to_sympy, to_sympy_number


def all_ops_function() -> ca.Function:
    """A function of x in (0.5, 2), y, z in (-2, 2) whose tape uses every mapped operation except ASSIGN/PRINTME/LIFT."""
    x, y, z = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("z")
    m = ca.SX.sym("m", 2, 2)
    e = [
        x + y, x - y, x * y, x / (y + 3), -x, ca.exp(y), ca.log(x), x**y, x**2.5, ca.sqrt(x), y**2, 2 * y,
        ca.sin(y), ca.cos(y), ca.tan(y / 2), ca.asin(y / 3), ca.acos(z / 3), ca.atan(y),
        ca.if_else(x < y, x, y), ca.if_else(y <= z, y * z, 1.0), (y == z) + 1, (y != z) * x,
        ca.logic_not(y < z) * x, ca.logic_and(x < y, y < z) + x, ca.logic_or(y < x, z < x) * y,
        ca.floor(3 * y), ca.ceil(3 * z), ca.fmod(3 * y, x), ca.remainder(3 * y, x), ca.fabs(y), ca.sign(y - z),
        ca.copysign(x, y - z), ca.erf(y), ca.fmin(y, z), ca.fmax(y, z), 1 / x,
        ca.sinh(y), ca.cosh(y), ca.tanh(y), ca.asinh(y), ca.acosh(1 + x), ca.atanh(y / 3), ca.atan2(y, z),
        ca.log1p(x), ca.expm1(y), ca.hypot(y, z), ca.mtimes(m, ca.vertcat(y, z))[1] + m[0, 1] * 0.1,
        ca.erfinv(ca.tanh(z) / 2),  # last: CasADi's own erfinv is only accurate to ~1e-12 relative
    ]
    return ca.Function("allops", [x, y, z, m], [ca.vertcat(*e)], ["x", "y", "z", "m"], ["e"])


def random_point(rng):
    """Random (x, y, z, m) inside the domains all_ops_function needs."""
    return [rng.uniform(0.5, 2.0), rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-2, 2, (2, 2))]


def evaluate_sympy(expr: sp.Matrix, subs: dict) -> np.ndarray:
    """Evaluate a sympy Matrix at a point with 30 significant digits."""
    vals = {k: sp.Float(float(v), 30) for k, v in subs.items()}
    return np.array([[float(sp.N(e.xreplace(vals), 30)) for e in row] for row in expr.tolist()])


def assert_close(a, b, rtol=1e-12):
    """Elementwise |a - b| <= rtol * max(1, |b|), reporting the offending entries."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    bad = np.argwhere(~(np.abs(a - b) <= rtol * np.maximum(1.0, np.abs(b))))
    assert bad.size == 0, [(tuple(i), a[tuple(i)], b[tuple(i)]) for i in bad]


def test_every_mapped_op_is_on_the_test_tape():
    used = {ins.name for ins in read_tape(all_ops_function()).instructions}
    assert SUPPORTED_OPS - {"ASSIGN", "PRINTME", "LIFT"} <= used


def test_all_ops_match_casadi_numerically():
    f = all_ops_function()
    (e,) = function_to_sympy(f)
    assert e.shape == (f.size1_out(0), 1)
    syms = {s.name: s for s in e.free_symbols}
    rng = np.random.default_rng(1)
    for _ in range(12):
        x, y, z, m = random_point(rng)
        ref = np.array(f(x, y, z, m))
        vals = {"x": x, "y": y, "z": z, **{f"m_{k}": v for k, v in enumerate(m.flatten(order="F"))}}
        subs = {s: vals[name] for name, s in syms.items()}
        got = evaluate_sympy(e, subs)
        assert_close(got[:-1], ref[:-1])
        assert_close(got[-1:], ref[-1:], rtol=1e-10)


def test_comparison_branches_both_ways():
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    f = ca.Function("f", [x, y], [ca.vertcat(ca.if_else(x < y, x, y), x == y, ca.logic_not(x), ca.sign(x))])
    (e,) = function_to_sympy(f)
    sx, sy = sp.Symbol("x", real=True), sp.Symbol("y", real=True)
    for a, b in [(1, 2), (2, 1), (3, 3), (0, 5), (-1, -1)]:
        got = [float(v) for v in e.xreplace({sx: a, sy: b})]
        assert got == [float(v) for v in np.array(f(a, b)).ravel()]


def test_exact_constants_make_identities_simplify_to_zero():
    x = ca.SX.sym("x")
    e = sx_to_sympy((x + 0.5) ** 2 - x**2 - x - 0.25, [x])
    assert e.shape == (1, 1)
    assert sp.simplify(e[0]) == 0
    e = sx_to_sympy(0.3 * x + 0.7 * x - x + 1 / 3.0, [x])
    assert sp.simplify(e[0]) == sp.Rational(1, 3)


def test_constant_conversion():
    assert to_sympy_number(0.5) == sp.Rational(1, 2)
    assert to_sympy_number(0.3) == sp.Rational(3, 10)
    assert to_sympy_number(9.81) == sp.Rational(981, 100)
    two = to_sympy_number(2.0)
    assert two == 2 and isinstance(two, sp.Integer)
    assert isinstance(to_sympy_number(2.0, rational=False), sp.Integer)
    assert to_sympy_number(float("inf")) == sp.oo
    tricky = 0.123456789012345678
    f = to_sympy_number(tricky)
    assert isinstance(f, sp.Float) and float(f) == tricky
    assert float(to_sympy_number(0.1, rational=False)) == 0.1


@settings(max_examples=200, deadline=None)
@given(st.integers(-10**6, 10**6), st.integers(1, 1000))
def test_small_rationals_are_recovered_exactly(p, q):
    assert to_sympy_number(p / q) == sp.Rational(p, q)


@settings(max_examples=200, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=False))
def test_constants_round_trip_to_the_same_double(v):
    assert float(to_sympy_number(v)) == v
    assert float(to_sympy_number(v, rational=False)) == v


def test_matrix_shape_sparsity_and_symbol_names():
    q1, q2 = ca.SX.sym("q1"), ca.SX.sym("q2")
    q = ca.vertcat(q1, q2)
    m = ca.SX(2, 2)
    m[0, 0] = ca.cos(q1)
    m[1, 0] = q1 * q2
    m[1, 1] = 1.5
    f = ca.Function("M", [q], [m, m.T, ca.SX(3, 1)])
    assert f.nnz_out(0) == 3
    a, at, z = function_to_sympy(f)
    s1, s2 = sp.symbols("q1 q2", real=True)
    assert a == sp.Matrix([[sp.cos(s1), 0], [s1 * s2, sp.Rational(3, 2)]])
    assert at == a.T
    assert z == sp.zeros(3, 1)


def test_explicit_symbols():
    x = ca.SX.sym("x", 2)
    m = ca.SX.sym("m", 2, 2)
    f = ca.Function("f", [x, m], [ca.mtimes(m, x)])
    a, b = sp.symbols("a b")
    M = sp.Matrix(2, 2, sp.symbols("m11 m12 m21 m22"))
    (e,) = function_to_sympy(f, [sp.Matrix([a, b]), M])
    assert sp.expand(e - M * sp.Matrix([a, b])) == sp.zeros(2, 1)
    (e,) = function_to_sympy(f, [[1, 2], [1, 0, 0, 1]])  # flat, column-major
    assert e == sp.Matrix([1, 2])
    with pytest.raises(ValueError):
        function_to_sympy(f, [[1, 2]])


def test_duplicate_symbol_names_are_refused():
    a, b = ca.SX.sym("x"), ca.SX.sym("x")
    f = ca.Function("f", [a, b], [a - b])
    with pytest.raises(ValueError, match="twice"):
        function_to_sympy(f)
    (e,) = function_to_sympy(f, [[sp.Symbol("u")], [sp.Symbol("v")]])
    assert e[0] == sp.Symbol("u") - sp.Symbol("v")


def test_free_variables_become_symbols():
    x, p = ca.SX.sym("x"), ca.SX.sym("p")
    f = ca.Function("f", [x], [x * p + 2 * p], {"allow_free": True})
    (e,) = function_to_sympy(f)
    sx, sp_ = sp.Symbol("x", real=True), sp.Symbol("p", real=True)
    assert sp.expand(e[0] - (sx * sp_ + 2 * sp_)) == 0


def test_mx_function_is_expanded():
    x = ca.MX.sym("x", 2)
    f = ca.Function("f", [x], [ca.sin(x) * 2], ["x"], ["y"])
    (e,) = function_to_sympy(f)  # expand() names the SX elements after the input: x_0, x_1
    assert e == sp.Matrix([2 * sp.sin(sp.Symbol("x_0", real=True)), 2 * sp.sin(sp.Symbol("x_1", real=True))])


def test_unsupported_call_raises():
    x = ca.SX.sym("x")
    g = ca.Function("g", [x], [ca.sin(x)], {"never_inline": True})
    f = ca.Function("f", [x], [g(x) * 2])
    assert any(ins.name == "CALL" for ins in read_tape(f).instructions)
    with pytest.raises(NotImplementedError, match="OP_CALL"):
        function_to_sympy(f)


def test_sx_to_sympy_requires_symbolic_inputs():
    x = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match="purely symbolic"):
        sx_to_sympy(x[0] * 2, [x * 2])


def test_count_ops():
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    f = ca.Function("f", [x, y], [x * y + 0.5, x])
    c = count_ops(f)
    assert c["operations"] == 2
    assert c["by_op"] == {"ADD": 1, "MUL": 1}
    assert c["instructions"] == f.n_instructions() > 2
    big = count_ops(all_ops_function())
    assert big["operations"] == sum(big["by_op"].values()) < big["instructions"]
    assert set(big["by_op"]) <= set(OP_NAMES.values())


def test_read_tape_lists_every_instruction_as_casadi_reports_it():
    """read_tape's instructions (named tuples since they are built once per instruction of large tapes) against
    CasADi's own per-instruction accessors, field by field, on a tape with constants, unary and binary operations."""
    import casadi as ca
    from symfunnel.sx.tape import read_tape
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [ca.vertcat(ca.sin(x[0]) * 2.5 + x[1] / x[2], ca.fmax(x[0], 0.3) - ca.sqrt(x[1]))])
    tape = read_tape(f)
    assert len(tape.instructions) == f.n_instructions()
    for k, ins in enumerate(tape.instructions):
        assert ins.op == f.instruction_id(k)
        assert ins.args == tuple(f.instruction_input(k)) and ins.res == tuple(f.instruction_output(k))
        assert ins.constant == (f.instruction_constant(k) if ins.op == ca.OP_CONST else None)
        assert ins.name == next(n[3:] for n in dir(ca) if n.startswith("OP_") and getattr(ca, n) == ins.op) \
            or getattr(ca, "OP_" + ins.name) == ins.op
    assert {ins.name for ins in tape.instructions} >= {"SIN", "DIV", "FMAX", "SQRT", "CONST"}

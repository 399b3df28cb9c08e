"""Tests for the numpy-only Python module emitted from SX instruction tapes."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import time

import casadi as ca
import mpmath
import numpy as np
import pytest

from symfunnel.emit.python import SUPPORTED_OPS, emit_python, manifest_entry
from symfunnel.sx.tape import read_tape

N_POINTS = 1000


def build_functions() -> list[ca.Function]:
    """Fresh test functions (rebuilt on each call, so re-emission is checked on new SX objects)."""
    x, y, z = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("z")
    m = ca.SX.sym("m", 2, 2)
    ops = [
        x + y, x - y, x * y, x / (y + 3), -x, ca.exp(y), ca.log(x), x**y, x**2.5, ca.sqrt(x), y**2, 2 * y,
        ca.sin(y), ca.cos(y), ca.tan(y / 2), ca.asin(y / 3), ca.acos(z / 3), ca.atan(y),
        ca.if_else(x < y, x, y), ca.if_else(y <= z, y * z, 1.0), (y == z) + 1, (y != z) * x,
        ca.logic_not(y < z) * x, ca.logic_and(x < y, y < z) + x, ca.logic_or(y < x, z < x) * y,
        ca.floor(3 * y), ca.ceil(3 * z), ca.fmod(3 * y, x), ca.remainder(3 * y, x), ca.fabs(y), ca.sign(y - z),
        ca.copysign(x, y - z), ca.erf(y), ca.fmin(y, z), ca.fmax(y, z), 1 / x,
        ca.sinh(y), ca.cosh(y), ca.tanh(y), ca.asinh(y), ca.acosh(1 + x), ca.atanh(y / 3), ca.atan2(y, z),
        ca.log1p(x), ca.expm1(y), ca.hypot(y, z), ca.mtimes(m, ca.vertcat(y, z))[1] + m[0, 1] * 0.1,
    ]
    allops = ca.Function("allops", [x, y, z, m], [ca.vertcat(*ops)], ["x", "y", "z", "m"], ["e"])

    q, A = ca.SX.sym("q", 3), ca.SX.sym("A", 3, 2)
    low = ca.SX(3, 3)
    for i in range(3):
        for j in range(i + 1):
            low[i, j] = ca.sin(q[i]) * q[j] + (i == j)
    mats = ca.Function(
        "mats", [q, A], [low, ca.mtimes(A.T, q), ca.mtimes(A, A.T), ca.SX(2, 3), ca.SX.zeros(1, 2), q.T],
        ["q", "A"], ["L", "Atq", "AAt", "empty", "zero", "qt"],
    )

    r = ca.SX.sym("r", 1, 4)
    row = ca.Function("row", [r, x], [ca.sum2(r) * x, ca.tanh(r) ** 2], ["r", "s"], ["total", "act"])

    e = ca.SX.sym("e")
    scalar = ca.Function("scalar", [e], [ca.erfinv(ca.tanh(e) * 0.99)], ["e"], ["v"])

    const = ca.Function("const", [], [ca.DM([[1.5, 0.1], [-2.0, 3.0]])], [], ["c"])
    return [allops, mats, row, scalar, const]


def random_args(f: ca.Function, rng, batch: int | None):
    """Random arguments of f's input shapes (with a trailing batch axis when `batch`), in safe domains."""
    args = []
    for i in range(f.n_in()):
        shape = (f.size1_in(i), f.size2_in(i)) + ((batch,) if batch else ())
        lo = 0.5 if f.name_in(i) == "x" else -2.0
        args.append(rng.uniform(lo, 2.0, shape))
    return args


def casadi_batched(f: ca.Function, args, batch: int):
    """Evaluate f with casadi's map over a batch, as arrays of shape (r, c, B); map works on horzcat'ed arguments."""
    hcat = [a.transpose(0, 2, 1).reshape(a.shape[0], batch * a.shape[1]) for a in args]
    res = f.map(batch)(*hcat)
    res = [res] if isinstance(res, ca.DM) else res
    return [
        np.array(v).reshape(f.size1_out(j), batch, f.size2_out(j)).transpose(0, 2, 1) for j, v in enumerate(res)
    ]


def assert_close(a, b, rtol=1e-13):
    """Elementwise |a - b| <= rtol * max(1, |b|), reporting the offending entries."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    bad = np.argwhere(~(np.abs(a - b) <= rtol * np.maximum(1.0, np.abs(b))))
    assert bad.size == 0, [(tuple(i), a[tuple(i)], b[tuple(i)]) for i in bad[:5]]


def load(path, name="generated_mod"):
    """Import a generated module from its file path."""
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """The test functions, their emitted module (imported) and its path."""
    fs = build_functions()
    path = tmp_path_factory.mktemp("gen") / "gen_mod.py"
    path.write_text(emit_python(fs, module_doc="Test functions."))
    return fs, load(path), path


def test_all_mapped_ops_are_exercised():
    used = {ins.name for f in build_functions() for ins in read_tape(f).instructions}
    assert SUPPORTED_OPS - {"ASSIGN", "PRINTME", "LIFT"} <= used


@pytest.mark.parametrize("name", ["allops", "mats", "row"])
def test_batched_agrees_with_casadi(generated, name):
    fs, mod, _ = generated
    f = {g.name(): g for g in fs}[name]
    args = random_args(f, np.random.default_rng(7), N_POINTS)
    got = getattr(mod, name)(*args)
    ref = casadi_batched(f, args, N_POINTS)
    assert isinstance(got, tuple) and len(got) == f.n_out()
    for g, r in zip(got, ref):
        assert g.shape == r.shape
        assert_close(g, r)


def test_unbatched_calls_and_flat_vectors(generated):
    fs, mod, _ = generated
    rng = np.random.default_rng(3)
    for f in fs:
        for _ in range(20):
            args = random_args(f, rng, None)
            res = f.call(args)  # a list of DM, also for functions without inputs
            ref = [np.array(v) for v in res]
            if f.name() == "scalar":  # CasADi's erfinv is off by up to ~4e-7 relative on the negative side
                ref = [np.array([[float(mpmath.erfinv(mpmath.mpf(np.tanh(args[0][0, 0]) * 0.99)))]])]
            got = getattr(mod, f.name())(*args)
            for j, (g, r) in enumerate(zip(got, ref)):
                assert g.shape == (f.size1_out(j), f.size2_out(j))
                assert_close(g, r)
    q, A = rng.normal(size=3), rng.normal(size=(3, 2))
    a, b = mod.mats(q, A), mod.mats(q.reshape(3, 1), A)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    Q = rng.normal(size=(3, 5))  # (r*c, B) for a column vector
    batched = mod.mats(Q, np.repeat(A[:, :, None], 5, axis=2))
    for k in range(5):
        single = mod.mats(Q[:, k], A)
        assert all(np.array_equal(u[..., k], v) for u, v in zip(batched, single))
    mixed = mod.mats(Q, A)  # unbatched arguments broadcast against batched ones
    assert all(np.array_equal(u, v) for u, v in zip(mixed, batched))
    assert mod.const()[0].tolist() == [[1.5, 0.1], [-2.0, 3.0]]
    assert float(mod.scalar(0.3)[0][0, 0]) == float(mod.scalar(np.array([[0.3]]))[0][0, 0])


def test_sparse_outputs_have_structural_zeros(generated):
    _, mod, _ = generated
    L, _, _, empty, zero, qt = mod.mats(np.array([1.0, 2.0, 3.0]), np.ones((3, 2)))
    assert np.all(np.triu(L, 1) == 0) and np.all(np.diag(L) != 0)
    assert empty.shape == (2, 3) and not empty.any()
    assert zero.shape == (1, 2) and not zero.any()
    assert qt.shape == (1, 3)


def test_erfinv_helper_is_accurate(generated):
    _, mod, _ = generated
    ys = np.concatenate([np.linspace(-0.999999, 0.999999, 101), [1e-12, -1e-300, 0.0]])
    got = mod._erfinv(ys)
    mpmath.mp.dps = 30
    ref = np.array([float(mpmath.erfinv(mpmath.mpf(float(y)))) for y in ys])
    assert_close(got, ref, rtol=1e-14)
    assert list(mod._erfinv(np.array([1.0, -1.0]))) == [np.inf, -np.inf] and np.isnan(mod._erfinv(1.5))


def test_bad_arguments_are_refused(generated):
    _, mod, _ = generated
    with pytest.raises(ValueError, match="A"):
        mod.mats(np.zeros(3), np.zeros(6))  # a flat vector is ambiguous for a 3x2 matrix
    with pytest.raises(ValueError, match="batch"):
        mod.mats(np.zeros((3, 4)), np.zeros((3, 2, 5)))


def test_emission_is_deterministic(generated):
    _, _, path = generated
    again = emit_python(build_functions(), module_doc="Test functions.")
    assert again == path.read_text()
    assert emit_python(build_functions()[:2]) == emit_python(build_functions()[:2])


def test_manifest_and_functions(generated):
    fs, mod, _ = generated
    assert mod.MANIFEST == [manifest_entry(f) for f in fs]
    assert mod.MANIFEST[1]["outputs"][0] == {"name": "L", "shape": [3, 3]}
    assert list(mod.FUNCTIONS) == [f.name() for f in fs]
    assert all(mod.FUNCTIONS[f.name()] is getattr(mod, f.name()) for f in fs)
    assert "allops(x[1x1], y[1x1], z[1x1], m[2x2]) -> (e[47x1])" in mod.__doc__


BLOCKER = """
import importlib.abc, importlib.util, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("casadi", "sympy", "symfunnel", "scipy"):
            raise ImportError("blocked: " + name)
sys.meta_path.insert(0, Block())
for banned in ("casadi", "sympy"):
    try:
        __import__(banned)
    except ImportError:
        pass
    else:
        raise SystemExit("blocker failed")
spec = importlib.util.spec_from_file_location("gen", sys.argv[1])
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
import numpy as np
out = mod.mats(np.array([1.0, 2.0, 3.0]), np.ones((3, 2)))
print(repr(float(out[0][2, 1])), float(mod.allops(1.0, 0.5, -0.5, np.eye(2))[0][0, 0]))
"""


def test_module_runs_without_casadi_or_sympy(generated):
    _, mod, path = generated
    res = subprocess.run([sys.executable, "-c", BLOCKER, str(path)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    expected = mod.mats(np.array([1.0, 2.0, 3.0]), np.ones((3, 2)))[0][2, 1]
    assert res.stdout.split() == [repr(float(expected)), "1.5"]


def test_refusals():
    x = ca.SX.sym("x")
    g = ca.Function("g", [x], [ca.sin(x)], {"never_inline": True})
    with pytest.raises(NotImplementedError, match="OP_CALL"):
        emit_python([ca.Function("f", [x], [g(x) * 2])])
    with pytest.raises(ValueError, match="Python name"):
        emit_python([ca.Function("f", [x], [x], ["lambda"], ["y"])])
    with pytest.raises(ValueError, match="work variables"):
        emit_python([ca.Function("f", [x], [x], ["w1"], ["y"])])
    with pytest.raises(ValueError, match="unique"):
        emit_python([ca.Function("f", [x], [x]), ca.Function("f", [x], [2 * x])])
    p = ca.SX.sym("p")
    with pytest.raises(ValueError, match="free"):
        emit_python([ca.Function("f", [x], [x * p], {"allow_free": True})])


def test_large_function_emits_and_imports_quickly(tmp_path):
    rng = np.random.default_rng(0)
    n = 50
    r, u = ca.SX.sym("r", n), ca.SX.sym("u", 4)
    W, Win, Wout = rng.normal(size=(n, n)) / np.sqrt(n), rng.normal(size=(n, 4)), rng.normal(size=(2, n))
    dr = -r + ca.tanh(ca.mtimes(ca.DM(W), r) + ca.mtimes(ca.DM(Win), u))
    f = ca.Function("esn", [r, u], [dr, ca.mtimes(ca.DM(Wout), r)], ["r", "u"], ["dr", "y"])
    assert f.n_instructions() > 5000
    t0 = time.perf_counter()
    text = emit_python([f])
    (tmp_path / "esn_mod.py").write_text(text)
    mod = load(tmp_path / "esn_mod.py", "esn_mod")
    assert time.perf_counter() - t0 < 2.0
    assert max(len(line) for line in text.splitlines()) <= 120
    R, U = rng.normal(size=(n, 1, 200)), rng.normal(size=(4, 1, 200))
    got = mod.esn(R, U)
    for g, ref in zip(got, casadi_batched(f, [R, U], 200)):
        assert_close(g, ref)

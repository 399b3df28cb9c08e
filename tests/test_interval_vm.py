"""The compiled interval interpreter (sx/batch_vm.py, csrc/interval_vm.c) against the numpy rules it ports.

Arithmetic, comparisons, logic, sign and if-else give the numpy backend's doubles bit for bit; with libm's functions
put in numpy's place the transcendental rules do too, on the rules' own test tape and on a design's tapes, so the C is
the same sequence of operations rule by rule; the transcendental rules enclose 60-digit values and are widened
beyond libm on both ends. A seeded error in the C (one rounding step dropped) is caught by the comparison."""

from __future__ import annotations

import ctypes
import ctypes.util
import types
from pathlib import Path

import casadi as ca
import mpmath
import numpy as np
import pytest

from symfunnel.sx import batch, batch_rules, batch_vm
from symfunnel.sx.tape import count_ops
from tests.test_interval import OP_EXPRS, OPS_F, op_boxes
from tests.test_interval_rules import UNARY, _points

mpmath.mp.dps = 60
ROOT = Path(__file__).resolve().parent.parent
ARITHMETIC = [n for n in OP_EXPRS if n in ("ADD", "SUB", "MUL", "NEG", "DIV", "SQ", "TWICE", "INV", "SQRT", "FABS",
                                           "SIGN", "FLOOR", "CEIL", "FMIN", "FMAX", "LT", "LE", "EQ", "NE", "NOT",
                                           "AND", "OR", "IF_ELSE_ZERO2")]


def _both(f, monkeypatch):
    """(numpy backend, interpreter) of one function."""
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "numpy")
    fn = batch.BatchIntervalFunction(f)
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    fc = batch.BatchIntervalFunction(f)
    assert isinstance(getattr(fc._run, "__self__", None), batch_vm.Program), "the interpreter was not used"
    return fn, fc


def _same(a, b) -> np.ndarray:
    """Equal as doubles, NaN equal to NaN (0.0 and -0.0 equal: no rule divides by a zero it has not flagged)."""
    return (a == b) | (np.isnan(a) & np.isnan(b))


def _boxes(n_in, K, seed):
    rng = np.random.default_rng(seed)
    B = np.array(op_boxes(rng, K))
    assert B.shape[1] == n_in
    return np.ascontiguousarray(B[:, :, 0]), np.ascontiguousarray(B[:, :, 1])


_LIBM = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")


def _libm(name, nargs=1):
    f = getattr(_LIBM, name)
    f.restype = ctypes.c_double
    f.argtypes = [ctypes.c_double] * nargs
    v = np.vectorize(lambda *a: f(*map(float, a)), otypes=[float])
    return lambda *a: v(*a)


def _numpy_with_libm():
    """numpy with libm's exp, log, sin, ... in place of its own SIMD ones (what the interpreter calls)."""
    ns = types.SimpleNamespace(**{k: getattr(np, k) for k in dir(np) if not k.startswith("__")})
    for npname, cname in (("exp", "exp"), ("log", "log"), ("sin", "sin"), ("cos", "cos"), ("tan", "tan"),
                          ("arcsin", "asin"), ("arccos", "acos"), ("arctan", "atan"), ("sinh", "sinh"),
                          ("cosh", "cosh"), ("tanh", "tanh"), ("arctanh", "atanh")):
        setattr(ns, npname, _libm(cname))
    ns.power = _libm("pow", 2)
    return ns


def _compare(fn, fc, LO, HI, cols=None):
    L1, H1, s1, c1 = fn.eval_batch_culprit(LO, HI)
    L2, H2, s2, c2 = fc.eval_batch_culprit(LO, HI)
    cols = range(L1.shape[1]) if cols is None else cols
    diff = {j: int((~_same(L1[:, j], L2[:, j]) | ~_same(H1[:, j], H2[:, j])).sum()) for j in cols}
    return {j: d for j, d in diff.items() if d}, np.array_equal(s1, s2), np.array_equal(c1, c2)


def test_arithmetic_and_logic_rules_are_the_numpy_backends_doubles_bit_for_bit(monkeypatch):
    """4,000 boxes of every kind (test_interval's: points, zeros, infinities, NaN, huge and tiny, straddling 0) run
    in chunks: every non-transcendental rule's ends, the switched flags and the culprits are the numpy backend's."""
    fn, fc = _both(OPS_F, monkeypatch)
    LO, HI = _boxes(2, 4000, 5)
    names = list(OP_EXPRS)
    diff, sw, cul = _compare(fn, fc, LO, HI, [names.index(n) for n in ARITHMETIC])
    assert not diff, {names[j]: d for j, d in diff.items()}
    assert sw and cul
    assert fn._deps == fc._deps and len(fc._deps) >= 8


def test_the_outward_step_is_nextafter_on_every_kind_of_double(monkeypatch):
    """[x, x] + [0, 0] is (dn(x + 0), up(x + 0)): on random bit patterns (every exponent, subnormals, both signs)
    and the edges -- +-0, the smallest subnormals, the largest finite doubles, +-inf, NaN -- the interpreter's bit
    arithmetic gives numpy's nextafter toward -inf and +inf."""
    x, y = ca.SX.sym("x"), ca.SX.sym("y")
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    F = batch.BatchIntervalFunction(ca.Function("add", [x, y], [x + y]))
    rng = np.random.default_rng(12)
    bits = rng.integers(0, 2 ** 63, 20000, dtype=np.uint64) | (rng.integers(0, 2, 20000, dtype=np.uint64) << 63)
    tiny, big = 5e-324, np.finfo(float).max
    edges = np.array([0.0, -0.0, tiny, -tiny, 2 * tiny, -2 * tiny, big, -big, np.inf, -np.inf, np.nan, 1.0, -1.0,
                      np.finfo(float).tiny, -np.finfo(float).tiny, np.nextafter(big, 0), -np.nextafter(big, 0)])
    v = np.concatenate([bits.view(float), edges])
    X = np.stack([v, np.zeros_like(v)], 1)
    L, H, *_ = F._run(X, X)                  # the raw ends (eval_batch makes a NaN end +-inf)
    with np.errstate(all="ignore"):         # NaN in, +-inf out: what the rules see too
        s = v + 0.0
        down, up = np.nextafter(s, -np.inf), np.nextafter(s, np.inf)
    assert np.array_equal(L[:, 0], down, equal_nan=True) and np.array_equal(H[:, 0], up, equal_nan=True)
    # and the signs of the zeros they give (nextafter(-tiny, +inf) is -0.0)
    num = ~np.isnan(s)
    assert np.array_equal(np.signbit(L[num, 0]), np.signbit(down[num]))
    assert np.array_equal(np.signbit(H[num, 0]), np.signbit(up[num]))


def test_with_libms_functions_in_numpy_every_rule_is_bit_for_bit(monkeypatch):
    """The transcendental rules too once numpy calls libm as the C does: the C is each rule's own sequence of
    operations (its widening, its clamps at 0 and +-1, pow's integer and real exponents, tan's poles)."""
    fn, fc = _both(OPS_F, monkeypatch)
    LO, HI = _boxes(2, 1500, 6)
    monkeypatch.setattr(batch_rules, "np", _numpy_with_libm())
    diff, sw, cul = _compare(fn, fc, LO, HI)
    names = list(OP_EXPRS)
    assert not diff, {names[j]: d for j, d in diff.items()}
    assert sw and cul


def test_a_designs_tapes_are_bit_for_bit_with_libm_in_numpy(monkeypatch):
    """The RBF design's torque (exp, log, atanh, sin, cos, division and if-else) and its Jacobian in all its
    inputs, on 600 boxes around points drawn here (widths from 1e-9 to 1 per input): the same doubles."""
    import symfunnel as sf
    d = sf.derive(sf.load_scenario(str(ROOT / "derivations" / "ppc_log_rbf.toml")))
    f = d.function("tau")
    x = ca.vertcat(*[ca.vec(d.sym[k]) for k in f.name_in()])
    tau = d.signals["tau"]
    g = ca.Function("g", [x], [tau, ca.jacobian(tau, x)])
    assert {"EXP", "LOG", "ATANH", "SIN", "COS", "IF_ELSE_ZERO", "DIV"} <= set(count_ops(g)["by_op"])
    fn, fc = _both(g, monkeypatch)
    rng = np.random.default_rng(8)
    n = x.numel()
    C = rng.normal(size=(600, n))
    W = 10.0 ** rng.uniform(-9, 0, size=(600, n))
    LO, HI = C - W, C + W
    monkeypatch.setattr(batch_rules, "np", _numpy_with_libm())
    diff, sw, cul = _compare(fn, fc, LO, HI)
    assert not diff and sw and cul, list(diff.items())[:5]


@pytest.mark.parametrize("name", sorted(UNARY))
def test_the_interpreters_transcendental_rules_enclose_and_are_widened_beyond_libm(name, monkeypatch):
    """On [x, x] the ends lie >= 4 ulps beyond libm's value on both sides and contain the 60-digit value; on [a, b]
    the value at a, b and interior points."""
    x = ca.SX.sym("x")
    op = {"EXP": ca.exp, "LOG": ca.log, "SIN": ca.sin, "COS": ca.cos, "TAN": ca.tan, "ASIN": ca.asin,
          "ACOS": ca.acos, "ATAN": ca.atan, "SINH": ca.sinh, "COSH": ca.cosh, "TANH": ca.tanh,
          "ATANH": ca.atanh}[name]
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    F = batch.BatchIntervalFunction(ca.Function("f", [x], [op(x)]))
    pts = _points(name, 300, 1)
    L, H, _ = F.eval_batch(pts[:, None], pts[:, None])
    libm = _libm({"ASIN": "asin", "ACOS": "acos", "ATAN": "atan", "ATANH": "atanh"}.get(name, name.lower()))(pts)
    ulp = np.spacing(np.abs(libm))
    assert np.all(libm - L[:, 0] >= 4 * ulp) and np.all(H[:, 0] - libm >= 4 * ulp)
    for xi, a, b in zip(pts[:60], L[:60, 0], H[:60, 0]):
        assert mpmath.mpf(float(a)) <= UNARY[name][1](mpmath.mpf(float(xi))) <= mpmath.mpf(float(b))
    rng = np.random.default_rng(2)
    a, b = np.sort(rng.choice(pts, (2, 40)), axis=0)
    L, H, _ = F.eval_batch(a[:, None], b[:, None])
    for i in np.flatnonzero(np.isfinite(L[:, 0]) & np.isfinite(H[:, 0])):
        for xv in [a[i], b[i]] + list(a[i] + (b[i] - a[i]) * rng.random(10)):
            assert mpmath.mpf(float(L[i, 0])) <= UNARY[name][1](mpmath.mpf(float(xv))) <= mpmath.mpf(float(H[i, 0]))


def mutant_interpreter(cache: Path, old: str, new: str):
    """`sfi_eval` of the interpreter built from its source with `old` replaced by `new` (exactly one occurrence)."""
    from symfunnel.core.ccompile import compile_cached
    src = (ROOT / "symfunnel" / "sx" / "csrc" / "interval_vm.c").read_text()
    assert src.count(old) == 1, old
    built = compile_cached({"interval_vm.c": src.replace(old, new), "interval_vm_ops.h": batch_vm.header()},
                           ["interval_vm.c"], "libsfs_interval_mutant.so", batch_vm.VM_FLAGS, cache=cache)
    lib = ctypes.CDLL(str(built.path))
    lib.sfi_eval.restype = ctypes.c_int
    lib.sfi_eval.argtypes = batch_vm.library().argtypes
    return lib.sfi_eval


def test_a_dropped_rounding_step_in_the_c_is_caught(tmp_path, monkeypatch):
    """The interpreter built from its source with ADD's downward step removed gives other doubles than the numpy
    rules on the same boxes: the comparison sees a one-ulp error."""
    fn, _ = _both(OPS_F, monkeypatch)
    monkeypatch.setattr(batch_vm, "_LIB", [mutant_interpreter(tmp_path, "rl[b] = dn(al + bl);", "rl[b] = al + bl;")])
    fc = batch.BatchIntervalFunction(OPS_F)
    LO, HI = _boxes(2, 2000, 5)
    diff, _, _ = _compare(fn, fc, LO, HI)
    assert list(OP_EXPRS).index("ADD") in diff


def test_it_refuses_to_run_in_another_rounding_mode(monkeypatch):
    """Upward rounding left set (as codac needs it) would move every result: the interpreter raises instead."""
    from symfunnel.core.errors import SymfunnelError
    from symfunnel.sx import rounding
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    F = batch.BatchIntervalFunction(OPS_F)
    LO, HI = _boxes(2, 10, 1)
    saved = rounding.get_mode()
    rounding.set_mode(rounding._find_upward())
    try:
        with pytest.raises(SymfunnelError, match="round-to-nearest"):
            F.eval_batch(LO, HI)
    finally:
        rounding.set_mode(saved)
    assert rounding.rounds_to_nearest()
    F.eval_batch(LO, HI)


def test_unknown_operations_and_free_variables_are_refused_by_name(monkeypatch):
    from symfunnel.sx.interval import IntervalError
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    x, p = ca.SX.sym("x"), ca.SX.sym("p")
    with pytest.raises(IntervalError, match="free SX variables"):
        batch.BatchIntervalFunction(ca.Function("f", [x], [x * p], {"allow_free": True}))
    with pytest.raises(IntervalError, match="OP_ATAN2"):
        batch.BatchIntervalFunction(ca.Function("g", [x], [ca.atan2(x, 2 * x)]))


@pytest.mark.slow
def test_bench_area_gives_both_backends_ids_with_equal_certificates():
    """`symfunnel bench --only certify`'s interpreter rows, one round: the contract's keys, the tau enclosures the
    same up to the last bits of libm's exp, sin and cos against numpy's, and `certify paper`'s four certificates with
    the same verdicts and box counts on both backends (the speed is the bench's to report, not this test's)."""
    from symfunnel.bench.certify import _interpreter
    rows = {r["id"]: r for r in _interpreter(lambda s: None, rounds=1)}
    assert set(rows) == {"certify.interval_c_boxes_per_s", "certify.interval_c_paper_cpu_s"}
    for r in rows.values():
        assert {"id", "value", "unit", "baseline", "baseline_value", "ratio"} <= set(r) and r["value"] > 0
    b = rows["certify.interval_c_boxes_per_s"]
    assert b["max_rel_diff"] <= 1e-12 and b["batch_16"]["ratio"] > 0
    c = rows["certify.interval_c_paper_cpu_s"]
    assert c["verdicts_and_boxes_equal"] and len(c["verdicts"]) == 4


def test_any_layout_of_the_boxes_is_read_as_rows_and_a_wrong_width_is_refused(monkeypatch):
    """The C reads rows of n_in doubles: a Fortran-ordered or strided batch gives the contiguous batch's bounds, a
    batch of another width is a ValueError (never a read past the rows)."""
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    F = batch.BatchIntervalFunction(OPS_F)
    LO, HI = _boxes(2, 300, 3)
    ref = F._run(LO, HI)
    for lo, hi in ((np.asfortranarray(LO), np.asfortranarray(HI)),
                   (np.repeat(LO, 2, axis=0)[::2], np.repeat(HI, 2, axis=0)[::2])):
        got = F._run(lo, hi)
        assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(ref, got))
    with pytest.raises(ValueError, match=r"expected \(K, 2\)"):
        F._run(np.zeros((4, 3)), np.zeros((4, 3)))


def test_without_a_compiler_the_numpy_rules_give_the_enclosures_with_a_warning(monkeypatch, tmp_path):
    """$CC naming no compiler and an empty cache: a RuntimeWarning, the numpy backend, the same bounds; a malformed
    $SYMFUNNEL_COMPILE_TIMEOUT is bad input (exit 2 in the CLI), not a reason to fall back."""
    from symfunnel.core.errors import InputError
    LO, HI = _boxes(2, 200, 4)
    monkeypatch.setenv("SYMFUNNEL_INTERVAL", "c")
    want = batch.BatchIntervalFunction(OPS_F).eval_batch_culprit(LO, HI)
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path))
    monkeypatch.setattr(batch_vm, "_LIB", [])
    monkeypatch.setenv("SYMFUNNEL_COMPILE_TIMEOUT", "soon")
    with pytest.raises(InputError, match="SYMFUNNEL_COMPILE_TIMEOUT"):
        batch_vm.library()
    monkeypatch.delenv("SYMFUNNEL_COMPILE_TIMEOUT")
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    with pytest.warns(RuntimeWarning, match="numpy backend"):
        F = batch.BatchIntervalFunction(OPS_F)
    assert not isinstance(getattr(F._run, "__self__", None), batch_vm.Program)
    got = F.eval_batch_culprit(LO, HI)
    names = list(OP_EXPRS)
    for a, b in zip(want[:2], got[:2]):
        cols = [names.index(n) for n in ARITHMETIC]
        assert np.array_equal(a[:, cols], b[:, cols], equal_nan=True)

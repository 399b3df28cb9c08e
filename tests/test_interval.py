"""Interval evaluation of SX tapes (codac and arb backends) and the branch-and-bound prover built on it.

Every enclosure test compares against CasADi's own double evaluation at many points of the box (or exact rational
arithmetic), so a rule that is too narrow, rounds the wrong way or mishandles a domain fails here.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import symfunnel as sf
from symfunnel.sx import interval as iv
from symfunnel.sx.branch import prove, rigorous_range
from symfunnel.sx.interval import BACKENDS, IntervalError, IntervalFunction, RULE_OPS
from symfunnel.sx.tape import count_ops

ROOT = Path(__file__).resolve().parent.parent
PPC = str(ROOT / "derivations" / "ppc_log_rbf.toml")


# --- helpers ----------------------------------------------------------------------------------------------------

def dense_args(F: IntervalFunction, X: np.ndarray) -> list[ca.DM]:
    """CasADi map arguments (input i as r x (c N)) for N flat points X (N, n_in_nz)."""
    N = X.shape[0]
    args = []
    for i, (r, c) in enumerate(F.in_sx_shapes):
        D = np.zeros((N, r * c))
        D[:, list(F.in_nz[i])] = X[:, F.in_off[i]:F.in_off[i + 1]]
        args.append(ca.DM(D.reshape(N, c, r).transpose(2, 0, 1).reshape(r, N * c)))
    return args


#: points per call of CasADi's map in float_values: building map(N) costs time linear in N (about as much as
#: evaluating it), so N points go through one map(CHUNK), built once per function, called N / CHUNK times
CHUNK = 4096
_CHUNK_MAPS: dict = {}


def _chunk_map(f: ca.Function):
    """f.map(CHUNK) on numpy buffers (CasADi's own buffer API: no dense DM of every input and output), with the
    positions of each input's and output's structural nonzeros among its dense (column-major) entries."""
    key = id(f)
    if key not in _CHUNK_MAPS or _CHUNK_MAPS[key][0] is not f:
        m = f.map(CHUNK)
        buf, run = m.buffer()
        args = [np.zeros(m.nnz_in(i)) for i in range(m.n_in())]
        res = [np.zeros(m.nnz_out(i)) for i in range(m.n_out())]
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        for i, r in enumerate(res):
            buf.set_res(i, memoryview(r))
        nz_in = [f.sparsity_in(i).find() for i in range(f.n_in())]
        nz_out = [f.sparsity_out(i).find() for i in range(f.n_out())]
        _CHUNK_MAPS[key] = (f, buf, run, args, res, nz_in, nz_out)
    return _CHUNK_MAPS[key][1:]


def float_values(F: IntervalFunction, X: np.ndarray) -> np.ndarray:
    """CasADi's double value of every output nonzero at N flat points: (N, n_out_nz).

    The same virtual-machine evaluation as F.function.map(N) on dense DMs (dense_args), bit for bit, in chunks of
    CHUNK points written straight into the map's buffers (the dense DMs of 1e5 points cost more than evaluating)."""
    f = F.function
    _, run, args, res, nz_in, nz_out = _chunk_map(f)
    N = X.shape[0]
    # where each flat input column goes among its input's structural nonzeros (a dense entry outside the sparsity
    # would be dropped by the DM conversion; there is none in these functions, and it is checked)
    pos_in = []
    for i in range(f.n_in()):
        where = {int(d): k for k, d in enumerate(nz_in[i])}
        assert all(int(d) in where for d in F.in_nz[i]), "a flat input outside the input's sparsity"
        pos_in.append([where[int(d)] for d in F.in_nz[i]])
    pos_out = []
    for k in range(f.n_out()):
        where = {int(d): j for j, d in enumerate(nz_out[k])}
        pos_out.append([where.get(int(d), -1) for d in F.out_nz[k]])
    out = np.empty((N, sum(len(p) for p in pos_out)))
    for s in range(0, N, CHUNK):
        Xs = X[s:s + CHUNK]
        n = Xs.shape[0]
        for i, a in enumerate(args):
            A = a.reshape(CHUNK, -1)
            if len(pos_in[i]) < A.shape[1]:   # entries no flat input sets are zero, as in the dense DM
                A[:] = 0.0
            A[:n, pos_in[i]] = Xs[:, F.in_off[i]:F.in_off[i + 1]]
            if n < CHUNK:                     # the unused copies evaluate the first point again (values dropped)
                A[n:] = A[0]
        run()
        col = 0
        for k, r in enumerate(res):
            R = r.reshape(CHUNK, -1)
            for j, pj in enumerate(pos_out[k]):
                out[s:s + n, col + j] = R[:n, pj] if pj >= 0 else 0.0
            col += len(pos_out[k])
    return out


def float_values_dense(F: IntervalFunction, X: np.ndarray) -> np.ndarray:
    """float_values as it was written first: F.function.map(N) on dense DMs (kept to check the chunked one)."""
    N = X.shape[0]
    res = F.function.map(N)(*dense_args(F, X))
    res = [res] if F.function.n_out() == 1 else list(res)
    cols = []
    for k, (r, c) in enumerate(F.out_sx_shapes):
        A = np.asarray(ca.DM(res[k]).full()).reshape(r, N, c).transpose(1, 2, 0).reshape(N, r * c)
        cols.append(A[:, list(F.out_nz[k])])
    return np.concatenate(cols, axis=1)


def points_in(lo: np.ndarray, hi: np.ndarray, n: int, rng) -> np.ndarray:
    """n random points of the box, its two corners included (lo + u (hi - lo) clipped, computed in place)."""
    u = rng.random((n, lo.size))
    u[0], u[1] = 0.0, 1.0
    u *= hi - lo
    u += lo
    return np.clip(u, lo, hi, out=u)


def funnel_point(d, rng) -> dict:
    """A random point of the design's inputs with e1 and e2 strictly inside their funnels (|e| < F / 2)."""
    n = d.n
    F1, F2 = d.function("F1", ["t"]), d.function("F2", ["t"])
    e2 = d.function("e2", ["t", "q", "dq", "qd", "dqd"])
    t = rng.uniform(0.0, 2.0)
    qd, dqd, ddqd = (rng.uniform(-0.5, 0.5, n) for _ in range(3))
    q = qd + rng.uniform(-0.5, 0.5, n) * np.asarray(F1(t)).ravel()
    e20 = np.asarray(e2(t, q, dqd, qd, dqd)).ravel()          # e2 = dq - dqd + (terms without dq)
    dq = dqd - e20 + rng.uniform(-0.5, 0.5, n) * np.asarray(F2(t)).ravel()
    assert np.all(np.abs(np.asarray(e2(t, q, dq, qd, dqd)).ravel()) < np.asarray(F2(t)).ravel())
    p = {"t": t, "q": q, "dq": dq, "qd": qd, "dqd": dqd, "ddqd": ddqd}
    for name, (r, c) in d.states:
        p[name] = rng.uniform(-0.5, 0.5, (r, c)) if c > 1 else rng.uniform(-0.5, 0.5, r)
    return p


_DESIGNS: dict = {}


def design(name):
    if name not in _DESIGNS:
        _DESIGNS[name] = sf.derive(sf.load_scenario(name))
    return _DESIGNS[name]


def check_enclosure(F: IntervalFunction, lo, hi, X, vals) -> tuple[int, int]:
    """(violations, valid outputs): a valid enclosure must contain every finite double value, and an output whose
    double value is NaN or infinite somewhere in the box must not pass for a valid enclosure."""
    L, H = F.eval_flat(lo, hi)
    valid = np.isfinite(L) & np.isfinite(H)
    finite = np.isfinite(vals)
    bad = valid & ~np.all(finite, axis=0)
    bad |= valid & np.any(finite & ((vals < L) | (vals > H)), axis=0)
    return int(bad.sum()), int(valid.sum())


# --- every operation's rule -------------------------------------------------------------------------------------

x_, y_ = ca.SX.sym("x"), ca.SX.sym("y")
#: one expression per tape operation (CasADi emits the named opcode for it; test_every_rule_op_is_exercised checks)
OP_EXPRS = {
    "ADD": x_ + y_, "SUB": x_ - y_, "MUL": x_ * y_, "DIV": x_ / y_, "NEG": -x_, "SQ": x_ * x_, "TWICE": x_ + x_,
    "INV": 1 / x_, "EXP": ca.exp(x_), "LOG": ca.log(x_), "SQRT": ca.sqrt(x_), "POW": x_ ** y_,
    "CONSTPOW": x_ ** 2.5, "CONSTPOW3": x_ ** -3, "SIN": ca.sin(x_), "COS": ca.cos(x_), "TAN": ca.tan(x_),
    "ASIN": ca.asin(x_), "ACOS": ca.acos(x_), "ATAN": ca.atan(x_), "SINH": ca.sinh(x_), "COSH": ca.cosh(x_),
    "TANH": ca.tanh(x_), "ATANH": ca.atanh(x_), "FABS": ca.fabs(x_), "SIGN": ca.sign(x_), "FLOOR": ca.floor(x_),
    "CEIL": ca.ceil(x_), "FMIN": ca.fmin(x_, y_), "FMAX": ca.fmax(x_, y_), "LT": x_ < y_, "LE": x_ <= y_,
    "EQ": x_ == y_, "NE": x_ != y_, "NOT": ca.logic_not(x_), "AND": ca.logic_and(x_, y_),
    "OR": ca.logic_or(x_, y_), "IF_ELSE_ZERO": ca.if_else(x_ < y_, ca.log(y_ - x_), 0),
    "IF_ELSE_ZERO2": ca.if_else(x_, y_, 0),
}
OPS_F = ca.Function("ops", [x_, y_], [ca.vertcat(*OP_EXPRS.values())], ["x", "y"], ["ops"])


def op_boxes(rng, n: int) -> np.ndarray:
    """n random (x, y) boxes (n, 2, 2): magnitudes 1e-300..1e300 (mostly 1e-6..1e6), boxes straddling 0, point
    boxes, integers (for pow, floor, eq) and boxes around +-1 (asin, atanh)."""
    out = np.empty((n, 2, 2))
    for k in range(n):
        for j in range(2):
            kind = rng.integers(7)
            if kind == 0:                                 # straddling 0
                lo, hi = -10.0 ** rng.uniform(-8, 3), 10.0 ** rng.uniform(-8, 3)
            elif kind == 1:                               # tiny or huge magnitudes
                c = rng.choice([-1, 1]) * 10.0 ** rng.choice([rng.uniform(-300, -200), rng.uniform(200, 300)])
                lo, hi = sorted((c, c * (1 + 10.0 ** rng.uniform(-15, 0))))
            elif kind == 2:                               # a point
                lo = hi = rng.choice([-1, 1]) * 10.0 ** rng.uniform(-6, 6)
            elif kind == 3:                               # an integer point
                lo = hi = float(rng.integers(-6, 7))
            elif kind == 4:                               # around +-1 and 0 (domain edges)
                c = float(rng.choice([-1.0, 0.0, 1.0]))
                lo, hi = c - 10.0 ** rng.uniform(-12, 0), c + 10.0 ** rng.uniform(-12, 0)
            else:                                         # ordinary
                c = rng.choice([-1, 1]) * 10.0 ** rng.uniform(-6, 6)
                w = abs(c) * 10.0 ** rng.uniform(-12, 0.5)
                lo, hi = c - w * rng.random(), c + w * rng.random()
            out[k, j] = lo, hi
    return out


def test_every_rule_op_is_exercised():
    ops = set(count_ops(OPS_F)["by_op"])
    assert ops >= RULE_OPS - {"ASSIGN"}, sorted(RULE_OPS - ops)
    for be in BACKENDS:
        assert set(iv.get_backend(be).rules) == RULE_OPS
        v = iv.get_backend(be).point(1.5)
        assert iv.get_backend(be).rules["ASSIGN"](v) is v


def _exact(name: str, x: float, y: float):
    """The exact value of an OP_EXPRS entry at the doubles (x, y), as a 200-bit arb ball, or None where the real
    function is undefined (or infinite)."""
    from flint import arb, ctx
    old, ctx.prec = ctx.prec, 200
    try:
        X, Y = arb(x), arb(y)
        fx, fy = Fraction(x), Fraction(y)
        rational = {       # exactly, in rationals
            "ADD": lambda: fx + fy, "SUB": lambda: fx - fy, "MUL": lambda: fx * fy, "NEG": lambda: -fx,
            "DIV": lambda: None if y == 0 else fx / fy, "SQ": lambda: fx * fx, "TWICE": lambda: 2 * fx,
            "INV": lambda: None if x == 0 else 1 / fx, "CONSTPOW3": lambda: None if x == 0 else 1 / (fx * fx * fx),
        }
        if name in rational:
            v = rational[name]()
            return v if v is None or abs(v) < Fraction(1.7e308) else None
        b = lambda c: arb(1 if c else 0)                                  # noqa: E731
        table = {
            "EXP": X.exp, "LOG": lambda: X.log() if x > 0 else None,
            "SQRT": lambda: X.sqrt() if x > 0 else (arb(0) if x == 0 else None),
            "POW": lambda: (None if x == 0 and y < 0 else X ** int(y)) if float(y).is_integer()
            else ((Y * X.log()).exp() if x > 0 else (arb(0) if x == 0 and y > 0 else None)),
            "CONSTPOW": lambda: (2.5 * X.log()).exp() if x > 0 else (arb(0) if x == 0 else None),
            "SIN": X.sin, "COS": X.cos, "TAN": X.tan, "ATAN": X.atan, "SINH": X.sinh, "COSH": X.cosh,
            "TANH": X.tanh, "ASIN": lambda: X.asin() if abs(x) <= 1 else None,
            "ACOS": lambda: X.acos() if abs(x) <= 1 else None, "ATANH": lambda: X.atanh() if abs(x) < 1 else None,
            "FABS": lambda: arb(abs(x)), "SIGN": lambda: arb((x > 0) - (x < 0)), "FLOOR": lambda: arb(math.floor(x)),
            "CEIL": lambda: arb(math.ceil(x)), "FMIN": lambda: arb(min(x, y)), "FMAX": lambda: arb(max(x, y)),
            "LT": lambda: b(x < y), "LE": lambda: b(x <= y), "EQ": lambda: b(x == y), "NE": lambda: b(x != y),
            "NOT": lambda: b(x == 0), "AND": lambda: b(x != 0 and y != 0), "OR": lambda: b(x != 0 or y != 0),
            "IF_ELSE_ZERO": lambda: (Y - X).log() if x < y else arb(0), "IF_ELSE_ZERO2": lambda: Y if x != 0 else arb(0),
        }
        v = table[name]()
        return v if v is not None and v.is_finite() and abs(v) < arb(1.7e308) else None
    finally:
        ctx.prec = old


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_op_encloses_exact_and_double_values(backend):
    """500 boxes of every kind per operation: the enclosure contains the exact (200-bit) value at the corners and
    the middle of the box, is invalid wherever the function is undefined there, and contains CasADi's double value
    at >= 1e5 random points of the box up to 4 ulps (libm's sinh or CasADi's pow are not correctly rounded)."""
    from flint import arb
    rng = np.random.default_rng(7)
    F = IntervalFunction(OPS_F, backend)
    boxes = op_boxes(rng, 500)
    per_box = 201
    X = np.concatenate([points_in(b[:, 0], b[:, 1], per_box, rng) for b in boxes])
    vals = float_values(F, X).reshape(len(boxes), per_box, -1)
    names = list(OP_EXPRS)
    bad_float = np.zeros(len(names), int)
    bad_exact = np.zeros(len(names), int)
    valid = np.zeros(len(names), int)
    for k, b in enumerate(boxes):
        L, H = F.eval_flat(b[:, 0], b[:, 1])
        ok = np.isfinite(L) & np.isfinite(H)
        v = vals[k]
        fin = np.isfinite(v)
        with np.errstate(over="ignore"):
            slack = 4 * np.spacing(np.abs(np.where(fin, v, 0.0)))
        bad = ok & ~np.all(fin, axis=0)
        bad |= ok & np.any(fin & ((v < L - slack) | (v > H + slack)), axis=0)
        bad_float += bad
        valid += ok
        corners = [(b[0, i], b[1, j]) for i in (0, 1) for j in (0, 1)] + [(0.5 * b[0, 0] + 0.5 * b[0, 1],
                                                                            0.5 * b[1, 0] + 0.5 * b[1, 1])]
        for i in np.flatnonzero(ok):
            for px, py in corners:
                e = _exact(names[i], float(px), float(py))
                if e is None:
                    bad_exact[i] += 1
                elif isinstance(e, Fraction):
                    bad_exact[i] += not Fraction(L[i]) <= e <= Fraction(H[i])
                else:       # the 200-bit ball lies (certainly) outside: missed by far more than its 2^-200 radius
                    bad_exact[i] += bool(e < arb(L[i]) or e > arb(H[i]))
    assert len(boxes) * per_box >= 100_000
    failing = {n: (int(c), int(e)) for n, c, e in zip(names, bad_float, bad_exact) if c or e}
    assert not failing, failing
    # every rule gave real enclosures on a good share of the boxes (else the test above would be vacuous)
    assert all(valid >= 100), dict(zip(names, valid.tolist()))


def test_float_values_in_chunks_is_the_dense_map_bit_for_bit():
    """The helper every enclosure test compares against: its chunked buffers give CasADi's map(N) on dense DMs
    exactly, NaN and infinities included, over several chunks and a partial last one."""
    rng = np.random.default_rng(1)
    boxes = op_boxes(rng, 45)
    X = np.concatenate([points_in(b[:, 0], b[:, 1], 201, rng) for b in boxes])        # 9045 points: 3 chunks
    F = IntervalFunction(OPS_F)
    np.testing.assert_array_equal(float_values(F, X), float_values_dense(F, X))
    d = design("paper")
    F = IntervalFunction(d.function("tau"))
    x = F.flatten_point({k: v for k, v in funnel_point(d, rng).items() if k in F.in_names})
    X = points_in(x - 1e-3 * (1 + np.abs(x)), x + 1e-3 * (1 + np.abs(x)), 5000, rng)
    np.testing.assert_array_equal(float_values(F, X), float_values_dense(F, X))


def test_codac_transcendentals_against_arb():
    """codac's own sinh, tanh, atanh miss the exact value by up to 1 ulp (codac 2.1.2); the backend's widened rules
    and every other transcendental rule contain the 200-bit value at 4000 random points each (rules called as the
    compiled tape calls them: under upward rounding, the backend's mode)."""
    from flint import arb, ctx
    be = iv.get_backend("codac")
    rng = np.random.default_rng(4)
    old, ctx.prec = ctx.prec, 200
    try:
        for name in ("EXP", "LOG", "SQRT", "SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN", "SINH", "COSH", "TANH",
                     "ATANH"):
            rule = be.rules[name]
            for _ in range(4000):
                x = float(rng.uniform(-1, 1) if name in ("ASIN", "ACOS", "ATANH")
                          else rng.choice([-1, 1]) * 10.0 ** rng.uniform(-300, 2))
                if name in ("LOG", "SQRT"):
                    x = abs(x)
                with be.mode():
                    r = rule(be.point(x))
                ex = getattr(arb(x), name.lower())()
                assert not (ex < arb(r.lb()) or ex > arb(r.ub())), (name, x)     # certainly outside
    finally:
        ctx.prec = old


@pytest.mark.parametrize("backend", BACKENDS)
def test_comparisons_logic_sign_and_if_else(backend):
    F = IntervalFunction(OPS_F, backend)
    names = list(OP_EXPRS)

    # python-flint rounds every radius up by 2^-30 relative: arb's [0, 1] is [-9.3e-10, 1 + 9.3e-10]
    tol = 0.0 if backend == "codac" else 2e-9

    class Near(tuple):
        def __eq__(self, other):
            return all(a == b or abs(a - b) <= tol for a, b in zip(self, other))

    def ev(x, y):
        L, H = F.eval_flat(np.array([x[0], y[0]]), np.array([x[1], y[1]]))
        return {n: Near((L[i], H[i])) for i, n in enumerate(names)}

    r = ev((-1.0, 2.0), (5.0, 6.0))
    assert r["LT"] == (1, 1) and r["LE"] == (1, 1) and r["EQ"] == (0, 0) and r["NE"] == (1, 1)
    assert r["SIGN"] == (-1, 1) and r["AND"] == (0, 1) and r["OR"] == (1, 1) and r["NOT"] == (0, 1)
    r = ev((3.0, 4.0), (1.0, 2.5))
    assert r["LT"] == (0, 0) and r["LE"] == (0, 0) and r["SIGN"] == (1, 1)
    if backend == "codac":      # touching intervals: arb's rounded-up radii make these undecided, still enclosures
        r = ev((3.0, 4.0), (1.0, 3.0))
        assert r["LT"] == (0, 0) and r["LE"] == (0, 1)
    # undecided condition: hull(0, log(y - x)); a certainly false one masks a domain error of its branch
    r = ev((0.0, 1.0), (0.5, 2.0))
    assert r["LT"] == (0, 1)
    assert r["IF_ELSE_ZERO"] == (-math.inf, math.inf)        # log(y - x) has y - x <= 0 in the box
    r = ev((5.0, 6.0), (1.0, 2.0))
    assert r["IF_ELSE_ZERO"] == (0, 0) and r["LOG"][0] > 1.6
    r = ev((0.0, 0.0), (-3.0, -2.0))
    assert r["SIGN"] == (0, 0) and r["IF_ELSE_ZERO2"] == (0, 0) and r["NOT"] == (1, 1)
    assert r["DIV"] == (0, 0)
    if backend == "codac":      # the ball of [0, 2] reaches below 0 by its rounded-up radius
        assert ev((0.0, 2.0), (1.0, 1.0))["SIGN"] == (0, 1)
    r = ev((-1.0, 1.0), (1.0, 1.0))
    assert r["DIV"][0] <= -1.0 and r["INV"] == (-math.inf, math.inf)
    assert ev((1.0, 2.0), (-1.0, 1.0))["DIV"] == (-math.inf, math.inf)
    assert ev((1.0, 2.0), (0.0, 1.0))["DIV"] == (-math.inf, math.inf)      # touching 0 is an error too


# --- outward rounding -------------------------------------------------------------------------------------------

def _exact_violations(F: IntervalFunction, rng, n: int = 400) -> int:
    """Point boxes of random doubles: how often the enclosure of x + y, x - y, x * y, x / y, x^2 misses the exact
    rational result."""
    bad = 0
    for _ in range(n):
        x, y = rng.uniform(-10, 10, 2)
        L, H = F.eval_flat(np.array([x, y]), np.array([x, y]))
        fx, fy = Fraction(x), Fraction(y)
        for k, exact in enumerate((fx + fy, fx - fy, fx * fy, fx / fy, fx * fx)):
            bad += not (Fraction(L[k]) <= exact <= Fraction(H[k]))
    return bad


ARITH = ca.Function("arith", [x_, y_], [ca.vertcat(x_ + y_, x_ - y_, x_ * y_, x_ / y_, x_ * x_)], ["x", "y"], ["a"])


@pytest.mark.parametrize("backend", BACKENDS)
def test_outward_rounding_against_exact_rationals(backend):
    F = IntervalFunction(ARITH, backend)
    assert _exact_violations(F, np.random.default_rng(3)) == 0
    # [0.1] + [0.2] as doubles: the exact sum of the two doubles is inside, and rounding happened (width > 0)
    L, H = F.eval_flat(np.array([0.1, 0.2]), np.array([0.1, 0.2]))
    assert Fraction(L[0]) <= Fraction(0.1) + Fraction(0.2) <= Fraction(H[0]) and L[0] < H[0]
    # boxes enclosing the real numbers 1/10 and 2/10 give a sum that encloses 3/10
    lo = np.array([math.nextafter(0.1, 0), math.nextafter(0.2, 0)])
    hi = np.array([math.nextafter(0.1, 1), math.nextafter(0.2, 1)])
    assert Fraction(lo[0]) < Fraction(1, 10) < Fraction(hi[0])
    L, H = F.eval_flat(lo, hi)
    assert Fraction(L[0]) <= Fraction(3, 10) <= Fraction(H[0])


def test_round_to_nearest_add_is_caught(monkeypatch):
    """The exact-arithmetic check fails once ADD rounds to nearest: the rounding direction is what it tests."""
    from flint import arb

    from symfunnel.sx import rounding
    with rounding.keeping_mode():
        import codac
    be = iv.get_backend("codac")
    monkeypatch.setitem(be.rules, "ADD", lambda a, b: codac.Interval(a.lb() + b.lb(), a.ub() + b.ub()))
    assert _exact_violations(IntervalFunction(ARITH, "codac"), np.random.default_rng(3)) > 0
    be = iv.get_backend("arb")
    monkeypatch.setitem(be.rules, "ADD", lambda a, b: arb(float((a + b).mid())))
    assert _exact_violations(IntervalFunction(ARITH, "arb"), np.random.default_rng(3)) > 0


def test_codac_leaves_the_process_rounding_to_nearest_and_is_outward_whatever_the_callers_mode():
    """Importing codac sets the process's rounding upward (it computes lower bounds as -(-a - b)); the backend
    restores the caller's mode, runs every evaluation under upward rounding, and so stays outward when the caller
    rounds to nearest -- without that context the same codac arithmetic is not outward."""
    from symfunnel.sx import rounding
    F = IntervalFunction(ARITH, "codac")
    F.eval_flat(np.array([1.0, 3.0]), np.array([1.0, 3.0]))
    assert rounding.rounds_to_nearest() and float("3.7525") == 3.7525 and repr(float("3.7525")) == "3.7525"
    L, H = F.eval_flat(np.array([1.0, 3.0]), np.array([1.0, 3.0]))
    assert Fraction(L[3]) < Fraction(1, 3) < Fraction(H[3])
    assert _exact_violations(F, np.random.default_rng(3)) == 0 and rounding.rounds_to_nearest()


def test_without_upward_rounding_codac_is_not_outward(monkeypatch):
    """The rounding context is what makes codac outward: replaced by a no-op, 1/3 is not enclosed."""
    import contextlib

    from symfunnel.sx import rounding
    be = iv.get_backend("codac")
    monkeypatch.setattr(be, "mode", contextlib.nullcontext)
    F = IntervalFunction(ARITH, "codac")
    assert rounding.rounds_to_nearest()
    L, H = F.eval_flat(np.array([1.0, 3.0]), np.array([1.0, 3.0]))
    assert not Fraction(L[3]) < Fraction(1, 3) < Fraction(H[3])
    assert _exact_violations(F, np.random.default_rng(3)) > 0


# --- refusals ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("backend", BACKENDS)
def test_op_without_rule_is_named(backend):
    f = ca.Function("tau", [x_], [ca.erfinv(x_) + 1])
    with pytest.raises(IntervalError, match=r"no interval rule for OP_ERFINV in function 'tau'"):
        IntervalFunction(f, backend)


def test_free_variable_is_refused():
    f = ca.Function("h", [x_], [x_ + y_], {"allow_free": True})
    with pytest.raises(IntervalError, match=r"free SX variables \(y\)"):
        IntervalFunction(f)


def test_bad_boxes_are_refused():
    F = IntervalFunction(ARITH)
    with pytest.raises(ValueError, match="lo > hi"):
        F.eval([(1.0, 0.0), (0.0, 1.0)])
    with pytest.raises(ValueError, match="NaN"):
        F.eval([(math.nan, 0.0), (0.0, 1.0)])
    with pytest.raises(ValueError, match="backend"):
        IntervalFunction(ARITH, "mpfi")


# --- the designs ------------------------------------------------------------------------------------------------

SIGNALS = ["tau", "alpha2_dot", "mu2", "M"]


@pytest.mark.parametrize("scenario", ["paper", pytest.param("arm7", marks=pytest.mark.slow), PPC],
                         ids=["paper", "arm7", "ppc_log_rbf"])
def test_design_signals_enclose_double_values(scenario):
    """Small boxes around a point inside both funnels: each backend's enclosure is valid and contains CasADi's
    value at 1e5 random points of the box (tau, alpha2_dot, mu2, M)."""
    d = design(scenario)
    rng = np.random.default_rng(11)
    for sig in SIGNALS:
        f = d.function(sig)
        Fs = [IntervalFunction(f, be) for be in BACKENDS]
        x = Fs[0].flatten_point({k: v for k, v in funnel_point(d, rng).items() if k in Fs[0].in_names})
        h = 1e-7 * (1 + np.abs(x))
        lo, hi = x - h, x + h
        n = 100_000 if sig == "tau" else 20_000
        X = points_in(lo, hi, n, rng)
        vals = float_values(Fs[0], X)
        for F in Fs:
            bad, valid = check_enclosure(F, lo, hi, X, vals)
            assert bad == 0, (scenario, sig, F.backend.name)
            assert valid == F.n_out_nz, (scenario, sig, F.backend.name, "enclosure not valid on a small box")


def _scenarios_shipped() -> list[str]:
    return ["paper", "arm7"] + sorted(str(p) for p in (ROOT / "derivations").glob("*.toml"))


@pytest.mark.parametrize("scenario", _scenarios_shipped(), ids=lambda s: Path(s).stem)
def test_backends_agree_on_tau(scenario):
    """Independent backends: on a box and at its midpoint each one's enclosure contains the other's point
    enclosure and CasADi's value there, and the box enclosures intersect."""
    d = design(scenario)
    f = d.function("tau")
    C, A = IntervalFunction(f, "codac"), IntervalFunction(f, "arb")
    rng = np.random.default_rng(5)
    for _ in range(2):
        x = C.flatten_point({k: v for k, v in funnel_point(d, rng).items() if k in C.in_names})
        lo, hi = x - 1e-7 * (1 + np.abs(x)), x + 1e-7 * (1 + np.abs(x))
        m = 0.5 * lo + 0.5 * hi
        v = C.eval_point_flat(m)
        (cl, ch), (al, ah) = C.eval_flat(lo, hi), A.eval_flat(lo, hi)
        (cml, cmh), (aml, amh) = C.eval_flat(m, m), A.eval_flat(m, m)
        assert np.all(np.isfinite([cl, ch, al, ah]))
        for L, H in ((cl, ch), (al, ah), (cml, cmh), (aml, amh)):
            assert np.all((L <= v) & (v <= H))
        assert np.all((cl <= aml) & (amh <= ch)) and np.all((al <= cml) & (cmh <= ah))
        assert np.all(np.maximum(cl, al) <= np.minimum(ch, ah))
        assert np.all(np.maximum(cml, aml) <= np.minimum(cmh, amh))


@pytest.mark.parametrize("backend", BACKENDS)
def test_mean_value_form_encloses_and_tightens(backend):
    """The mean-value form is still an enclosure (1e4 points per box on mu2 and M) and beats the natural form on
    narrow boxes where the dependency effect dominates."""
    d = design("paper")
    rng = np.random.default_rng(2)
    for sig in ("mu2", "M"):
        f = d.function(sig)
        N, MV = IntervalFunction(f, backend), IntervalFunction(f, backend, form="mean_value")
        for h in (1e-2, 1e-4):
            x = N.flatten_point({k: v for k, v in funnel_point(d, rng).items() if k in N.in_names})
            lo, hi = x - h * (1 + np.abs(x)), x + h * (1 + np.abs(x))
            X = points_in(lo, hi, 10_000, rng)
            vals = float_values(N, X)
            bad, _ = check_enclosure(MV, lo, hi, X, vals)
            assert bad == 0
            (nl, nh), (ml, mh) = N.eval_flat(lo, hi), MV.eval_flat(lo, hi)
            assert np.all((nl <= ml) & (mh <= nh))
    g = ca.Function("g", [x_], [x_ * x_ - 2 * x_ + 1])
    N, MV = IntervalFunction(g, backend), IntervalFunction(g, backend, form="mean_value")
    (nl, nh), (ml, mh) = N.eval_flat(np.array([0.99]), np.array([1.01])), MV.eval_flat(np.array([0.99]),
                                                                                        np.array([1.01]))
    assert mh - ml < 0.1 * (nh - nl) and ml <= 0 <= mh
    # a discontinuity switching on the box: the mean-value form is not applied (sign(x) is 0 at the midpoint)
    s = ca.Function("s", [x_], [ca.sign(x_) + x_])
    assert IntervalFunction(s, backend, form="mean_value").eval_flat(np.array([-1.0]), np.array([1.0]))[0][0] <= -1


def test_eval_shapes_and_structural_zeros():
    q = ca.SX.sym("q", 2)
    W = ca.SX.sym("W", 3, 2)
    f = ca.Function("f", [q, W], [ca.vertcat(ca.mtimes(W, q), 0), ca.diag(q)], ["q", "W"], ["y", "D"])
    F = IntervalFunction(f, "arb")
    Wlo = np.arange(6.0).reshape(3, 2)
    y, D = F.eval([(np.array([1.0, 2.0]), np.array([1.0, 2.0])), (Wlo, Wlo)])
    assert y.lo.shape == (4,) and D.lo.shape == (2, 2)
    assert np.allclose(y.lo[:3], Wlo @ [1, 2]) and y.lo[3] == y.hi[3] == 0.0
    assert D.lo[0, 1] == D.hi[0, 1] == 0.0 and D.lo[1, 1] <= 2 <= D.hi[1, 1]
    boxes = np.stack([np.array([0.5, 1.0]), np.array([1.0, 2.0])], axis=-1)      # (2, 2): (lo, hi) per element
    assert F.eval({"q": boxes, "W": np.stack([Wlo, Wlo + 1], axis=-1)})[0].all_valid
    assert np.allclose(F.eval_point([[1.0, 2.0], Wlo])[0][:3], Wlo @ [1, 2])


# --- branch and bound -------------------------------------------------------------------------------------------

G_POS = ca.Function("g", [x_], [x_ * x_ - 2 * x_ + 1.01], ["x"], ["g"])
G_NEG = ca.Function("g", [x_], [x_ * x_ - 2 * x_ + 0.99], ["x"], ["g"])


@pytest.mark.parametrize("backend", BACKENDS)
def test_proves_positive_quadratic(backend):
    r = prove(IntervalFunction(G_POS, backend), {"x": (-10.0, 10.0)})
    assert r.status == "proven" and r.undecided_fraction == 0.0 and r.counterexample is None
    assert 0 < r.lower <= 0.01 and r.upper >= 121.01 and r.boxes > 10


@pytest.mark.parametrize("backend", BACKENDS)
def test_refutes_with_a_confirmed_counterexample(backend):
    r = prove(IntervalFunction(G_NEG, backend), {"x": (-10.0, 10.0)})
    assert r.status == "refuted"
    x = float(r.counterexample["x"][0])
    assert abs(x - 1) < 0.1
    assert float(G_NEG(x)) < 0 and r.counterexample_value[0] < 0 and r.rigorous_counterexample


def test_two_dimensional_case_needs_splits():
    """cos(x - y) + 1.05 written so that x and y each occur twice: the natural enclosure on the whole square is
    [-0.95, 3.05], so only splitting proves it."""
    y = ca.SX.sym("y")
    g = ca.Function("g", [x_, y], [ca.cos(x_) * ca.cos(y) + ca.sin(x_) * ca.sin(y) + 1.05], ["x", "y"], ["g"])
    box = {"x": (-3.0, 3.0), "y": (-3.0, 3.0)}
    r = prove(g, box)
    assert r.status == "proven" and r.boxes > 50 and 0 < r.lower <= 0.05
    r = prove(g, box, relation=">", bound=0.1)
    assert r.status == "refuted" and float(g(r.counterexample["x"], r.counterexample["y"])) <= 0.1
    # the upper-bound form: g < 2.1 everywhere, and the prover's upper bound is rigorous
    r = prove(g, box, relation="<", bound=2.1)
    assert r.status == "proven" and 2.05 <= r.upper < 2.1


C3 = 1.0 / 3.0
SQ3 = ca.Function("g", [x_], [(x_ - C3) * (x_ - C3)], ["x"], ["g"])


def test_undecided_with_a_volume_fraction_on_a_tiny_budget():
    r = prove(G_POS, {"x": (-10.0, 10.0)}, max_boxes=5)
    assert r.status == "undecided" and r.stopped == "boxes" and 0 < r.undecided_fraction < 1
    r = prove(G_POS, {"x": (-10.0, 10.0)}, seconds=0.0)
    assert r.status == "undecided" and r.stopped == "seconds" and r.undecided_fraction == 1.0
    # (x - 1/3)^2 > 0 fails only at the double 1/3, which no midpoint hits: splitting stops at the width limit
    r = prove(SQ3, {"x": (0.3, 1.7)}, max_boxes=100_000)
    assert r.status == "undecided" and r.stopped == "min_width" and r.undecided_fraction < 1e-9


def test_deterministic():
    y = ca.SX.sym("y")
    g = ca.Function("g", [x_, y], [(x_ - C3) * (x_ - C3) + (y + C3) * (y + C3)], ["x", "y"], ["g"])
    runs = [prove(g, {"x": (-2.0, 2.0), "y": (-1.0, 1.0)}, max_boxes=400) for _ in range(2)]
    a, b = (r.to_dict() for r in runs)
    a.pop("seconds"), b.pop("seconds")
    assert a == b and runs[0].boxes > 10 and runs[0].status == "undecided"
    ra, rb = (rigorous_range(g, {"x": (-2.0, 2.0), "y": (-1.0, 1.0)}, max_boxes=300).to_dict() for _ in range(2))
    ra.pop("seconds"), rb.pop("seconds")
    assert ra == rb


def test_no_split_inputs_stay_whole():
    y = ca.SX.sym("y")
    g = ca.Function("g", [x_, y], [x_ * x_ + 0.5 + 0.1 * y], ["x", "y"], ["g"])
    r = prove(g, {"x": (-1.0, 1.0), "y": (-1.0, 1.0)}, no_split=["y"])
    assert r.status == "proven"
    r = prove(g, {"x": (-1.0, 1.0), "y": (-1.0, 1.0)}, split=["y"], max_boxes=50)
    assert r.status == "proven" and r.boxes == 1          # y alone cannot help; x^2 >= 0 already proves it
    r = prove(g, {"x": (-1.0, 1.0), "y": (-10.0, 10.0)}, no_split=["y"], max_boxes=200)
    assert r.status in ("undecided", "refuted")


def test_rigorous_range():
    r = rigorous_range(G_POS, {"x": (-10.0, 10.0)}, tol=1e-6)
    assert r.converged and r.lo <= 0.01 <= r.lo_seen and r.lo_seen - r.lo <= 1e-6
    assert r.hi >= 121.01 >= r.hi_seen and r.hi - r.hi_seen <= 1e-6
    assert abs(float(r.argmin["x"][0]) - 1) < 1e-3 and float(r.argmax["x"][0]) < -9.99
    # a tiny budget still gives a rigorous (wider) enclosure
    r2 = rigorous_range(G_POS, {"x": (-10.0, 10.0)}, tol=1e-9, max_boxes=4)
    assert not r2.converged and r2.lo <= 0.01 and r2.hi >= 121.01


def test_mass_matrix_is_positive_definite_over_all_q2():
    """Sylvester on the paper's M(q): M11 > 0 and det M > 0 for q2 in [-pi, pi] (q1 is irrelevant: never split)."""
    M = design("paper").function("M")
    q = ca.SX.sym("q", 2)
    Mq = M(q)
    syl = ca.Function("syl", [q], [ca.vertcat(Mq[0, 0], Mq[0, 0] * Mq[1, 1] - Mq[0, 1] * Mq[1, 0])], ["q"], ["s"])
    for backend in BACKENDS:
        r = prove(syl, {"q": (np.array([-np.pi, -np.pi]), np.array([np.pi, np.pi]))}, backend=backend)
        assert r.status == "proven" and r.lower > 0
    # the lower bound is close to the sampled minimum of det M
    g = np.array([float(ca.det(M(ca.DM([0.0, a])))) for a in np.linspace(-np.pi, np.pi, 721)])
    rr = rigorous_range(syl, {"q": (np.array([0.0, -np.pi]), np.array([0.0, np.pi]))}, element=1, tol=1e-9)
    assert rr.lo <= g.min() and g.min() - rr.lo < 1e-6


def test_input_gain_condition_2dof():
    """sym(M(q)^-1 D M(q)) > 0 (Sylvester) for dead-zone-like slopes D = diag(d), over all q2: proven for slopes
    3 % apart, refuted (with a counterexample that CasADi confirms) for slopes 0.2 and 1. (Boxes of slopes too: the
    margin is thin -- lambda_min 0.29 at +-5 % -- and the natural form then needs far more than 20000 boxes.)"""
    M = design("paper").function("M")
    q, dd = ca.SX.sym("q", 2), ca.SX.sym("d", 2)
    Mq = M(q)
    G = ca.mtimes([ca.inv(Mq), ca.diag(dd), Mq])
    S = 0.5 * (G + G.T)
    g = ca.Function("gain", [q, dd], [ca.vertcat(S[0, 0], S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0])], ["q", "d"],
                    ["s"])
    qbox = (np.array([0.0, -np.pi]), np.array([0.0, np.pi]))
    r = prove(g, {"q": qbox, "d": np.array([0.97, 1.0])}, max_boxes=20_000)
    assert r.status == "proven", r
    r = prove(g, {"q": qbox, "d": np.array([0.2, 1.0])}, max_boxes=20_000)
    assert r.status == "refuted"
    v = np.asarray(g(r.counterexample["q"], r.counterexample["d"])).ravel()
    assert np.any(v <= 0)


def test_batch_eval_points_are_casadis_values_point_by_point():
    """BatchIntervalFunction.eval_points (the map on numpy buffers) gives, at every point, the nonzeros CasADi's own
    call gives, for sparse and dense inputs and outputs, and any number of points."""
    from symfunnel.sx.batch import BatchIntervalFunction
    a = ca.SX.sym("a", 3)
    B = ca.SX(ca.Sparsity.lower(2))
    B.nz[:] = ca.SX.sym("b", 3).nz[:]
    y1 = ca.vertcat(ca.sin(a[0]) * B[1, 0], a[1] / (2 + B[0, 0] ** 2))
    y2 = ca.SX(ca.Sparsity.diag(3))
    y2.nz[:] = ca.vertcat(a[2] * B[1, 1], ca.exp(a[0] - a[1]), B[0, 0])
    f = ca.Function("f", [a, B], [y1, y2])
    F = BatchIntervalFunction(f)
    rng = np.random.default_rng(3)
    for K in (1, 5, 64, 100):
        X = rng.normal(size=(K, F.n_in_nz))
        got = F.eval_points(X)
        assert got.shape == (K, 2 + 3)
        for k in range(K):
            o1, o2 = f(X[k, :3], ca.DM(ca.Sparsity.lower(2), X[k, 3:]))
            want = np.array(ca.DM(o1).nonzeros() + ca.DM(o2).nonzeros(), float)
            assert np.array_equal(got[k], want)


def test_batch_eval_points_over_several_maps_is_casadis_map_bit_for_bit():
    """More points than one map holds (POINTS_PER_MAP) go through it chunk by chunk: the values are CasADi's map over
    all of them, NaN included, in the same order."""
    from symfunnel.sx.batch import POINTS_PER_MAP, BatchIntervalFunction
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [ca.vertcat(ca.sin(x[0]) * x[1] / x[2], ca.log(x[2]))])
    K = 2 * POINTS_PER_MAP + 123
    X = np.random.default_rng(3).normal(size=(K, 3))
    got = BatchIntervalFunction(f).eval_points(X)
    assert got.shape == (K, 2) and np.isnan(got[:, 1]).any()
    np.testing.assert_array_equal(got, np.array(f.map(K)(X.T)).T)

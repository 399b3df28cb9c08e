"""Each interval rule of the batched backend at both ends, against mpmath at 60 digits, where numpy's libm is not
correctly rounded; the widening of the transcendental functions applied (not only relied on by luck); and the
eigenvalue bound of the positive-definiteness search against numpy's eigenvalues of matrices of its box."""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest

from symfunnel.sx import batch
from symfunnel.sx.search import gershgorin

mpmath.mp.dps = 60

#: rule -> (numpy function, mpmath function, sampler of points away from the rule's clamps and domain ends)
UNARY = {
    "EXP": (np.exp, mpmath.exp, lambda r, k: r.uniform(-20, 20, k)),
    "LOG": (np.log, mpmath.log, lambda r, k: np.exp(r.uniform(-7, 7, k))),
    "SIN": (np.sin, mpmath.sin, lambda r, k: r.uniform(-10, 10, k)),
    "COS": (np.cos, mpmath.cos, lambda r, k: r.uniform(-10, 10, k)),
    "TAN": (np.tan, mpmath.tan, lambda r, k: r.uniform(-1.5, 1.5, k)),
    "ASIN": (np.arcsin, mpmath.asin, lambda r, k: r.uniform(-0.99, 0.99, k)),
    "ACOS": (np.arccos, mpmath.acos, lambda r, k: r.uniform(-0.99, 0.99, k)),
    "ATAN": (np.arctan, mpmath.atan, lambda r, k: r.uniform(-50, 50, k)),
    "SINH": (np.sinh, mpmath.sinh, lambda r, k: r.uniform(-10, 10, k)),
    "COSH": (np.cosh, mpmath.cosh, lambda r, k: r.choice([-1, 1], k) * r.uniform(0.5, 10, k)),
    "TANH": (np.tanh, mpmath.tanh, lambda r, k: r.uniform(-3, 3, k)),
    "ATANH": (np.arctanh, mpmath.atanh, lambda r, k: r.uniform(-0.99, 0.99, k)),
}


def _points(name, k, seed):
    x = UNARY[name][2](np.random.default_rng(seed), k)
    f = UNARY[name][0](x)
    keep = np.abs(f) < 0.99 if name in ("SIN", "COS") else (f != 0)     # away from sin/cos's clamps at +-1
    return x[keep]


def _exact(name, x):
    return UNARY[name][1](mpmath.mpf(float(x)))


@pytest.mark.parametrize("name", sorted(UNARY))
def test_transcendental_rules_are_widened_beyond_libm_on_both_ends(name):
    """On a point interval [x, x] each transcendental rule's ends lie at least 4 ulps beyond numpy's value on both
    sides (it is not correctly rounded: the rule must not rely on being lucky) and contain the 60-digit value."""
    x = _points(name, 400, 1)
    lo, hi, *_ = batch._RULES[name](x, x)
    f = UNARY[name][0](x)
    ulp = np.spacing(np.abs(f))
    assert np.all(f - lo >= 4 * ulp), (name, x[np.argmin((f - lo) / ulp)])
    assert np.all(hi - f >= 4 * ulp), (name, x[np.argmin((hi - f) / ulp)])
    for xi, a, b in zip(x[:60], lo[:60], hi[:60]):
        e = _exact(name, xi)
        assert mpmath.mpf(float(a)) <= e <= mpmath.mpf(float(b))


@pytest.mark.parametrize("name", sorted(UNARY))
def test_rules_enclose_exact_values_at_both_ends_and_inside_of_wide_intervals(name):
    """[a, b] with random ends: the enclosure contains the 60-digit value at a, at b and at 20 interior points."""
    rng = np.random.default_rng(2)
    pts = _points(name, 200, 3)
    a, b = np.sort(rng.choice(pts, (2, 40), replace=True), axis=0)
    lo, hi, *rest = batch._RULES[name](a, b)
    bad = rest[0] if rest and rest[0] is not None else np.zeros(a.shape, bool)
    for i in np.flatnonzero(~bad):
        inner = [a[i], b[i]] + list(a[i] + (b[i] - a[i]) * rng.random(20))
        for xv in inner:
            e = _exact(name, xv)
            assert mpmath.mpf(float(lo[i])) <= e <= mpmath.mpf(float(hi[i])), (name, a[i], b[i], xv)


def test_where_libm_is_not_correctly_rounded_the_rules_still_enclose():
    """Points where numpy's result is not the double nearest the exact value exist (found here by a seeded search);
    at every one of them the rule's enclosure contains the exact value."""
    found = {}
    for name in sorted(UNARY):
        x = _points(name, 3000, 11)
        f = UNARY[name][0](x)
        for xi, fi in zip(x, f):
            e = _exact(name, xi)
            if float(e) != fi:                      # mpmath's float() rounds to nearest
                found.setdefault(name, []).append(xi)
    assert sum(len(v) for v in found.values()) >= 5, found       # the premise: libm is not correctly rounded
    for name, xs in found.items():
        xs = np.array(xs[:50])
        lo, hi, *_ = batch._RULES[name](xs, xs)
        for xi, a, b in zip(xs, lo, hi):
            e = _exact(name, xi)
            assert mpmath.mpf(float(a)) <= e <= mpmath.mpf(float(b)), (name, xi)


def test_pow_with_a_real_exponent_encloses_and_is_widened():
    rng = np.random.default_rng(4)
    x = rng.uniform(0.1, 10.0, 300)
    y = np.full_like(x, 2.5)
    lo, hi, bad = batch._RULES["POW"](x, x, y, y)
    f = np.power(x, 2.5)
    assert not bad.any() and np.all(f - lo >= 4 * np.spacing(f)) and np.all(hi - f >= 4 * np.spacing(f))
    for xi, a, b in zip(x[:50], lo, hi):
        e = mpmath.mpf(float(xi)) ** mpmath.mpf(2.5)
        assert mpmath.mpf(float(a)) <= e <= mpmath.mpf(float(b))


# --- the eigenvalue bound ---------------------------------------------------------------------------------

def _box_case(rng, n, r, skew=0.0):
    """A random SPD S0, the preconditioner L = V^T of its eigenvectors, and the exact enclosures of P = L S L^T and
    Q = L L^T over the box S0 + E, |E_ij| <= r (E symmetric): P = L S0 L^T + L E L^T, |L E L^T| <= r |L| 1 1^T |L|^T."""
    A = rng.normal(size=(n, n))
    S0 = A @ A.T + 0.5 * np.eye(n)
    _, V = np.linalg.eigh(S0)
    L = V.T @ (np.eye(n) + skew * rng.normal(size=(n, n)))     # any invertible L works; Q = L L^T is then no I
    P0 = L @ S0 @ L.T
    R = r * np.abs(L) @ np.ones((n, n)) @ np.abs(L).T
    slack = 1e-12 * (1 + np.abs(P0).max())
    PL, PH = P0 - R - slack, P0 + R + slack
    Q = L @ L.T
    QL, QH = Q - 1e-12 * (1 + np.abs(Q).max()), Q + 1e-12 * (1 + np.abs(Q).max())
    return S0, PL, PH, QL, QH


def test_gershgorin_bound_is_below_every_eigenvalue_of_the_box_and_close_for_a_point():
    """For 200 random boxes (half with a non-orthogonal preconditioner L, so Q = L L^T has off-diagonal discs) the
    bound is <= lambda_min of S0 + E at 50 sampled symmetric E (vertices of the box and the worst rank-one one for
    S0's smallest eigenvector); for point boxes with L = V^T (r = 0) it is within 1e-9 of lambda_min."""
    rng = np.random.default_rng(5)
    for k in range(200):
        n = int(rng.integers(2, 6))
        r = float(rng.choice([0.0, 1e-3, 1e-2, 0.1]))
        skew = 0.0 if k % 2 else 0.3
        S0, PL, PH, QL, QH = _box_case(rng, n, r, skew)
        bound, _ = gershgorin(PL[None], PH[None], QL[None], QH[None])
        lam0 = np.linalg.eigvalsh(S0)
        if r == 0.0:
            assert bound[0] <= lam0[0]
            if skew == 0.0:              # the preconditioner diagonalises S0: the discs are points
                assert bound[0] >= lam0[0] - 1e-9 * (1 + abs(lam0[0]))
            continue
        v = np.linalg.eigh(S0)[1][:, 0]
        Es = [-r * np.outer(np.sign(v), np.sign(v))]
        for _ in range(49):
            E = rng.choice([-r, r], (n, n))
            Es.append(np.triu(E) + np.triu(E, 1).T)
        worst = min(np.linalg.eigvalsh(S0 + E)[0] for E in Es)
        assert bound[0] <= worst, (k, bound[0], worst)


def test_gershgorin_refuses_a_box_it_cannot_bound_and_ranks_it():
    """A non-finite entry or a box whose discs reach 0 gives -inf (no bound), never a number."""
    n = 3
    PL = np.eye(n)[None] * 1.0
    PH = PL.copy()
    Q = np.eye(n)[None]
    assert gershgorin(PL, PH, Q, Q)[0][0] == pytest.approx(1.0, rel=1e-12)
    bad = PL.copy()
    bad[0, 0, 1] = bad[0, 1, 0] = -1.5                     # off-diagonal mass beyond the diagonal
    assert gershgorin(bad, PH, Q, Q)[0][0] == -math.inf
    nan = PL.copy()
    nan[0, 2, 2] = math.nan
    assert gershgorin(nan, PH, Q, Q)[0][0] == -math.inf


def test_gershgorin_bound_holds_for_any_invertible_preconditioner():
    """The bound's argument holds for every invertible L (not only S's eigenvectors): 3000 point matrices with random
    L; the bound never exceeds numpy's lambda_min (the search's L is near-orthogonal, which hides Q's own discs)."""
    rng = np.random.default_rng(6)
    proven = 0
    for _ in range(3000):
        n = int(rng.integers(2, 5))
        A = rng.normal(size=(n, n))
        S = A @ A.T + 0.01 * np.eye(n)
        L = rng.normal(size=(n, n))
        P, Q = L @ S @ L.T, L @ L.T
        eps = 1e-12 * (1 + np.abs(P).max())
        bound, _ = gershgorin((P - eps)[None], (P + eps)[None], (Q - eps)[None], (Q + eps)[None])
        if bound[0] > -math.inf:
            proven += 1
            assert bound[0] <= np.linalg.eigvalsh(S)[0]
    assert proven >= 100


def test_the_three_backends_contain_each_others_point_values():
    """codac, arb and the batched backend on the same wide intervals of every transcendental op: each backend's
    enclosure over [a, b] meets every backend's enclosure of the value at a, at b and at the midpoint (both hold the
    exact value: disjoint ones would mean one backend is wrong)."""
    import casadi as ca

    from symfunnel.sx.batch import BatchIntervalFunction
    from symfunnel.sx.interval import IntervalFunction
    x = ca.SX.sym("x")
    fns = {"EXP": ca.exp, "LOG": ca.log, "SIN": ca.sin, "COS": ca.cos, "TAN": ca.tan, "ASIN": ca.asin,
           "ACOS": ca.acos, "ATAN": ca.atan, "SINH": ca.sinh, "COSH": ca.cosh, "TANH": ca.tanh, "ATANH": ca.atanh}
    rng = np.random.default_rng(9)
    for name, fn in fns.items():
        f = ca.Function(name, [x], [fn(x)])
        back = {"codac": IntervalFunction(f, "codac"), "arb": IntervalFunction(f, "arb"),
                "batch": BatchIntervalFunction(f)}
        pts = _points(name, 60, 10)
        for a, b in np.sort(rng.choice(pts, (2, 15)), axis=0).T:
            wide = {k: B.eval_flat(np.array([a]), np.array([b])) for k, B in back.items()}
            for xv in (a, b, 0.5 * (a + b)):
                pt = {k: B.eval_flat(np.array([xv]), np.array([xv])) for k, B in back.items()}
                for k, (L, H) in wide.items():
                    if not (np.isfinite(L[0]) and np.isfinite(H[0])):
                        continue
                    for k2, (pl, ph) in pt.items():
                        if np.isfinite(pl[0]) and np.isfinite(ph[0]):
                            # the exact value lies in both: the point enclosure meets the wide one
                            assert pl[0] <= H[0] and ph[0] >= L[0], (name, k, k2, a, b, xv)

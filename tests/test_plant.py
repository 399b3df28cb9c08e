"""Plant nonlinearities: exact dead zone = eq. 2, smoothing error rates, friction, and the dead-zone checks."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from symfunnel.plant.nonlinearities import check_dead_zone, dead_zone, dead_zone_numpy, dead_zone_slope_bounds, friction, friction_numpy, ramp, ramp_numpy, sign, sign_numpy

B_L = np.array([-0.4, -1.0])
B_R = np.array([0.5, 0.8])
# joint 1 linear, joint 2 nonlinear (the brief's right branch and a cubic left branch), all increasing
RIGHT = [lambda u: 1.5 * (u - 0.5), lambda u: 1.2 * (u - 0.8) + 0.1 * (u - 0.8) ** 2]
LEFT = [lambda u: 0.9 * (u + 0.4), lambda u: 1.1 * (u + 1.0) + 0.05 * (u + 1.0) ** 3]


def eq2(u, i):
    """The dead zone as printed in eq. 2, piecewise."""
    if u >= B_R[i]:
        return RIGHT[i](u)
    if u <= B_L[i]:
        return LEFT[i](u)
    return 0.0


def dz_function(w):
    u = ca.SX.sym("u", 2)
    return ca.Function("d", [u], [dead_zone(u, B_L, B_R, LEFT, RIGHT, w)])


GRID = np.concatenate([np.linspace(-6, 6, 2001), B_L, B_R, B_L + 1e-12, B_R - 1e-12])


def test_exact_dead_zone_is_eq2():
    f = dz_function(0.0).map(GRID.size)
    vals = np.asarray(f(np.vstack([GRID, GRID])))
    for i in range(2):
        expected = np.array([eq2(u, i) for u in GRID])
        np.testing.assert_allclose(vals[i], expected, rtol=1e-14, atol=1e-14)
    # and its array form (the same SX)
    np.testing.assert_allclose(dead_zone_numpy(np.vstack([GRID, GRID]), B_L, B_R, LEFT, RIGHT, 0.0), vals,
                               rtol=1e-14, atol=1e-14)


def test_dead_zone_is_zero_inside_band_and_continuous():
    f = dz_function(0.0)
    inside = np.asarray(f(np.array([0.0, 0.3]))).ravel()
    assert np.all(inside == 0.0)
    eps = 1e-9
    for b in (B_R, B_L):
        lo = np.asarray(f(b - eps)).ravel()
        hi = np.asarray(f(b + eps)).ravel()
        assert np.all(np.abs(hi - lo) < 1e-8)


def test_smooth_dead_zone_converges_linearly():
    # slope bounds on the grid: |d_r'| <= 1.2 + 0.2*5.2, |d_l'| <= 1.1 + 0.15*25 for joint 2; C = (L_l + L_r)/2
    L = np.array([1.5 + 0.9, (1.2 + 0.2 * 5.3) + (1.1 + 0.15 * 5.1 ** 2)])
    exact = np.asarray(dz_function(0.0).map(GRID.size)(np.vstack([GRID, GRID])))
    errs = []
    for w in (1e-1, 1e-2, 1e-3):
        smooth = np.asarray(dz_function(w).map(GRID.size)(np.vstack([GRID, GRID])))
        err = np.max(np.abs(smooth - exact), axis=1)
        assert np.all(err <= L / 2 * w + 1e-14), (w, err)
        errs.append(err.max())
        np.testing.assert_allclose(dead_zone_numpy(np.vstack([GRID, GRID]), B_L, B_R, LEFT, RIGHT, w), smooth,
                                   rtol=1e-12, atol=1e-14)
    rates = np.log10(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 0.9) and np.all(rates < 1.1), rates    # first order in w


def test_smooth_dead_zone_is_differentiable_at_breakpoints():
    u = ca.SX.sym("u", 2)
    d = dead_zone(u, B_L, B_R, LEFT, RIGHT, 1e-2)
    J = ca.Function("J", [u], [ca.jacobian(d, u)])
    for pt in (B_L, B_R, np.zeros(2)):
        jac = np.asarray(J(pt))
        assert np.all(np.isfinite(jac))
        assert np.all(np.diag(jac) > 0)            # smoothing keeps the dead zone strictly increasing


@pytest.mark.parametrize("w", [1e-1, 1e-2, 1e-3])
def test_ramp_error_bound(w):
    x = np.linspace(-3, 3, 6001)
    err = ramp_numpy(x, w) - np.maximum(x, 0)
    assert np.all(err >= 0) and np.all(err <= w / 2 + 1e-15)
    assert abs(ramp_numpy(0.0, w) - w / 2) < 1e-16           # the bound is attained at 0
    xs = ca.SX.sym("x")
    f = ca.Function("f", [xs], [ramp(xs, w), ca.jacobian(ramp(xs, w), xs)])
    v, dv = (np.asarray(a).ravel() for a in f.map(x.size)(x.reshape(1, -1)))
    np.testing.assert_allclose(v, 0.5 * (x + np.sqrt(x * x + w * w)), rtol=1e-14, atol=1e-16)   # the formula
    assert np.all(np.isfinite(dv)) and abs(float(f(0.0)[1]) - 0.5) < 1e-15
    # derivative continuous: Lipschitz with constant max|ramp_w''| = 1/(2w), checked on a grid of step w/100 at 0
    xf = np.linspace(-10 * w, 10 * w, 2001)
    dvf = np.asarray(f.map(xf.size)(xf.reshape(1, -1))[1]).ravel()
    assert np.max(np.abs(np.diff(dvf))) <= (xf[1] - xf[0]) / (2 * w) * (1 + 1e-9)


@pytest.mark.parametrize("w", [1e-1, 1e-2, 1e-3])
def test_sign_error_bound(w):
    x = np.concatenate([np.linspace(-3, 3, 6001), [0.0, 1e-300, -1e-300]])
    err = np.abs(sign_numpy(x, w) - np.sign(x))
    nz = np.abs(x) > 1e-100
    assert np.all(err <= 1.0)
    assert np.all(err[nz] <= np.minimum(1.0, w ** 2 / (2 * x[nz] ** 2)) + 1e-15)
    assert sign_numpy(0.0, w) == 0.0
    xs = ca.SX.sym("x")
    f = ca.Function("f", [xs], [sign(xs, w), ca.jacobian(sign(xs, w), xs)])
    v, dv = (np.asarray(a).ravel() for a in f.map(x.size)(x.reshape(1, -1)))
    np.testing.assert_allclose(v, x / np.sqrt(x * x + w * w), rtol=1e-14, atol=1e-16)           # the formula
    assert np.all(np.isfinite(dv))
    assert abs(float(f(0.0)[1]) - 1 / w) < 1e-9 / w           # finite slope 1/w at 0


def test_exact_forms_and_bad_width():
    xs = ca.SX.sym("x")
    f = ca.Function("f", [xs], [ramp(xs, 0), sign(xs, 0)])
    for v in (-2.0, 0.0, 3.0):
        r, s = f(v)
        assert float(r) == max(v, 0.0) and float(s) == np.sign(v)
    for bad in (-1e-3, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            ramp(xs, bad)
        with pytest.raises(ValueError):
            sign_numpy(1.0, bad)


def test_friction_paper_values():
    dq = ca.SX.sym("dq", 2)
    f = ca.Function("F", [dq], [friction(dq, [15.0, 15.0], [6.0, 6.0], 0.0)])
    rng = np.random.default_rng(0)
    for v in list(rng.uniform(-3, 3, (20, 2))) + [np.zeros(2), np.array([0.0, -1.0])]:
        np.testing.assert_allclose(np.asarray(f(v)).ravel(), 15 * v + 6 * np.sign(v), rtol=1e-15, atol=0)
        np.testing.assert_allclose(friction_numpy(v, 15.0, 6.0), 15 * v + 6 * np.sign(v), rtol=1e-15, atol=0)
    # per-joint coefficients and smoothing
    smooth = ca.Function("S", [dq], [friction(dq, np.array([1.0, 2.0]), np.array([3.0, 4.0]), 0.1)])
    v = np.array([0.05, -0.2])
    expected = np.array([1.0, 2.0]) * v + np.array([3.0, 4.0]) * v / np.sqrt(v ** 2 + 0.01)
    np.testing.assert_allclose(np.asarray(smooth(v)).ravel(), expected, rtol=1e-14)
    np.testing.assert_allclose(friction_numpy(v, [1.0, 2.0], [3.0, 4.0], 0.1), expected, rtol=1e-14)


def test_check_dead_zone_accepts_good():
    assert check_dead_zone(LEFT, RIGHT, B_L, B_R, span=5.0) == []


def test_check_dead_zone_flags_discontinuous_branch():
    right = [lambda u: 1.5 * u, RIGHT[1]]          # 1.5*b_r != 0: a jump at b_r
    problems = check_dead_zone(LEFT, right, B_L, B_R)
    assert len(problems) == 1 and "joint 1: right branch" in problems[0] and "jumps" in problems[0]


def test_check_dead_zone_flags_decreasing_branch():
    left = [LEFT[0], lambda u: -0.5 * (u + 1.0)]  # decreasing left branch on joint 2
    problems = check_dead_zone(left, RIGHT, B_L, B_R)
    assert len(problems) == 1 and "joint 2: left branch" in problems[0] and "slope" in problems[0]
    # a branch that turns over beyond the breakpoint is caught by the sampling
    right = [lambda u: (u - 0.5) - 0.2 * (u - 0.5) ** 2, RIGHT[1]]   # slope 1 - 0.4 (u - 0.5) < 0 for u > 3
    problems = check_dead_zone(LEFT, right, B_L, B_R, span=5.0)
    assert any("joint 1: right branch has slope" in p for p in problems)
    assert check_dead_zone(LEFT, right, B_L, B_R, span=2.0) == []


def test_check_dead_zone_flags_breakpoint_signs():
    problems = check_dead_zone([lambda u: u - 0.1, LEFT[1]], RIGHT, [0.1, -1.0], B_R)
    assert problems == ["joint 1: b_l = 0.1 is not < 0 (eq. 2 needs b_l < 0 < b_r)"]
    problems = check_dead_zone(LEFT, [lambda u: u + 0.2, RIGHT[1]], B_L, [-0.2, 0.8])
    assert problems == ["joint 1: b_r = -0.2 is not > 0 (eq. 2 needs b_l < 0 < b_r)"]


def test_check_dead_zone_reports_broken_branch():
    def boom(u):
        raise RuntimeError("unknown name 'v'")

    problems = check_dead_zone(LEFT, [boom, RIGHT[1]], B_L, B_R)
    assert len(problems) == 1 and "could not be evaluated" in problems[0]
    problems = check_dead_zone(LEFT, [lambda u: ca.sqrt(u - 0.5) * 0 + ca.log(u - 0.6), RIGHT[1]], B_L, B_R)
    assert any("not finite" in p or "jumps" in p for p in problems)


def test_slope_bounds():
    lo, hi = dead_zone_slope_bounds(LEFT, RIGHT, B_L, B_R, span=2.0)
    assert lo.shape == hi.shape == (2,)
    np.testing.assert_allclose([lo[0], hi[0]], [0.9, 1.5], rtol=1e-14)
    # joint 2: right slope 1.2 + 0.2 s, left slope 1.1 + 0.15 s^2, s in [0, 2] the distance from the breakpoint
    np.testing.assert_allclose([lo[1], hi[1]], [1.1, 1.1 + 0.15 * 4], rtol=1e-14)


def test_length_mismatch_raises():
    with pytest.raises(ValueError):
        dead_zone(ca.SX.sym("u", 2), B_L, B_R, LEFT[:1], RIGHT)
    with pytest.raises(ValueError):
        dead_zone(ca.SX.sym("u", 3), B_L, B_R, LEFT, RIGHT)
    with pytest.raises(ValueError):
        dead_zone(ca.SX.sym("u", 2), [-1, -1, -1], B_R, LEFT, RIGHT)

"""core.neldermead against scipy's Nelder-Mead: the same iterates (point, value, iterations, evaluations) to the
last bit, on smooth, nonsmooth, flat and non-finite functions."""

import numpy as np
import pytest

from symfunnel.core.neldermead import minimize

optimize = pytest.importorskip("scipy.optimize")


def rosen(x):
    return float(np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2))


def min_eig(x):
    """The audit's kind of objective: the smallest eigenvalue of a matrix depending on x (nonsmooth at crossings)."""
    M = np.array([[2 + np.cos(x[0]), 0.3 * np.sin(x[1])], [0.3 * np.sin(x[1]), 1.5 + 0.5 * np.cos(x[0] + x[1])]])
    return np.linalg.eigvalsh(M)[0]


def clipped(x):
    v = abs(x[0] - 0.3) + (x[1] + 0.2) ** 2
    return v if v < 4 else -1e300          # a sentinel like the audit's for a non-finite eigenvalue


CASES = [(rosen, [-1.2, 1.0]), (rosen, [0.0, 0.0, 0.0]), (min_eig, [0.4, -1.1]), (clipped, [1.0, 0.0]),
         (lambda x: 1.0, [2.0, 3.0]), (lambda x: float(x[0] ** 2), [0.0])]


@pytest.mark.parametrize("f, x0", CASES)
@pytest.mark.parametrize("xatol, fatol, maxiter", [(1e-10, 1e-14, 800), (1e-4, 1e-4, 30), (1e-10, 1e-14, 5)])
def test_same_iterates_as_scipy(f, x0, xatol, fatol, maxiter):
    want = optimize.minimize(f, np.array(x0), method="Nelder-Mead",
                             options={"xatol": xatol, "fatol": fatol, "maxiter": maxiter})
    got = minimize(f, np.array(x0), xatol=xatol, fatol=fatol, maxiter=maxiter)
    assert np.array_equal(got.x, want.x) and got.fun == want.fun
    assert (got.nit, got.nfev) == (want.nit, want.nfev)


def test_finds_the_minimum_of_a_quadratic():
    """Independent of scipy: the minimiser of a shifted quadratic to the tolerance asked."""
    r = minimize(lambda x: float((x[0] - 1.5) ** 2 + 3 * (x[1] + 0.25) ** 2), [0.0, 0.0], xatol=1e-10,
                 fatol=1e-14, maxiter=2000)
    assert np.allclose(r.x, [1.5, -0.25], atol=1e-7) and r.fun < 1e-13

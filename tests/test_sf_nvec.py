"""CVODES' vector operations four doubles at a time (csrc/sf_nvec.h) against SUNDIALS' own serial ones, called
through CVODES' dispatch on the same vectors: every coefficient case of N_VLinearSum and N_VScale, in place and
not, N_VAbs, N_VInv, N_VAddConst, N_VMin, on lengths around the vector width and on values with signed zeros,
infinities and NaNs: the same doubles, bit for bit (NaN for NaN); and a run with them is the run without them."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from symfunnel.simulation import sundials

from .test_sf_lu import assert_same_run, runs_with

pytestmark = pytest.mark.skipif(not sundials.available(), reason="the CVODES driver does not build here")

SPECIAL = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-310, -1e300, 3.0])


def _apply(op, a, b, x, y, alias, wide):
    lib = sundials.driver_library()
    x, y = x.copy(), y.copy()
    z = np.full_like(x, 7.0)
    r = ctypes.c_double(0.0)
    p = lambda v: v.ctypes.data_as(ctypes.POINTER(ctypes.c_double))   # noqa: E731
    on = lib.sf_nv_apply(op, a, b, x.size, p(x), p(y), p(z), alias, wide, ctypes.byref(r))
    assert on >= 0
    return on, np.concatenate([x, y, z, [r.value]])


def _same_bits(u, v):
    """Equal bit for bit, NaNs aside: NaN where the other has NaN (which NaN, its sign and payload, follows the
    operand order a compiler picks for a commutative product or sum, and is no number the run uses)."""
    nan = np.isnan(u)
    return np.array_equal(nan, np.isnan(v)) and np.array_equal(u[~nan].view(np.int64), v[~nan].view(np.int64))


def _vectors(rng, n):
    x, y = rng.normal(size=n) * 10.0 ** rng.integers(-3, 4, n), rng.normal(size=n)
    if n >= 8:
        x[rng.choice(n, 8, replace=False)] = SPECIAL
        y[rng.choice(n, 8, replace=False)] = SPECIAL[::-1]
    return x, y


COEFFS = [1.0, -1.0, 0.5, -0.5, 0.0, 2.75, np.nan]


def test_every_case_gives_sundials_doubles():
    rng = np.random.default_rng(5)
    installed = set()
    for n in (1, 3, 4, 5, 7, 8, 156):
        x, y = _vectors(rng, n)
        cases = [(0, a, b, al) for a in COEFFS for b in COEFFS for al in (0, 1, 2)]
        cases += [(1, a, 0.0, al) for a in COEFFS for al in (0, 1)]
        cases += [(op, 1.5, 0.0, al) for op in (2, 3, 4) for al in (0, 1)] + [(4, -0.0, 0.0, 0)]
        for op, a, b, al in cases:
            on, got = _apply(op, a, b, x, y, al, 1)
            _, want = _apply(op, a, b, x, y, al, 0)
            installed.add(on)
            assert _same_bits(got, want), (n, op, a, b, al)
    assert installed == {1} or not _avx2()


def test_min_is_sundials_min_with_its_zero_and_nan_rules():
    """N_VMin keeps x[0] and replaces it by each later smaller element: which zero (+0 or -0) comes first, a NaN
    at x[0] returned, NaNs later skipped -- with four running minima the same doubles."""
    rng = np.random.default_rng(8)
    cases = [np.array([1.0, 5, 0.0, 5, 5, -0.0, 5, 5, 5]), np.array([1.0, 5, -0.0, 5, 5, 0.0, 5, 5, 5]),
             np.array([1.0, 0.0, 2.0, -0.0, 5.0, 0.0, -0.0, 3.0, 4.0]), np.array([1.0, 2, 3, 4, 5, -0.0, 0.0, 9, 1]),
             np.array([np.nan, -1.0, -2.0, 3, 4, 5]), np.array([2.0, np.nan, np.nan, -1.0, np.nan, 7, 8, 9]),
             np.array([0.0] * 9), np.array([-np.inf, 1.0, 2, 3, 4])]
    cases += [_vectors(rng, n)[k] for n in (1, 2, 5, 12, 156) for k in (0, 1)]
    for x in cases:
        _, got = _apply(5, 0.0, 0.0, x, x, 0, 1)
        _, want = _apply(5, 0.0, 0.0, x, x, 0, 0)
        assert _same_bits(got[-1:], want[-1:]), x


def _avx2() -> bool:
    try:
        return "avx2" in open("/proc/cpuinfo", encoding="ascii").read()
    except OSError:
        return False


@pytest.mark.parametrize("scenario", ["paper", "arm7"])
def test_a_run_with_the_wide_vectors_is_the_run_without(scenario, monkeypatch):
    """A 1 s run with the four-wide operations (the default) and with SUNDIALS' own: the same trajectory, logged
    signals and counts, array by array."""
    assert_same_run(*runs_with(scenario, monkeypatch, "WIDE_VECTORS"))

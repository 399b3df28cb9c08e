"""The Newton matrix's two LU forms (csrc/sf_lu.h): the scheduled factorisation and row-wise solve the driver uses,
against the column form kept as the reference -- the same doubles, the same refusals -- and numpy's dense solve;
and a whole run on either form, array by array."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from symfunnel.simulation import sundials

from .test_sundials import _jacobian, _solver


def _both(D, Jx, gamma, b):
    """(I - gamma J)^-1 b by the scheduled form and by the column form (None: refused)."""
    out = []
    for columns in (0, 1):
        D._lib.sf_set_lu_columns(D._h, columns)
        out.append(D.factor_solve(Jx, gamma, b))
    D._lib.sf_set_lu_columns(D._h, 0)
    return out


def test_scheduled_lu_gives_the_column_forms_doubles_and_numpys_solution(paper_run):
    """On the paper loop's Jacobian at its start and at perturbed states, gamma from 1e-6 to 1: the two forms'
    solutions are equal to the last bit, and within 1e-12 of numpy's dense LU with partial pivoting."""
    cl, comp, D = _solver(paper_run)
    jac = _jacobian(cl, comp)
    rng = np.random.default_rng(11)
    for x in (cl.x0, cl.x0 + rng.normal(0, 0.05, cl.nx), cl.x0 + rng.normal(0, 0.3, cl.nx)):
        J = jac(1.3, x)
        Jd = np.array(ca.densify(J))
        for gamma in (1e-6, 1e-4, 3e-3, 0.05, 1.0):
            b = rng.normal(size=cl.nx)
            got, ref = _both(D, np.array(J.nonzeros()), gamma, b)
            assert got is not None and ref is not None
            assert np.array_equal(got, ref)
            want = np.linalg.solve(np.eye(cl.nx) - gamma * Jd, b)
            assert np.max(np.abs(got - want)) <= 1e-12 * max(1.0, np.max(np.abs(want)))


def test_scheduled_lu_refuses_what_the_column_form_refuses(paper_run):
    """A zero pivot (gamma = 1/J_00), a tiny one whose multipliers grow past the threshold, a non-finite Jacobian
    entry: both forms refuse; a good factorisation afterwards solves again, bit for bit alike."""
    cl, comp, D = _solver(paper_run)
    J = _jacobian(cl, comp)(0.0, cl.x0)
    Jx = np.array(J.nonzeros())
    J00 = float(J[0, 0])
    bad = Jx.copy()
    bad[len(bad) // 2] = np.nan
    b = np.linspace(-1.0, 1.0, cl.nx)
    for Jv, gamma in ((Jx, 1.0 / J00), (Jx, (1 - 1e-13) / J00), (bad, 1e-3)):
        assert _both(D, Jv, gamma, b) == [None, None]
        got, ref = _both(D, Jx, 1e-3, b)
        assert got is not None and np.array_equal(got, ref)


@pytest.mark.parametrize("scenario", ["paper", "arm7"])
def test_a_run_on_the_scheduled_lu_is_the_column_forms_run(scenario, monkeypatch):
    """A 1 s run with the scheduled LU (the default) and with the column form: the same trajectory, logged signals,
    step, right-hand-side and Jacobian counts and between-points statistics, array by array."""
    runs = runs_with(scenario, monkeypatch, "SCHEDULED_LU")
    assert runs[0].stats["steps"] > 100
    assert_same_run(*runs)


def runs_with(scenario, monkeypatch, flag: str) -> list:
    """Two 1 s runs of `scenario` on the driver, with the `sundials` switch `flag` on, then off."""
    from symfunnel.pipeline import Run
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    run = Run.load(scenario)
    runs = []
    for on in (True, False):
        monkeypatch.setattr(sundials, flag, on)
        runs.append(simulate(run.scenario, run.design, t_final=1.0, closed_loop=run.closed_loop))
    return runs


def assert_same_run(a, b):
    """Two runs of the direct backend with the same trajectory, logged signals, counts and between-points
    statistics, array by array."""
    assert a.stats["cvodes_backend"] == "direct" == b.stats["cvodes_backend"]
    assert np.array_equal(a.t, b.t) and np.array_equal(a.x, b.x)
    assert a.signals.keys() == b.signals.keys()
    for k in a.signals:
        assert np.array_equal(a.signals[k], b.signals[k], equal_nan=True), k
    for k in ("steps", "rhs_evaluations", "jacobian_evaluations", "error_test_failures", "between"):
        assert a.stats[k] == b.stats[k], k

"""The closed-loop ODE: assembled from the design, plant alone conserves energy, LDL solve, state packing."""

from __future__ import annotations

import copy

import casadi as ca
import numpy as np
import pytest

from symfunnel.design import derive
from symfunnel.plant.equations import plant_acceleration
from symfunnel.simulation.closedloop import build_closed_loop
from symfunnel.sx.linalg import ldl_solve
from symfunnel.scenario import from_dict, load_scenario


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def _variant(sc, edit):
    raw = copy.deepcopy(sc.raw)
    edit(raw)
    return from_dict(raw, file="variant.toml", base_dir=sc.path.parent, default_name="variant")


def test_ldl_solve_matches_numpy():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 7):
        A = rng.normal(size=(n, n))
        M = A @ A.T + n * np.eye(n)
        b = rng.normal(size=n)
        x = np.array(ca.evalf(ldl_solve(ca.SX(ca.DM(M)), ca.SX(ca.DM(b))))).ravel()
        assert np.allclose(x, np.linalg.solve(M, b), rtol=1e-12, atol=1e-12)


def test_state_layout_and_shapes(paper):
    cl = build_closed_loop(paper, derive(paper))
    nr = cl.design.n_regressor
    assert cl.nx == 2 * cl.n + cl.N + nr * cl.n == 156
    x = cl.pack([1, 2], [3, 4], np.arange(cl.N), np.arange(nr * cl.n).reshape(cl.n, nr).T)
    parts = cl.unpack(x)
    assert parts["q"].tolist() == [1, 2] and parts["dq"].tolist() == [3, 4]
    assert parts["w_hat"].shape == (nr, cl.n)
    assert np.array_equal(parts["w_hat"], np.arange(nr * cl.n).reshape(cl.n, nr).T)   # column-major vec
    assert cl.rhs(0.0, cl.x0).shape == (cl.nx,)
    assert cl.f.name_in() == ["t", "x"]


def test_ddq_splits_into_nominal_plus_unknown(paper):
    """ddq_plant = v - W^T Phi + f_true, and the ESN estimate is W^T Phi (the lead's identity)."""
    cl = build_closed_loop(paper, derive(paper))
    rng = np.random.default_rng(1)
    x = cl.x0 + 0.01 * rng.normal(size=cl.nx)
    o = cl.evaluate_outputs([0.3], x[None, :])
    assert np.allclose(o["ddq"], o["ddq_nom"] + o["f_true"])
    assert np.allclose(cl.rhs(0.3, x)[cl.n:2 * cl.n], o["ddq"][0])


def _energy_drift(sc) -> tuple[float, float]:
    q, dq = sc.model.q, sc.model.dq
    t = ca.SX.sym("t")
    parts = plant_acceleration(sc, q, dq, t, ca.SX.zeros(sc.n), 0.0)
    x = ca.vertcat(q, dq)
    F = ca.integrator("F", "cvodes", {"x": x, "t": t, "ode": ca.vertcat(dq, parts["ddq"])}, 0.0,
                      list(np.linspace(0.5, 5.0, 10)), {"abstol": 1e-12, "reltol": 1e-12})
    E = ca.Function("E", [x], [0.5 * ca.mtimes([dq.T, parts["M"], dq])])
    x0 = np.array([0.3, -0.7, 2.0, -1.5])
    X = np.array(F(x0=x0)["xf"])
    E0 = float(E(x0))
    drift = max(abs(float(E(X[:, k])) - E0) for k in range(X.shape[1]))
    return E0, drift


def test_plant_alone_conserves_energy(paper):
    """Friction, dead zone, disturbance and input off: E = dq^T M dq / 2 is constant (G = 0).

    The paper's model types in the C of eq. 41, which breaks Property 1; the plant takes the physical Coriolis
    matrix of M, so energy is conserved all the same.
    """
    def edit(raw):
        raw["plant"] = {"viscous": 0.0, "coulomb": 0.0, "disturbance": "0", "mass_scale": 1.2}
    E0, drift = _energy_drift(_variant(paper, edit))
    assert E0 > 1.0
    assert drift / E0 < 1e-8


def test_plant_with_the_printed_C_does_not_conserve_energy(paper):
    """The same check fails when the plant is made to use eq. 41's C: the test can tell."""
    def edit(raw):
        raw["plant"] = {"viscous": 0.0, "coulomb": 0.0, "disturbance": "0", "coriolis": "model"}
    E0, drift = _energy_drift(_variant(paper, edit))
    assert drift / E0 > 1e-3


def test_no_dead_zone_means_tau_applied_is_tau(paper):
    sc = _variant(paper, lambda raw: raw["plant"].pop("dead_zone"))
    cl = build_closed_loop(sc, derive(sc))
    o = cl.evaluate_outputs([0.0, 0.1], np.vstack([cl.x0, cl.x0]))
    assert np.array_equal(o["tau"], o["tau_applied"])

"""`plant.equations.dead_zone_deviation`: D(tau) - tau in the form where tau enters once equals the plant's own
D(tau) - tau (numpy from `plant_forces`' dead zone at width 0) on every branch, its interval enclosure over a box
of large torques is as narrow as the true range (the form as written is ~100 times wider), and it is what
`region.true_unknown` uses."""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from symfunnel.plant.equations import dead_zone_deviation, plant_forces
from symfunnel.scenario import load_scenario
from symfunnel.sx.batch import BatchIntervalFunction

ROOT = Path(__file__).resolve().parent.parent


def _scenario(left="0.98*(u - b_l)", right="1.02*(u - b_r)"):
    return load_scenario(str(ROOT / "derivations" / "paper_small_dead_zone.toml")).replace(
        {"plant.dead_zone.left": left, "plant.dead_zone.right": right})


def _numpy_deviation(u, b_l, b_r, left, right):
    """D(u) - u of eq. 2 by its definition (the branch outside [b_l, b_r], 0 inside)."""
    d = np.where(u > b_r, right(u), np.where(u < b_l, left(u), 0.0))
    return d - u


def test_the_deviation_equals_the_dead_zone_minus_tau_on_every_branch():
    cases = [("0.98*(u - b_l)", "1.02*(u - b_r)", lambda u: 0.98 * (u + 1.5), lambda u: 1.02 * (u - 1.0)),
             ("(u - b_l) + 0.0008*(u - b_l)^3", "1.1*(u - b_r) - 0.001*(u - b_r)^2",
              lambda u: (u + 1.5) + 0.0008 * (u + 1.5) ** 3, lambda u: 1.1 * (u - 1.0) - 0.001 * (u - 1.0) ** 2),
             ("0.98*(u - b_l)", "(u - b_r) + 0.01*(1 - exp(-(u - b_r)))", lambda u: 0.98 * (u + 1.5),
              lambda u: (u - 1.0) + 0.01 * (1 - np.exp(-(u - 1.0))))]
    rng = np.random.default_rng(2)
    for left, right, fl, fr in cases:
        sc = _scenario(left, right)
        tau = ca.SX.sym("tau", 2)
        f = ca.Function("dev", [tau], [dead_zone_deviation(sc, tau)])
        g = ca.Function("direct", [tau], [plant_forces(sc, ca.SX.zeros(2), ca.SX.zeros(2), 0.0, tau, 0.0)
                                           ["tau_applied"] - tau])
        U = np.concatenate([rng.uniform(-50, 50, (200, 2)), rng.uniform(-1.5, 1.0, (50, 2)),
                            rng.uniform(-400, 400, (50, 2))])
        for u in U:
            got = np.asarray(f(u), float).ravel()
            want = _numpy_deviation(u, -1.5, 1.0, fl, fr)
            assert np.allclose(got, want, rtol=1e-12, atol=1e-9), (u, got, want)
            assert np.allclose(got, np.asarray(g(u), float).ravel(), rtol=1e-12, atol=1e-9)


def test_the_deviation_is_enclosed_without_taus_width_twice():
    sc = _scenario()
    tau = ca.SX.sym("tau", 2)
    new = BatchIntervalFunction(ca.Function("dev", [tau], [dead_zone_deviation(sc, tau)]))
    old = BatchIntervalFunction(ca.Function("direct", [tau], [plant_forces(
        sc, ca.SX.zeros(2), ca.SX.zeros(2), 0.0, tau, 0.0)["tau_applied"] - tau]))
    lo, hi = np.array([[3000.0, -3100.0]]), np.array([[3100.0, -3000.0]])
    NL, NH, _ = new.eval_batch(lo, hi)
    OL, OH, _ = old.eval_batch(lo, hi)
    # the true ranges: right 1.02 (tau - 1) - tau = 0.02 tau - 1.02; left 0.98 (tau + 1.5) - tau = 1.47 - 0.02 tau
    want_lo, want_hi = np.array([58.98, 61.47]), np.array([60.98, 63.47])
    assert np.all(NL[0] <= want_lo + 1e-9) and np.all(want_hi - 1e-9 <= NH[0])
    assert np.all(NH[0] - NL[0] <= 2.0 + 1e-9), (NL, NH)             # the true width 0.02 * 100
    assert np.all(OH[0] - OL[0] >= 190.0), (OL, OH)                    # as written: (s + 1) * 100


def test_true_unknown_uses_the_deviation_and_keeps_its_values(monkeypatch):
    from symfunnel.certificates import region
    from symfunnel.pipeline import derive
    from symfunnel.plant.equations import plant_parameters
    sc = load_scenario(str(ROOT / "derivations" / "paper_small_dead_zone.toml")).replace({"esn.size": 6})
    d = derive(sc)
    names, p0 = plant_parameters(sc)
    p = ca.SX.sym("p", len(names))
    ins = [d.sym[k] for k in d.sym] + [p]
    new = ca.Function("new", ins, [region.true_unknown(d, p)["f_true"]])
    monkeypatch.setattr(region, "DEAD_ZONE_DEVIATION", False)
    old = ca.Function("old", ins, [region.true_unknown(d, p)["f_true"]])
    assert new.n_instructions() != old.n_instructions()
    rng = np.random.default_rng(4)
    for _ in range(50):
        args = [rng.uniform(-1, 1, d.sym[k].shape) for k in d.sym] + [p0 * rng.uniform(0.95, 1.05, p0.size)]
        a, b = (np.asarray(f(*args), float).ravel() for f in (new, old))
        assert np.allclose(a, b, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(b).max())), (a, b)

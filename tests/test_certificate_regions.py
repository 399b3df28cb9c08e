"""The certificates' regions and level sets rebuilt independently -- from the scenario's funnels and reference
directly, not by calling certificates/region.py's constructions -- and checked against simulated runs: every state
of a run lies in the region a certificate works on, the region lies in the set it declares, and the margins the
invariance certificate refutes by V(0) are exactly those whose level 1/2 z(1 - m)^2 is below V(0)."""

from __future__ import annotations

import copy
from pathlib import Path

import casadi as ca
import numpy as np

import symfunnel as sf
from symfunnel.certificates import run_certificates
from symfunnel.certificates.bounds import BOUNDS_MARGIN
from symfunnel.certificates.invariance import M_GRID
from symfunnel.certificates.problem import Context, RegionProblem, controller_state_boxes
from symfunnel.certificates.region import joint_box, parameter_box
from symfunnel.core.toml_write import dumps

NONE = Path(__file__).resolve().parent / "data" / "certify_none.toml"
T_FINAL = 2.0
_CACHE: dict = {}


def _wide_start(tmp_path_factory):
    """certify_none started at 60 % of the e1 funnel (q1(0) = 0.15, F1(0) = 0.25) and 22 % of e2's: its run uses the
    funnels' width."""
    if "path" not in _CACHE:
        raw = copy.deepcopy(sf.load_scenario(str(NONE)).raw)
        raw["initial"]["q"] = [0.15, 0.2]
        raw["initial"]["dq"] = [-2.6, 0.0]             # alpha2(0) = [-2.82, 0]: e2(0) inside F2(0) = 1
        raw["simulation"]["t_final"] = T_FINAL
        p = tmp_path_factory.mktemp("regions") / "wide.toml"
        p.write_text(dumps(raw), encoding="utf-8")
        _CACHE["path"] = str(p)
    return _CACHE["path"]


def _independent(sc, design):
    """q_d(t) from the reference expressions, F1, F2 from the funnel shapes, alpha2 the design's own signal."""
    t = ca.SX.sym("t")
    qd = ca.Function("qd", [t], [ca.vertcat(*[ca.SX(e.to_casadi({"t": t})) for e in sc.reference])])
    F1 = ca.Function("F1", [t], [ca.SX(sc.funnels["e1"].sx(t))])
    F2 = ca.Function("F2", [t], [ca.SX(sc.funnels["e2"].sx(t))])
    return qd, F1, F2, design.function("alpha2", ["t", "q", "qd", "dqd"])


def test_every_simulated_state_lies_in_the_bounds_region_and_the_region_in_its_declared_set(tmp_path_factory):
    """R_m (m = BOUNDS_MARGIN): each state of the run, written in region coordinates s = e / ((1 - m) F) with the
    independently built q_d, F and e2 = dq - alpha2, lies in the certificate's box; 2000 random points of that box,
    mapped to states by the certificate, satisfy |e_i| <= (1 - m) F_i computed independently."""
    path = _wide_start(tmp_path_factory)
    sc = sf.load_scenario(path)
    d = sf.derive(sc)
    run = sf.simulate(path)
    assert run.status == "ok"
    ctx = Context(sc, d, T_FINAL, parameter_box(sc), None, None)
    p = ca.SX.sym("p", len(ctx.params.names))
    prob = RegionProblem(ctx, {"tau": d.signals["tau"]}, p, "regions")
    m = BOUNDS_MARGIN
    region = prob.region(m, controller_state_boxes(ctx, None))
    qd_f, F1_f, F2_f, a2_f = _independent(sc, d)
    t = np.asarray(run.t, float)
    q = np.asarray(run.signals["q"], float).reshape(len(t), -1)
    dq = np.asarray(run.signals["dq"], float).reshape(len(t), -1)
    used = 0.0
    # reference derivatives by AD of the expressions (independent of the design's reference_t)
    ts = ca.SX.sym("ts")
    qexpr = ca.vertcat(*[ca.SX(e.to_casadi({"t": ts})) for e in sc.reference])
    dqd_f = ca.Function("dqd", [ts], [ca.jacobian(qexpr, ts)])
    for k in range(len(t)):
        tk = float(t[k])
        qd = np.asarray(qd_f(tk), float).ravel()
        dqd = np.asarray(dqd_f(tk), float).ravel()
        F1 = np.asarray(F1_f(tk), float).ravel()
        F2 = np.asarray(F2_f(tk), float).ravel()
        e1 = q[k] - qd
        e2 = dq[k] - np.asarray(a2_f(tk, q[k], qd, dqd), float).ravel()
        s1, s2 = e1 / ((1 - m) * F1), e2 / ((1 - m) * F2)
        used = max(used, float(np.max(np.abs(s1))))
        assert region["t"][0] <= tk <= region["t"][1]
        for s, key in ((s1, "s1"), (s2, "s2")):
            lo, hi = region[key]
            assert np.all(lo <= s) and np.all(s <= hi), (key, tk, s, lo, hi)
    assert used > 0.6                        # the run uses the funnel's width (a region half as wide fails)
    # the region lies in the declared set
    lo, hi = prob.flat(region)
    rng = np.random.default_rng(8)
    X = lo + rng.random((2000, lo.size)) * (hi - lo)
    for x in X[:2000:10]:
        sp = prob.state_point(prob.point(x))
        tk = sp["t"]
        qd = np.asarray(qd_f(tk), float).ravel()
        dqd = np.asarray(dqd_f(tk), float).ravel()
        F1 = np.asarray(F1_f(tk), float).ravel()
        F2 = np.asarray(F2_f(tk), float).ravel()
        assert 0.0 <= tk <= T_FINAL
        assert np.all(np.abs(sp["q"] - qd) <= (1 - m) * F1 * (1 + 1e-12))
        a2 = np.asarray(a2_f(tk, sp["q"], qd, dqd), float).ravel()
        assert np.all(np.abs(sp["dq"] - a2) <= (1 - m) * F2 * (1 + 1e-9))


def test_joint_box_holds_the_funnel_tube_and_the_run(tmp_path_factory):
    """The input gain's joint box contains q_d(t) +- F1(t) on a 20001-point grid (built from the expressions and
    the funnel shape) and every q of the simulated run."""
    path = _wide_start(tmp_path_factory)
    sc = sf.load_scenario(path)
    d = sf.derive(sc)
    ql, qh, _ = joint_box(d, T_FINAL)
    qd_f, F1_f, _, _ = _independent(sc, d)
    grid = np.linspace(0.0, T_FINAL, 20001)
    qd = np.asarray(qd_f.map(grid.size)(grid[None, :]), float)
    F1 = np.asarray(F1_f.map(grid.size)(grid[None, :]), float)
    assert np.all(ql[:, None] <= qd - F1) and np.all(qd + F1 <= qh[:, None])
    q = np.asarray(sf.simulate(path).signals["q"], float)
    assert np.all(ql <= q.min(axis=0)) and np.all(q.max(axis=0) <= qh)
    # and no wider than range(q_d) +- sup F1 (its construction), up to 1e-6
    assert np.all(ql >= qd.min(axis=1) - F1.max(axis=1) - 1e-6) and np.all(qh <= qd.max(axis=1) + F1.max(axis=1) + 1e-6)


def test_invariance_levels_are_the_transformations_own(tmp_path_factory):
    """The level a margin m allows is c_max(m) = 1/2 z(1 - m)^2 with z the transformation's own build at the
    normalised error 1 - m (F = 1): a margin is refuted by V(0) exactly when V(0) >= c_max(m), on every grid margin."""
    path = _wide_start(tmp_path_factory)
    sc = sf.load_scenario(path)
    d = sf.derive(sc)
    c = run_certificates(sc, d, t_final=T_FINAL, only=("certify.invariance",),
                         work={"certify.invariance": 1e6}).certificates[0]
    V0 = c.extra["V0"][0]
    T = d.variant.transform

    def c_max(m):
        z = float(T.build(ca.DM(1 - m), ca.DM(1.0))["z"])
        return 0.5 * z * z
    outcome = {}
    for run_ in c.extra["margins"]:
        for m in M_GRID:
            if run_["m"][0] <= m <= run_["m"][1]:
                outcome[m] = run_["outcome"]
    assert len(outcome) == len(M_GRID)
    by_v0 = [m for m in M_GRID if V0 >= c_max(m) * (1 + 1e-9)]
    assert 0 < len(by_v0) < len(M_GRID)            # the start uses 60 % of the funnel: some margins are excluded
    for m in M_GRID:
        if abs(V0 / c_max(m) - 1) < 1e-6:
            continue                               # at the level itself the safety factor decides
        assert (outcome[m] == "V(0)") == (V0 >= c_max(m)), (m, V0, c_max(m), outcome[m])

"""`certify.containment` (issue 45, item 2): Nagumo's condition on the faces of S, checked against what does not
use the certificate's machinery.

- the face expressions (with the terms a graph identity cancels dropped) equal the normal component written by
  hand from the plant's own acceleration, at random states;
- a proven set: runs started on its boundary (faces and corners, at the corners of the parameter box) never leave
  it -- S rebuilt from the funnels' formulas and the virtual control written out in numpy, not from the certificate;
- designs that cannot keep their funnels are not proven (k1 tiny; the sign of k2 flipped);
- refuted only by a real breach of the simulated loop; verify shows it as a check (proven pass, undecided warn).
"""

from __future__ import annotations

import copy
import itertools
import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import symfunnel as sf
from symfunnel.certificates import run_certificates
from symfunnel.certificates.containment import face_expressions
from symfunnel.cli import main
from symfunnel.core.toml_write import dumps
from symfunnel.plant.equations import plant_acceleration, plant_parameters

from .pins import pins

ROOT = Path(__file__).resolve().parent.parent
NONE = str(ROOT / "tests" / "data" / "certify_none.toml")
BREACH = str(ROOT / "derivations" / "sim_breach.toml")
ONLY = ("certify.containment",)


def _write(tmp_path, raw, name="s.toml"):
    p = tmp_path / name
    p.write_text(dumps(raw), encoding="utf-8")
    return str(p)


def _none_with_box(tmp_path):
    """certify_none with a parameter box: the plant's mass scale and disturbance scale uncertain."""
    raw = copy.deepcopy(sf.load_scenario(NONE).raw)
    raw["uncertainty"] = [{"key": "plant.mass_scale", "dist": "uniform", "low": 0.95, "high": 1.05},
                          {"key": "plant.disturbance_scale", "dist": "uniform", "low": 0.0, "high": 2.0}]
    return raw, _write(tmp_path, raw)


def _certify(path, **kw):
    sc = sf.load_scenario(path)
    return run_certificates(sc, sf.derive(sc, **kw), t_final=sc.simulation.t_final, only=ONLY).certificates[0]


def test_face_expressions_are_the_normal_components_of_the_plant(tmp_path):
    """n1 = de1 - (e1/F1) dF1 and n2 = ddq_plant - alpha2_dot - (e2/F2) dF2, at random states, against the same
    quantities composed without the certificate: the plant's ddq under the design's tau and the design's
    alpha2_dot, e, F, dF (and, for n1, dq - dqd written out)."""
    for path in (NONE, str(ROOT / "derivations" / "paper_small_dead_zone.toml")):
        sc = sf.load_scenario(path)
        d = sf.derive(sc)
        names, p0 = plant_parameters(sc)
        p = ca.SX.sym("p", len(names))
        exprs, info = face_expressions(d, p)
        assert info["cancelled"]["alpha2_dot in de2"] and info["cancelled"]["dqd in de1"]
        assert info.get("estimate", False) == bool(d.n_regressor)      # tau sees W_hat only through W_hat^T Phi
        S, sym = d.signals, d.sym
        pl = plant_acceleration(sc, sym["q"], sym["dq"], sym["t"], S["tau"], 0.0, p=p)
        ins = [sym[k] for k in ("t", "q", "dq", "qd", "dqd", "ddqd")] + [sym[k] for k, _ in d.states] + [p]
        f = ca.Function("f", ins, [exprs["n1"], exprs["n2"], pl["ddq"], S["alpha2_dot"], S["e1"], S["e2"], S["F1"],
                                   S["F2"], S["dF1"], S["dF2"]])
        names_s = [k for k, _ in d.states]
        phi = ca.Function("phi", ins, [S["Phi"] if d.n_regressor else ca.SX(0, 1)])
        rng = np.random.default_rng(7)
        for _ in range(20):
            t = rng.uniform(0, 3)
            qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(t))
            q = qd + rng.uniform(-0.5, 0.5, d.n) * 0.05
            dq = dqd + rng.uniform(-0.1, 0.1, d.n)
            states = [rng.uniform(-0.3, 0.3, sh) for _, sh in d.states]
            pp = p0 * rng.uniform(0.95, 1.05, p0.size)
            vals = [np.asarray(v, float).ravel() for v in f(t, q, dq, qd, dqd, ddqd, *states, pp)]
            _, _, ddq, a2d, e1, e2, F1, F2, dF1, dF2 = vals
            n1, n2 = vals[0], vals[1]
            if info.get("estimate"):
                # the e2 face sees W_hat only through W_hat^T Phi, carried by W_hat's first row
                k = names_s.index("w_hat")
                W = states[k]
                est = W.T @ np.asarray(phi(t, q, dq, qd, dqd, ddqd, *states, pp), float).ravel()
                carried = [np.array(x) for x in states]
                carried[k] = np.zeros_like(W)
                carried[k][0, :] = est
                n2 = np.asarray(f(t, q, dq, qd, dqd, ddqd, *carried, pp)[1], float).ravel()
            np.testing.assert_allclose(n1, (dq - dqd) - e1 / F1 * dF1, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(n2, ddq - a2d - e2 / F2 * dF2, rtol=1e-8, atol=1e-8 * np.abs(a2d).max())


def _alpha2(t, q, sc):
    """The virtual control written out (funnel transform z = e/(F - |e|)): dqd + dF1/F1 e1 - k1 z1."""
    f1 = sc.raw["funnel"]["e1"]
    F1 = f1["phi0"] * np.exp(-f1["a"] * t) + f1["phi_inf"]
    dF1 = -f1["a"] * f1["phi0"] * np.exp(-f1["a"] * t)
    qd = np.array([0.3 * np.sin(t), 0.2 * np.cos(t)])
    dqd = np.array([0.3 * np.cos(t), -0.2 * np.sin(t)])
    e1 = q - qd
    return dqd + dF1 / F1 * e1 - sc.raw["controller"]["k1"] * e1 / (F1 - np.abs(e1)), e1, F1


def _F2(t, sc):
    f2 = sc.raw["funnel"]["e2"]
    return f2["phi0"] * np.exp(-f2["a"] * t) + f2["phi_inf"]


@pins("certify.containment", "pass")
def test_proven_on_certify_none_and_runs_from_the_boundary_stay_in_the_set(tmp_path):
    raw, path = _none_with_box(tmp_path)
    c = _certify(path)
    assert c.status == "proven", c.detail
    m1, m2 = c.extra["margin"]["e1"], c.extra["margin"]["e2"]
    assert c.extra["horizon"] == "finite" and c.extra["w_bound"] is None
    assert c.region["kind"] == "proven_invariant" and "plant.mass_scale" in c.region["parameters"]
    c1, c2 = 1 - m1, 1 - m2
    sc = sf.load_scenario(path)
    # initial states on S's boundary: every corner of (s1, s2) and the middle of each e2 face, at the corners of
    # the parameter box
    starts = [np.array(s) for s in itertools.product((-1.0, 1.0), repeat=4)][::3]
    starts += [np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0, 0.0])]
    worst = 0.0
    for k, s in enumerate(starts):
        r = copy.deepcopy(raw)
        r.pop("uncertainty")
        r["plant"]["mass_scale"] = (0.95, 1.05)[k % 2]
        r["plant"]["disturbance_scale"] = (0.0, 2.0)[(k // 2) % 2]
        q0 = np.array([0.0, 0.2]) + s[:2] * c1 * _alpha2(0.0, np.zeros(2), sc)[2]
        a2, _, _ = _alpha2(0.0, q0, sc)
        dq0 = a2 + s[2:] * c2 * _F2(0.0, sc)
        r["initial"] = {"q": q0.tolist(), "dq": dq0.tolist()}
        r["simulation"]["t_final"] = 3.0
        res = sf.simulate(_write(tmp_path, r, f"run{k}.toml"))
        assert res.status == "ok", res.message
        t = res.t
        q, dq = res.signals["q"], res.signals["dq"]
        for i, ti in enumerate(t):
            a2, e1, F1 = _alpha2(ti, q[i], sc)
            e2 = dq[i] - a2
            r1 = np.abs(e1) / (c1 * F1)
            r2 = np.abs(e2) / (c2 * _F2(ti, sc))
            worst = max(worst, float(r1.max()), float(r2.max()))
    print(f"{len(starts)} runs from the boundary of S: worst |e|/((1 - m) F) = {worst:.8f}")
    assert worst <= 1 + 1e-6, worst          # none leaves S (and so none leaves the funnels)
    assert worst > 0.99                      # the runs did start on the boundary


@pytest.mark.parametrize("how", ["k1_tiny", "flip_k2"])
def test_designs_that_cannot_keep_their_funnels_are_not_proven(tmp_path, how):
    raw, path = _none_with_box(tmp_path)
    if how == "k1_tiny":
        raw["controller"]["k1"] = 1e-3
        c = _certify(_write(tmp_path, raw, "k1.toml"))
    else:
        c = _certify(path, mutant="flip_k2")
    assert c.status == "undecided", c.detail
    assert c.extra["face"] and c.extra["face"].startswith(("e1", "e2"))


@pins("certify.containment", "fail")
def test_refuted_only_by_a_breach_of_the_simulated_loop(capsys):
    code = main(["certify", BREACH, "--only", "containment", "--json", "-q"])
    out = json.loads(capsys.readouterr().out)
    (c,) = out["certificates"]
    assert c["status"] == "refuted" and c["counterexample"]["t"] > 0 and c["check"] == "fail"
    assert code == 1 and out["unexpected"] == ["certify.containment"]


def test_verify_shows_containment_as_a_check(capsys):
    code = main(["verify", NONE, "--json", "-q"])
    out = json.loads(capsys.readouterr().out)
    by = {c["id"]: c for c in out["checks"]}
    assert code == 0 and by["certify.containment"]["status"] == "pass"
    ev = by["certify.containment"]["evidence"]
    assert set(ev["margin"]) == {"e1", "e2"} and ev["horizon"] == "finite"
    # with containment proven, certify.bounds holds on a set the loop stays in
    assert by["certify.bounds"]["status"] == "pass"
    assert by["certify.bounds"]["evidence"]["region"]["kind"] == "proven_invariant"


def test_bounds_hold_on_the_proven_set_without_the_level_set_argument():
    sc = sf.load_scenario(NONE)
    cert = run_certificates(sc, sf.derive(sc), t_final=sc.simulation.t_final,
                            only=("certify.containment", "certify.bounds"), work={"certify.bounds": 1e7})
    cont, bounds = cert.by_id("certify.containment"), cert.by_id("certify.bounds")
    assert cont.status == "proven" and bounds.status == "proven"
    m1, m2 = cont.extra["margin"]["e1"], cont.extra["margin"]["e2"]
    assert bounds.region["kind"] == "proven_invariant" and "containment" in bounds.region["margin_source"]
    assert bounds.region["e1"] == f"|e1| <= (1 - {m1:g}) F1(t)" and bounds.region["e2"] == f"|e2| <= (1 - {m2:g}) F2(t)"
    checks = {c.id: c for c in cert.checks(sc)}
    assert checks["certify.bounds"].status == "pass"


@pytest.mark.parametrize("key, value", [
    ("reference", ["0.3*sin(t) + 0.2*sign(t - 1)", "0.2*cos(t)"]),      # q_d jumps at t = 1
    ("reference", ["0.3*abs(sin(2*t))", "0.2*cos(t)"]),                # dq_d jumps
    ("funnel", "0.1 - 0.099*sign(t - 1)"),                             # F1 jumps
    ("funnel", "(0.2*exp(-t) + 0.01)*(1 - exp(-((t - 1.00321)/1e-6)^2))"),   # F1 touches 0
])
def test_a_reference_or_funnel_without_the_regularity_is_never_proven(tmp_path, key, value):
    """The issue's defects: each one gives a simulated breach or an empty funnel, so a 'proven' would be wrong."""
    raw = copy.deepcopy(sf.load_scenario(NONE).raw)
    raw["initial"]["q"] = [-0.2, 0.2] if key == "reference" else raw["initial"]["q"]
    if key == "reference":
        raw["reference"]["q"] = value
    else:
        raw["funnel"]["e1"] = {"F": value}
    try:
        c = _certify(_write(tmp_path, raw))
    except sf.InputError:
        return                                   # refused at load: fine too
    assert c.status != "proven", c.detail


def test_a_term_is_dropped_only_where_it_provably_cancels():
    """CasADi differentiates sign as 0: (A + x + sign(A)) - A has a zero Jacobian in A but depends on A."""
    from symfunnel.certificates.face_forms import _drop_cancelled
    x, a = ca.SX.sym("x"), ca.SX.sym("a", 2)
    e, ok = _drop_cancelled((a[0] + 3 * x) - a[0], a)
    assert ok and not ca.depends_on(e, a)
    f = ca.Function("f", [x], [e])
    assert float(f(2.0)) == 6.0
    for bad in ((a[0] + x + ca.sign(a[0])) - a[0], x * ca.floor(a[1]), ca.if_else(a[0] > 0, x, 2 * x)):
        e, ok = _drop_cancelled(bad, a)
        assert not ok and ca.depends_on(e, a)

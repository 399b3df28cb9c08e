"""verify: the checks on simulated trajectories, the exact V_dot by AD, the falsification, and the CLI's exit codes."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest

from symfunnel.checks.lyapunov import _sub_reference, lyapunov_function
from symfunnel.pipeline import Run, RunOptions

from .conftest import VERIFY_PAPER_2S, main_once

T_FINAL = 5.0          # a shortened horizon keeps the suite fast; the CLI default is the scenario's 20 s


@pytest.fixture(scope="module")
def ver(paper):
    """verify() on the paper scenario over a shortened horizon (once per module), without the certificates: none of
    this module's tests on it reads one (test_certify checks them as verify's checks, on VERIFY_PAPER_2S)."""
    return Run(paper, RunOptions(t_final=T_FINAL, samples=10000, certify=False)).verification


def _by_id(v):
    return {c.id: c for c in v.checks}


def test_every_check_id_is_there_with_a_verdict_margin_and_where(ver, paper):
    ids = _by_id(ver)
    expected = ["simulation.completed", "funnel.initial_condition", "claim.theorem1", "lyapunov.decay",
                "lyapunov.bound", "lyapunov.falsification", "bounded.tau", "bounded.w_hat", "bounded.x_esn",
                "design.identity.vdot", "lyapunov.rho_positive", "assumption.input_gain"]
    expected += [f"funnel.containment.{k}.joint{j + 1}" for k in ("e1", "e2") for j in range(paper.n)]
    for cid in expected:
        assert cid in ids, cid
        c = ids[cid]
        assert c.status in ("pass", "fail"), (cid, c.status, c.detail)
        assert c.margin is not None and np.isfinite(c.margin), cid
        assert c.where, cid
        assert (c.margin >= 0) == (c.status == "pass") or cid.startswith(("bounded.", "simulation.")), cid


def test_paper_run_stays_in_its_funnels_and_the_corrected_claims_hold(ver):
    ids = _by_id(ver)
    assert ver.result.status == "ok"
    for cid, c in ids.items():
        if cid.startswith(("funnel.containment", "lyapunov.decay", "lyapunov.bound", "lyapunov.falsification",
                           "bounded.", "design.identity")):
            assert c.status == "pass", (cid, c.detail)


def test_paper_theorem_is_falsified_and_says_where(ver):
    c = _by_id(ver)["claim.theorem1"]
    assert c.status == "fail" and c.expected == "fail" and not c.unexpected
    assert c.evidence["violations"] > 0 and c.margin < 0
    assert "t" in c.where
    assert "printed constants" in c.detail


def test_falsification_uses_at_least_10000_states(ver):
    assert ver.falsification["samples"] >= 10000
    assert ver.falsification["corrected"]["evaluated"] >= 10000
    assert ver.falsification["method"] == "scrambled Sobol"


def test_v_dot_is_the_exact_derivative_along_the_flow(ver):
    """AD V_dot against a central difference of V along a tightly integrated piece of the closed-loop flow."""
    cl = ver.closed_loop
    L = ver.lyapunov
    f = lyapunov_function(cl, L.W_star)
    res = ver.result
    h = 1e-5
    for k in (50, 170, 333, 421):
        t0, x0 = float(res.t[k]), res.x[k]
        # integrate t0 -> t0 + h and t0 -> t0 - h by rescaling time: x' = s f(t0 + s tau, x), tau in [0, 1]
        vals = []
        for s in (h, -h):
            tau = ca.SX.sym("tau")
            ode = s * ca.substitute(cl.xdot, cl.t, t0 + s * tau)
            J = ca.integrator("J", "cvodes", {"t": tau, "x": cl.x, "ode": ode}, 0.0, 1.0,
                              {"abstol": 1e-14, "reltol": 1e-13})
            xs = np.asarray(J(x0=x0)["xf"]).ravel()
            vals.append(float(f(t0 + s, xs)[0]))
        fd = (vals[0] - vals[1]) / (2 * h)
        ad = float(f(t0, x0)[1])
        assert abs(fd - ad) <= 1e-5 * max(1.0, abs(ad)), (t0, fd, ad)


def test_corrected_decay_is_the_documented_identity(ver):
    """V_dot = -sum k1 mu1 z1^2 - sum k2 mu2 z2^2 + (mu2 z2)^T eps + sigma tr(W~^T W_hat) (docs/derivation.md)."""
    cl = ver.closed_loop
    sc = cl.scenario
    d = ver.design
    W = ver.lyapunov.W_star
    f = lyapunov_function(cl, W)
    S = {k: _sub_reference(d, d.signals[k]) for k in ("z1", "z2", "mu1", "mu2", "Phi")}
    w_hat = d.sym["w_hat"]
    eps = cl.signals["f_true"] - ca.mtimes(ca.DM(W).T, S["Phi"])
    rhs = (-ca.sum1(ca.DM(sc.k1) * S["mu1"] * S["z1"] ** 2) - ca.sum1(ca.DM(sc.k2) * S["mu2"] * S["z2"] ** 2)
           + ca.mtimes((S["mu2"] * S["z2"]).T, eps) + sc.sigma * ca.trace(ca.mtimes((ca.DM(W) - w_hat).T, w_hat)))
    g = ca.Function("g", [cl.t, cl.x], [rhs])
    res = ver.result
    for k in range(0, res.t.size, 37):
        ad = float(f(res.t[k], res.x[k])[1])
        ex = float(g(res.t[k], res.x[k]))
        assert abs(ad - ex) <= 1e-8 * max(1.0, abs(ad)), (res.t[k], ad, ex)


def test_verify_json_and_exit_code(tmp_path_factory):
    p = main_once(tmp_path_factory, *VERIFY_PAPER_2S)          # shared with test_certify, once per session
    code, out = p.returncode, json.loads(p.stdout)
    unexpected = [c["id"] for c in out["checks"] if c["status"] in ("pass", "fail") and c["status"] != c["expected"]]
    assert code == (1 if unexpected else 0) == 0 and out["status"] == "pass"
    failed = {c["id"]: c for c in out["checks"] if c["status"] == "fail"}
    assert failed["claim.theorem1"]["expected"] == "fail"      # the paper's Theorem 1 is falsified, as declared
    assert failed["claim.theorem1"]["reason"]
    for c in out["checks"]:
        assert {"id", "status", "expected", "detail"} <= set(c)


def test_initial_error_outside_its_funnel_fails_verify(write_scenario, capsys):
    from symfunnel.cli import main
    from symfunnel.scenario import DATA_DIR
    text = (DATA_DIR / "paper_2dof.toml").read_text(encoding="utf-8")
    text = text.replace("phi0 = 0.4 ", "phi0 = 0.18 ", 1)
    assert "phi0 = 0.18 " in text
    p = write_scenario(text)
    code = main(["verify", str(p), "--json", "--samples", "1000"])
    out = json.loads(capsys.readouterr().out)
    ids = {c["id"]: c for c in out["checks"]}
    assert code == 1
    assert ids["funnel.initial_condition"]["status"] == "fail"
    assert ids["simulation.completed"]["status"] == "fail"
    assert ids["funnel.containment.e2.joint1"]["status"] == "fail"
    assert ids["funnel.containment.e2.joint1"]["where"]["t"] == 0.0


def test_corrected_decay_fails_when_the_implementation_departs_from_the_derivation(paper):
    """Not vacuous: with the adaptive law's sign flipped in the graph (as printed in eq. 33's first term under
    symfunnel's convention), V_dot exceeds -rho V + delta along the run and the check says so."""
    # without the certificates, as mutation testing runs a mutant: none of them feeds the checks asserted here
    v = Run(paper, RunOptions(t_final=2.0, samples=10000, mutant="flip_adaptation", certify=False)).verification
    ids = {c.id: c for c in v.checks}
    assert ids["lyapunov.decay"].status == "fail"
    assert ids["lyapunov.decay"].margin < 0
    assert ids["design.identity.vdot"].status == "fail"
    assert v.status == "fail"

"""certify.sampled and `rate --certify`: a proven sample rate beside the simulated one (docs/certify.md)."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import SAMPLED_1DOF_RATE, cli_once

DATA = Path(__file__).parent / "data"
ONE = DATA / "sampled_1dof.toml"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "symfunnel", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    """`rate sampled_1dof --certify --json`, run once per session (cli_once) for this module's tests on any worker and
    test_api_contract's."""
    r = cli_once(tmp_path_factory, *SAMPLED_1DOF_RATE)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _ctx(path, t_final=None, mutant=None):
    from symfunnel.certificates.problem import Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    sc = load_scenario(str(path))
    d = derive(sc, mutant=mutant)
    return Context(sc, d, float(t_final or sc.simulation.t_final), parameter_box(sc), None, None)


def test_rate_certify_reports_the_contract_keys(bracket):
    """rate --certify --json: min_rate_hz, proven_rate_hz, theory_rate_hz, ratio and a certificate as certify's."""
    for k in ("min_rate_hz", "proven_rate_hz", "theory_rate_hz", "ratio", "certificate", "tried"):
        assert k in bracket
    c = bracket["certificate"]
    assert c["id"] == "certify.sampled" and c["status"] == "proven"
    for k in ("status", "lower", "upper", "counterexample", "region", "boxes", "undecided_fraction", "seconds",
              "detail", "method"):
        assert k in c
    # S is the set certify.containment proves invariant (proven here), its margins raised to the rate's margin
    assert c["set_choice"]["source"] == "certify.containment" and c["region"]["source"] == "certify.containment"
    cm = c["set_choice"]["containment"]["margin"]
    assert c["region"]["margin"] == {k: max(v, 0.05) for k, v in cm.items()}
    assert bracket["ratio"] == pytest.approx(bracket["proven_rate_hz"] / bracket["min_rate_hz"])
    # the theory bound's constants are finite and it is a rate
    assert bracket["theory_rate_hz"] is not None and bracket["theory_rate_hz"] > 0


def test_proven_rate_is_never_below_the_simulated_one(bracket):
    """A proven rate below the simulated minimum (same margin) would be a bug: the proof covers the simulated run
    (the initial state is in S), so the simulation must hold there -- and the sampled run at f_proven holds."""
    fp, fs = bracket["proven_rate_hz"], bracket["min_rate_hz"]
    assert fp is not None and fs is not None
    assert fp >= fs
    assert bracket["sampled_run_at_proven"]["holds"] is True
    assert bracket["certificate"]["initial_in_set"] is True
    # a state of S that leaves S within a period refutes every rate at or below its floor for this S
    floor = bracket["certificate"]["set_floor"]
    assert floor is None or floor["rate_hz"] < fp


def test_sampled_loop_at_the_proven_rate_from_the_corners_of_S(bracket):
    """The generated C step in the sampled loop (deployed.loop), started at each corner of S (|e_i| = (1 - m_i) F_i,
    e = q - q_d and dq - alpha2 computed here from the design's functions), keeps both funnels with margin 0.05 at
    the proven rate: an independent check of the proof by simulation."""
    from symfunnel.deployed.loop import simulate_sampled
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    from symfunnel.scenario.load import from_dict
    fp = bracket["proven_rate_hz"]
    m = bracket["certificate"]["region"]["margin"]          # S's margins (containment's): the set built here
    c1, c2 = 1 - m["e1"], 1 - m["e2"]
    sc = load_scenario(str(ONE))
    d = derive(sc)
    qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(0.0))
    F1, F2 = (np.asarray(v, float).ravel() for v in d.function("funnel_bounds", ["t"], ["F1", "F2"])(0.0))
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    for s1 in (-1.0, 1.0):
        for s2 in (-1.0, 1.0):
            q0 = qd + s1 * c1 * F1
            dq0 = np.asarray(a2(0.0, q0, qd, dqd), float).ravel() + s2 * c2 * F2
            raw = copy.deepcopy(sc.raw)
            raw["initial"] = {"q": q0.tolist(), "dq": dq0.tolist()}
            sc2 = from_dict(raw, file=sc.file, base_dir=sc.path.parent, default_name=sc.name)
            res = simulate_sampled(sc2, derive(sc2), rate_hz=fp, t_final=1.0)
            # the start is on S's face (e2's margin may be the rate's 0.05): its rounding is allowed
            assert res.ok and res.min_margin >= 0.05 - 1e-9, (s1, s2, res.status, res.min_margin)


def test_the_certificate_holds_the_c_step_torque():
    """One source: the torque the proof holds over the period is the generated step's (emit.step.step_function) at
    the same state, to rounding."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.emit.step import step_function
    ctx = _ctx(ONE)
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    d = ctx.design
    step = step_function(d, 1000.0)
    rng = np.random.default_rng(3)
    F = d.function("funnel_bounds", ["t"], ["F1", "F2"])
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    for _ in range(5):
        t = float(rng.uniform(0, 2))
        s1, s2 = rng.uniform(-0.5, 0.5, 2)
        qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(t))
        F1, F2 = (float(np.asarray(v, float).ravel()[0]) for v in F(t))
        q = qd + s1 * F1
        dq = np.asarray(a2(t, q, qd, dqd), float).ravel() + s2 * F2
        mine = float(op.tau_f(t, s1, s2, 0.0, np.zeros(0)))
        theirs = float(np.asarray(step(t, q, dq, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()[0])
        assert mine == pytest.approx(theirs, rel=1e-9, abs=1e-9)


def test_a_period_too_long_is_not_proven():
    """A much lower rate than the proven one (20 Hz) is not proven; the proven one is, and every shorter period."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set, prove_period
    ctx = _ctx(ONE)
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    assert not prove_period(op, 1 / 20.0, 0.05, 2.0, max_boxes=5000)["proven"]
    assert prove_period(op, 1 / 5000.0, 0.05, 2.0, max_boxes=20000)["proven"]
    assert prove_period(op, 1 / 20000.0, 0.05, 2.0, max_boxes=20000)["proven"]


def test_a_flipped_k2_is_not_proven():
    """The design's mutant flip_k2 (v with +k2 z2: the inner loop pushes outward) is not proven at any rate."""
    from symfunnel.certificates.problem import Budget
    from symfunnel.certificates.sampled_rate import certify_sampled
    ctx = _ctx(ONE, mutant="flip_k2")
    c = certify_sampled(ctx, Budget(5e6, time.monotonic() + 60), theory=False)
    assert c.status != "proven" and c.extra["proven_rate_hz"] is None


@pytest.mark.parametrize("args,key", [(["--set-margin", "1.5", "0.5"], "--set-margin"),
                                      (["--set-margin", "0", "0.5"], "--set-margin")])
def test_bad_set_margin_is_one_line_exit_2(args, key):
    r = _cli("rate", ONE, "--certify", *args)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and key in r.stderr


@pytest.mark.slow
def test_certify_none_proven_rate_is_not_below_the_simulated_one(certify_none_rate):
    """The two-joint model-based scenario (horizon 2 s): a proven rate, never below the simulated minimum rate for
    the same margin, and the C step's sampled run holds at it (the command's run is shared with test_report_deployed,
    tests/conftest.py's CERTIFY_NONE_RATE)."""
    r = certify_none_rate
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["certificate"]["status"] == "proven"
    assert out["proven_rate_hz"] >= out["min_rate_hz"]
    assert out["sampled_run_at_proven"]["holds"] is True
    floor = out["certificate"]["set_floor"]
    assert floor is None or floor["rate_hz"] < out["proven_rate_hz"]


def test_continuity_is_claimed_only_without_a_state_switch(tmp_path):
    """The second-order form of the next sample rests on sigma' being continuous along a period: claimed for the
    model-based scenario (the funnel transformation's z is C^1, sympy), refused with Coulomb friction (sign(dq))."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    ctx = _ctx(ONE)
    assert OnePeriod(ctx, declared_set(ctx, 0.5, 0.5)).continuous
    p = tmp_path / "coulomb.toml"
    p.write_text(ONE.read_text().replace("coulomb = 0.0", "coulomb = 0.5"))
    ctx = _ctx(p)
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    assert not op.continuous and "plant" in op.continuity


@pytest.mark.slow
def test_certify_only_sampled_gives_the_certificate():
    """`certify --only sampled` computes certify.sampled (and only it); a bad id names the known ones."""
    r = _cli("certify", ONE, "--only", "sampled", "--json", "-q")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert [c["id"] for c in out["certificates"]] == ["certify.sampled"]
    c = out["certificates"][0]
    assert c["status"] == "proven" and c["lower"] > 0 and c["proven_rate_hz"] == c["lower"]
    bad = _cli("certify", ONE, "--only", "nope")
    assert bad.returncode == 2 and "certify.sampled" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_w_hat_update_is_accepted_only_as_the_steps_convex_combination():
    """W_hat's box is kept by W+ = (1 - phi c) W + phi A only when the rate's decay c is the step's Gamma sigma: the
    paper-like design (Gamma 10, sigma 0.02) gives c = 0.2; the flip_sigma mutant (W_hat' = ... + sigma W_hat) is
    refused, and its certificate is undecided."""
    from symfunnel.certificates.problem import Budget
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.certificates.sampled_rate import certify_sampled
    path = Path(__file__).parent.parent / "derivations" / "paper_small_dead_zone.toml"
    ctx = _ctx(path, t_final=1.0)
    nr, n = ctx.design.n_regressor, ctx.design.n
    box = (-np.ones((nr, n)), np.ones((nr, n)))
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5, w_box=box, w_source="test"))
    assert op.w_rate == pytest.approx(10.0 * 0.02, rel=1e-12)
    ctx = _ctx(path, t_final=1.0, mutant="flip_sigma")
    S = declared_set(ctx, 0.5, 0.5, w_box=box, w_source="test")
    assert OnePeriod(ctx, S).w_rate is None
    c = certify_sampled(ctx, Budget(1e6), S=S, theory=False)
    assert c.status == "undecided" and "W_hat" in c.detail


def test_one_period_enclosure_contains_the_integrated_plant():
    """Soundness against a second implementation: from states of S drawn here, the plant integrated over one period
    by scipy (tight tolerances) under the generated step's held torque stays inside the certificate's a-priori
    enclosure of sigma = e / F at every output time, and its end inside the certificate's bound of the next sample."""
    from scipy.integrate import solve_ivp

    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.emit.step import step_function

    from .test_sampled_set import plant_and_sigma, state_at
    ctx = _ctx(ONE)
    d = ctx.design
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    h = 1.0 / 3000.0
    step = step_function(d, 3000.0)
    acc, sigma = plant_and_sigma(ctx)
    rng = np.random.default_rng(11)
    checked = 0
    for _ in range(12):
        tk, s1, s2 = rng.uniform(0, 2.0), rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5)
        q0, dq0 = state_at(d, tk, [s1, s2])
        tau = float(np.asarray(step(tk, q0, dq0, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()[0])
        X = np.array([[tk, s1, s2, 0.0]])
        ok, info = op.check(X, X, h, 0.05)
        if not np.all(np.isfinite(info["DL"])):
            continue
        sol = solve_ivp(lambda tt, x: [x[1], float(acc(tt, x[:1], x[1:], [tau]))], (tk, tk + h),
                        [q0[0], dq0[0]], rtol=1e-11, atol=1e-13, dense_output=True)
        for tt in np.linspace(tk, tk + h, 9):
            sg = sigma(tt, sol.sol(tt))
            assert np.all(sg >= info["SL"][0] - 1e-9) and np.all(sg <= info["SH"][0] + 1e-9), (tk, tt, sg)
        end = sigma(tk + h, sol.sol(tk + h))
        assert np.all(end >= np.array([s1, s2]) + h * info["DL"][0] - 1e-9)
        assert np.all(end <= np.array([s1, s2]) + h * info["DH"][0] + 1e-9)
        checked += 1
    assert checked >= 10

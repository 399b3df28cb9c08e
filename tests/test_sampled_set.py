"""certify.sampled's set S: the containment certificate's S when it is proven (docs/certify.md, certify.sampled)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).parent / "data"
NONE = DATA / "certify_none.toml"


def _ctx(path, t_final=None):
    from symfunnel.certificates.problem import Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    sc = load_scenario(str(path))
    return Context(sc, derive(sc), float(t_final or sc.simulation.t_final), parameter_box(sc), None, None)


def plant_and_sigma(ctx):
    """The plant's acceleration at the nominal parameters (a CasADi Function of t, q, dq, u) and sigma(t, x) =
    (e1 / F1, (dq - alpha2) / F2) of a state x = (q, dq), built from the design's reference, funnels and alpha2
    (not from the certificate's region functions)."""
    import casadi as ca

    from symfunnel.plant.equations import plant_acceleration, plant_parameters
    d, sc = ctx.design, ctx.scenario
    n = d.n
    q, dq, t, u = ca.SX.sym("q", n), ca.SX.sym("dq", n), ca.SX.sym("t"), ca.SX.sym("u", n)
    _, p0 = plant_parameters(sc)
    acc = ca.Function("acc", [t, q, dq, u], [plant_acceleration(sc, q, dq, t, u, 0.0, p=ca.DM(p0))["ddq"]])
    F = d.function("funnel_bounds", ["t"], ["F1", "F2"])
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])

    def sigma(tt, x):
        qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(tt))
        F1, F2 = (np.asarray(v, float).ravel() for v in F(tt))
        return np.concatenate([(x[:n] - qd) / F1, (x[n:] - np.asarray(a2(tt, x[:n], qd, dqd), float).ravel()) / F2])
    return acc, sigma


def state_at(design, t: float, s) -> tuple[np.ndarray, np.ndarray]:
    """The joint state (q, dq) whose normalised errors at time t are s = (e1 / F1, e2 / F2) (2n numbers), from the
    design's reference, funnels and alpha2."""
    n = design.n
    s = np.asarray(s, float)
    qd, dqd, _ = (np.asarray(v, float).ravel() for v in design.reference(t))
    F1, F2 = (np.asarray(v, float).ravel() for v in design.function("funnel_bounds", ["t"], ["F1", "F2"])(t))
    q = qd + s[:n] * F1
    a2 = np.asarray(design.function("alpha2", ["t", "q", "qd", "dqd"])(t, q, qd, dqd), float).ravel()
    return q, a2 + s[n:] * F2


@pytest.mark.slow
def test_certify_none_uses_the_containment_set_and_proves_a_rate_from_it():
    """certify_none: certify.containment is proven (m1, m2), and certify.sampled then starts from and returns to
    that S (not the declared 0.5 / 0.5): the JSON says so, the margins are containment's and a rate is proven; an
    explicit set margin overrides it."""
    from symfunnel.certificates.containment import CID, certify_containment
    from symfunnel.certificates.problem import Budget
    from symfunnel.certificates.sampled_rate import certify_sampled
    ctx = _ctx(NONE, t_final=1.0)
    cont = certify_containment(ctx, Budget(5e7))
    ctx.results[CID] = cont
    assert cont.status == "proven"
    m = cont.extra["margin"]
    c = certify_sampled(ctx, Budget(4e6, time.monotonic() + 120), start_hz=4e5, theory=False)
    assert c.status == "proven", c.detail
    assert c.extra["set_choice"]["source"] == "certify.containment"
    assert c.region["source"] == "certify.containment"
    assert c.region["margin"] == {"e1": max(m["e1"], 0.05), "e2": max(m["e2"], 0.05)}
    assert "certify.containment" in c.detail
    # the override is S's choice, made before any rate is tried: a spent wall budget keeps the search (3.5 CPU-s
    # of the test's 8 here) out of what these records check
    d = certify_sampled(ctx, Budget(4e6, time.monotonic()), start_hz=4e5, theory=False, set_margin=(0.5, 0.5))
    assert d.region["source"] == "declared" and d.region["margin"] == {"e1": 0.5, "e2": 0.5}
    assert d.extra["set_choice"]["source"] == "--set-margin"


def test_containment_is_computed_when_not_given_and_the_default_is_said_when_not_proven():
    """Without a containment result in the context certify.sampled computes it; a scenario where it is not proven
    (the flip_k2 mutant) falls back to the declared default margins and the choice names containment's status."""
    from symfunnel.certificates.problem import Budget, Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.certificates.sampled_rate import choose_set
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    ctx = _ctx(NONE, t_final=1.0)
    S, rec = choose_set(ctx, Budget(5e7), 0.05)
    assert S.source == "certify.containment" and rec["containment"]["status"] == "proven"
    sc = load_scenario(str(DATA / "sampled_1dof.toml"))
    ctx = Context(sc, derive(sc, mutant="flip_k2"), 2.0, parameter_box(sc), None, None)
    S, rec = choose_set(ctx, Budget(5e7), 0.05)
    assert S.source == "declared" and (S.m1, S.m2) == (0.5, 0.5)
    assert rec["containment"]["status"] != "proven" and rec["containment"]["status"] in rec["source"]


def test_the_w_hat_ball_is_kept_only_when_the_update_stays_in_it():
    """W_hat in the containment's ball: the update W+ = b W + (1 - b) A / c stays in ||W||_F <= w iff ||A||_F <= c w.
    On the paper-like design (c = Gamma sigma = 0.2), A is the design's own w_hat_dot at W_hat = 0 (its forcing),
    evaluated here at a point of S: a radius 1 % below ||A|| / c is refused there, 1 % above is accepted."""
    import casadi as ca

    from symfunnel.certificates.sampled import OnePeriod, SampledSet
    from symfunnel.certificates.problem import controller_state_boxes
    path = Path(__file__).parent.parent / "derivations" / "paper_small_dead_zone.toml"
    ctx = _ctx(path, t_final=1.0)
    d = ctx.design
    nr, n = d.n_regressor, d.n

    def S(w):
        W0 = np.zeros((nr, n))
        return SampledSet(0.5, 0.5, controller_state_boxes(ctx, (W0 - w, W0 + w)), "test", {}, w_ball=w)
    op = OnePeriod(ctx, S(1.0))
    assert op.w_rate == pytest.approx(0.2, rel=1e-12)
    # ||A||_F at a point, independently: the design's w_hat_dot at W_hat = 0 (its affine part), x_esn = 0
    names = [k for k, _ in d.states]
    f = d.function("w_hat_dot", ["t", "q", "dq", "qd", "dqd", "ddqd", *names])
    t = 0.3
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(t))
    F1, F2 = (np.asarray(v, float).ravel() for v in d.function("funnel_bounds", ["t"], ["F1", "F2"])(t))
    s1, s2 = np.full(n, 0.3), np.full(n, -0.4)
    q = qd + s1 * F1
    a2 = np.asarray(d.function("alpha2", ["t", "q", "qd", "dqd"])(t, q, qd, dqd), float).ravel()
    dq = a2 + s2 * F2
    zeros = [np.zeros((r, c)) for _, (r, c) in d.states]
    A = np.asarray(ca.evalf(f(t, q, dq, qd, dqd, ddqd, *zeros)), float)
    normA = float(np.linalg.norm(A))
    assert normA > 0
    P = ctx.params
    X = np.concatenate([[t], s1, s2, [0.0], P.nominal[op.wide]])[None, :]
    for w, kept in ((0.99 * normA / 0.2, False), (1.01 * normA / 0.2, True)):
        op = OnePeriod(ctx, S(w))
        FL, FH = op._full(X, X)
        FL[:, op.i_st:] = FH[:, op.i_st:] = 0.0          # W_hat = 0 and x_esn = 0 at the point: A is a point
        assert bool(op.w_kept(FL, FH)[0]) == kept, (w, normA)


def test_a_face_of_s_on_the_rate_margin_is_proven_where_the_flow_points_inward():
    """S with e2's margin equal to the rate's (0.95 F2, as containment proves on sampled_1dof): a sample on that
    face whose rate points inward keeps the face's value in the a-priori box (no outward inflation or ulp crossing
    the margin), and the funnel check (a) follows from the return to S (b); proven at 1 kHz, and the one-period
    bound of a face point is checked against the plant integrated by scipy from that point."""
    from scipy.integrate import solve_ivp

    from symfunnel.certificates.sampled import OnePeriod, declared_set, prove_period
    from symfunnel.emit.step import step_function
    ctx = _ctx(DATA / "sampled_1dof.toml")
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.05))
    assert prove_period(op, 1e-3, 0.05, 2.0, max_boxes=20000)["proven"]
    # a face point: sigma2 = 0.95 at t = 0.7, sigma1 = 0.2; the plant from there under the step's torque
    d = ctx.design
    t0, s1, s2, h = 0.7, 0.2, 0.95, 1e-3
    X = np.array([[t0, s1, s2, 0.0]])
    ok, info = op.check(X, X, h, 0.05)
    assert ok[0]
    q0, dq0 = (float(v[0]) for v in state_at(d, t0, [s1, s2]))
    tau = float(np.asarray(step_function(d, 1000.0)(t0, [q0], [dq0], np.zeros(1), np.zeros((1, 1)))[0], float).ravel()[0])
    acc, sigma = plant_and_sigma(ctx)
    sol = solve_ivp(lambda tt, x: [x[1], float(acc(tt, x[:1], x[1:], [tau]))], (t0, t0 + h), [q0, dq0],
                    rtol=1e-11, atol=1e-13, dense_output=True)
    for tt in np.linspace(t0, t0 + h, 9):
        sg = sigma(tt, sol.sol(tt))
        assert np.all(np.abs(sg) <= [0.5 + 1e-9, 0.95 + 1e-9]), (tt, sg)       # stays in S, so in the funnels
        assert np.all(sg >= info["SL"][0] - 1e-9) and np.all(sg <= info["SH"][0] + 1e-9)


def test_taylor_enclosure_contains_the_integrated_two_joint_plant_and_is_tighter():
    """The Taylor a-priori enclosure against scipy on certify_none (2 joints), from points on the faces and corners
    of containment's S (|e1| = 0.5 F1, |e2| = 0.95 F2, built here from the design's funnels and alpha2): the
    integrated trajectory under the generated step's held torque stays in the enclosure Sigma at every output
    time and its rate in D (the end in sigma_k + h D); and D is narrower than the first-order Picard's."""
    from scipy.integrate import solve_ivp

    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.emit.step import step_function
    ctx = _ctx(NONE, t_final=5.0)
    d = ctx.design
    n = d.n
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.05))
    h = 1.0 / 4000.0
    step = step_function(d, 4000.0)
    acc, sigma = plant_and_sigma(ctx)
    rng = np.random.default_rng(5)
    narrower = 0
    for k in range(10):
        tk = float(rng.uniform(0, 5.0))
        s = np.concatenate([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.95, 0.95, n)])
        j = int(rng.integers(0, 2 * n))
        s[j] = rng.choice([-1, 1]) * (0.5 if j < n else 0.95)                           # on a face
        if k < 3:
            s = np.array([0.5, -0.5, 0.95, -0.95]) * rng.choice([-1, 1], 4)              # a corner
        q0, dq0 = state_at(d, tk, s)
        tau = np.asarray(step(tk, q0, dq0, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()
        # a small box of sample states around the point, inside S (the point in it)
        lim = np.array([0.5] * n + [0.95] * n)
        XL = np.concatenate([[max(tk - 0.01, 0.0)], np.maximum(s - 0.01, -lim), [0.0]])[None, :]
        XH = np.concatenate([[tk + 0.01], np.minimum(s + 0.01, lim), [0.0]])[None, :]
        op.taylor = True
        _, info = op.check(XL, XH, h, 0.05)
        op.taylor = False
        _, first = op.check(XL, XH, h, 0.05)
        assert np.all(np.isfinite(info["DL"])), s
        narrower += bool(np.all(np.isinf(first["DL"])) or np.all(info["DH"] - info["DL"] < first["DH"] - first["DL"]))
        sol = solve_ivp(lambda tt, x: np.concatenate([x[n:], np.asarray(acc(tt, x[:n], x[n:], tau), float).ravel()]),
                        (tk, tk + h), np.concatenate([q0, dq0]), rtol=1e-11, atol=1e-13, dense_output=True)
        for tt in np.linspace(tk, tk + h, 9):
            sg = sigma(tt, sol.sol(tt))
            assert np.all(sg >= info["SL"][0] - 1e-9) and np.all(sg <= info["SH"][0] + 1e-9), (tk, tt, sg)
            disp = sg - s
            assert np.all(disp >= (tt - tk) * info["DL"][0] - 1e-9) and np.all(disp <= (tt - tk) * info["DH"][0]
                                                                                + 1e-9), (tk, tt, disp)
            # and the rate itself: sigma' by a central difference of the integrated solution, inside D
            e = 1e-7
            if tk + e <= tt <= tk + h - e:
                rate = (sigma(tt + e, sol.sol(tt + e)) - sigma(tt - e, sol.sol(tt - e))) / (2 * e)
                assert np.all(rate >= info["DL"][0] - 1e-4 * (1 + np.abs(rate))), (rate, info["DL"][0])
                assert np.all(rate <= info["DH"][0] + 1e-4 * (1 + np.abs(rate))), (rate, info["DH"][0])
    assert narrower >= 8


def test_a_warm_started_period_agrees_with_the_cold_search_and_costs_less():
    """Bisection warm start: the boxes a budget-ended search at a longer period did not leave are proven at every
    shorter period, so the search there starts from the queue; on sampled_1dof (containment's S 0.5 / 0.05) the
    warm search at 600 Hz from the one ended at 560 Hz proves what the cold search proves, with fewer boxes; a
    queue from a shorter period is refused."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set, prove_period
    ctx = _ctx(DATA / "sampled_1dof.toml")
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.05))
    long_ = prove_period(op, 1 / 560.0, 0.05, 2.0, max_boxes=3000)
    assert not long_["proven"] and long_["reason"] == "boxes" and long_["queue"] is not None
    cold = prove_period(op, 1 / 600.0, 0.05, 2.0, max_boxes=40000)
    warm = prove_period(op, 1 / 600.0, 0.05, 2.0, max_boxes=40000, warm=long_)
    assert cold["proven"] and warm["proven"]
    assert warm["boxes"] < cold["boxes"], (warm["boxes"], cold["boxes"])
    with pytest.raises(ValueError):
        prove_period(op, 1 / 500.0, 0.05, 2.0, max_boxes=100, warm=long_)


def test_monotone_next_sample_bounds_contain_the_sampled_values_and_are_tighter():
    """The next sample's bounds on monotone faces: over boxes of sample states near S's faces on certify_none, every
    value of next = sigma_k + h sigma'(sample) at 300 random points of the box (the ordinary CasADi function) lies
    within the tightened bounds, and they are tighter than the centered form's on most boxes."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    ctx = _ctx(NONE, t_final=5.0)
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.05))
    n, h = ctx.design.n, 1 / 2500.0
    rng = np.random.default_rng(8)
    lim = np.array([0.5] * n + [0.95] * n)
    tighter = 0
    for k in range(12):
        c = rng.uniform(-lim, lim)
        c[k % (2 * n)] = np.sign(c[k % (2 * n)]) * lim[k % (2 * n)]
        wdt = rng.uniform(0.02, 0.15, 2 * n)
        lo, hi = np.maximum(c - wdt, -lim), np.minimum(c + wdt, lim)
        t0 = rng.uniform(0, 4.5)
        LO = np.concatenate([[t0], lo, [0.0]])[None, :]
        HI = np.concatenate([[t0 + 0.3], hi, [0.0]])[None, :]
        XL, XH = op._with_h(*op._full(LO, HI), h)
        NL, NH, sw = op.next.eval_batch(XL, XH)
        ML, MH = op._monotone(XL, XH, NL, NH, np.asarray(sw, bool))
        assert np.all(ML >= NL) and np.all(MH <= NH)
        tighter += bool(np.any(ML > NL) or np.any(MH < NH))
        P = XL + rng.random((300, XL.shape[1])) * (XH - XL)
        vals = np.array([np.asarray(op.next_f(*_split(op, x)), float).ravel() for x in P])
        assert np.all(vals >= ML - 1e-12) and np.all(vals <= MH + 1e-12)
    assert tighter >= 8


def _split(op, x):
    """A flat row of the next-sample function's layout as its inputs."""
    F = op.next.natural
    return [x[F.in_off[i]:F.in_off[i + 1]] for i in range(len(F.in_names))]


def test_the_scaling_bench_generates_planar_arms_and_its_n2_period_is_proven():
    """bench certify's scaling: the generated planar arms have n joints and load; at n = 2 one period at 100 kHz
    from S (0.5 / 0.5) is proven within a small budget (the figure the bench times), with the split dimensions
    2n + 1 (t and the 2n normalised errors; no uncertain parameter)."""
    from symfunnel.bench._sampled import period_scaling, planar_text
    from symfunnel.scenario.load import from_dict
    import tomllib
    for n in (2, 3, 4):
        sc = from_dict(tomllib.loads(planar_text(n)), file=f"planar{n}.toml", base_dir=DATA, default_name="p")
        assert sc.n == n
    row = period_scaling(2, max_boxes=4000)
    assert row["proven"] and row["left"] == 0.0 and row["split_dims"] == 5 and row["boxes"] <= 4000
    assert row["solve"] == "adjugate"


UNCERTAIN = """
[[uncertainty]]
key = "plant.parameters.a"
dist = "uniform"
low = 1.8
high = 2.2

[[uncertainty]]
key = "plant.viscous"
dist = "uniform"
low = 0.0
high = 0.3
"""


@pytest.mark.slow
def test_sampled_runs_at_f_proven_over_the_parameter_box_from_the_boundary_of_s_never_breach(tmp_path):
    """Issue 40's acceptance: the generated C step's sampled loop at f_proven, for each corner of the parameter box
    (sampled_1dof with the plant's inertia a in [1.8, 2.2] and viscous friction in [0, 0.3]) and from each corner
    and face midpoint of S at t = 0, keeps both funnels with the rate's margin between the samples and returns to S
    at every sample -- S rebuilt here from the design's funnels, reference and alpha2 at the certificate's margins."""
    import copy
    import tomllib

    from symfunnel.certificates.problem import Budget, Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.certificates.sampled_rate import certify_sampled
    from symfunnel.deployed.loop import simulate_sampled
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    from symfunnel.scenario.load import from_dict
    text = (DATA / "sampled_1dof.toml").read_text().replace("[simulation]", "[plant.parameters]\na = 2.0\n[simulation]")
    path = tmp_path / "uncertain.toml"
    path.write_text(text + UNCERTAIN)
    sc = load_scenario(str(path))
    d = derive(sc)
    T = 1.0
    ctx = Context(sc, d, T, parameter_box(sc), None, None)
    cert = certify_sampled(ctx, Budget(5e7, time.monotonic() + 300), theory=False)
    assert cert.status == "proven", cert.detail
    fp = cert.extra["proven_rate_hz"]
    m1, m2 = cert.region["margin"]["e1"], cert.region["margin"]["e2"]
    M = cert.extra["rate_margin"]
    raw0 = tomllib.loads(text)
    _, sigma = plant_and_sigma(ctx)
    starts = [(s1, s2) for s1 in (-1.0, 0.0, 1.0) for s2 in (-1.0, 0.0, 1.0) if abs(s1) == 1 or abs(s2) == 1]
    runs = 0
    for a in (1.8, 2.2):
        for visc in (0.0, 0.3):
            for s1, s2 in starts:
                q0, dq0 = state_at(d, 0.0, [s1 * (1 - m1), s2 * (1 - m2)])
                raw = copy.deepcopy(raw0)
                raw["plant"]["parameters"]["a"] = a
                raw["plant"]["viscous"] = visc
                raw["initial"] = {"q": q0.tolist(), "dq": dq0.tolist()}
                sc2 = from_dict(raw, file=str(path), base_dir=tmp_path, default_name="corner")
                res = simulate_sampled(sc2, d, rate_hz=fp, t_final=T)       # the controller: the same design
                assert res.ok, (a, visc, s1, s2, res.status, res.message)
                assert np.min(res.between_margins) >= M - 1e-9, (a, visc, s1, s2)
                # back in S at every sample: e1 / F1 and (dq - alpha2) / F2 from the design's own functions
                for k in range(0, res.t.size, 7):
                    tk = float(res.t[k])
                    r = np.abs(sigma(tk, np.concatenate([res.q[k], res.dq[k]])))
                    r1, r2 = r[:d.n], r[d.n:]
                    assert np.all(r1 <= 1 - m1 + 1e-9) and np.all(r2 <= 1 - m2 + 1e-9), (a, visc, s1, s2, tk, r1, r2)
                runs += 1
    assert runs == 32


def test_enclosure_with_coulomb_friction_contains_the_integrated_plant_across_its_switch(tmp_path):
    """With Coulomb friction (sign(dq): sigma' is not continuous along a period) the Taylor form is used only on
    boxes where no switch can happen; from states with dq near 0 (the sign may flip inside the period) the
    enclosure still contains the plant integrated by scipy (event-free, tight tolerances) under the held torque."""
    from scipy.integrate import solve_ivp

    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.emit.step import step_function
    p = tmp_path / "coulomb.toml"
    p.write_text((DATA / "sampled_1dof.toml").read_text().replace("coulomb = 0.0", "coulomb = 0.5"))
    ctx = _ctx(p)
    d = ctx.design
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    assert not op.continuous
    h = 1.0 / 2000.0
    step = step_function(d, 2000.0)
    acc, sigma = plant_and_sigma(ctx)
    rng = np.random.default_rng(2)
    checked = 0
    for _ in range(40):
        tk = float(rng.uniform(0, 2.0))
        s1 = float(rng.uniform(-0.5, 0.5))
        # e2 such that dq is within a few 1e-3 of 0: the friction's sign can switch during the period
        q0, a2 = state_at(d, tk, [s1, 0.0])
        F2 = float(np.asarray(d.function("funnel_bounds", ["t"], ["F1", "F2"])(tk)[1], float).ravel()[0])
        s2 = float(np.clip((rng.uniform(-3e-3, 3e-3) - a2[0]) / F2, -0.5, 0.5))
        q0, dq0 = state_at(d, tk, [s1, s2])
        tau = float(np.asarray(step(tk, q0, dq0, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()[0])
        X = np.array([[tk, s1, s2, 0.0]])
        ok, info = op.check(X, X, h, 0.05)
        if not np.all(np.isfinite(info["DL"])):
            continue
        sol = solve_ivp(lambda tt, x: [x[1], float(acc(tt, x[:1], x[1:], [tau]))], (tk, tk + h),
                        [q0[0], dq0[0]], rtol=1e-12, atol=1e-14, dense_output=True, max_step=h / 200)
        for tt in np.linspace(tk, tk + h, 17):
            sg = sigma(tt, sol.sol(tt))
            assert np.all(sg >= info["SL"][0] - 1e-8) and np.all(sg <= info["SH"][0] + 1e-8), (tk, tt, sg)
            disp = sg - np.array([s1, s2])
            assert np.all(disp >= (tt - tk) * info["DL"][0] - 1e-8)
            assert np.all(disp <= (tt - tk) * info["DH"][0] + 1e-8)
        checked += 1
    assert checked >= 20


def test_the_theory_bound_on_the_declared_set_reuses_the_forms_and_equals_a_fresh_one_period_map(monkeypatch):
    """`_theory` on a set whose margins leave no gap (m2 = M) falls back to the declared default set: its one-period
    map there (`OnePeriod.on_set`) shares the forms of S's map (none built again: the forms do not depend on the set)
    and gives the same bound, number for number, as a map built from scratch on that set."""
    from symfunnel.certificates import sampled as SM
    from symfunnel.certificates.problem import controller_state_boxes
    from symfunnel.certificates.sampled import DEFAULT_SET_MARGIN, OnePeriod, SampledSet, declared_set
    from symfunnel.certificates.sampled_rate import _theory, theory_rate
    path = Path(__file__).parent.parent / "derivations" / "paper_small_dead_zone.toml"
    ctx = _ctx(path, t_final=1.0)
    d = ctx.design
    W0 = np.zeros((d.n_regressor, d.n))
    M = 0.05
    S = SampledSet(0.5, M, controller_state_boxes(ctx, (W0 - 1.0, W0 + 1.0)), "test", {}, w_ball=1.0)
    op = OnePeriod(ctx, S)
    assert op.ball == 1.0
    built = []
    for cls in (SM.BatchCenteredForm, SM.BatchIntervalFunction):
        init = cls.__init__
        monkeypatch.setattr(cls, "__init__", lambda self, *a, _i=init, **k: built.append(a) or _i(self, *a, **k))
    got = _theory(ctx, op, S, M, None)
    assert built == []                                   # the old path built every form again
    monkeypatch.undo()
    D = declared_set(ctx, *DEFAULT_SET_MARGIN, w_box=S.states.get("w_hat"), w_source="S's W_hat box")
    fresh = OnePeriod(ctx, D)
    want = theory_rate(fresh, D, M, 1.0)
    assert want["rate_hz"] is not None and got["rate_hz"] == want["rate_hz"]
    assert {k: v for k, v in got.items() if k != "set"} == want
    # the set's own parts are the set's, not the first map's (its W_hat ball and margins)
    on = op.on_set(D)
    assert on.ball is None and op.ball == 1.0 and on.S is D
    assert np.array_equal(on.lim_S, fresh.lim_S) and not np.array_equal(on.lim_S, op.lim_S)
    assert np.array_equal(on.st_lo, fresh.st_lo) and np.array_equal(on.st_hi, fresh.st_hi)

"""certify.sampled's one-period map in containment's exact forms (alpha2_dot through e1, M_p^-1 by the adjugate for
two joints, tip-first LDL^T for a planar arm of three): the enclosures of the rates sigma' (held torque) and of the
rates at the sample (the step's own torque) contain sigma' computed the plain way -- the plant's M and forces
solved by numpy, the design's forward-AD alpha2_dot, the design's torque -- at points of small boxes, and a mutant
of each rewrite (e2's sign flipped, M^-1 scaled by 0.99) is caught by the same check."""

from __future__ import annotations

import tempfile
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

DATA = Path(__file__).parent / "data"
UNCERTAIN = """
[[uncertainty]]
key = "plant.parameters.c"
dist = "uniform"
low = 0.7
high = 0.9

[[uncertainty]]
key = "plant.viscous"
dist = "uniform"
low = 0.0
high = 0.3
"""


def _two_joints(tmp_path):
    text = (DATA / "certify_none.toml").read_text().replace("[simulation]",
                                                             "[plant.parameters]\nc = 0.8\n[simulation]")
    p = tmp_path / "uncertain.toml"
    p.write_text(text + UNCERTAIN)
    return p


def _planar(n):
    from symfunnel.bench._sampled import planar_text
    from symfunnel.scenario import load_scenario
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / f"planar{n}.toml"
        p.write_text(planar_text(n))
        return load_scenario(str(p))


def _ctx(sc):
    from symfunnel.certificates.problem import Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.design import derive
    return Context(sc, derive(sc), float(sc.simulation.t_final), parameter_box(sc), None, None)


def _plain(ctx):
    """sigma'(t, s, p_wide, u) the plain way, from the design's functions and the plant's own M and forces (numpy
    solve); u None: the design's torque at the state."""
    from symfunnel.plant.equations import plant_acceleration, plant_parameters
    d, sc = ctx.design, ctx.scenario
    n = d.n
    q, dq, t, u = ca.SX.sym("q", n), ca.SX.sym("dq", n), ca.SX.sym("t"), ca.SX.sym("u", n)
    names, _ = plant_parameters(sc)
    p = ca.SX.sym("p", len(names))
    pl = plant_acceleration(sc, q, dq, t, u, 0.0, p=p)
    parts = ca.Function("parts", [t, q, dq, u, p], [pl["M"], pl["tau_applied"] - ca.mtimes(pl["C"], dq) - pl["G"]
                                                     - pl["friction"] - pl["disturbance"]])
    F = d.function("funnel_bounds", ["t"], ["F1", "F2", "dF1", "dF2"])
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    a2dot = d.function("alpha2_dot", ["t", "q", "dq", "qd", "dqd", "ddqd"])
    tau = d.function("tau", ["t", "q", "dq", "qd", "dqd", "ddqd"])
    wide = np.flatnonzero(ctx.params.lo < ctx.params.hi)
    p0 = np.asarray(ctx.params.nominal, float)

    def rate(tt, s, pw, uu=None):
        qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(tt))
        F1, F2, dF1, dF2 = (np.asarray(v, float).ravel() for v in F(tt))
        qq = qd + s[:n] * F1
        dqq = np.asarray(a2(tt, qq, qd, dqd), float).ravel() + s[n:] * F2
        if uu is None:
            uu = np.asarray(tau(tt, qq, dqq, qd, dqd, ddqd), float).ravel()
        pp = p0.copy()
        pp[wide] = pw
        M, rhs = (np.asarray(v, float) for v in parts(tt, qq, dqq, uu, pp))
        ddq = np.linalg.solve(M, rhs.ravel())
        de1, de2 = dqq - dqd, ddq - np.asarray(a2dot(tt, qq, dqq, qd, dqd, ddqd), float).ravel()
        return np.concatenate([(de1 - s[:n] * dF1) / F1, (de2 - s[n:] * dF2) / F2]), uu
    return rate


def _escapes(op, ctx, boxes=25, points=6, half=1e-5, seed=4) -> int:
    """How many sampled points lie outside the enclosures of op's rates (held torque, and at the sample) and of its
    held torque (against the generated C step's) on small boxes of S (t, s, the wide parameters drawn here; the
    held torque a tiny box around a drawn value)."""
    from symfunnel.emit.step import step_function

    from .test_sampled_set import state_at
    n = op.n
    rate = _plain(ctx)
    step = step_function(ctx.design, 1000.0)
    lo, hi = op.box(ctx.t_final)
    rng = np.random.default_rng(seed)
    i_s, i_p = slice(1, 2 * n + 1), slice(op.i_p, op.i_st)
    bad = 0
    for _ in range(boxes):
        c = lo + rng.random(lo.size) * (hi - lo)
        w = np.full(lo.size, half) * np.maximum(hi - lo, 1e-300)
        w[2 * n + 1] = 0.0
        BL, BH = np.maximum(c - w, lo)[None], np.minimum(c + w, hi)[None]
        _, u0 = rate(c[0], c[i_s], c[i_p])
        uw = 1e-6 * (1 + np.abs(u0))
        FL, FH = op._full(BL, BH)
        KL, KH, _ = op.ratek.eval_batch(FL, FH)
        TL, TH, _ = op.tau.eval_batch(FL, FH)
        RL, RH, _ = op.rate.eval_batch(*(np.concatenate([A[:, :op.i_st], U[None], A[:, op.i_st:]], axis=1)
                                         for A, U in ((FL, u0 - uw), (FH, u0 + uw))))
        for _ in range(points):
            x = BL[0] + rng.random(lo.size) * (BH[0] - BL[0])
            uu = u0 + (2 * rng.random(n) - 1) * uw
            q, dq = state_at(ctx.design, x[0], x[i_s])
            tc = np.asarray(step(x[0], q, dq, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()
            tol = 1e-9 * (1 + np.abs(tc))
            bad += int(np.any(tc < TL[0] - tol) or np.any(tc > TH[0] + tol))
            for (L, H), val in (((KL, KH), rate(x[0], x[i_s], x[i_p])[0]), ((RL, RH), rate(x[0], x[i_s], x[i_p], uu)[0])):
                tol = 1e-9 * (1 + np.abs(val))
                bad += int(np.any(val < L[0] - tol) or np.any(val > H[0] + tol))
    return bad


def _op(ctx, **kw):
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    return OnePeriod(ctx, declared_set(ctx, 0.5, 0.5), **kw)


def _flip_e2(monkeypatch):
    """The mutant of alpha2_dot through e1: de1 = g - e2 instead of g + e2."""
    from symfunnel.certificates import face_forms
    from symfunnel.sx.rewrite import replace_nodes
    orig = face_forms.alpha2_dot_through_e1

    def flipped(design):
        adot, why = orig(design)
        e2 = ca.vec(design.signals["e2"])
        return (replace_nodes([adot], e2, -e2)[0] if adot is not None else None), why
    monkeypatch.setattr(face_forms, "alpha2_dot_through_e1", flipped)


def test_two_joint_rates_in_the_exact_forms_contain_the_plain_plant(tmp_path, monkeypatch):
    from symfunnel.scenario import load_scenario
    ctx = _ctx(load_scenario(str(_two_joints(tmp_path))))
    op = _op(ctx)
    assert op.forms["solve"] == "adjugate" and op.forms["cancelled"]["dqd in alpha2_dot"]
    assert op.forms_k["solve"] == "adjugate" and op.forms_k["f_true"] == "inverse dynamics"
    assert op.np == 3                                   # c and the viscous coefficient of each joint
    assert _escapes(op, ctx) == 0
    # the mutants: e2's sign flipped in alpha2_dot through e1; the adjugate's solve scaled by 0.99
    with monkeypatch.context() as m:
        _flip_e2(m)
        assert _escapes(_op(ctx), ctx) > 0
    import symfunnel.sx.linalg as L
    orig = L.solve2
    monkeypatch.setattr(L, "solve2", lambda M, b: 0.99 * orig(M, b))
    assert _escapes(_op(ctx), ctx) > 0


def test_one_joint_rates_through_e1_contain_the_plain_plant(monkeypatch):
    from symfunnel.scenario import load_scenario
    ctx = _ctx(load_scenario(str(DATA / "sampled_1dof.toml")))
    op = _op(ctx)
    assert op.forms["cancelled"]["dqd in alpha2_dot"]
    assert _escapes(op, ctx) == 0
    _flip_e2(monkeypatch)
    assert _escapes(_op(ctx), ctx) > 0


def test_planar_three_joints_preconditioned_solve_contains_the_plain_plant(monkeypatch):
    """Three joints: M_p^-1 as (C M)^-1 C b with C the model's M^-1 at each box's centre (a point per box set by
    OnePeriod._full); the enclosures contain the plain plant, and a solve scaled by 0.99 is caught."""
    ctx = _ctx(_planar(3))
    op = _op(ctx)
    assert op.forms["solve"].startswith("preconditioned") and op.forms_k["solve"] == op.forms["solve"]
    assert op.state_names[-1] == "qc"
    assert _escapes(op, ctx, boxes=15) == 0
    import symfunnel.sx.linalg as L
    orig = L.preconditioned_solve
    monkeypatch.setattr(L, "preconditioned_solve", lambda M, b, C: 0.99 * orig(M, b, C))
    assert _op(ctx).forms["solve"].startswith("preconditioned")
    assert _escapes(_op(ctx), ctx, boxes=15) > 0


def test_planar_three_joints_tip_first_ldl_contains_the_plain_plant(monkeypatch):
    """Without the preconditioner (no per-box point), three joints take LDL^T tip-first; the same check."""
    from symfunnel.certificates import face_forms
    orig_form = face_forms.solver_form
    monkeypatch.setattr(face_forms, "solver_form", lambda d, a, p, qc=None: orig_form(d, a, p, None))
    ctx = _ctx(_planar(3))
    op = _op(ctx)
    assert op.forms["solve"] == "LDL^T tip-first" and op.forms_k["solve"] == "LDL^T tip-first"
    assert _escapes(op, ctx, boxes=15) == 0
    import symfunnel.sx.linalg as L
    orig = L.ldl_solve
    monkeypatch.setattr(L, "ldl_solve", lambda M, b, order=None: orig(M, b, order) * (0.99 if order else 1.0))
    assert _op(ctx).forms["solve"] == "LDL^T tip-first"
    assert _escapes(_op(ctx), ctx, boxes=15) > 0


@pytest.mark.parametrize("n,with_point,form", [(3, True, "preconditioned at the box's centre"),
                                               (3, False, "LDL^T tip-first"), (4, True,
                                                                               "preconditioned at the box's centre"),
                                               (2, True, "LDL^T")])
def test_the_form_of_m_inverse_is_picked_on_the_enclosures(n, with_point, form):
    """The preconditioned solve where a point per box is available (its enclosure of M^-1 is finite on the most
    boxes), else tip-first LDL^T (finite on more boxes than base-first: planar 3); two joints without the adjugate
    keep base-first LDL^T (the choice is for three or more)."""
    from symfunnel.certificates.face_forms import solver_form
    d = _ctx(_planar(n)).design
    qc = ca.SX.sym("qc", n) if with_point else None
    assert solver_form(d, adjugate=False, pivots=True, qc=qc)[1] == form


def _period_escapes(ctx, op, h=1.0 / 20000.0, tries=8) -> tuple[int, int]:
    """(points outside, states checked): from states of S drawn here (the design's funnels and alpha2), the plant
    integrated by scipy over one period under the generated step's held torque, against op's a-priori enclosure
    (7 times) and its bound sigma_k + h D of the end."""
    from scipy.integrate import solve_ivp

    from symfunnel.emit.step import step_function

    from .test_sampled_set import plant_and_sigma, state_at
    d, n = ctx.design, ctx.design.n
    step = step_function(d, 1.0 / h)
    acc, sigma = plant_and_sigma(ctx)
    rng = np.random.default_rng(2)
    bad = checked = 0
    for _ in range(tries):
        tk = float(rng.uniform(0, 1.0))
        s = rng.uniform(-0.5, 0.5, 2 * n)
        q0, dq0 = state_at(d, tk, s)
        tau = np.asarray(step(tk, q0, dq0, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()
        X = np.concatenate([[tk], s, [0.0]])[None, :]
        _, info = op.check(X, X, h, 0.05)
        if not np.all(np.isfinite(info["DL"])):
            continue
        sol = solve_ivp(lambda tt, x: np.concatenate([x[n:], np.asarray(acc(tt, x[:n], x[n:], tau), float).ravel()]),
                        (tk, tk + h), np.concatenate([q0, dq0]), rtol=1e-11, atol=1e-13, dense_output=True)
        for tt in np.linspace(tk, tk + h, 7):
            sg = sigma(tt, sol.sol(tt))
            bad += int(np.any(sg < info["SL"][0] - 1e-9) or np.any(sg > info["SH"][0] + 1e-9))
        end = sigma(tk + h, sol.sol(tk + h))
        bad += int(np.any(end < s + h * info["DL"][0] - 1e-9) or np.any(end > s + h * info["DH"][0] + 1e-9))
        checked += 1
    return bad, checked


def test_planar_three_joints_one_period_contains_the_integrated_plant(monkeypatch):
    """The whole one-period map with the preconditioned solve, against scipy (planar 3, S 0.5 / 0.5, 20 kHz): the
    integrated plant stays in the a-priori enclosure and ends in sigma_k + h D; with the solve scaled by 0.99 it
    does not."""
    ctx = _ctx(_planar(3))
    op = _op(ctx)
    assert op.forms["solve"].startswith("preconditioned")
    bad, checked = _period_escapes(ctx, op)
    assert bad == 0 and checked >= 6
    import symfunnel.sx.linalg as L
    orig = L.preconditioned_solve
    monkeypatch.setattr(L, "preconditioned_solve", lambda M, b, C: 0.99 * orig(M, b, C))
    bad, checked = _period_escapes(ctx, _op(ctx))
    assert bad > 0

"""certify.sampled's Taylor a-priori form across Coulomb friction's jump: sign(dq) enters the rates as an input in
its hull over the period's box, and the enclosure still contains the plant integrated over a period in which dq
crosses zero (scipy, from states drawn here)."""

from __future__ import annotations

import numpy as np

from .test_sampled_forms import _ctx
from .test_sampled_set import plant_and_sigma, state_at

#: Coulomb friction [N m]: small enough against the light arm's inertia that a joint's rate crosses zero instead of
#: sticking there (the transversal case this test is about)
COULOMB = 0.1


def _coulomb_planar(coulomb=3.0):
    import tempfile
    from pathlib import Path

    from symfunnel.bench._sampled import planar_text
    from symfunnel.scenario import load_scenario
    text = planar_text(2).replace("coulomb = 0.0", f"coulomb = {coulomb!r}")
    assert f"coulomb = {coulomb!r}" in text
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "planar2_coulomb.toml"
        p.write_text(text)
        return load_scenario(str(p))


def _frozen_plant(coulomb):
    """The plant's acceleration with Coulomb friction's sign as an argument: acc(t, q, dq, u, s) = ddq of the same
    arm without Coulomb friction minus M^-1 coulomb s (from the plant's own M; smooth for fixed s)."""
    import casadi as ca

    from symfunnel.plant.equations import plant_acceleration, plant_parameters
    sc = _coulomb_planar(0.0)
    n = sc.model.n
    q, dq, t, u, sg = (ca.SX.sym(k, n) for k in ("q", "dq", "t", "u", "s"))
    _, p0 = plant_parameters(sc)
    pl = plant_acceleration(sc, q, dq, t[0], u, 0.0, p=ca.DM(p0))
    return ca.Function("acc_s", [t[0], q, dq, u, sg], [pl["ddq"] - ca.solve(pl["M"], coulomb * sg)])


def _integrate(acc_s, tau, tk, h, x0, n, pieces=6):
    """The plant under the held torque over [tk, tk + h] by scipy in local time, the friction's sign frozen on each
    piece and flipped where the joint's rate crosses zero (an event): (times, states) at 41 points of the period,
    or None if a joint's rate reaches zero and friction holds it there (sticking) or pieces run out."""
    from scipy.integrate import solve_ivp
    x = np.asarray(x0, float)
    sg = np.sign(x[n:])

    def rhs(s_, x_, sg_):
        return np.concatenate([x_[n:], np.asarray(acc_s(tk + s_, x_[:n], x_[n:], tau, sg_), float).ravel()])
    grid = np.linspace(0.0, h, 41)
    ts, xs = [], []
    t0 = 0.0
    for _ in range(pieces):
        events = []
        for j in range(n):
            ev = (lambda j: lambda s_, x_, *_: x_[n + j])(j)
            ev.terminal = True
            ev.direction = -sg[j]
            events.append(ev)
        sol = solve_ivp(rhs, (t0, h), x, rtol=1e-11, atol=1e-13, dense_output=True, events=events, args=(sg,))
        t1 = float(sol.t[-1])
        for tt in grid[(grid >= t0) & (grid <= t1)]:
            ts.append(tk + tt)
            xs.append(sol.sol(tt))
        if sol.status != 1:
            return np.array(ts), np.array(xs)
        x, t0 = sol.y[:, -1].copy(), t1
        j = next(k for k in range(n) if len(sol.t_events[k]))
        flipped = sg.copy()
        flipped[j] = -sg[j]
        if np.sign(rhs(t0, x, flipped)[n + j]) != flipped[j]:
            return None             # the joint would come back at once: friction holds it
        sg = flipped
    return None


def _crossings(ctx, op, h, coulomb, tries=150, seed=3):
    """(points outside the Taylor enclosure, periods checked in which some dq changes sign): states of S with a
    small dq drawn here, the plant integrated by scipy under the generated step's held torque; only periods whose
    Taylor form is valid count."""
    from symfunnel.certificates.sampled import _up
    from symfunnel.emit.step import step_function
    d, n = ctx.design, ctx.design.n
    step = step_function(d, 1.0 / h)
    _, sigma = plant_and_sigma(ctx)
    acc = _frozen_plant(coulomb)
    rng = np.random.default_rng(seed)
    bad = crossed = 0
    F2 = d.function("funnel_bounds", ["t"], ["F1", "F2"])
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    for _ in range(tries):
        tk = float(rng.uniform(0, 1.0))
        s1 = rng.uniform(-0.4, 0.4, n)
        # sigma2 with dq = alpha2 + sigma2 F2 within a few ulps... of zero: dq_j = +-1e-3
        qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(tk))
        F1v, F2v = (np.asarray(v, float).ravel() for v in F2(tk))
        q = qd + s1 * F1v
        al = np.asarray(a2(tk, q, qd, dqd), float).ravel()
        s2 = (rng.choice([-1e-3, 1e-3], n) - al) / F2v
        if np.any(np.abs(s2) > 0.5):
            continue
        s = np.concatenate([s1, s2])
        q0, dq0 = state_at(d, tk, s)
        tau = np.asarray(step(tk, q0, dq0, np.zeros(1), np.zeros((1, 1)))[0], float).ravel()
        X = np.concatenate([[tk], s, [0.0]])[None, :]
        FL, FH = op._full(X, X)
        UL, UH, _ = op.tau.eval_batch(FL, FH)
        kl = X[:, 1:2 * n + 1]
        valid, DL, DH, SL, SH, _ = op._taylor(FL, FH, kl, kl, X[:, 0], _up(X[:, 0] + h), UL, UH, h, 1.0)
        if not valid[0]:
            continue
        path = _integrate(acc, tau, tk, h, np.concatenate([q0, dq0]), n)
        if path is None:            # dq stuck at zero (friction holds the joint): not the transversal case
            continue
        ts, xs = path
        if not np.any(np.sign(xs[0][n:]) != np.sign(xs[-1][n:])):
            continue
        crossed += 1
        for tt, x in zip(ts, xs):
            sg = sigma(tt, x)
            bad += int(np.any(sg < SL[0] - 1e-9) or np.any(sg > SH[0] + 1e-9))
        end = sigma(ts[-1], xs[-1])
        bad += int(np.any(end < s + h * DL[0] - 1e-9) or np.any(end > s + h * DH[0] + 1e-9))
    return bad, crossed


def test_taylor_form_across_coulomb_jump_contains_the_integrated_plant(monkeypatch):
    """Planar 2 with Coulomb friction 3 N m, S 0.5 / 0.5, 2 kHz: the rates take sign(dq) as an input (n_sw = 2)
    and the Taylor form is valid on periods where dq crosses zero; the plant integrated over such periods stays in
    its a-priori box and ends in sigma_k + h D. With the signs held at their value at the sample instead of their
    hull over the period (the mistake the hull prevents), some period escapes."""
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    ctx = _ctx(_coulomb_planar(COULOMB))
    op = OnePeriod(ctx, declared_set(ctx, 0.5, 0.5))
    assert not op.continuous and op.n_sw == 2
    h = 1.0 / 2000.0
    bad, crossed = _crossings(ctx, op, h, COULOMB)
    assert crossed >= 8 and bad == 0
    hull, taylor = op._signs, op._taylor
    held = {}

    def at_sample(L, H):
        # the first call of a period is the sample's own sign (`_taylor`); later calls get that same value
        if "s" not in held:
            held["s"] = hull(L, H)
        return held["s"]

    def fresh(*a, **k):
        held.clear()
        return taylor(*a, **k)
    monkeypatch.setattr(op, "_signs", at_sample)
    monkeypatch.setattr(op, "_taylor", fresh)
    bad, crossed = _crossings(ctx, op, h, COULOMB)
    assert crossed >= 8 and bad > 0

"""The rate below which no proof over S exists (`sampled_floor`): the state it reports leaves S at the time it
reports when the plant is integrated here independently (scipy's Radau on the plant's own acceleration, the held
torque of the step); a floor computed from a wrong torque reports an exit the plant does not make."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .test_sampled_set import plant_and_sigma, state_at

NONE = Path(__file__).parent / "data" / "certify_none.toml"


def _setup():
    from symfunnel.certificates.problem import Context
    from symfunnel.certificates.region import parameter_box
    from symfunnel.certificates.sampled import OnePeriod, declared_set
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    sc = load_scenario(str(NONE))
    d = derive(sc)
    ctx = Context(sc, d, float(sc.simulation.t_final), parameter_box(sc), None, None)
    S = declared_set(ctx, 0.5, 0.5)
    return ctx, OnePeriod(ctx, S), S


def _exit_here(ctx, floor, S, h):
    """The first time (to 1e-3 of the step) at which the plant from the floor's state leaves S by 1e-6 in e/F, by
    Radau at the nominal parameters and the step's torque at that state; None if it stays for a period h."""
    from scipy.integrate import solve_ivp

    from symfunnel.emit.step import step_function
    d, n = ctx.design, ctx.design.n
    acc, sigma = plant_and_sigma(ctx)
    tk = floor["t"]
    q0, dq0 = state_at(d, tk, floor["e_over_F"])
    tau = np.asarray(step_function(d, 1.0 / h)(tk, q0, dq0, np.zeros(1), np.zeros((1, n)))[0], float).ravel()
    lim = np.concatenate([np.full(n, 1 - S.m1), np.full(n, 1 - S.m2)])
    sol = solve_ivp(lambda s, x: np.concatenate([x[n:], np.asarray(acc(tk + s, x[:n], x[n:], tau), float).ravel()]),
                    (0.0, h), np.concatenate([q0, dq0]), method="Radau", rtol=1e-10, atol=1e-12, dense_output=True)
    ts = np.linspace(0.0, h, 20001)
    out = [np.max(np.abs(sigma(tk + s, sol.sol(s))) - lim) > 1e-6 for s in ts]
    return float(ts[out.index(True)]) if any(out) else None


def test_the_floor_state_leaves_s_when_integrated_independently(monkeypatch):
    """certify_none, S at 0.5 / 0.5, one period at 23 Hz (its simulated rate): a state on S's e2 faces leaves S
    within the period, at the time the floor says (Radau, to 0.5 %); the floor is above 23 Hz. With the step's
    torque scaled by 1.3 inside the floor's computation, the reported exit time is not the plant's."""
    import symfunnel.certificates.sampled_floor as F
    ctx, op, S = _setup()
    h = 1.0 / 23.0
    floor = F.set_floor(op, S, ctx.t_final, h)
    assert floor is not None and floor["rate_hz"] > 23.0
    te = _exit_here(ctx, floor, S, h)
    assert te is not None and abs(te - floor["leaves_after_s"]) <= 5e-3 * floor["leaves_after_s"] + h / 20000
    orig = F.step_function

    def scaled(*a, **k):
        import casadi as ca
        f = orig(*a, **k)
        ins = f.sx_in()
        outs = f.call(ins)
        return ca.Function("scaled", ins, [1.3 * outs[0]] + outs[1:])
    monkeypatch.setattr(F, "step_function", scaled)
    wrong = F.set_floor(op, S, ctx.t_final, h)
    assert wrong is not None
    te = _exit_here(ctx, wrong, S, h)
    assert te is None or abs(te - wrong["leaves_after_s"]) > 5e-3 * wrong["leaves_after_s"] + h / 20000

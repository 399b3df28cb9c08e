"""A rate below which no proof over S exists, found by integration: `certify.sampled`'s "undecided" made specific.

A proof at period h shows that from every state of S the sampled loop stays in S for the whole period (the convexity
argument of `sampled`'s module doc). So one state of S from which the plant under the step's held torque leaves S
within a time t_exit refutes every period h >= t_exit *for this S* (not the rate for the loop: the loop's states may
never come near that one). The states tried lie on S's e2 faces (each joint at +-(1 - m2) F2 in turn, and all joints
at once), at a grid of sample times, with the controller states at the centres of their sets and the nominal
parameters; the plant is integrated by scipy with Coulomb friction's sign frozen on each piece and flipped where a
joint's rate crosses zero (a joint friction holds at rest ends that state's integration: no exit claimed). An exit
counts once |e/F| passes S's margin by EXIT_MARGIN, well beyond the integration's error.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..emit.step import step_function
from ..plant.equations import plant_acceleration
from .sampled_graph import _switching_on, coulomb_signs_as
from .sampled_set import normalised_errors

#: how far past S's margin (in e/F) a state must be to count as having left S
EXIT_MARGIN = 1e-6
#: sample times tried, evenly over [0, T)
TIMES = 8
#: pieces of an integration (crossings of zero by a joint's rate) before it is given up
PIECES = 8


def _frozen_plant(op):
    """acc(t, q, dq, u, s): the plant's acceleration at the nominal parameters with sign(dq) replaced by s, or None
    where another operation of the plant switches with the state."""
    sc, n = op.ctx.scenario, op.n
    q, dq, u, s = (ca.SX.sym(k, n) for k in ("q", "dq", "u", "s"))
    t = ca.SX.sym("t")
    ddq = plant_acceleration(sc, q, dq, t, u, 0.0, p=ca.DM(np.asarray(op.ctx.params.nominal, float)))["ddq"]
    ddq = coulomb_signs_as(ddq, dq, s)[0]
    if _switching_on([t, q, dq, u, s], [t, q, dq], [ddq]):
        return None
    return ca.Function("acc_frozen", [t, q, dq, u, s], [ddq])


def _exit_time(acc, sigma, tk, x0, tau, n, lim, h):
    """The first time in (0, h] at which the held-torque plant from x0 at tk leaves |e/F| <= lim (+ EXIT_MARGIN), or
    None (stays, or a joint sticks)."""
    from scipy.integrate import solve_ivp
    x, sg, t0 = np.asarray(x0, float), np.sign(x0[n:]), 0.0
    if np.any(sg == 0):
        return None                     # a joint at rest: which friction holds it is not this method's question

    def rhs(s_, x_, sg_):
        return np.concatenate([x_[n:], np.asarray(acc(tk + s_, x_[:n], x_[n:], tau, sg_), float).ravel()])

    def out(s_, x_, *_):
        return float(np.min(lim + EXIT_MARGIN - np.abs(sigma(tk + s_, x_))))
    out.terminal = True
    for _ in range(PIECES):
        evs = [out]
        for j in range(n):
            ev = (lambda j: lambda s_, x_, *_: x_[n + j])(j)
            ev.terminal, ev.direction = True, -sg[j]
            evs.append(ev)
        sol = solve_ivp(rhs, (t0, h), x, rtol=1e-10, atol=1e-12, events=evs, args=(sg,))
        if sol.status != 1:
            return None
        if len(sol.t_events[0]):
            return float(sol.t_events[0][0])
        x, t0 = sol.y[:, -1].copy(), float(sol.t[-1])
        j = next(k for k in range(n) if len(sol.t_events[k + 1]))
        flipped = sg.copy()
        flipped[j] = -sg[j]
        if np.sign(rhs(t0, x, flipped)[n + j]) != flipped[j]:
            return None                 # friction holds the joint at rest
        sg = flipped
    return None


def set_floor(op, S, t_final: float, h: float, tau_max=None) -> dict | None:
    """{"rate_hz": 1 / t_exit, "leaves_after_s", "t", "e_over_F"} for the state of S's e2 faces tried here that
    leaves S soonest within a period h, or None (none leaves within h, or the plant cannot be integrated so)."""
    acc = _frozen_plant(op)
    if acc is None or not np.isfinite(h) or h <= 0:
        return None
    d, n = op.ctx.design, op.n
    step = step_function(d, 1.0 / h, tau_max)
    F = d.function("funnel_bounds", ["t"], ["F1", "F2"])
    a2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
    errors = normalised_errors(d)

    def sigma(tt, x):
        return errors(tt, x[:n], x[n:])
    xs, ws = step.size_in(3), step.size_in(4)
    centre = {k: 0.5 * (np.asarray(lo, float) + np.asarray(hi, float)) for k, (lo, hi) in S.states.items()}
    x_esn = centre.get("x_esn", np.zeros(xs)).reshape(xs, order="F")
    w_hat = centre.get("w_hat", np.zeros(ws)).reshape(ws, order="F")
    lim = np.concatenate([np.full(n, 1 - S.m1), np.full(n, 1 - S.m2)])
    faces = [np.eye(n)[j] * sgn for j in range(n) for sgn in (1.0, -1.0)] + [np.ones(n), -np.ones(n)]
    best = None
    for tk in np.linspace(0.0, float(t_final), TIMES, endpoint=False):
        qd, dqd, _ = (np.asarray(v, float).ravel() for v in d.reference(tk))
        F1, F2 = (np.asarray(v, float).ravel() for v in F(tk))
        for f in faces:
            s2 = f * (1 - S.m2)
            q0 = qd.copy()
            dq0 = np.asarray(a2(tk, q0, qd, dqd), float).ravel() + s2 * F2
            tau = np.asarray(step(tk, q0, dq0, x_esn, w_hat)[0], float).ravel()
            te = _exit_time(acc, sigma, tk, np.concatenate([q0, dq0]), tau, n, lim, h if best is None else
                            best["leaves_after_s"])
            if te is not None and (best is None or te < best["leaves_after_s"]):
                best = {"rate_hz": 1.0 / te if te > 0 else float("inf"), "leaves_after_s": te, "t": float(tk),
                        "e_over_F": (np.concatenate([np.zeros(n), s2]) + 0.0).tolist()}
    return best

"""The parameter columns of the e2 faces' Jacobian by the regressor identity, for the mean-value form of
`certify.containment` (issue 45).

AD differentiates f_true = M_p^-1 r_p by the product rule, -M_p^-1 dM_p/dp M_p^-1 r_p + M_p^-1 dr_p/dp, and interval
arithmetic encloses each factor on its own: with r_p carrying the design's torque (thousands of N m near the e1
faces) the p-columns come out tens of times wider than the change they bound. For the true plant
M_p ddq = D(tau) - C_p dq - G_p - friction - d, with the applied torque D(tau) independent of p, the same derivative is

    d ddq / dp_k = -M_p^-1 (dM_p/dp_k ddq + d(C_p dq + G_p + friction + d)/dp_k)        (the regressor form)

and ddq itself is the face's own quantity, ddq = n2 + alpha2_dot + (e2/F2) dF2: any enclosure of n2 on the box (the
mean-value form's own, first with AD's columns) gives one of ddq there, so every piece is a valid enclosure of the
true Jacobian entry on the box, and it is intersected with AD's. The identity is checked on the graph before use
(the torque's independence of p structurally, the two Jacobians equal at random points of the funnel region);
where it fails, the faces keep AD's columns.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..sx.batch import BatchIntervalFunction
from ..sx.interval import IntervalError
from .face_forms import alpha2_dot_through_e1, normal_components, solver_form
from .region import region_signals

#: relative tolerance of the identity check at random points (the two forms differ by rounding only)
IDENTITY_RTOL = 1e-7
#: random points of the identity check
IDENTITY_POINTS = 24


def regressor_form(design, p: ca.SX, wide, adjugate: bool, through_e1: bool,
                   t_final: float) -> tuple[ca.SX | None, ca.SX, str]:
    """(Jp, N2, why): Jp (n x len(wide)) the regressor form of d n2/dp_wide (the uncertain parameters' columns) in
    the design's symbols, p and a symbol N2 (n) standing for n2 itself; (None, N2, why not) where the plant's applied
    torque depends on those parameters or the form does not reproduce AD's Jacobian of n2 at random points."""
    from ..plant.equations import plant_acceleration
    from ..sx.linalg import ldl_solve
    S, sym, n = design.signals, design.sym, design.n
    N2 = ca.SX.sym("N2", n)
    pl = plant_acceleration(design.scenario, sym["q"], sym["dq"], sym["t"], S["tau"], 0.0, p=p)
    pw = p[[int(j) for j in wide]]
    if ca.depends_on(pl["tau_applied"], pw):
        return None, N2, "the applied torque depends on the uncertain parameters"
    adot = alpha2_dot_through_e1(design)[0] if through_e1 else None
    adot = S["alpha2_dot"] if adot is None else adot
    ddq = N2 + adot + S["e2"] / S["F2"] * S["dF2"]
    A = ca.SX.sym("A", n)
    Y = ca.jacobian(ca.mtimes(pl["M"], A) + ca.mtimes(pl["C"], sym["dq"]) + pl["G"] + pl["friction"]
                    + pl["disturbance"], pw)
    solve = solver_form(design, adjugate, pivots=False)[0] or ldl_solve      # the faces' own form of M_p^-1
    Jp = -ca.horzcat(*[(ca.solve(pl["M"], Y[:, k]) if n == 1 else solve(pl["M"], Y[:, k]))
                       for k in range(pw.numel())])
    Jp = ca.substitute(Jp, A, ddq)
    n2 = normal_components(design, p, adjugate, through_e1=through_e1)[1]
    why = _identity(design, p, wide, n2, Jp, N2, t_final)
    return (None if why else Jp), N2, why


def _identity(design, p: ca.SX, wide, n2: ca.SX, Jp: ca.SX, N2: ca.SX, T: float) -> str:
    """'' if AD's d n2/dp_wide equals the regressor form (N2 = n2) at random points of the funnel region
    (states inside the funnels on [0, T], the uncertain parameters in [0.5, 1.5] times their nominal, the others
    nominal), else why not."""
    from ..plant.equations import plant_parameters
    sym = design.sym
    names = [k for k in sym]
    ins = [sym[k] for k in names] + [p]
    wide = [int(j) for j in wide]
    f = ca.Function("identity", ins, [ca.jacobian(n2, p[wide]), ca.substitute(Jp, N2, n2)])
    rng = np.random.default_rng(7)
    alpha2 = design.function("alpha2", ["t", "q", "qd", "dqd"])
    bounds = design.function("funnel_bounds", ["t"], ["F1", "F2"])
    p0 = np.asarray(plant_parameters(design.scenario)[1], float)
    for _ in range(IDENTITY_POINTS):
        t = rng.uniform(0.0, T)
        qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in design.reference(t))
        F1, F2 = (np.asarray(v, float).ravel() for v in bounds(t))
        q = qd + rng.uniform(-0.9, 0.9, design.n) * F1
        dq = np.asarray(alpha2(t, q, qd, dqd), float).ravel() + rng.uniform(-0.9, 0.9, design.n) * F2
        vals = {"t": t, "q": q, "dq": dq, "qd": qd, "dqd": dqd, "ddqd": ddqd}
        args = [vals[k] if k in vals else rng.uniform(-0.5, 0.5, sym[k].shape) for k in names]
        pv = p0.copy()
        pv[wide] *= rng.uniform(0.5, 1.5, len(wide))
        a, b = (np.asarray(v, float) for v in f(*args, pv))
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return "the Jacobians are not finite at a point of the funnel region"
        scale = max(1.0, float(np.max(np.abs(a))))
        if np.max(np.abs(a - b)) > IDENTITY_RTOL * scale:
            return f"AD's d n2/dp and the regressor form differ by {np.max(np.abs(a - b)):.3g} at t = {t:.4g}"
    return ""


class RegressorColumns:
    """The hook `BatchCenteredForm.refine` of the faces' form: n2's p-columns of the Jacobian's enclosure
    intersected with the regressor form's, evaluated with N2 = the faces' current enclosure of n2 on the box."""

    def __init__(self, prob, Jp: ca.SX, N2: ca.SX, p: ca.SX, n2_pos: int):
        d = prob.design
        P = prob.ctx.params
        pu = ca.SX.sym("p", int(prob.wide.size))
        full = [ca.SX(float(v)) for v in P.nominal]
        for i, j in enumerate(prob.wide):
            full[j] = pu[i]
        # only the uncertain parameters' columns, in the region's own variables (the faces' layout, then N2)
        Jw = ca.substitute(Jp, p, ca.vertcat(*full))
        ins, outs, _, states, _ = region_signals(d, {"Jp": ca.vec(Jw)})
        F = prob.F
        extra = [ca.SX.sym(k, F.in_off[F.in_names.index(k) + 1] - F.in_off[F.in_names.index(k)])
                 for k in prob.extra_names]
        f = ca.Function("containment_jp", ins + [pu] + states + extra + [N2], outs,
                        {"cse": True, "allow_duplicate_io_names": True})
        self.F = BatchIntervalFunction(f)
        self.n, self.n2_pos = d.n, int(n2_pos)
        wpos = {int(j): i for i, j in enumerate(F.w_flat)}
        i = F.in_names.index("p")
        self.pcols = np.array([wpos[j] for j in range(F.in_off[i], F.in_off[i + 1])], dtype=int)

    def __call__(self, LO, HI, L, H, JL, JH):
        n, a = self.n, self.n2_pos
        NL, NH, _ = self.F.eval_batch(np.c_[LO, L[:, a:a + n]], np.c_[HI, H[:, a:a + n]])
        K, npc = LO.shape[0], self.pcols.size
        NL, NH = NL.reshape(K, npc, n), NH.reshape(K, npc, n)            # vec: column k (dp_k) after column k-1
        JL, JH = JL.copy(), JH.copy()
        rows = slice(a, a + n)
        lo = np.maximum(JL[:, self.pcols, rows], NL)
        hi = np.minimum(JH[:, self.pcols, rows], NH)
        if np.any(lo > hi):
            raise IntervalError("containment: the regressor form's and AD's enclosures of dn2/dp are disjoint -- "
                                "a rule or the identity is wrong")
        JL[:, self.pcols, rows], JH[:, self.pcols, rows] = lo, hi
        return JL, JH


__all__ = ["RegressorColumns", "regressor_form"]

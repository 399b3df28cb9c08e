"""Checks of the design's proof itself: its Lyapunov identity, its rho, the guarantee it gives, its assumptions.

- ``design.identity.vdot``: along the nominal model plus a *symbolic* unknown term f = W*^T Phi + eps (W* and eps
  free), the exact V_dot (AD) equals the variant's target form -- any controller term that disagrees with the proof
  breaks it. Checked at random states inside the funnels with random W*, eps, and along the simulated trajectory.
- ``lyapunov.rho_positive``: the constant lower bound of rho over the horizon is > 0 (sigma = 0 gives rho = 0).
- ``lyapunov.guarantee``: the ultimate bound V <= delta/rho with eps measured along the run for one fitted W*, turned
  into |z| <= sqrt(2 max(V(0), delta/rho)) and into the funnel margin it implies; `warn` ("vacuous") when that margin
  is below GUARANTEE_MIN_MARGIN, i.e. it adds (almost) nothing to what the barrier ensures by itself.
- ``assumption.input_gain``: the torque uses the nominal M, so the plant sees ddq = M_p^-1 D M (v - ...) + ...; the
  proof needs the effective input gain M_p(q)^-1 D M(q) positive definite (symmetric part), for every combination
  of each joint's dead-zone branch slopes and the plant's mass and parameter mismatch.
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np

from .audit import CheckResult
from ..design.sampling import eval_mapped, funnel_states, point_of

#: relative residual of the identity above which it fails (round-off of the terms is ~1e-13 relative) -- unless the
#: round-off bound of the residual's own evaluation is larger at that state (large terms that cancel)
IDENTITY_TOL = 1e-9
#: a state whose round-off allowance exceeds this (relative) cannot decide the identity
IDENTITY_UNRESOLVED = 1e-3
#: sampled states of the identity check (besides the trajectory's)
IDENTITY_SAMPLES = 2000
#: a guarantee keeping |e| below (1 - this) F adds too little to the barrier to count
GUARANTEE_MIN_MARGIN = 0.05


def _g(x) -> str:
    return f"{float(x):.4g}"


# --- the identity ------------------------------------------------------------------------------------

def identity_function(design) -> ca.Function:
    """(design inputs..., W_star, eps) -> (V_dot - target, scale) along the nominal model plus f = W*^T Phi + eps."""
    n, nr = design.n, design.n_regressor
    Ws = ca.SX.sym("W_star", nr, n)
    eps = ca.SX.sym("eps", n)
    f = (ca.mtimes(Ws.T, design.signals["Phi"]) if nr else 0) + eps
    lyap = design.variant.lyapunov(design, Ws, eps)
    x, xdot = design.variant.nominal_flow(design, f)
    V_dot = ca.jtimes(lyap["V"], x, xdot)
    ins = [design.sym[k] for k in design.inputs] + [Ws, eps]
    names = list(design.inputs) + ["W_star", "eps"]
    return ca.Function("identity", ins, [V_dot - lyap["target"], ca.fabs(V_dot) + lyap["scale"]], names,
                       ["residual", "scale"], {"cse": True})


def _trajectory_points(design, closed_loop, result, k: int) -> dict[str, np.ndarray] | None:
    """Up to k states of the simulated run as design-input arrays (casadi map layout)."""
    if result is None or result.t.size == 0:
        return None
    idx = np.unique(np.linspace(0, result.t.size - 1, min(k, result.t.size)).astype(int))
    t = result.t[idx]
    m = idx.size
    parts = closed_loop.unpack(result.x[idx])
    qd, dqd, ddqd = (np.array(v) for v in design.reference.map(m)(t[None, :]))
    pts = {"t": t[None, :], "q": parts["q"].T, "dq": parts["dq"].T, "qd": qd, "dqd": dqd, "ddqd": ddqd}
    for name, (r, c) in design.states:
        v = parts[name]
        pts[name] = v.T if c == 1 else np.concatenate(list(v), axis=1)       # (r, m*c), block j = sample j
    return pts


def _nonzero_rows(f: ca.Function, pts: dict[str, np.ndarray], idx: np.ndarray) -> list[np.ndarray]:
    """The inputs of f at the sampled points idx as (nnz_in, len(idx)) arrays of column-major nonzeros (the layout
    `RoundoffBound` takes) from casadi's map layout (block j of an r x c input = sample j)."""
    out = []
    for i in range(f.n_in()):
        r, c = f.size1_in(i), f.size2_in(i)
        a = np.asarray(pts[f.name_in(i)], dtype=float)
        a = a.reshape(r, a.shape[1] // c, c)[:, idx, :]
        nz = f.sparsity_in(i).find()
        out.append(np.array([a[j % r, :, j // r] for j in nz]).reshape(len(nz), idx.size))
    return out


def identity_allowance(f: ca.Function, pts: dict[str, np.ndarray], resid: np.ndarray, scale: np.ndarray,
                       bound: list) -> np.ndarray:
    """The relative residual each state may have: IDENTITY_TOL, or more where the round-off bound of the residual's
    own evaluation (sx.roundoff, x ROUNDOFF_SAFETY) is larger, i.e. where the terms V_dot sums are so much larger
    than V_dot that their rounding exceeds IDENTITY_TOL. The bound is computed only at states above IDENTITY_TOL;
    `bound` (a one-element list) caches the compiled `RoundoffBound` across calls. A non-finite residual gets 0."""
    from ..sx.roundoff import ROUNDOFF_SAFETY, UNIT_ROUNDOFF, RoundoffBound
    rel = np.abs(resid) / np.maximum(scale, 1e-300)
    allowed = np.full(rel.shape, IDENTITY_TOL)
    finite = np.isfinite(resid) & np.isfinite(scale)
    allowed[~finite] = 0.0
    above = np.flatnonzero(finite & (rel > IDENTITY_TOL))
    if above.size:
        if not bound:
            bound.append(RoundoffBound(ca.Function("identity_residual", f.sx_in(), [f.call(f.sx_in())[0]],
                                                   f.name_in(), ["residual"])))
        _, mags = bound[0](_nonzero_rows(f, pts, above))
        floor = ROUNDOFF_SAFETY * UNIT_ROUNDOFF * mags[0].reshape(-1) / np.maximum(scale[above], 1e-300)
        allowed[above] = np.maximum(IDENTITY_TOL, floor)
    return allowed


def _across_layer(design, pts: dict, proj: dict, rng) -> dict:
    """The points with each W_hat scaled to a norm uniform in [R (1 - eps), R (1 + 2 eps)]."""
    r, c = design.sym["w_hat"].shape
    k = pts["t"].shape[1]
    V = pts["vec_w_hat"]
    R, eps = float(proj["R"]), float(proj["eps"])
    V = V / np.maximum(np.linalg.norm(V, axis=0), 1e-300) * rng.uniform(R * (1 - eps), R * (1 + 2 * eps), k)
    out = dict(pts)
    out["vec_w_hat"] = V
    out["w_hat"] = V.reshape(r, c, k, order="F").transpose(0, 2, 1).reshape(r, k * c) if c > 1 else V
    return out


def _first_states(pts: dict[str, np.ndarray], k: int, m: int) -> dict[str, np.ndarray]:
    """The first m of k sampled states (casadi map layout: an (r, k*c) input holds state j in columns j*c..j*c+c-1)."""
    return {name: a[:, :m * (a.shape[1] // k)] for name, a in pts.items()}


def check_identity(design, rng, *, closed_loop=None, result=None, samples: int = IDENTITY_SAMPLES,
                   failure_first: int | None = None) -> CheckResult:
    """design.identity.vdot: V_dot along nominal model + f equals the variant's target form (sampled, by AD), to
    IDENTITY_TOL relative, or to the round-off bound of the residual's evaluation where that is larger.

    `failure_first` (mutation testing, which reads only whether the check fails): the first that many states of the
    first set are judged first, and a state failing among them fails the check at once (detail, margin and evidence
    then of those states). Each state is judged alone (its residual, scale and round-off allowance are its own), so
    the status is the full check's: a failing state fails it wherever it lies; without one the full check runs."""
    f = identity_function(design)
    n, nr = design.n, design.n_regressor
    sets = [("inside the funnels", funnel_states(design, samples, rng, fill=0.98))]
    proj = design.parts.get("projection")
    if proj is not None:
        # W_hat across the projection's boundary layer too (W_hat's box alone may lie inside or far outside it)
        sets.append(("with W_hat across the projection's layer", _across_layer(
            design, funnel_states(design, samples, rng, fill=0.98), proj, rng)))
    traj = _trajectory_points(design, closed_loop, result, 500)
    if traj is not None:
        sets.append(("along the simulated trajectory", traj))
    worst, where, evaluated, label = 0.0, None, 0, ""
    margin, widened, unresolved, widest = np.inf, 0, 0, IDENTITY_TOL
    failing = None                                    # (relative residual, where, label) of the most violated state
    bound: list = []

    def judged(pts, k):
        resid, scale = (a.ravel() for a in eval_mapped(f, pts, k))
        rel = np.abs(resid) / np.maximum(scale, 1e-300)
        rel = np.where(np.isfinite(rel), rel, np.inf)
        allowed = identity_allowance(f, pts, resid, scale, bound)
        with np.errstate(invalid="ignore"):
            slack = allowed - rel
        return rel, allowed, np.where(np.isnan(slack), -np.inf, slack)

    for i, (what, pts) in enumerate(sets):
        k = pts["t"].shape[1]
        pts = dict(pts)
        pts["W_star"] = rng.normal(0.0, 1.0, (nr, k * n)) if nr else np.zeros((0, k * n))
        pts["eps"] = rng.normal(0.0, 10.0, (n, k))
        out = None
        if i == 0 and failure_first and failure_first < k:
            first = _first_states(pts, k, failure_first)
            out = judged(first, failure_first)
            if np.min(out[2]) < 0:
                pts, k = first, failure_first
            else:
                out = None
        rel, allowed, slack = judged(pts, k) if out is None else out
        evaluated += k
        widened += int(np.sum(allowed > IDENTITY_TOL))
        unresolved += int(np.sum(allowed > IDENTITY_UNRESOLVED))
        widest = max(widest, float(np.max(np.where(allowed > IDENTITY_UNRESOLVED, 0.0, allowed))))
        j = int(np.argmin(slack))
        if slack[j] < margin:
            margin = float(slack[j])
            if margin < 0:
                failing = (float(rel[j]), point_of(pts, j), what)
        jr = int(np.argmax(rel))
        if rel[jr] >= worst:
            worst, label = float(rel[jr]), what
            where = point_of(pts, jr)
        if failure_first and failing is not None:
            break
    form = design.variant.target_text()
    ev = {"states": evaluated, "max_relative_residual": worst, "tolerance": IDENTITY_TOL, "target": form,
          "roundoff_widened_states": widened, "roundoff_unresolved_states": unresolved,
          "max_roundoff_allowance": widest}
    method = (f"AD of V along the nominal model + symbolic f = W*^T Phi + eps, {evaluated} states with random W*, "
              f"eps; tolerance {IDENTITY_TOL:g} relative, or the round-off bound of the residual's own evaluation")
    roundoff = (f"; at {widened} states the terms V_dot sums are so large that their round-off allows up to "
                f"{widest:.2g}" if widened else "")
    if failing is not None:
        rel_f, where, label = failing
        return CheckResult("design.identity.vdot", "fail",
                           f"V_dot differs from {form}: relative residual {rel_f:.3g} {label}, beyond both "
                           f"the tolerance {IDENTITY_TOL:g} and the round-off of the terms there: the controller "
                           "disagrees with the proof", method=method, margin=margin, where=where, evidence=ev)
    if unresolved == evaluated:
        return CheckResult("design.identity.vdot", "warn",
                           f"V_dot = {form} cannot be decided: at every one of the {evaluated} states the round-off "
                           f"of the terms exceeds {IDENTITY_UNRESOLVED:g} relative (worst residual {worst:.2g})",
                           method=method, margin=margin, where=where, evidence=ev)
    return CheckResult("design.identity.vdot", "pass",
                       f"V_dot = {form} holds at {evaluated} states (worst relative residual {worst:.2g}{roundoff})",
                       method=method, margin=margin, where=where, evidence=ev)


# --- rho and the guarantee ---------------------------------------------------------------------------

def check_rho_positive(design, t_final: float) -> CheckResult:
    """lyapunov.rho_positive: the constant lower bound of rho on [0, t_final] is positive."""
    from .lyapunov import constant_rho_lower
    from ..family.funnels import extremes
    rho = constant_rho_lower(design, t_final)
    sc = design.scenario
    sup1 = extremes(sc.funnels["e1"], t_final)[1]
    sup2 = extremes(sc.funnels["e2"], t_final)[1]
    terms = {"2 k1/sup F1": float(np.min(2 * np.asarray(sc.k1) / sup1)),
             "k2/sup F2": float(np.min(np.asarray(sc.k2) / sup2))}
    if design.n_regressor:
        terms["sigma Gamma"] = float(sc.sigma * sc.gamma)
    binding = min(terms, key=terms.get)
    ev = {"rho_lower": rho, "terms": terms, "k1": sc.k1, "k2": sc.k2, "sigma": sc.sigma, "gamma": sc.gamma}
    where = {"t_range": [0.0, float(t_final)], "binding": binding}
    text = design.variant.rho_text()
    if rho > 0:
        return CheckResult("lyapunov.rho_positive", "pass", f"rho >= {text} = {_g(rho)} > 0 on [0, {t_final:g}] s "
                           f"(set by {binding})", method="exact (sup of F on the horizon)", margin=rho, where=where,
                           evidence=ev)
    return CheckResult("lyapunov.rho_positive", "fail",
                       f"rho >= {text} = {_g(rho)} (set by {binding}): no decay rate, so the Lyapunov bounds give "
                       "nothing (sigma = 0 is pure gradient adaptation: W~ is not attracted)",
                       method="exact (sup of F on the horizon)", margin=rho, where=where, evidence=ev)


def check_guarantee(design, L) -> CheckResult:
    """lyapunov.guarantee: the funnel margin the ultimate bound delta/rho implies (warn when vacuous)."""
    cid = "lyapunov.guarantee"
    if L is None or not np.isfinite(L.rho_const_lower) or L.rho_const_lower <= 0 or not np.isfinite(L.delta_max):
        return CheckResult(cid, "warn", "no guarantee: rho <= 0 or no trajectory to measure eps on (vacuous)",
                           method="ultimate bound")
    rho, delta = L.rho_const_lower, L.delta_max
    V0 = float(L.V[0]) if np.isfinite(L.V[0]) else 0.0
    V_ult = delta / rho
    z_bound = float(np.sqrt(2 * max(V0, V_ult)))
    usage = float(design.variant.transform.usage(z_bound))
    margin = 1.0 - usage
    eps_rms = L.w_star_info.get("rms_residual")
    ev = {"rho": rho, "delta": delta, "V0": V0, "delta_over_rho": V_ult, "z_bound": z_bound,
          "implied_margin": margin, "W_star": L.w_star_info, "eps_rms": eps_rms, "threshold": GUARANTEE_MIN_MARGIN}
    head = (f"V <= max(V(0), delta/rho) = {_g(max(V0, V_ult))} (delta = {_g(delta)} with eps measured along the run "
            f"for one fitted W*, rho = {_g(rho)}) bounds |z| <= {_g(z_bound)}, i.e. |e| <= {usage:.4g} F")
    if margin < GUARANTEE_MIN_MARGIN:
        return CheckResult(cid, "warn", head + f": vacuous -- a margin of {margin:.3g} adds nothing to what the "
                           f"barrier ensures by itself (threshold {GUARANTEE_MIN_MARGIN:g})",
                           method="ultimate bound", margin=margin, evidence=ev)
    return CheckResult(cid, "pass", head + f": a guaranteed funnel margin of {margin:.3g}",
                       method="ultimate bound", margin=margin, evidence=ev)


# --- the input gain ----------------------------------------------------------------------------------

def _slope_sets(scenario) -> list[np.ndarray]:
    """Per joint, the dead-zone branch slopes to combine (1 without a dead zone)."""
    from ..plant.equations import dead_zone_branches
    from ..plant.nonlinearities import dead_zone_slope_bounds
    n = scenario.n
    dz = scenario.plant.dead_zone
    if dz is None:
        return [np.array([1.0])] * n
    left, right = dead_zone_branches(scenario)
    lo_l, hi_l = dead_zone_slope_bounds(left, left, dz.b_l, dz.b_l)
    lo_r, hi_r = dead_zone_slope_bounds(right, right, dz.b_r, dz.b_r)
    return [np.unique(np.round([lo_l[j], hi_l[j], lo_r[j], hi_r[j]], 12)) for j in range(n)]


def check_input_gain(design, rng, *, samples: int = 400) -> CheckResult:
    """assumption.input_gain: lambda_min of sym(M_p(q)^-1 D M(q)) > 0 over sampled q and every slope combination."""
    from ..plant.equations import plant_acceleration
    sc = design.scenario
    n = design.n
    q, dq = design.sym["q"], design.sym["dq"]
    tau = ca.SX.sym("tau", n)
    Mp = plant_acceleration(sc, q, dq, design.sym["t"], tau, 0.0)["M"]
    fM = ca.Function("M", [q], [design.signals["M"], Mp])
    # q: the reference +- F1 over the horizon, or the audit's joint range where the model gives joint limits
    pts = funnel_states(design, samples, rng, fill=1.0)
    Q = pts["q"]
    if sc.audit.joint_lower and sc.model.kind in ("urdf",):
        lo, hi = np.array(sc.audit.joint_lower)[:, None], np.array(sc.audit.joint_upper)[:, None]
        Q = np.concatenate([Q, lo + (hi - lo) * rng.random((n, samples))], axis=1)
    Mm, Mpl = (np.array(v) for v in fM.map(Q.shape[1])(Q))
    k = Q.shape[1]
    Mm = Mm.reshape(n, k, n).transpose(1, 0, 2)
    Mpl = Mpl.reshape(n, k, n).transpose(1, 0, 2)
    A = np.linalg.solve(Mpl, Mm)                     # M_p^-1 M, (k, n, n)
    slopes = _slope_sets(sc)
    worst, where = np.inf, None
    combos = 0
    for d in itertools.product(*slopes):
        D = np.asarray(d)
        G = np.linalg.solve(Mpl, D[None, :, None] * Mm)          # M_p^-1 D M
        S = 0.5 * (G + np.swapaxes(G, 1, 2))
        lam = np.linalg.eigvalsh(S)[:, 0]
        j = int(np.argmin(lam))
        combos += 1
        if lam[j] < worst:
            worst, where = float(lam[j]), {"q": Q[:, j].tolist(), "slopes": D.tolist()}
    nominal = float(np.min(np.linalg.eigvalsh(0.5 * (A + np.swapaxes(A, 1, 2)))[:, 0]))
    ev = {"states": k, "slope_combinations": combos, "lambda_min": worst, "lambda_min_without_dead_zone": nominal,
          "slopes_per_joint": [s.tolist() for s in slopes], "mass_scale": sc.plant.mass_scale}
    method = f"eigenvalues at {k} joint states x {combos} slope combinations"
    if worst > 0:
        return CheckResult("assumption.input_gain", "pass",
                           f"sym(M_p^-1 D M) is positive definite: lambda_min = {_g(worst)} over {k} states and "
                           f"{combos} dead-zone slope combinations", method=method, margin=worst, where=where,
                           evidence=ev)
    return CheckResult("assumption.input_gain", "fail",
                       f"sym(M_p^-1 D M) loses positive definiteness: lambda_min = {_g(worst)} at q = "
                       f"{np.round(where['q'], 4).tolist()} with slopes {where['slopes']} (without the dead zone "
                       f"{_g(nominal)}): the lumped uncertainty then depends on W_hat and the proof's bound on it fails",
                       method=method, margin=worst, where=where, evidence=ev)

"""The Lyapunov argument of docs/derivation.md, evaluated exactly on the closed-loop graph.

    V = 1/2 z1^T z1 + 1/2 z2^T z2 + 1/(2 gamma) ||W* - W_hat||_F^2

is built as CasADi SX in the closed-loop time and state (t, x) -- z1 and z2 are the design's signals with the reference
substituted as functions of t, exactly as the closed loop uses them -- and its derivative along the flow is the exact
forward-mode AD

    V_dot = dV/dt + dV/dx . f(t, x)          (casadi.jtimes of V along (1, f(t, x)))

evaluated at the simulated states (never a finite difference of samples).

Two versions of the decay claim V_dot <= -rho V + delta are evaluated side by side:

- **paper** (Theorem 1 as printed): rho = min_i{2 k1 zeta1_i, 2 k2 zeta2_i, sigma} (zeta evaluated pointwise, the
  minimum over joints), delta = sigma/2 ||W*||_F^2;
- **corrected** (docs/derivation.md eq. 8): rho = min(2 k1 min_i mu1_i, k2 min_i mu2_i, sigma gamma),
  delta = sigma/2 ||W*||_F^2 + sum_i mu2_i eps_i^2 / (2 k2_i) with eps = f_true - W*^T Phi.

The ideal weight W* is never given by the paper: it is *estimated* as the least-squares fit of the true unknown
term f_true on the regressor Phi along the simulated trajectory (so eps is the fit's residual).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

#: relative round-off allowance for an inequality evaluated in floating point:
#: a point violates when V_dot - (-rho V + delta) > REL_TOL * (|V_dot| + |rho V| + |delta| + scale of the terms)
REL_TOL = 1e-8


# --- W* -------------------------------------------------------------------------------------------

def regressor_values(cl, X: np.ndarray) -> np.ndarray:
    """Phi at every state of a trajectory X (T, n_x) -> (T, n_regressor)."""
    d = cl.design
    X = np.asarray(X, dtype=float).reshape(-1, cl.nx)
    T = X.shape[0]
    if T == 0 or d.n_regressor == 0:
        return np.zeros((T, d.n_regressor))
    f = ca.Function("Phi", [cl.x], [d.signals["Phi"]])
    return np.asarray(f.map(T)(X.T)).T


def estimate_w_star(cl, t: np.ndarray, X: np.ndarray, f_true: np.ndarray) -> tuple[np.ndarray, dict]:
    """W* fitted along a trajectory: the least-squares fit of f_true on Phi that makes the corrected delta smallest.

    Per joint i, W*_i = argmin_w  sigma/2 ||w||^2 + mean_t mu2_i(t) (f_true_i(t) - w^T Phi(t))^2 / (2 k2_i),
    i.e. the time average of delta(t) of eq. (8): a least-squares fit weighted by mu2/(2 k2) and regularised by
    delta's own sigma/2 ||W||^2 term (closed form). The plain least-squares fit is reported beside it: along one
    trajectory the reservoir states are strongly correlated, so the plain fit is ill-conditioned and its huge norm
    would make sigma/2 ||W*||^2 (hence delta) meaningless.
    """
    d = cl.design
    sc = cl.scenario
    nr = d.n_regressor
    n = d.n
    T = int(np.size(t))
    if nr == 0:
        return np.zeros((0, n)), {"samples": 0, "norm": 0.0, "method": "no approximator: no ideal weights"}
    Phi = regressor_values(cl, X)
    f_true = np.asarray(f_true, dtype=float).reshape(T, -1)
    mu2 = np.full((T, n), np.nan)
    if T:
        fm = ca.Function("mu2", [cl.t, cl.x], [_sub_reference(d, d.signals["mu2"])]).map(T)
        mu2 = np.asarray(fm(np.reshape(t, (1, -1)), np.asarray(X, float).T)).T
    ok = (np.all(np.isfinite(Phi), axis=1) & np.all(np.isfinite(f_true), axis=1)
          & np.all(np.isfinite(mu2), axis=1) & np.all(mu2 > 0, axis=1))
    if ok.sum() == 0:
        return np.zeros((nr, n)), {"samples": 0, "norm": 0.0, "method": "no usable samples: W* = 0"}
    A, B, Wt = Phi[ok], f_true[ok], mu2[ok]
    m = A.shape[0]
    sigma = float(sc.sigma)
    k2 = np.asarray(sc.k2, dtype=float)
    W = np.zeros((nr, n))
    for i in range(n):
        w = Wt[:, i] / (2 * k2[i] * m)
        H = A.T @ (w[:, None] * A) + (sigma / 2 + 1e-12) * np.eye(nr)
        W[:, i] = np.linalg.solve(H, A.T @ (w * B[:, i]))
    res = B - A @ W
    W_ls, _, rank, sv = np.linalg.lstsq(A, B, rcond=None)
    res_ls = B - A @ W_ls
    info = {"samples": int(m), "columns": nr, "norm": float(np.linalg.norm(W)),
            "rms_residual": float(np.sqrt(np.mean(res ** 2))), "max_abs_residual": float(np.max(np.abs(res))),
            "rms_f_true": float(np.sqrt(np.mean(B ** 2))),
            "mean_delta": float(sigma / 2 * np.sum(W ** 2) + np.mean(np.sum(Wt * res ** 2 / (2 * k2), axis=1))),
            "plain_ls_norm": float(np.linalg.norm(W_ls)), "plain_ls_rms_residual": float(np.sqrt(np.mean(res_ls ** 2))),
            "plain_ls_rank": int(rank),
            "plain_ls_condition": float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf"),
            "method": ("least squares of f_true on Phi along the simulated trajectory, weighted by mu2/(2 k2) and "
                       "regularised by sigma/2 ||W||^2: the W* minimising the time-averaged corrected delta")}
    return W, info


# --- symbolic V, V_dot, rho, delta -----------------------------------------------------------------

def _sub_reference(design, e):
    ref_syms = ca.vertcat(design.sym["qd"], design.sym["dqd"], design.sym["ddqd"])
    ref_t = ca.vertcat(design.reference_t["qd"], design.reference_t["dqd"], design.reference_t["ddqd"])
    return ca.substitute(e, ref_syms, ref_t)


def claim_rho_delta(design, claim, W_star) -> tuple[ca.SX, ca.SX]:
    """A decay claim's printed rho (min over joints of its expression) and delta, as SX in the design's symbols."""
    from .audit import claim_env
    env = claim_env(design)
    env["W_star_norm2"] = float(np.sum(np.asarray(W_star, dtype=float) ** 2))
    return ca.mmin(ca.SX(claim.rho.to_casadi(env))), ca.SX(claim.delta.to_casadi(env))


def lyapunov_function(cl, W_star: np.ndarray, claim=None) -> ca.Function:
    """casadi.Function (t, x) -> V, V_dot, rho_paper, delta_paper, rho, delta, V_z, V_w, inside, scale.

    V, rho and delta are the design variant's (`Design.variant.lyapunov`) with eps = f_true - W*^T Phi of the
    closed loop; V_dot is the exact derivative along the closed-loop flow: jtimes(V, [t; x], [1; f(t, x)]).
    `inside` is 1 where both funnels hold strictly (z finite), else 0. rho_paper/delta_paper are those of a printed
    decay claim (`claim`, e.g. a paper's theorem: its constants applied to this design), NaN without one.
    """
    d = cl.design
    t, x = cl.t, cl.x
    Ws = ca.DM(np.asarray(W_star, dtype=float).reshape(d.n_regressor, d.n))
    Phi = _sub_reference(d, d.signals["Phi"])
    eps = cl.signals["f_true"] - ca.mtimes(Ws.T, Phi)
    lyap = d.variant.lyapunov(d, Ws, eps)
    L = {k: _sub_reference(d, e) for k, e in lyap.items()}
    S = {k: _sub_reference(d, d.signals[k]) for k in ("e1", "e2", "F1", "F2")}
    xdot = cl.f(t, x)
    V_dot = ca.jtimes(L["V"], ca.vertcat(t, x), ca.vertcat(ca.SX(1), xdot))
    if claim is not None:
        rho_p, delta_p = (_sub_reference(d, e) for e in claim_rho_delta(d, claim, W_star))
    else:
        rho_p, delta_p = ca.SX(np.nan), ca.SX(np.nan)
    inside = ca.logic_and(ca.mmin(S["F1"] - ca.fabs(S["e1"])) > 0, ca.mmin(S["F2"] - ca.fabs(S["e2"])) > 0)
    names = ["V", "V_dot", "rho_paper", "delta_paper", "rho", "delta", "V_z", "V_w", "inside", "scale"]
    return ca.Function("lyapunov", [t, x], [L["V"], V_dot, rho_p, delta_p, L["rho"], L["delta"], L["V_z"], L["V_w"],
                                            inside, L["scale"]], ["t", "x"], names, {"cse": True})


def evaluate_lyapunov(cl, W_star, t: np.ndarray, X: np.ndarray, claim=None) -> dict[str, np.ndarray]:
    """The outputs of `lyapunov_function` at T points (t (T,), X (T, nx)); NaN where outside a funnel."""
    f = lyapunov_function(cl, W_star, claim)
    T = int(np.size(t))
    names = [f.name_out(i) for i in range(f.n_out())]
    if T == 0:
        return {k: np.zeros(0) for k in names}
    vals = f.map(T, "serial")(np.reshape(t, (1, -1)), np.asarray(X, dtype=float).T)
    out = {k: np.asarray(v).ravel() for k, v in zip(names, vals)}
    bad = out["inside"] < 0.5
    for k in names:
        if k not in ("inside",):
            out[k] = np.where(bad, np.nan, out[k])
    return out


# --- along a trajectory ---------------------------------------------------------------------------

@dataclass
class LyapunovTrajectory:
    """V, its exact derivative and both versions of rho, delta along a simulated trajectory, with the bounds."""

    t: np.ndarray
    V: np.ndarray
    V_dot: np.ndarray
    rho_paper: np.ndarray
    delta_paper: np.ndarray
    rho: np.ndarray
    delta: np.ndarray
    V_z: np.ndarray
    V_w: np.ndarray
    scale: np.ndarray
    W_star: np.ndarray
    w_star_info: dict
    rho_const: float            # min over the trajectory of the corrected rho(t)
    rho_const_lower: float      # the constant lower bound min(2 k1 / F1(0), k2 / F2(0), sigma gamma)
    delta_max: float            # max over the trajectory of the corrected delta(t)
    rho_paper_const: float      # min over the trajectory of the paper's rho(t)
    delta_paper_const: float
    bound: np.ndarray           # V(0) e^{-rho_const t} + delta_max / rho_const (1 - e^{-rho_const t})
    bound_paper: np.ndarray
    extra: dict = field(default_factory=dict)

    def rhs(self, which: str = "corrected") -> np.ndarray:
        """-rho V + delta along the trajectory ('corrected' or 'paper')."""
        if which == "paper":
            return -self.rho_paper * self.V + self.delta_paper
        return -self.rho * self.V + self.delta


def integrated_bound(t: np.ndarray, V0: float, rho: float, delta: float) -> np.ndarray:
    """V(0) e^{-rho t} + (delta/rho)(1 - e^{-rho t}) (rho > 0), or V(0) + delta t when rho = 0."""
    t = np.asarray(t, dtype=float) - (t[0] if np.size(t) else 0.0)
    if rho > 0:
        e = np.exp(-rho * t)
        return V0 * e + (delta / rho) * (1 - e)
    return V0 + delta * t


def constant_rho_lower(design, t_final: float) -> float:
    """A constant lower bound of the design's rho over [0, t_final] (mu_i >= 1/sup F_i, sup taken on the horizon)."""
    from ..family.funnels import extremes
    sc = design.scenario
    sup1 = extremes(sc.funnels["e1"], t_final)[1]
    sup2 = extremes(sc.funnels["e2"], t_final)[1]
    return design.variant.rho_lower(sup1, sup2)


def along_trajectory(cl, t: np.ndarray, X: np.ndarray, f_true: np.ndarray, *,
                     W_star: np.ndarray | None = None, claim=None) -> LyapunovTrajectory:
    """Evaluate the Lyapunov argument along a trajectory (t (T,), X (T, nx), f_true (T, n) logged signals)."""
    if W_star is None:
        W_star, info = estimate_w_star(cl, t, X, f_true)
    else:
        info = {"method": "given", "norm": float(np.linalg.norm(W_star))}
    L = evaluate_lyapunov(cl, W_star, t, X, claim)
    with np.errstate(invalid="ignore"):
        rho_const = float(np.nanmin(L["rho"])) if np.any(np.isfinite(L["rho"])) else float("nan")
        delta_max = float(np.nanmax(L["delta"])) if np.any(np.isfinite(L["delta"])) else float("nan")
        rho_p_const = float(np.nanmin(L["rho_paper"])) if np.any(np.isfinite(L["rho_paper"])) else float("nan")
    with np.errstate(invalid="ignore"):
        delta_p = float(np.nanmax(L["delta_paper"])) if np.any(np.isfinite(L["delta_paper"])) else float("nan")
    V0 = float(L["V"][0]) if np.size(t) and np.isfinite(L["V"][0]) else float("nan")
    bound = integrated_bound(t, V0, rho_const, delta_max) if np.isfinite(rho_const) else np.full(len(t), np.nan)
    bound_p = integrated_bound(t, V0, rho_p_const, delta_p) if np.isfinite(rho_p_const) else np.full(len(t), np.nan)
    return LyapunovTrajectory(t=np.asarray(t, float), V=L["V"], V_dot=L["V_dot"], rho_paper=L["rho_paper"],
                              delta_paper=L["delta_paper"], rho=L["rho"], delta=L["delta"], V_z=L["V_z"],
                              V_w=L["V_w"], scale=L["scale"], W_star=np.asarray(W_star), w_star_info=info,
                              rho_const=rho_const, rho_const_lower=constant_rho_lower(cl.design, float(t[-1]) if np.size(t) else 0.0),
                              delta_max=delta_max, rho_paper_const=rho_p_const, delta_paper_const=delta_p,
                              bound=bound, bound_paper=bound_p,
                              extra={"atol": float(cl.scenario.simulation.atol)})


def decay_margin(V_dot, rhs, scale) -> tuple[np.ndarray, np.ndarray]:
    """(rhs - V_dot, allowance): the claim holds at a point when margin >= -allowance (round-off)."""
    margin = rhs - V_dot
    allowance = REL_TOL * (np.abs(V_dot) + np.abs(rhs) + np.nan_to_num(scale) + 1e-300)
    return margin, allowance


# --- region-wide falsification --------------------------------------------------------------------

def falsify(cl, W_star: np.ndarray, *, samples: int = 10000, seed: int = 0, w_scale: float | None = None,
            fill: float = 0.98, t_range: tuple[float, float] | None = None, claim=None) -> dict:
    """Sample states inside both funnels (scrambled Sobol) and test V_dot <= -rho V + delta at each, both versions.

    This is falsification (a search for counterexamples at sampled states), not a proof. x_esn is sampled in the
    reservoir's invariant box, W_hat within +-w_scale (default: the largest |entry| of W*, at least 1).
    """
    from ..design.sampling import funnel_states
    d = cl.design
    k = int(samples)
    rng = np.random.default_rng([seed, 7])
    if w_scale is None:
        w_scale = float(max(np.max(np.abs(W_star)) if np.size(W_star) else 0.0, 1.0))
    pts = funnel_states(d, k, rng, method="sobol", fill=fill, t_range=t_range, w_scale=w_scale)
    X = np.hstack([pts["q"].T, pts["dq"].T, *[pts["vec_" + name].T for name, _ in d.states]])
    t = pts["t"].ravel()
    L = evaluate_lyapunov(cl, W_star, t, X, claim)
    out = {"samples": k, "method": "scrambled Sobol", "fill": fill, "w_scale": w_scale,
           "t_range": list(t_range) if t_range else [0.0, float(cl.scenario.simulation.t_final)]}
    for which in ("corrected", "paper"):
        rhs = (-L["rho"] * L["V"] + L["delta"]) if which == "corrected" else \
            (-L["rho_paper"] * L["V"] + L["delta_paper"])
        margin, allow = decay_margin(L["V_dot"], rhs, L["scale"])
        finite = np.isfinite(margin)
        viol = finite & (margin < -allow)
        rel = margin / np.maximum(np.abs(L["V_dot"]) + np.abs(rhs), 1e-300)
        j = int(np.nanargmin(np.where(finite, margin, np.inf))) if finite.any() else 0
        where = {"t": float(t[j]), "q": pts["q"][:, j].tolist(), "dq": pts["dq"][:, j].tolist(),
                 "e1": (pts["q"][:, j] - pts["qd"][:, j]).tolist()}
        out[which] = {"violations": int(viol.sum()), "evaluated": int(finite.sum()),
                      "fraction": float(viol.sum() / max(finite.sum(), 1)),
                      "worst_margin": float(margin[j]) if finite.any() else None,
                      "worst_relative": float(rel[j]) if finite.any() else None,
                      "where": where, "V_dot": float(L["V_dot"][j]), "rhs": float(rhs[j]), "V": float(L["V"][j])}
        # where violations concentrate: by funnel usage |e|/F at the violating points
        if viol.any():
            F1 = np.array(d.function("F1", ["t"]).map(k)(pts["t"]))
            u1 = np.max(np.abs(pts["q"] - pts["qd"]) / F1, axis=0)
            out[which]["median_e1_usage_violating"] = float(np.median(u1[viol]))
            out[which]["median_e1_usage_all"] = float(np.median(u1))
            out[which]["t_violating_quartiles"] = np.quantile(t[viol], [0.25, 0.5, 0.75]).tolist()
    out["arrays"] = {"t": t, "V": L["V"], "V_dot": L["V_dot"], "rhs": -L["rho"] * L["V"] + L["delta"],
                     "rhs_paper": -L["rho_paper"] * L["V"] + L["delta_paper"]}
    return out

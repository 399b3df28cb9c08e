"""`certify.invariance`: the barrier closure of the Lyapunov argument, decided over a grid of margins m.

The design variant gives V, rho and delta (`variant.lyapunov(design, W*, eps)`, eps = f_true - W*^T Phi of the
true plant): along the closed loop V_dot <= -rho V + delta holds pointwise (the design identity plus Young's
inequality, docs/derivation.md). On K(m, c) = R_m x the parameter box x the reservoir's invariant box x
{||W_hat - W*||_F^2 <= 2 Gamma c}, let rho(m) = inf rho over R_m and delta(m, c) = sup delta over K(m, c). If

    (i) V(0) <= c,   (ii) delta(m, c) <= c rho(m),   (iii) |z| <= sqrt(2c) implies |e| < (1 - m) F,

then V <= c as long as the state is in K(m, c), and V <= c keeps it strictly inside K(m, c) (|e| by (iii), W_hat by
V >= ||W~||^2/(2 Gamma)): the state never leaves, the funnels are forward invariant with margin m on [0, T] for
every parameter of the box -- proven, with m and c. Rigorous bounds: rho(m) from below and delta(m, c) from above by
batched branch and bound, V(0) by interval evaluation at the initial state (box).

Refutation (the guarantee is provably vacuous): for a margin m the closure is impossible when V(0) >= c_max(m)
(the largest c that (iii) allows), or when a witness point of K(m, V(0)) has delta >= c_max(m) rho_w with rho_w the
value of rho at a point of R_m (>= its infimum): then (ii) fails for every admissible c. Witness values are
rigorous interval lower bounds at the point, re-evaluated by the ordinary CasADi Function. When every m of the grid
is refuted the certificate is refuted and says which term keeps the argument open at each m: V(0), the
sigma/2 ||W*||^2 part of delta alone, or delta's eps part.

What it rests on besides the interval bounds: the identity V_dot = the variant's target form along the plant
(`design.identity.vdot`, checked by AD at sampled states, not proven here), the scenario's W* (fitted along the
simulated run; another W* gives another certificate), x_esn(0) in the reservoir box, and the plant's exact
nonlinearities (no smoothing).
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np

from .problem import Budget, Context, RegionProblem, controller_state_boxes, improve, unknown_exprs
from .result import Certificate
from .selfcheck import check_contains
from ..sx.search import extremum

CID = "certify.invariance"
#: the margins tried: a fine linear grid of (0, 1) and a geometric one below 0.01
M_GRID = tuple(sorted(set([round(float(v), 12) for v in np.geomspace(1e-4, 1e-2, 9)] +
                          [round(0.01 * k, 12) for k in range(1, 100)])))
#: witness points sampled per margin
WITNESS_SAMPLES = 256
#: margins for which a proof is attempted (the largest plausible ones, after the refutations)
PROOF_ATTEMPTS = 4
#: a margin is plausible when its witness needs less than this fraction of the level the margin allows
PLAUSIBLE = 0.5
_SAFE = 1e-9


def z_limit(transform, u: float) -> float:
    """The z with usage(z) = u (usage is increasing): |z| < z_limit(u) means |e| < u F."""
    lo, hi = 0.0, 1.0
    while float(transform.usage(hi)) < u and hi < 1e300:
        hi *= 2.0
    for _ in range(200):
        m = 0.5 * (lo + hi)
        if float(transform.usage(m)) < u:
            lo = m
        else:
            hi = m
    return lo


def certify_invariance(ctx: Context, budget: Budget) -> Certificate:
    """certify.invariance over the grid M_GRID."""
    t0 = time.monotonic()
    d, sc = ctx.design, ctx.scenario
    n = d.n
    T = d.variant.transform
    nr = d.n_regressor
    if nr and ctx.W_star is None:
        return Certificate(CID, "undecided", "no W* (no simulated run to fit it on)", undecided_fraction=1.0,
                           seconds=time.monotonic() - t0)
    gamma, sigma = float(sc.gamma), float(sc.sigma)
    Ws = np.asarray(ctx.W_star, float) if nr else np.zeros((0, n))
    p = ca.SX.sym("p", len(ctx.params.names))
    eps = unknown_exprs(ctx, p, Ws)["eps"]
    lyap = d.variant.lyapunov(d, ca.DM(Ws) if nr else ca.DM(0, n), eps)
    w_const = sigma / 2 * float(np.sum(Ws ** 2)) if nr else 0.0

    # V(0): interval enclosure at the initial state (a box with [[uncertainty]] on initial.q / initial.dq)
    V0_lo, V0_hi, x0_note = _initial_V(ctx, lyap["V"])
    if "x_esn" in dict(d.states):
        x0 = np.asarray(sc.x_esn0, float)
        if np.any(np.abs(x0) > 1.0 / float(sc.esn.leak)):
            return Certificate(CID, "undecided", "x_esn(0) is outside the reservoir's invariant box |x| <= 1/leak",
                               undecided_fraction=1.0, seconds=time.monotonic() - t0)
    prob = RegionProblem(ctx, {"rho": lyap["rho"], "delta": lyap["delta"]}, p, "invariance")
    budget.set_tape(prob.work_per_box())
    F = prob.F
    pos_rho = F.out_off[F.out_names.index("rho")]
    pos_delta = F.out_off[F.out_names.index("delta")]
    rng = np.random.default_rng(20240519)
    base_states = controller_state_boxes(ctx, (Ws, Ws) if nr else None)
    r0 = math.sqrt(2 * gamma * max(V0_lo, 0.0)) if nr else 0.0
    rows, pending = [], []
    for m in M_GRID:
        u = 1.0 - m
        zc = z_limit(T, u)
        c_max = 0.5 * zc * zc
        row = {"m": m, "c_max": c_max}
        if np.isfinite(V0_lo) and V0_lo >= c_max * (1 + _SAFE):     # a refutation needs a finite value
            row.update(refuted=True, reason="V(0)", V0=V0_lo)
            rows.append(row)
            continue
        # witnesses in K(m, V(0)): W_hat within the V(0) ball (a box inside it), states in their boxes
        states = dict(base_states)
        if nr:
            h = r0 / math.sqrt(Ws.size) * (1 - 1e-9)
            states["w_hat"] = (Ws - h, Ws + h)
        lo, hi = prob.flat(prob.region(m, states))
        X = _samples(prob, lo, hi, rng)
        vals = F.eval_points(X)
        rho_pts = vals[:, pos_rho]
        delta_pts = vals[:, pos_delta]
        k = int(np.nanargmax(np.where(np.isfinite(delta_pts), delta_pts, -np.inf)))
        x, best = improve(prob.function, X[k], lo, hi, pos_delta, 1.0, iterations=25)
        j = int(np.nanargmin(np.where(np.isfinite(rho_pts), rho_pts, np.inf)))
        pending.append((row, x, X[j]))
        rows.append(row)
    # rigorous values at the witnesses: delta from below, rho (at the witness and the sampled points) from above;
    # all margins' points in one batch (the tape's cost per call is its length, nearly whatever the batch)
    if pending:
        P = np.array([v for _, x, xj in pending for v in (x, xj)])
        L, H, _ = F.natural.eval_batch(P, P)
        D = F.eval_points(P)                   # the same Function in double (plain CasADi), for the self-check
    for i, (row, x, xj) in enumerate(pending):
        for r_, pt in ((2 * i, x), (2 * i + 1, xj)):        # self-check: each point enclosure holds its value
            for name_, pos in (("rho", pos_rho), ("delta", pos_delta)):
                check_contains(f"{name_} at a witness of m = {row['m']:g}", float(L[r_, pos]), float(H[r_, pos]),
                               D[r_, pos], pt, slack=float(H[r_, pos] - L[r_, pos]))
        delta_w = float(L[2 * i, pos_delta])
        rho_w = float(min(H[2 * i + 1, pos_rho], H[2 * i, pos_rho]))
        c_max = row["c_max"]
        row.update(delta_witness=delta_w, rho_witness=rho_w, witness=x)
        if np.isfinite(delta_w) and np.isfinite(rho_w) and rho_w > 0 and delta_w >= c_max * rho_w * (1 + _SAFE):
            reason = "sigma" if w_const >= c_max * rho_w * (1 + _SAFE) else "eps"
            row.update(refuted=True, reason=reason)
        else:
            row.update(refuted=False, ratio=(max(V0_hi, delta_w / rho_w) / c_max) if rho_w > 0 else np.inf)
    # proofs are tried at the largest open margins first (the most informative guarantee), among those whose
    # witness does not already come close to refuting them
    open_rows = sorted([r for r in rows if not r["refuted"]], key=lambda r: (r["ratio"] >= PLAUSIBLE, -r["m"]))
    summary = _summary(rows)
    region = {"t": [0.0, float(ctx.t_final)], "margins": [float(M_GRID[0]), float(M_GRID[-1])],
              "grid": len(M_GRID), "parameters": ctx.params.describe(),
              "x_esn": "the reservoir's invariant box |x_i| <= 1/leak" if "x_esn" in dict(d.states) else None,
              "w_hat": "||W_hat - W*||_F^2 <= 2 Gamma c" if nr else None}
    extra = {"V0": [V0_lo, V0_hi], "W_star_norm": float(np.linalg.norm(Ws)) if nr else 0.0,
             "sigma_W_star_term": w_const, "margins": summary, "initial": x0_note,
             "W_star": ctx.w_star_info.get("method") if nr else None}
    boxes = 0
    # proofs: the most promising open margins
    for row in open_rows[:PROOF_ATTEMPTS]:
        if budget.expired() or budget.boxes <= 0:
            break
        res = _prove_at(ctx, prob, row["m"], row["c_max"], V0_hi, base_states, Ws, gamma, budget, pos_rho,
                        pos_delta)
        boxes += res.pop("boxes")
        row.update(res)
        if res.get("proven"):
            m, c = row["m"], res["c"]
            extra.update(m=m, c=c, rho=res["rho"], delta=res["delta"], w_hat_radius=res.get("w_hat_radius"))
            usage = float(T.usage(math.sqrt(2 * c)))
            return Certificate(CID, "proven", f"the funnels are forward invariant with margin m = {m:g} for every "
                               f"parameter of the box: c = max(V(0), delta/rho) = {c:.4g} (V(0) <= {V0_hi:.4g}, "
                               f"delta <= {res['delta']:.4g}, rho >= {res['rho']:.4g}) gives |e| <= {usage:.4g} F "
                               f"< (1 - m) F", lower=m, region=region, boxes=boxes, seconds=time.monotonic() - t0,
                               method=_METHOD, extra=extra)
    if not open_rows:
        closest = max(rows, key=lambda r: r["c_max"] / max(_needed(r, V0_lo), 1e-300))
        ce = prob.counterexample(prob.point(closest["witness"])) if "witness" in closest else \
            {"t": 0.0, "q": list(map(float, sc.q0)), "dq": list(map(float, sc.dq0)), "initial_state": True}
        ce["m"] = closest["m"]
        if "witness" in closest:
            ce["delta"] = float(prob.ordinary_values(prob.point(closest["witness"]))["delta"][0])
        extra["closest_margin"] = {k: v for k, v in closest.items() if k != "witness"}
        return Certificate(CID, "refuted", "no margin m of the grid closes the barrier argument: the theorem's "
                           f"guarantee is provably vacuous for this design ({_reasons(summary)})",
                           counterexample=ce, region=region, boxes=boxes, seconds=time.monotonic() - t0,
                           method=_METHOD, extra=extra)
    left = [r["m"] for r in open_rows]
    return Certificate(CID, "undecided", f"{len(left)} margin(s) of the grid neither refuted nor proven within the "
                       f"budget (m = {', '.join(f'{v:g}' for v in left[:6])}{', ...' if len(left) > 6 else ''}); "
                       f"refuted elsewhere ({_reasons(summary)})", region=region, boxes=boxes,
                       undecided_fraction=len(left) / len(M_GRID), seconds=time.monotonic() - t0, method=_METHOD,
                       extra=extra)


_METHOD = ("barrier closure over a grid of margins: rigorous inf rho / sup delta by batched branch and bound, "
           "refutations by rigorous witness values")


def _needed(row, V0_lo):
    if row.get("reason") == "V(0)":
        return V0_lo
    rw = row.get("rho_witness") or 0.0
    return row.get("delta_witness", 0.0) / rw if rw > 0 else math.inf


def _samples(prob, lo, hi, rng) -> np.ndarray:
    """Witness candidates: random points of the flat box, half of them with e2 on the region's edge (|s2| = 1)."""
    K = WITNESS_SAMPLES
    X = lo + rng.random((K, lo.size)) * (hi - lo)
    F = prob.F
    i = F.in_names.index("s2")
    sl = slice(F.in_off[i], F.in_off[i + 1])
    X[: K // 2, sl] = np.sign(X[: K // 2, sl] - 0.5 * (lo[sl] + hi[sl]) + 1e-300) * hi[sl]
    X[0] = np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
    return np.clip(X, lo, hi)


def _initial_V(ctx, V) -> tuple[float, float, str]:
    """Rigorous (lo, hi) of V at the initial state (its box under initial-state uncertainty)."""
    from ..sx.batch import BatchIntervalFunction
    d, sc = ctx.design, ctx.scenario
    names = ["t", "q", "dq", "qd", "dqd", "ddqd", *[k for k, _ in d.states]]
    f = ca.Function("V0", [d.sym[k] for k in names], [V], names, ["V"])
    F = BatchIntervalFunction(f)
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(0.0))
    init = d.variant.initial_states()
    q0 = ctx.params.q0 or (np.asarray(sc.q0, float), np.asarray(sc.q0, float))
    dq0 = ctx.params.dq0 or (np.asarray(sc.dq0, float), np.asarray(sc.dq0, float))
    box = {"t": (0.0, 0.0), "q": q0, "dq": dq0, "qd": (qd, qd), "dqd": (dqd, dqd), "ddqd": (ddqd, ddqd)}
    for k, _ in d.states:
        box[k] = (init[k], init[k])
    lo, hi = (np.asarray(v, float) for v in F.flatten_box({k: box[k] for k in names}))
    note = "the scenario's initial state" if np.all(lo == hi) else "the [[uncertainty]] box of the initial state"
    if np.all(lo == hi):
        L, H, _ = F.eval_batch(lo[None, :], hi[None, :])
        check_contains("V(0)", float(L[0, 0]), float(H[0, 0]), float(f(*[box[k][0] for k in names])), None,
                       slack=float(H[0, 0] - L[0, 0]))      # the ordinary Function at x0
        return float(L[0, 0]), float(H[0, 0]), note
    split = np.flatnonzero(lo < hi)
    top = extremum(F, lo, hi, split, 0, -1.0, max_boxes=2000, rel_tol=1e-3)
    bot = extremum(F, lo, hi, split, 0, 1.0, max_boxes=2000, rel_tol=1e-3)
    return float(bot.bound), float(-top.bound), note


def _prove_at(ctx, prob, m, c_max, V0_hi, base_states, Ws, gamma, budget, pos_rho, pos_delta) -> dict:
    """Try to close the argument at margin m: rho from below, then delta(m, c) from above for growing c."""
    F = prob.F
    nr = ctx.design.n_regressor
    T = ctx.design.variant.transform
    lo, hi = prob.flat(prob.region(m, base_states))
    split = prob.split_indices(lo, hi)
    share = max(64, budget.boxes // 4)
    ex = extremum(F, lo, hi, split, pos_rho, 1.0, max_boxes=share, seconds=budget.seconds(0.25), rel_tol=1e-3,
                  initial=prob.initial_boxes(lo, hi))
    boxes = ex.boxes
    rho = float(ex.bound)
    check_contains(f"rho at m = {m:g}", rho, None, F.eval_points(ex.argbest[None, :])[0, pos_rho], ex.argbest,
                   slack=_point_width(F, ex.argbest, pos_rho))
    out = {"rho": rho, "proven": False}
    if not rho > 0:
        budget.boxes -= boxes
        return {**out, "boxes": boxes}
    c = max(V0_hi, 1e-300)
    for _ in range(6):
        states = dict(base_states)
        if nr:
            r = math.sqrt(2 * gamma * c) * (1 + 1e-9)
            states["w_hat"] = (Ws - r, Ws + r)
        lo, hi = prob.flat(prob.region(m, states))
        # the search decides (2), it does not tighten delta: a gap below 1 % of the largest delta that could
        # still close at this margin (c_max rho) ends it (a delta near 0 never meets a relative tolerance)
        ex = extremum(F, lo, hi, split, pos_delta, -1.0, max_boxes=share, seconds=budget.seconds(0.25),
                      rel_tol=1e-2, abs_tol=1e-2 * c_max * rho, initial=prob.initial_boxes(lo, hi))
        boxes += ex.boxes
        delta = -float(ex.bound)
        check_contains(f"delta at m = {m:g}", None, delta, F.eval_points(ex.argbest[None, :])[0, pos_delta],
                       ex.argbest, slack=_point_width(F, ex.argbest, pos_delta))
        if not np.isfinite(delta):
            break
        need = max(V0_hi, math.nextafter(delta / rho, math.inf))
        if not nr:                      # delta does not depend on c: c = need satisfies (i) and (ii)
            c = need
        if need <= c:
            usage = float(T.usage(math.sqrt(2 * c) * (1 + _SAFE)))
            if usage < (1 - m) * (1 - _SAFE):
                budget.boxes -= boxes
                return {**out, "proven": True, "c": c, "delta": delta, "boxes": boxes,
                        "w_hat_radius": math.sqrt(2 * gamma * c) * (1 + 1e-9) if nr else None}
            break
        if need > c_max:
            break
        c = min(need * 1.05, c_max)
    budget.boxes -= boxes
    return {**out, "boxes": boxes}


def _point_width(F, x: np.ndarray, pos: int) -> float:
    """Width of the interval evaluation at the point x (the scale of the double value's round-off there)."""
    L, H, _ = F.natural.eval_batch(x[None, :], x[None, :])
    return float(H[0, pos] - L[0, pos])


def _summary(rows) -> list[dict]:
    """Runs of consecutive margins with the same outcome: [{"m": [first, last], "outcome"}]."""
    out = []
    for r in rows:
        key = r["reason"] if r.get("refuted") else "open"
        if out and out[-1]["outcome"] == key:
            out[-1]["m"][1] = r["m"]
        else:
            out.append({"m": [r["m"], r["m"]], "outcome": key})
    return out


_WHY = {"V(0)": "V(0) alone exceeds the level the margin allows", "sigma": "the sigma/2 ||W*||^2 part of delta alone",
        "eps": "delta's eps part", "open": "open"}


def _reasons(summary) -> str:
    return "; ".join(f"m in [{s['m'][0]:g}, {s['m'][1]:g}]: {_WHY[s['outcome']]}" for s in summary)

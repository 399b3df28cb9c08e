"""`certify.bounds`: rigorous enclosures of mu2, the torque tau and eps = f_true - W*^T Phi over the funnel region,
and the saturation verdict against `tau_max`.

The region is R_m (|e_i| <= (1 - m) F_i, t in [0, T]) x the parameter box x the controller-state boxes: m and the
W_hat box are the invariance certificate's when it is proven (then the enclosures hold along every trajectory of the
closed loop), else m = BOUNDS_MARGIN and W_hat in the range it took along the simulated run, widened by that range's
own width on each side (then the enclosures are proven for every state of that box, and the box is only as good as
one simulated run). x_esn lies in its invariant box |x_i| <= 1/leak (a theorem for the tanh reservoir).

Per signal and joint, `sx.branch.rigorous_range` (best-first on each bound, mean-value form in t, s, p) gives a
rigorous [lo, hi] and the attained [lo_seen, hi_seen]; the torque's extremes are improved by a local search over
every input (states included) and re-evaluated by the ordinary CasADi Function of the design. With `tau_max`:
proven when the rigorous max|tau_j| < tau_max_j on every joint (saturation provably inactive on the region), refuted
when |tau_j(0, x0)| >= tau_max_j at the initial state (on every trajectory) or when an attained |tau_j| >= tau_max_j
inside the set the invariance certificate proves (R_m with the W_hat *ball*, not its bounding box: a box witness is
moved into the ball and re-evaluated; the state is the counterexample), undecided in between -- and undecided when such a state lies in the stand-in
region R_BOUNDS_MARGIN, which the loop is not shown to stay in (the state is kept as `witness`).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from .problem import Budget, Context, RegionProblem, controller_state_boxes, improve, unknown_exprs
from ..sx.search import extrema
from .result import Certificate
from .selfcheck import check_contains

CID = "certify.bounds"
#: the margin m of the region when no invariance certificate gives one: |e| <= 0.95 F
BOUNDS_MARGIN = 0.05
#: relative tolerance of each range search (the gap lo_seen - lo it stops at)
RANGE_REL_TOL = 1e-2


def w_hat_box(ctx: Context) -> tuple[tuple[np.ndarray, np.ndarray] | None, str]:
    """The W_hat box of the bounds region and where it comes from."""
    from .containment import proven_set
    S = proven_set(ctx)
    inv = ctx.results.get("certify.invariance")
    if S is not None and S["w"] is not None and not (inv is not None and inv.status == "proven"):
        w = float(S["w"])
        W = np.zeros_like(np.asarray(ctx.design.variant.initial_states()["w_hat"], float))
        return (W - w, W + w), f"the containment certificate's ball ||W_hat||_F <= {w:.4g} (proven for the closed loop)"
    if inv is not None and inv.status == "proven" and "w_hat_radius" in inv.extra:
        r = float(inv.extra["w_hat_radius"])
        W = np.asarray(ctx.W_star, float)
        return (W - r, W + r), (f"the invariance certificate's ball ||W_hat - W*||_F <= {r:.4g} (proven for the "
                                "closed loop)")
    if ctx.w_hat_range is None:
        return None, "no simulated run to take a W_hat box from"
    lo, hi = ctx.w_hat_range
    width = np.maximum(hi - lo, 1e-3 * (1 + np.maximum(np.abs(lo), np.abs(hi))))
    return (lo - width, hi + width), ("the range W_hat took along the simulated run, widened by its own width on "
                                      "each side (a box from one run: the enclosures hold for every W_hat in it)")


def initial_saturation(ctx: Context, tau_max: np.ndarray) -> dict | None:
    """The initial state's counterexample when |tau_j(0, x0)| >= tau_max_j (by the design's ordinary CasADi Function
    at t = 0, the scenario's q0, dq0 and the controller's initial states: a state on every trajectory), else None.
    Under an initial-state [[uncertainty]] box the scenario's own q0/dq0 is used only when it lies in the box."""
    d, sc = ctx.design, ctx.scenario
    q0, dq0 = np.asarray(sc.q0, float), np.asarray(sc.dq0, float)
    for v, box in ((q0, ctx.params.q0), (dq0, ctx.params.dq0)):
        if box is not None and not (np.all(box[0] <= v) and np.all(v <= box[1])):
            return None
    names = [k for k, _ in d.states]
    f = d.function("tau", ["t", "q", "dq", "qd", "dqd", "ddqd", *names])
    init = d.variant.initial_states()
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(0.0))
    tau = np.asarray(f(0.0, q0, dq0, qd, dqd, ddqd, *[init[k] for k in names]), float).ravel()
    over = np.flatnonzero(np.isfinite(tau) & (np.abs(tau) >= tau_max))
    if not over.size:
        return None
    return {"t": 0.0, "q": q0.tolist(), "dq": dq0.tolist(), "initial_state": True, "tau": tau.tolist(),
            "joint": int(over[0])}


def _into_ball(point: dict, W: np.ndarray, r: float) -> tuple[dict, float | None]:
    """The region point with W_hat moved radially into the ball ||W_hat - W*||_F <= r (the set the invariance
    certificate proves; the search ran on its bounding box), and the distance it was moved from (None: inside)."""
    Wh = np.asarray(point["w_hat"], float).reshape(W.shape)
    dist = float(np.linalg.norm(Wh - W))
    if dist <= r:
        return point, None
    out = dict(point)
    out["w_hat"] = (W + (Wh - W) * (r / dist) * (1 - 1e-12)).reshape(np.shape(point["w_hat"]))
    return out, dist


def certify_bounds(ctx: Context, budget: Budget) -> Certificate:
    """certify.bounds on the scenario's region."""
    t0 = time.monotonic()
    d, sc = ctx.design, ctx.scenario
    n = d.n
    from .containment import proven_set
    inv = ctx.results.get("certify.invariance")
    # the smaller proven set: the invariance certificate's R_m when proven, else the containment certificate's S
    S = None if (inv is not None and inv.status == "proven") else proven_set(ctx)
    invariant = S is not None or (inv is not None and inv.status == "proven")   # the loop stays in the region
    if S is not None:
        m, m_source = min(S["m1"], S["m2"]), "the set certify.containment proves invariant"
    elif invariant:
        m, m_source = float(inv.extra["m"]), "the margin the invariance certificate proves"
    else:
        m, m_source = BOUNDS_MARGIN, "a stand-in margin: no certificate proves a set the loop stays in"
    states = {}
    w_source = None
    tau_max = None
    if sc.implementation is not None and sc.implementation.tau_max is not None:
        tau_max = np.broadcast_to(np.asarray(sc.implementation.tau_max, float), (n,))
        ce0 = initial_saturation(ctx, tau_max)
        if ce0 is not None:          # decided without a search: the initial state is on every trajectory
            j = ce0.pop("joint")
            return Certificate(CID, "refuted", f"|tau_{j + 1}| = {abs(ce0['tau'][j]):.6g} >= tau_max = "
                               f"{tau_max[j]:g} at the initial state (t = 0, on every trajectory): saturation is "
                               "active", counterexample=ce0, undecided_fraction=0.0, lower=abs(ce0["tau"][j]),
                               method="the design's tau at the initial state (ordinary CasADi Function)",
                               extra={"tau_max": tau_max.tolist()}, seconds=time.monotonic() - t0)
    ball = None         # (centre, r): the proven W_hat ball (the box searched is its bounding box)
    if S is not None and S["w"] is not None and d.n_regressor:
        ball = (np.zeros_like(np.asarray(d.variant.initial_states()["w_hat"], float)), float(S["w"]))
    elif invariant and d.n_regressor and "w_hat_radius" in inv.extra and ctx.W_star is not None:
        ball = (np.asarray(ctx.W_star, float), float(inv.extra["w_hat_radius"]))
    if d.n_regressor:
        wb, w_source = w_hat_box(ctx)
        if wb is None or ctx.W_star is None:
            return Certificate(CID, "undecided", f"no W_hat box or W*: {w_source}", method="interval range search",
                               seconds=time.monotonic() - t0, undecided_fraction=1.0)
        states = controller_state_boxes(ctx, wb)
    else:
        states = controller_state_boxes(ctx, None)
    p = ca.SX.sym("p", len(ctx.params.names))
    exprs = {"mu2": d.signals["mu2"], "tau": d.signals["tau"]}
    # eps is a function of the state (t, q, dq, p, W_hat) only without a reservoir: an ESN's eps also depends on
    # x_esn, whose box makes its enclosure meaningless (certify.invariance bounds it over that box where it needs it)
    with_eps = "x_esn" not in dict(d.states)
    if with_eps:
        exprs["eps"] = unknown_exprs(ctx, p, ctx.W_star)["eps"]
    prob = RegionProblem(ctx, exprs, p, "bounds")
    budget.set_tape(prob.work_per_box())
    region = prob.region(m, states)
    if S is not None:                   # S: |e_i| <= (1 - m_i) F_i, one margin per funnel (m = 0, s_i scaled)
        region = prob.region(0.0, states)
        for key, mi in (("s1", S["m1"]), ("s2", S["m2"])):
            region[key] = (-(1 - mi) * np.ones(n), (1 - mi) * np.ones(n))
    F = prob.F
    lo, hi = prob.flat(region)
    split = prob.split_indices(lo, hi)
    first = prob.initial_boxes(lo, hi)
    searches = [(k, j, sgn) for k in exprs for j in range(n) for sgn in (1.0, -1.0)]
    objectives = []
    for k, j, sgn in searches:
        objectives.append((F.out_off[F.out_names.index(k)] + list(F.out_nz[F.out_names.index(k)]).index(j), sgn))
    found = extrema(F, lo, hi, split, objectives, max_boxes=budget.boxes, seconds=budget.seconds(),
                    rel_tol=RANGE_REL_TOL, initial=first)
    boxes = found[0].boxes if found else 0
    encl: dict = {}
    witness = {}
    for (k, j, sgn), (pos, _), ex in zip(searches, objectives, found):
        x, best = ex.argbest, ex.best
        if k == "tau":                          # the torque's extremes: improved over every input, states included
            x2, b2 = improve(prob.function, x, lo, hi, pos, -sgn)
            if np.isfinite(b2) and -b2 < best:
                x, best = x2, -b2
        e = encl.setdefault(k, [dict() for _ in range(n)])[j]
        side = "lo" if sgn > 0 else "hi"
        e[side] = sgn * ex.bound               # min of sgn*g >= bound: g >= bound (sgn 1), g <= -bound (sgn -1)
        e[side + "_seen"] = sgn * best
        e["converged"] = e.get("converged", True) and ex.converged
        witness[(k, j, side)] = x
    # self-check: each enclosure contains the double value (plain CasADi evaluation of the region Function) at each
    # of its own witnesses
    keys = list(witness)
    Xw = np.array([witness[key] for key in keys])
    vals = F.eval_points(Xw)
    PL, PH, _ = F.natural.eval_batch(Xw, Xw)           # the tape at the point: the double value's round-off scale
    for i, ((k, j, side), v) in enumerate(zip(keys, vals)):
        e = encl[k][j]
        pos = F.out_off[F.out_names.index(k)] + list(F.out_nz[F.out_names.index(k)]).index(j)
        check_contains(f"{k}[{j + 1}] on the bounds region", e["lo"], e["hi"], v[pos], witness[(k, j, side)],
                       slack=PH[i, pos] - PL[i, pos])
    moved = []
    if ball is not None:
        # the search ran on the ball's bounding box: each torque witness is moved radially into the ball (the set
        # the invariance certificate proves) and its attained value is the ordinary Function's there
        for j in range(n):
            for side in ("lo", "hi"):
                point, dist = _into_ball(prob.point(witness[("tau", j, side)]), *ball)
                if dist is None:
                    continue
                v = float(prob.ordinary_values(point)["tau"][j])
                witness[("tau", j, side)] = prob.F.flatten_point(point)
                encl["tau"][j][side + "_seen"] = v
                moved.append(f"tau_{j + 1} {side} (||W_hat - W*|| = {dist:.4g} > {ball[1]:.4g})")
    finite = all(np.isfinite(e["lo"]) and np.isfinite(e["hi"]) for v in encl.values() for e in v)
    tau = encl["tau"]
    abs_hi = [max(abs(e["lo"]), abs(e["hi"])) for e in tau]
    abs_seen = [max(abs(e["lo_seen"]), abs(e["hi_seen"])) for e in tau]
    region_info = {"kind": "proven_invariant" if invariant else "stand_in",   # whether the loop stays in it
                   "t": [0.0, float(ctx.t_final)], "margin": m, "margin_source": m_source,
                   "e1": f"|e1| <= (1 - {S['m1'] if S else m:g}) F1(t)",
                   "e2": f"|e2| <= (1 - {S['m2'] if S else m:g}) F2(t)",
                   "parameters": ctx.params.describe()}
    for name, (lo_, hi_) in states.items():
        region_info[name] = {"lo": float(np.min(lo_)), "hi": float(np.max(hi_)), "shape": list(np.shape(lo_))}
    if w_source:
        region_info["w_hat"]["source"] = w_source
    if "x_esn" in states:
        region_info["x_esn"]["source"] = "the tanh reservoir's invariant box |x_i| <= 1/leak"
    extra = {"enclosures": encl, "tau_max": None if tau_max is None else tau_max.tolist(),
             "eps": "enclosed" if with_eps else "not enclosed: the ESN's eps depends on the reservoir state x_esn",
             "max_abs_tau": {"lower": abs_seen, "upper": abs_hi}}
    if moved:
        extra["witnesses_moved_into_the_ball"] = moved
    text = "; ".join(f"{k}: " + ", ".join(f"[{e['lo']:.4g}, {e['hi']:.4g}]" for e in v) for k, v in encl.items())
    where = "the proven set S" if S is not None else f"the funnel region |e_i| <= (1 - {m:g}) F_i"
    head = f"on {where} ({m_source}) x the parameter box x the state boxes: {text}"
    common = dict(region=region_info, boxes=boxes, seconds=time.monotonic() - t0,
                  method="interval range search (best-first, mean-value form in t, s, p; states as boxes)",
                  extra=extra, lower=float(max(abs_seen)), upper=float(max(abs_hi)))
    if tau_max is not None:
        for j in range(n):
            if abs_seen[j] >= tau_max[j]:
                side = "hi" if abs(tau[j]["hi_seen"]) >= abs(tau[j]["lo_seen"]) else "lo"
                point = prob.point(witness[("tau", j, side)])
                vals = prob.ordinary_values(point)["tau"]
                if not np.all(np.isfinite(vals)):
                    extra["witness_note"] = (f"the witness of |tau_{j + 1}| evaluates to {vals[j]!r} in double: "
                                             "a refutation needs a finite value")
                    continue
                if abs(vals[j]) >= tau_max[j]:
                    ce = prob.counterexample(point)
                    ce["tau"] = vals.tolist()
                    if not invariant:
                        # R_m is then a stand-in (m = BOUNDS_MARGIN, W_hat from one run): the closed loop is not
                        # shown to stay in it, so a saturating state there is no counterexample of the design --
                        # on these designs |tau| near the funnel boundary is always enormous (docs/certify.md);
                        # saturation is neither excluded nor shown reachable (the sampled loop's
                        # implementation.saturation measures it along the run)
                        extra["witness"] = ce
                        return Certificate(CID, "undecided", f"saturation not excluded: |tau_{j + 1}| = "
                                           f"{abs(vals[j]):.6g} >= tau_max = {tau_max[j]:g} at a state of the "
                                           f"funnel region with margin {m:g}, "
                                           "a region the closed loop is not proven to stay in (no invariance "
                                           "certificate), so no counterexample of the loop; " + head,
                                           undecided_fraction=1.0, **common)
                    return Certificate(CID, "refuted", f"|tau_{j + 1}| = {abs(vals[j]):.6g} >= tau_max = "
                                       f"{tau_max[j]:g} inside the funnels (saturation can be active); " + head,
                                       counterexample=ce, undecided_fraction=0.0, **common)
        if finite and all(abs_hi[j] < tau_max[j] for j in range(n)):
            return Certificate(CID, "proven", f"max |tau_j| <= {', '.join(f'{v:.4g}' for v in abs_hi)} < tau_max: "
                               "saturation is provably inactive on the region; " + head, **common)
        return Certificate(CID, "undecided", f"tau_max lies between the attained and the rigorous max |tau| "
                           f"({', '.join(f'[{a:.4g}, {b:.4g}]' for a, b in zip(abs_seen, abs_hi))}); " + head,
                           undecided_fraction=1.0, **common)
    if finite:
        return Certificate(CID, "proven", "finite enclosures (no tau_max to compare with); " + head, **common)
    bad = [f"{k}[{j + 1}]" for k, v in encl.items() for j, e in enumerate(v)
           if not (np.isfinite(e["lo"]) and np.isfinite(e["hi"]))]
    return Certificate(CID, "undecided", f"no finite enclosure of {', '.join(bad)} within the budget; " + head,
                       undecided_fraction=1.0, **common)

"""The proven sample rate: bisection in the period over `sampled.prove_period`, the theory's reach-time bound with
rigorous constants, and `rate --certify`'s bracket with the simulated rate (docs/certify.md, certify.sampled).

Proven at h is proven at every h' <= h (`sampled`'s module doc), so the lowest proven rate of the bisection,
f_proven, is a rate above which the sampled loop provably keeps the funnels from S.
"""

from __future__ import annotations

import functools
import math
import time

import numpy as np

from ..core import deadline
from .problem import Budget, Context
from .result import Certificate
from .sampled import CID, DEFAULT_SET_MARGIN, OnePeriod, SampledSet, containment_set, declared_set, prove_period
from .sampled_floor import set_floor
from .sampled_set import normalised_errors


#: the highest rate tried (the simulated search's ceiling)
MAX_RATE_HZ = 1e6
#: the bracket [not proven, proven] ends below this ratio
RATE_REL_TOL = 0.1
#: a budget-ended search warm-starts the next (shorter period) one when its queue is at most 1/WARM_QUEUE of the
#: box budget
WARM_QUEUE = 4
#: the work budget of certify.containment when certify.sampled computes it (its budget in `certify`)
CONTAINMENT_WORK = 1.5e8
#: the share of a wall-clock limit certify.containment may use when certify.sampled computes it
CONTAINMENT_SHARE = 0.4
#: boxes per period h tried (a deterministic budget; --wall-limit can only end a search earlier)
BOXES_PER_RATE = 40000
#: a budget over the whole bracket (`sampled_bracket(budget_owner=...)`, the report's): the rate search's proof
#: attempts end at this share of it, the theory bound at THEORY_BY, and the sampled run at f_proven has the rest
SEARCH_BY = 0.6
THEORY_BY = 0.85
#: the steps of the bracket, named for a wall-clock limit reached inside them (core.deadline.step)
STEP_SET = "choosing the set S (certify.containment)"
STEP_MAP = "building the one-period map"
STEP_FLOOR = "checking S's floor"
STEP_SEARCH = "searching the proven rate"
STEP_THEORY = "bounding the theory's rate"
STEP_CHECK = "running the sampled loop at f_proven"
STEPS = (STEP_SET, STEP_MAP, STEP_FLOOR, STEP_SEARCH, STEP_THEORY, STEP_CHECK)


class _Cut(BaseException):
    """A budget's deadline reached while doing `step` (a BaseException, so no `except Exception` swallows it)."""

    def __init__(self, step: str):
        self.step = step
        super().__init__(step)


class _TheoryCut(_Cut):
    """The theory bound's own share ran out (not the whole budget's)."""


def _cut_at_first_step(cls=_Cut):
    """deadline.limit's on_expiry: a `cls` naming the bracket's step (STEPS) the expiry was first found in, with the
    innermost step inside it (the alarm's handler makes it there; a re-raise after a swallowed alarm, outside that
    step, keeps the first step)."""
    seen: list[str] = []

    def make() -> _Cut:
        if not seen:
            mine = [s for s in deadline.current_steps() if s in STEPS]
            inner = deadline.current_step()
            step = mine[-1] if mine else "setting up the bracket"
            seen.append(step if inner == step or not mine else f"{step} ({inner})")
        return cls(seen[0])
    return make


def initial_in_set(ctx: Context, S: SampledSet) -> tuple[bool, list]:
    """Whether the scenario's initial state (t = 0) lies in S, and its normalised errors e/F."""
    d, sc = ctx.design, ctx.scenario
    sig = normalised_errors(d)(0.0, sc.q0, sc.dq0)
    inside = bool(np.all(np.abs(sig[:d.n]) <= 1 - S.m1) and np.all(np.abs(sig[d.n:]) <= 1 - S.m2))
    if ctx.params.q0 is not None or ctx.params.dq0 is not None:
        inside = False              # an initial-state box: not checked here (the detail says so)
    return inside, sig.tolist()


def theory_rate(op: OnePeriod, S: SampledSet, M: float, t_final: float, max_boxes: int = 3000) -> dict:
    """The sampled-data funnel literature's intersample reach-time bound with rigorous constants: from a sample
    state in S (margins m_i) the normalised error sigma_i needs at least (m_i - M) / L_i to reach the margin M, where
    L_i = sup |sigma_i'| over the funnel set |sigma| <= 1 - M, the parameter box and every torque the step outputs on
    S; h_theory = min_i (m_i - M) / L_i. Null when some m_i <= M or an L_i has no finite bound."""
    from ..sx.search import extrema
    n = op.n
    gaps = np.concatenate([np.full(n, S.m1 - M), np.full(n, S.m2 - M)])
    if np.any(gaps <= 0):
        return {"rate_hz": None, "reason": f"S's margins ({S.m1:g}, {S.m2:g}) leave no gap above the rate's margin "
                                           f"M = {M:g}"}
    lo, hi = op.box(t_final)
    FL, FH = op._full(lo[None, :], hi[None, :])
    split = op.split_vars(lo, hi)
    F = op.tau
    objs = [(j, s) for j in range(n) for s in (1.0, -1.0)]
    ex = extrema(F, FL[0], FH[0], split, objs, max_boxes=max_boxes, rel_tol=0.05)
    ulo = np.array([ex[2 * j].bound for j in range(n)])
    uhi = np.array([-ex[2 * j + 1].bound for j in range(n)])
    if not (np.all(np.isfinite(ulo)) and np.all(np.isfinite(uhi))):
        return {"rate_hz": None, "reason": "the step's torque over S has no finite enclosure"}
    lim = 1.0 - M
    # the rate function over [0, T] x |sigma| <= 1 - M x p x U x states
    P = op.ctx.params
    rl = np.concatenate([[0.0], np.full(2 * n, -lim), [0.0], P.lo[op.wide], ulo, op.st_lo])
    rh = np.concatenate([[float(t_final)], np.full(2 * n, lim), [0.0], P.hi[op.wide], uhi, op.st_hi])
    rsplit = np.array([j for j in range(rl.size) if j != 2 * n + 1 and j < op.i_st + n and rl[j] < rh[j]], dtype=int)
    objs = [(i, s) for i in range(2 * n) for s in (1.0, -1.0)]
    er = extrema(op.rate, rl, rh, rsplit, objs, max_boxes=max_boxes, rel_tol=0.05)
    L = np.array([max(-er[2 * i].bound, -er[2 * i + 1].bound) for i in range(2 * n)])
    if not np.all(np.isfinite(L)):
        return {"rate_hz": None, "reason": "sup |sigma'| over the funnel set has no finite bound within the budget"}
    with np.errstate(divide="ignore"):
        hs = np.where(L > 0, gaps / L, np.inf)
    h = float(np.min(hs))
    return {"rate_hz": None if not np.isfinite(h) or h <= 0 else float(np.nextafter(1.0 / h, np.inf)),
            "L": L.tolist(), "gaps": gaps.tolist(), "tau_range": [ulo.tolist(), uhi.tolist()],
            "binding": int(np.argmin(hs)), "converged": bool(all(e.converged for e in er))}


def choose_set(ctx: Context, budget: Budget, margin: float, set_margin=None) -> tuple[SampledSet, dict]:
    """S for certify.sampled: `set_margin` (E1, E2) declares it; else the set a proven `certify.containment`
    shows invariant (computed here when this context has not computed it), else the declared default margins.
    Returns S and a record of the choice ({"source", "containment": status, margins and W_hat radius})."""
    if set_margin is not None:
        return declared_set(ctx, float(set_margin[0]), float(set_margin[1])), {"source": "--set-margin"}
    from .containment import CID as CONTAINMENT, certify_containment
    c = ctx.results.get(CONTAINMENT)
    if c is None:
        # at most CONTAINMENT_SHARE of what is left of a wall-clock limit: the rate's own search keeps the rest
        expiry = None if budget.expiry is None else \
            time.monotonic() + CONTAINMENT_SHARE * max(0.0, budget.expiry - time.monotonic())
        c = certify_containment(ctx, Budget(CONTAINMENT_WORK, expiry))
        ctx.results[CONTAINMENT] = c
    rec = {"containment": {"status": c.status, "margin": c.extra.get("margin"), "w_bound": c.extra.get("w_bound")}}
    S = containment_set(ctx, margin)
    if S is not None:
        return S, {"source": "certify.containment", **rec}
    S = declared_set(ctx, *DEFAULT_SET_MARGIN)
    return S, {"source": f"the default margins (certify.containment is {c.status})", **rec}


def certify_sampled(ctx: Context, budget: Budget, *, margin: float = 0.05, set_margin=None, tau_max=None,
                    start_hz: float | None = None, S: SampledSet | None = None, theory: bool = True,
                    progress=None, floor_check: bool = True, theory_by: float | None = None,
                    owner: str = "the") -> Certificate:
    """certify.sampled: the lowest rate (within RATE_REL_TOL) at which one period from S provably keeps the
    funnels with margin `margin` and returns to S; undecided with what is left otherwise. S: given, else declared by
    `set_margin`, else the containment certificate's (`choose_set`). `theory_by` (time.monotonic()): the theory
    bound ends by then, else it is "not computed (`owner` budget ran out)"."""
    t0 = time.monotonic()
    say = progress or (lambda s: None)
    sc, d = ctx.scenario, ctx.design
    T = float(ctx.t_final)
    choice = {"source": S.source} if S is not None else None
    if S is None:
        with deadline.step(STEP_SET):
            S, choice = choose_set(ctx, budget, margin, set_margin)
    region = S.describe(T)
    region["parameters"] = ctx.params.describe()
    if S.w_ball is not None:
        region["w_hat_ball"] = S.w_ball
    base = {"rate_margin": margin, "set": region, "set_choice": choice}
    impl = getattr(sc, "implementation", None)
    if impl is not None and (impl.delay_samples or impl.noise_q or impl.noise_dq or impl.encoder_resolution):
        return Certificate(CID, "undecided", "the scenario's [implementation] has a delay, measurement noise or "
                           "quantisation, which the one-period proof does not model", region=region,
                           undecided_fraction=1.0, seconds=time.monotonic() - t0, method=_METHOD,
                           extra={**base, "proven_rate_hz": None})
    if d.n_regressor and "w_hat" not in S.states:
        return Certificate(CID, "undecided", "no W_hat box (no simulated run to take it from)", region=region,
                           undecided_fraction=1.0, seconds=time.monotonic() - t0, method=_METHOD,
                           extra={**base, "proven_rate_hz": None})
    with deadline.step(STEP_MAP):
        op = OnePeriod(ctx, S, tau_max)
    if "w_hat" in S.states and op.w_ball is not None:
        lo, hi = (np.asarray(v, float) for v in S.states["w_hat"])
        if not (np.all(lo <= -op.w_ball) and np.all(hi >= op.w_ball)):
            return Certificate(CID, "undecided", f"W_hat's box does not contain the projection's ball ||W_hat||_F <= "
                               f"{op.w_ball:.6g}, onto which the step clips W_hat, so the box is not shown to be "
                               "kept", region=region, undecided_fraction=1.0, seconds=time.monotonic() - t0,
                               method=_METHOD, extra={**base, "proven_rate_hz": None})
    elif "w_hat" in S.states and op.w_rate is None:
        return Certificate(CID, "undecided", "W_hat's update is not affine in W_hat with a constant diagonal "
                           "decay, so its box is not shown to be kept", region=region, undecided_fraction=1.0,
                           seconds=time.monotonic() - t0, method=_METHOD, extra={**base, "proven_rate_hz": None})
    inside, sig0 = initial_in_set(ctx, S)
    tried: list[dict] = []
    max_boxes = int(min(BOXES_PER_RATE, max(1000, budget.work // 2000)))

    warm: dict = {}         # the last budget-ended search at the highest rate below the ones tried next

    def attempt(f: float) -> bool:
        if budget.expired():
            tried.append({"rate_hz": f, "proven": False, "reason": "seconds", "boxes": 0, "left": 1.0})
            return False
        h = 1.0 / f
        w = warm.get("r")
        # a queue from a much longer period is most of S in many small boxes: re-checking it costs more than a
        # cold search at the shorter period, whose large boxes pass whole (measured on certify_none)
        w = w if w is not None and w["h"] >= h and len(w["queue"][2]) <= max_boxes // WARM_QUEUE else None
        with deadline.step(STEP_SEARCH):
            r = prove_period(op, h, margin, T, max_boxes=max_boxes, expiry=budget.expiry, warm=w)
        if r.get("queue") is not None and (w is None or r["h"] <= w["h"]):
            warm["r"] = r
        tried.append({"rate_hz": f, "proven": r["proven"], "reason": r["reason"], "boxes": r["boxes"],
                      "left": r["left"], **({"failed": r["failed"]} if "failed" in r else {}),
                      **({"warm_from_hz": 1.0 / w["h"]} if w is not None else {})})
        say(f"certify.sampled: {f:.6g} Hz {'proven' if r['proven'] else 'not proven (' + str(r['reason']) + ')'}"
            f" ({r['boxes']} boxes)")
        return r["proven"]

    f = float(start_hz or (impl.rate_hz if impl is not None else 1000.0))
    lo = hi = None
    # a state of S that leaves S within a period at the starting rate: no proof over S at or below the rate it
    # gives, so the search starts above it (`sampled_floor`)
    with deadline.step(STEP_FLOOR):
        floor = set_floor(op, S, T, 1.0 / f, tau_max) if floor_check else None
    if floor is not None:
        lo = min(floor["rate_hz"], MAX_RATE_HZ)
        tried.append({"rate_hz": lo, "proven": False, "reason": "floor", "boxes": 0, "left": 1.0})
        say(f"certify.sampled: a state of S leaves S after {floor['leaves_after_s']:.3g} s: no proof at or below "
            f"{floor['rate_hz']:.6g} Hz")
    elif attempt(f):
        hi = f
        while lo is None and hi / 4 >= 1.0:
            if attempt(hi / 4):
                hi = hi / 4
            else:
                lo = hi / 4
    else:
        lo = f
    if hi is None:
        while hi is None and lo < MAX_RATE_HZ and not budget.expired():
            g = min(lo * 4, MAX_RATE_HZ)
            if attempt(g):
                hi = g
            else:
                lo = g
    while hi is not None and lo is not None and hi / lo > 1 + RATE_REL_TOL and not budget.expired():
        mid = math.sqrt(lo * hi)
        if attempt(mid):
            hi = mid
        else:
            lo = mid
    th = _theory_within(ctx, op, S, margin, tau_max, theory_by, owner) if theory else \
        {"rate_hz": None, "reason": "not computed"}
    boxes = sum(r["boxes"] for r in tried)
    extra = {**base, "proven_rate_hz": hi, "not_proven_below_hz": lo, "tried": tried, "initial_in_set": inside,
             "initial_e_over_F": sig0, "theory": th, "set_floor": floor}
    secs = time.monotonic() - t0
    if hi is not None and inside:
        return Certificate(CID, "proven", f"at every rate >= {hi:.6g} Hz one period from any state of S (margins "
                           f"e1 {S.m1:g}, e2 {S.m2:g}{_source_words(S)}) keeps both funnels with margin {margin:g} and returns to S, "
                           f"for every parameter of the box; the initial state is in S, so the sampled loop keeps "
                           f"the funnels on [0, {T:g}] s", lower=hi, upper=lo, region=region, boxes=boxes,
                           seconds=secs, method=_METHOD, extra=extra)
    if hi is not None:
        return Certificate(CID, "undecided", f"one period from S is proven at rates >= {hi:.6g} Hz, but the initial "
                           f"state (e/F = {np.round(sig0, 4).tolist()}) is not shown to lie in S", lower=hi,
                           upper=lo, region=region, boxes=boxes, seconds=secs, method=_METHOD,
                           undecided_fraction=1.0, extra=extra)
    last = tried[-1] if tried else {"left": 1.0, "reason": None}
    why = f"; a point of S fails the check '{last['failed']}'" if last.get("failed") else ""
    if floor is not None:
        at = (f"at any rate up to {MAX_RATE_HZ:g} Hz (S is not kept even between samples this close)"
              if floor["rate_hz"] > MAX_RATE_HZ else f"at or below {floor['rate_hz']:.6g} Hz")
        why += (f"; no proof over this S exists {at}: from the state of S at t = "
                f"{floor['t']:g} s, e/F = {np.round(floor['e_over_F'], 4).tolist()} (controller states at their "
                f"sets' centres, nominal parameters) the plant under the step's held torque leaves S after "
                f"{floor['leaves_after_s']:.3g} s (integrated)")
    return Certificate(CID, "undecided", f"no rate up to {lo:.6g} Hz proven (the last attempt ended on "
                       f"'{last['reason']}' with {last['left']:.3g} of S left{why})", upper=lo, region=region,
                       boxes=boxes, undecided_fraction=float(last["left"]), seconds=secs, method=_METHOD,
                       extra=extra)


def _theory(ctx: Context, op: OnePeriod, S: SampledSet, margin: float, tau_max) -> dict:
    """The reach-time bound on S; when S's margins leave no gap above the rate's margin (a containment set at
    m2 = M), on the declared default S instead, and the record says which set it is on."""
    T = float(ctx.t_final)
    if min(S.m1, S.m2) > margin:
        return {**theory_rate(op, S, margin, T), "set": {"e1": S.m1, "e2": S.m2, "source": S.source}}
    D = declared_set(ctx, *DEFAULT_SET_MARGIN, w_box=S.states.get("w_hat"), w_source="S's W_hat box")
    out = theory_rate(op.on_set(D), D, margin, T)      # the same forms: only S's parts differ
    return {**out, "set": {"e1": D.m1, "e2": D.m2, "source": "declared (S's margins leave no gap above the rate's "
                                                              f"margin {margin:g})"}}


def _theory_within(ctx: Context, op: OnePeriod, S: SampledSet, margin: float, tau_max, by: float | None,
                   owner: str) -> dict:
    """`_theory`, ended at time.monotonic() `by` (None: unbounded) as "not computed": its branch and bound stopped
    early would give a looser number than the command's, so a cut bound is no number at all."""
    cut = {"rate_hz": None, "reason": f"not computed ({owner} budget ran out)"}
    left = math.inf if by is None else by - time.monotonic()
    if left <= 0:
        return cut
    try:
        with deadline.limit(left, on_expiry=_cut_at_first_step(_TheoryCut)), deadline.step(STEP_THEORY):
            return _theory(ctx, op, S, margin, tau_max)
    except _TheoryCut:
        return cut


def _source_words(S: SampledSet) -> str:
    """Where S comes from, for the detail."""
    if S.source == "certify.containment":
        return ", the set certify.containment proves invariant" + (
            f", W_hat in its ball ||W_hat||_F <= {S.w_ball:.4g}" if S.w_ball is not None else "")
    return ", declared"


_METHOD = ("one-period validated enclosure (Taylor-form a-priori box around the rates at the sample, the first-order "
           "Picard box where it fails; second-order Taylor form of the next sample) by batched interval branch and "
           "bound over S; bisection in the period, warm-started from the boxes left at a longer period")


def simulated_w_hat_range(design, closed_loop, result):
    """W_hat's box for certify.sampled: the simulated run's range per entry (the certificate widens it); None for a
    design without an approximator or a run without W_hat."""
    if not design.n_regressor:
        return None
    wh = closed_loop.unpack(result.x).get("w_hat")
    if wh is None or not len(wh):
        return None
    return (np.min(wh, axis=0), np.max(wh, axis=0))


def same_problem(a: Context, b: Context) -> bool:
    """Whether two contexts pose certify.containment the same problem: the same scenario and design (objects), the
    same horizon and the same parameter and initial-state box, value for value (W* and the W_hat range, which
    containment does not read, may differ)."""
    def eq(x, y):
        if x is None or y is None:
            return x is None and y is None
        return all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(x, y)) and len(x) == len(y)
    p, q = a.params, b.params
    return (a.scenario is b.scenario and a.design is b.design and float(a.t_final) == float(b.t_final)
            and list(p.names) == list(q.names) and list(p.uncertain) == list(q.uncertain)
            and eq((p.nominal, p.lo, p.hi), (q.nominal, q.lo, q.hi)) and eq(p.q0, q.q0) and eq(p.dq0, q.dq0))


def reuse_containment(ctx: Context, prior: Context | None) -> bool:
    """Put `prior`'s certify.containment into ctx when it is proven or undecided for the same problem
    (`same_problem`), so that choose_set does not compute it again; a refutation (from `prior`'s simulated breach,
    which ctx does not hold) is not reused. True when reused."""
    from .containment import CID as CONTAINMENT
    c = None if prior is None else prior.results.get(CONTAINMENT)
    if c is None or c.status not in ("proven", "undecided") or not same_problem(ctx, prior):
        return False
    ctx.results[CONTAINMENT] = c
    return True


def sampled_bracket(scenario, design, *, t_final: float, margin: float = 0.05, set_margin=None,
                    f_sim: float | None = None, w_hat_range=None, wall_limit: float | None = None,
                    work: float = 5e7, progress=None, prior: Context | None = None,
                    budget_owner: str | None = None) -> dict:
    """`rate --certify`'s additions: {"proven_rate_hz", "theory_rate_hz", "ratio" (proven / simulated),
    "certificate", "sampled_run_at_proven"} -- the last a sampled run of the generated C step at f_proven from the
    scenario's initial state, which a proof must never contradict (a breach there would refute the certificate).
    `prior`: the context of certificates already computed (a report's), whose containment is reused when it poses
    the same problem (`reuse_containment`). `wall_limit` bounds the proof's search; with `budget_owner` (e.g.
    "the report's") it bounds the whole bracket instead -- set, one-period map, floor, search (to SEARCH_BY of it),
    theory bound (to THEORY_BY) and the sampled run at f_proven -- and a bracket still running at its end is
    undecided, naming the step it ran out in, with nothing proven."""
    t0 = time.monotonic()
    W = None if wall_limit is None else float(wall_limit)
    owned = budget_owner is not None and W is not None
    work_of = functools.partial(_bracket, scenario, design, t_final=t_final, margin=margin, set_margin=set_margin,
                                f_sim=f_sim, w_hat_range=w_hat_range, work=work, progress=progress, prior=prior)
    if not owned:
        return work_of(expiry=None if W is None else t0 + W)
    try:
        with deadline.limit(W, on_expiry=_cut_at_first_step()):
            return work_of(expiry=t0 + SEARCH_BY * W, theory_by=t0 + THEORY_BY * W, owner=budget_owner)
    except _Cut as cut:
        why = f"{budget_owner} {W:g} s ran out while {cut.step}"
        cert = Certificate(CID, "undecided", why, undecided_fraction=1.0, seconds=time.monotonic() - t0,
                           method=_METHOD, extra={"proven_rate_hz": None, "budget_ran_out": cut.step, "theory": {
                               "rate_hz": None, "reason": f"not computed ({budget_owner} budget ran out)"}})
        return {"proven_rate_hz": None, "theory_rate_hz": None, "ratio": None, "certificate": cert.to_json(),
                "sampled_run_at_proven": None}


def _bracket(scenario, design, *, t_final, margin, set_margin, f_sim, w_hat_range, work, progress, prior, expiry,
             theory_by=None, owner="the") -> dict:
    """sampled_bracket's work: the proof's search ends at `expiry`, the theory bound at `theory_by`."""
    from ..deployed.loop import simulate_sampled
    from .region import parameter_box
    ctx = Context(scenario, design, float(t_final), parameter_box(scenario), None, w_hat_range)
    reuse_containment(ctx, prior)
    impl = getattr(scenario, "implementation", None)
    tau_max = impl.tau_max if impl is not None else None
    cert = certify_sampled(ctx, Budget(float(work), expiry), margin=margin, set_margin=set_margin, tau_max=tau_max,
                           start_hz=f_sim, progress=progress, theory_by=theory_by, owner=owner)
    fp = cert.extra.get("proven_rate_hz") if cert.status == "proven" else None
    check = None
    if fp is not None:
        with deadline.step(STEP_CHECK):
            res = simulate_sampled(scenario, design, rate_hz=fp, t_final=t_final)
        check = {"rate_hz": fp, "status": res.status, "min_margin": res.min_margin, "holds": bool(
            res.ok and res.min_margin >= margin)}
        if not check["holds"]:
            cert = Certificate(CID, "refuted", f"the sampled run of the C step at the rate the enclosure proves "
                               f"({fp:.6g} Hz) does not keep margin {margin:g} (min margin {res.min_margin:.4g}): "
                               "the proof's model and the deployed loop disagree", counterexample=check,
                               region=cert.region, boxes=cert.boxes, seconds=cert.seconds, method=cert.method,
                               extra=cert.extra)
            fp = None
    th = cert.extra.get("theory", {}).get("rate_hz")
    return {"proven_rate_hz": fp, "theory_rate_hz": th,
            "ratio": (fp / f_sim) if (fp is not None and f_sim) else None,
            "certificate": cert.to_json(), "sampled_run_at_proven": check}

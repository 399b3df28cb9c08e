"""`certify.containment`: the funnels are kept with a margin, proven by Nagumo's condition on the faces of a
box-shaped set, for the closed loop as it is -- without the Lyapunov level set.

The set, for margins m1, m2 and a radius w (c_i = 1 - m_i):

    S = {|e1_j| <= c1 F1_j(t), |e2_j| <= c2 F2_j(t), ||W_hat||_F <= w, |x_esn| <= 1/leak},  t in [0, T].

S is a finite intersection of sets {h <= 0} with h smooth in (t, x). If on every part of its boundary the active
constraint strictly decreases along the closed loop -- every plant of the parameter box, the dead zone's exact
branches (the interval evaluation of the plant's own graph: a box on which tau's sign is decided uses that branch,
so corners of the e2 funnel are split on tau rather than bounded by the slope hull), Coulomb friction's Filippov
values ([-1, 1] at dq = 0) -- then no trajectory that starts in S can leave it before T (at a first exit time some h
would reach 0 from below with dh/dt < 0). The faces:

- e_i face, joint j, side sigma = +-1 (s_i_j = sigma c_i fixed, every other coordinate free in S): the outward
  normal component sigma F_i d/dt(e_i_j / F_i_j) = sigma (de_i_j - (e_i_j / F_i_j) dF_i_j) < 0, with de1 = dq - dq_d
  and de2 = ddq_plant - alpha2_dot along the true plant (ddq_plant = the design's nominal ddq + f_true,
  `region.true_unknown`). Terms that cancel by a graph identity (alpha2_dot in ddq - alpha2_dot, dq_d in
  alpha2 - dq_d) are dropped when the Jacobian in them is structurally zero (`_drop_cancelled`), so interval
  arithmetic does not subtract two huge equal enclosures.
- W_hat face: when the adaptive law is W_hat_dot = G(x) - kappa W_hat with G independent of W_hat and kappa > 0
  (sigma-modification, Jacobian -kappa I checked on the graph), d/dt ||W_hat||^2/2 <= ||W_hat|| (||G|| - kappa
  ||W_hat||) < 0 on ||W_hat|| = w for any w > sup_S ||G||_F / kappa: w is that rigorous bound (times 1.01).
  On the e2 faces W_hat ranges over the box [-w, w] (a superset of the ball).
- x_esn face: the tanh reservoir's box is invariant (a theorem, checked along the run by `bounded.x_esn`).

Each face is one dimension lower than S (one normalised coordinate fixed); a batched interval branch and bound
(mean-value form in t, s, p; controller states as boxes, never split) proves sigma n < 0 on it or finds a point
where the flow points outward (a failed certificate at that margin, not a counterexample of the loop). The initial
state must lie in S (interval evaluation of e_i(0)/F_i(0), ||W_hat(0)||, x_esn(0)). Margins are tried in a fixed
order within a deterministic budget: a cheap screen of sampled face points discards margins first; then, per e1
margin, the smallest surviving e2 margin (the guarantee) with all that is left, then the stronger ones.

Outcomes: proven (m1, m2, w, the horizon [0, T] -- "finite" --, the parameter box); refuted only by a real breach
of the simulated closed loop from its initial state; undecided otherwise (the face left and the fraction of it).
"""

from __future__ import annotations

import math
import time
from collections import deque

import casadi as ca
import numpy as np

from .problem import Budget, Context, RegionProblem, controller_state_boxes
from .face_bisect import bisect_open
from .face_forms import normal_components
from .projection_face import projection_face
from .regressor_jacobian import RegressorColumns, regressor_form
from .result import Certificate
from ..sx.rewrite import replace_nodes
from ..sx.search import extrema

CID = "certify.containment"
#: with two joints, f_true's M_p^-1 by the adjugate (`sx.linalg.solve2`) rather than LDL^T: narrower face bounds
ADJUGATE = True
#: the order of the faces' mean-value form (2: its Jacobian enclosed by a mean-value form of its own, see
#: `sx.batch.BatchCenteredForm`)
FACE_ORDER = 1
#: alpha2_dot through e1 (`face_forms.alpha2_dot_through_e1`) where the design's alpha2 has that form
THROUGH_E1 = True
#: the e2 faces' p-columns of the mean-value Jacobian also by the regressor identity (`regressor_jacobian`): tighter
#: boxes, but once D(tau) - tau is written with tau once, the sensitivity-driven splits then bisect the masses less
#: and a whole proof takes more boxes (paper_small_dead_zone, projection 2, m2 = 0.002: 100,955 against 72,555), so
#: it is available, not the default
REGRESSOR = False
#: the margins: e1's in this order; per e1 margin the smallest e2 margin the screen leaves is attempted first, then
#: the others in this order with what its proof left (the strongest proven is reported)
M1_GRID = (0.9, 0.8, 0.5, 0.3, 0.1)
M2_GRID = (0.05, 0.02, 0.01, 0.005, 0.002, 0.1, 0.2, 0.5)
#: sampled points per face in the screen that discards a margin before any branch and bound
SCREEN = 192
#: margins on which a proof is attempted (those surviving the screen, in grid order)
PROOF_ATTEMPTS = 3
#: boxes for the rigorous sup ||G||_F over S (the W_hat radius) per e2 margin
W_BOXES = 256
#: the W_hat radius is this factor above the rigorous sup ||G|| / kappa (strictly above: the face then points in)
W_SAFETY = 1.01


def face_expressions(design, p: ca.SX) -> tuple[dict[str, ca.SX], dict]:
    """The normal components n1 = de1 - (e1/F1) dF1 and n2 = de2 - (e2/F2) dF2 along the true plant (parameters
    p), and ||G||_F^2 of the adaptive law's forcing where the design has adaptive weights."""
    S = design.signals
    sym = design.sym
    n1, n2, info = normal_components(design, p, ADJUGATE, through_e1=THROUGH_E1)
    exprs = {"n1": n1, "n2": n2}
    info = {**info, "adaptation": None}
    info.pop("solve")
    if design.n_regressor:
        W = sym["w_hat"]
        Wd = S["w_hat_dot"]
        J = ca.jacobian(ca.vec(Wd), ca.vec(W))
        kappa = None
        if not ca.depends_on(J, ca.vertcat(*[ca.vec(v) for v in sym.values()])) and J.is_constant():
            Jd = np.asarray(ca.DM(J), float)
            k = -Jd[0, 0]
            if k > 0 and np.array_equal(Jd, -k * np.eye(Jd.shape[0])):
                kappa = float(k)
        if kappa is not None:
            G = Wd + kappa * W
            exprs["G2"] = ca.sumsqr(G)
        info["adaptation"] = {"kappa": kappa}
        # The e2 faces see W_hat only through the estimate W_hat^T Phi (checked: once that node is a variable, n2
        # does not depend on W_hat): |(W_hat^T Phi)_j| <= ||W_hat||_F ||Phi||, a box of half-width w sup ||Phi|| per
        # joint instead of sum_i w |Phi_i| from W_hat's box (sqrt(N) times tighter). The variable is carried by
        # W_hat's first row (the region function's inputs are the design's states); its other rows are unused.
        est = ca.mtimes(W.T, S["Phi"])
        row = ca.vec(W[0, :])
        n2 = replace_nodes([exprs["n2"]], ca.vec(est), ca.SX.sym("west", design.n))[0]
        if not ca.depends_on(n2, ca.vec(W)):
            exprs["n2"] = replace_nodes([exprs["n2"]], ca.vec(est), row)[0]
            exprs["P2"] = ca.sumsqr(S["Phi"])
            info["estimate"] = True
        else:
            info["estimate"] = False
    return exprs, info


class _Faces:
    """The face problem of one scenario: one region function with outputs n1, n2 (and ||G||^2)."""

    def __init__(self, ctx: Context):
        d = ctx.design
        self.ctx = ctx
        self.n = d.n
        p = ca.SX.sym("p", len(ctx.params.names))
        exprs, self.info = face_expressions(d, p)
        extra = {k: exprs.pop(k) for k in ("G2", "P2") if k in exprs}
        # the estimate W_hat^T Phi (carried by W_hat's first row) enters n2 through M_p^-1 D M, which is near the
        # identity: in the mean-value form its box costs about its own width, in plain intervals tens of times that.
        # Every sign(g) of the faces (Coulomb friction's sign(dq), the AD of |e| in the transformation) becomes an
        # input sgn_k of its own, set per box to the hull of sign over the box's enclosure of g ([-1, 1] where it
        # contains 0: Filippov's set-valued sign), `_Filippov`: the faces are then continuous in every other input,
        # so the mean-value form applies across dq = 0 and e = 0 too (with sign in the graph a box meeting them had
        # only the natural enclosure, whose width shrinks only linearly)
        names = list(exprs)
        nodes = sign_nodes([exprs[k] for k in names])
        inputs = {}
        if nodes:
            sgn = ca.SX.sym("sgn", len(nodes))
            exprs = dict(zip(names, replace_nodes([exprs[k] for k in names], ca.vertcat(*nodes), sgn)))
            inputs = {"sgn": sgn}
        centered = (("w_hat",) if self.info.get("estimate") else ()) + tuple(inputs)
        self.prob = RegionProblem(ctx, exprs, p, "containment", centered=centered, extra=inputs, order=FACE_ORDER)
        self.info["regressor"] = None
        if REGRESSOR and self.prob.wide.size:
            Jp, N2, why = regressor_form(d, p, self.prob.wide, ADJUGATE, THROUGH_E1, ctx.t_final)
            self.info["regressor"] = why or "p-columns of n2 by -M_p^-1 (dM_p/dp ddq + dh_p/dp)"
            if Jp is not None:
                G = self.prob.F
                G.refine = RegressorColumns(self.prob, Jp, N2, p, G.out_off[G.out_names.index("n2")])
        F = self.prob.F
        if inputs:
            args = ca.vertcat(*[v.dep(0) for v in nodes])
            F = _Filippov(F, RegionProblem(ctx, {"g": args}, p, "containment_sign").F)
        self.F = F
        self.pos = {k: F.out_off[F.out_names.index(k)] for k in exprs}
        # ||G||^2 (and ||Phi||^2) on their own (their mean-value Jacobian is not the faces' and costs as much)
        self.gprob = RegionProblem(ctx, extra, p, "containment_w") if extra else None
        self.si = {k: (F.in_off[F.in_names.index(k)], F.in_off[F.in_names.index(k) + 1]) for k in ("s1", "s2")}

    def split_indices(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The bisected coordinates: the region's (t, s, p) and the estimate W_hat^T Phi's (W_hat's first row) where
        it carries it -- near a zero of the torque the dead zone's branch is decided only on a narrower estimate."""
        idx = self.prob.split_indices(lo, hi)
        if not self.info.get("estimate"):
            return idx
        F = self.F
        i = F.in_names.index("w_hat")
        rows = self.ctx.design.sym["w_hat"].shape[0]
        est = [j for j in range(F.in_off[i], F.in_off[i + 1], rows) if lo[j] < hi[j]]
        return np.concatenate([idx, np.array(est, dtype=int)])

    def box(self, c1: float, c2: float, states: dict, prob=None) -> tuple[np.ndarray, np.ndarray]:
        """The flat box of S (m = 0, s_i in [-c_i, c_i]) in the layout of `prob` (default: the faces')."""
        prob = prob or self.prob
        reg = prob.region(0.0, states)
        reg["s1"] = (-c1 * np.ones(self.n), c1 * np.ones(self.n))
        reg["s2"] = (-c2 * np.ones(self.n), c2 * np.ones(self.n))
        if "sgn" in prob.in_names:
            k = prob.F.in_names.index("sgn")
            size = prob.F.in_off[k + 1] - prob.F.in_off[k]
            reg["sgn"] = (-np.ones(size), np.ones(size))
        return prob.flat(reg)

    def faces(self, lo: np.ndarray, hi: np.ndarray) -> list[dict]:
        """Every face of the box: e_i, joint j, side sigma, with its flat box and objective position."""
        out = []
        for i, key in ((1, "s1"), (2, "s2")):
            a, _ = self.si[key]
            for j in range(self.n):
                for sg in (1.0, -1.0):
                    flo, fhi = lo.copy(), hi.copy()
                    v = hi[a + j] if sg > 0 else lo[a + j]
                    flo[a + j] = fhi[a + j] = v
                    out.append({"name": f"e{i} joint {j + 1} {'+' if sg > 0 else '-'}", "i": i, "j": j,
                                "sign": sg, "lo": flo, "hi": fhi, "pos": self.pos[f"n{i}"] + j})
        return out


def sign_nodes(exprs: list) -> list:
    """The distinct sign(g) nodes of the expressions' graph (a walk over it, each node once)."""
    seen, out, keys = set(), [], set()
    stack = [e for x in exprs for e in ca.vertsplit(ca.vec(ca.SX(x)), 1)]
    while stack:
        e = stack.pop()
        h = e.element_hash()
        if h in seen:
            continue
        seen.add(h)
        if e.is_op(ca.OP_SIGN):
            key = str(e.dep(0))
            if key not in keys:
                keys.add(key)
                out.append(e)
        stack.extend(e.dep(i) for i in range(e.n_dep()))
    return out


class _Filippov:
    """The face function with its last input sgn (each sign(g) of the faces) filled in per box: the hull of sign
    over the box's enclosure of g, with [-1, 1] where it contains 0 (Filippov's set-valued sign; it contains sign's
    own values too), sign(g) at a point. An enclosure over sgn's hull contains the faces' values on the box, as
    sign(g(x)) lies in it for every x of the box. Every other attribute is the face function's."""

    def __init__(self, F, args):
        self.F, self.args = F, args
        i = F.in_names.index("sgn")
        self.sidx = np.arange(F.in_off[i], F.in_off[i + 1])
        self.k0 = args.n_in_nz           # the arguments' function has the face function's inputs without sgn

    def __getattr__(self, name):
        return getattr(self.F, name)

    def eval_batch(self, LO, HI, with_jacobian: bool = False):
        LO, HI = np.array(LO, float), np.array(HI, float)
        DL, DH, _ = self.args.eval_batch(LO[:, :self.k0], HI[:, :self.k0])
        LO[:, self.sidx] = np.where(DL > 0, 1.0, -1.0)
        HI[:, self.sidx] = np.where(DH < 0, -1.0, 1.0)
        return self.F.eval_batch(LO, HI, with_jacobian=with_jacobian)

    def eval_points(self, X):
        X = np.array(X, float)
        X[:, self.sidx] = np.sign(self.args.eval_points(X[:, :self.k0]))
        return self.F.eval_points(X)


def _screen(F, faces: list[dict], rng, worst: dict | None = None) -> dict | None:
    """The first sampled face point where the flow points outward (sign * n >= 0 or not finite), or None; `worst`
    collects each screened face's largest sampled sign * n (how far inward the flow points at worst there)."""
    for f in faces:
        lo, hi = f["lo"], f["hi"]
        X = lo + rng.random((SCREEN, lo.size)) * (hi - lo)
        # the corners of the state boxes too: W_hat's extreme, the reservoir's
        X[: SCREEN // 2] = np.where(rng.random((SCREEN // 2, lo.size)) < 0.5, lo, hi)
        X[0] = 0.5 * lo + 0.5 * hi
        V = f["sign"] * F.eval_points(X)[:, f["pos"]]
        if worst is not None:
            worst[f["name"]] = float(np.max(V))
        bad = ~(V < 0)
        if bad.any():
            k = int(np.argmax(np.where(np.isfinite(V), V, np.inf)))
            return {"face": f, "x": X[k], "value": float(V[k])}
    return None


def _decide(F, faces: list[dict], split_of, max_boxes: int, seconds: float | None) -> dict:
    """Batched branch and bound: sign * n < 0 on every face (proven), a point where it is >= 0 (failed), or the
    budget ends with boxes left (undecided: the face with the largest fraction left)."""
    t0 = time.monotonic()
    # a box is its face's box but in the split coordinates: only those are stored (about a tenth of the inputs;
    # at 10x the default budget the queue held ~1 GB), in a deque (slicing a list copied it at every batch)
    queue = deque((f["lo"][split_of[k]].copy(), f["hi"][split_of[k]].copy(), k, 1.0) for k, f in enumerate(faces))
    boxes = 0
    while queue:
        if boxes >= max_boxes or (seconds is not None and time.monotonic() - t0 > seconds):
            left = np.zeros(len(faces))
            for _, _, k, vol in queue:
                left[k] += vol
            k = int(np.argmax(left))
            return {"status": "undecided", "boxes": boxes, "face": faces[k]["name"], "fraction": float(left[k]),
                    "fractions": {faces[i]["name"]: float(v) for i, v in enumerate(left) if v > 0},
                    "proven_faces": [f["name"] for i, f in enumerate(faces) if left[i] == 0]}
        batch = [queue.popleft() for _ in range(min(1024, len(queue)))]
        LO = np.array([faces[b[2]]["lo"] for b in batch])
        HI = np.array([faces[b[2]]["hi"] for b in batch])
        for i, (slo, shi, k, _) in enumerate(batch):
            LO[i, split_of[k]] = slo
            HI[i, split_of[k]] = shi
        L, H, _, J = F.eval_batch(LO, HI, with_jacobian=True)
        boxes += len(batch)
        pos = np.array([faces[b[2]]["pos"] for b in batch])
        sg = np.array([faces[b[2]]["sign"] for b in batch])
        r = np.arange(len(batch))
        ub = np.where(sg > 0, H[r, pos], -L[r, pos])          # an upper bound of sign * n on the box
        proven = ub < 0
        mid = np.where(LO == HI, LO, 0.5 * LO + 0.5 * HI)
        V = sg * F.eval_points(mid)[r, pos]
        bad = ~(V < 0)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            return {"status": "failed", "boxes": boxes, "face": faces[batch[k][2]], "x": mid[k],
                    "value": float(V[k])}
        children, thin = bisect_open(batch, np.flatnonzero(~proven), J, pos, split_of, faces, F.w_flat)
        if thin is not None:
            # too thin to split: stays open for good
            fk, vol = batch[thin][2], batch[thin][3]
            return {"status": "undecided", "boxes": boxes, "face": faces[fk]["name"], "fraction": vol,
                    "fractions": {faces[fk]["name"]: vol}}
        queue.extend(children)
    return {"status": "proven", "boxes": boxes}


def regularity(ctx: Context) -> str | None:
    """Why the argument cannot apply, or None: the first-exit argument needs q_d in C^2 and F_i > 0 in C^1 on
    [0, T]. That is the loader's proof (`scenario.regularity`: no jump or kink of t can switch on the horizon, F
    proven positive), memoised per expression and horizon, asked again here so that a certificate never rests on a
    scenario that reached it without that proof."""
    from ..core.errors import InputError
    from ..scenario.regularity import check_funnel_regular, check_reference_regular
    sc = ctx.scenario
    try:
        check_reference_regular(sc.reference, ctx.t_final, file=sc.file)
        for key, shape in sc.funnels.items():
            check_funnel_regular(shape, ctx.t_final, file=sc.file,
                                 key=f"funnel.{key}" + (".F" if "F" in shape.KEYS else ""))
    except InputError as exc:
        return (f"{exc.key}: {exc.reason} -- the argument needs q_d in C^2 and F in C^1 with F > 0 on "
                f"[0, {ctx.t_final:g}]")
    return None


def _initial_ratios(ctx: Context) -> tuple[np.ndarray, np.ndarray, str]:
    """Rigorous upper bounds of |e1_j(0)| / F1_j(0) and |e2_j(0)| / F2_j(0) at the initial state (its box)."""
    from ..sx.batch import BatchIntervalFunction
    d, sc = ctx.design, ctx.scenario
    S = d.signals
    names = ["t", "q", "dq", "qd", "dqd", "ddqd"]
    f = ca.Function("ratios0", [d.sym[k] for k in names], [ca.vertcat(S["e1"] / S["F1"], S["e2"] / S["F2"])],
                    names, ["r"])
    F = BatchIntervalFunction(f)
    qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in d.reference(0.0))
    q0 = ctx.params.q0 or (np.asarray(sc.q0, float), np.asarray(sc.q0, float))
    dq0 = ctx.params.dq0 or (np.asarray(sc.dq0, float), np.asarray(sc.dq0, float))
    box = {"t": (0.0, 0.0), "q": q0, "dq": dq0, "qd": (qd, qd), "dqd": (dqd, dqd), "ddqd": (ddqd, ddqd)}
    lo, hi = (np.asarray(v, float) for v in F.flatten_box({k: box[k] for k in names}))
    L, H, _ = F.eval_batch(lo[None, :], hi[None, :])
    a = np.maximum(np.abs(L[0]), np.abs(H[0]))
    a = np.where(np.isfinite(a), a, np.inf)
    note = "the scenario's initial state" if np.all(lo == hi) else "the [[uncertainty]] box of the initial state"
    return a[:d.n], a[d.n:], note


def certify_containment(ctx: Context, budget: Budget) -> Certificate:
    """certify.containment over the margins M1_GRID x M2_GRID."""
    t0 = time.monotonic()
    d, sc = ctx.design, ctx.scenario

    def done(status, detail, **kw):
        kw.setdefault("method", "Nagumo's condition on the faces of S by batched interval branch and bound "
                                "(mean-value form in t, s, p; states as boxes)")
        return Certificate(CID, status, detail, seconds=time.monotonic() - t0, **kw)
    breach = getattr(ctx, "breach", None)
    if breach:
        return done("refuted", f"the simulated closed loop (the scenario's plant, integrator and smoothing width) "
                    f"leaves its funnels from its initial state: {breach.get('message', '')}", counterexample=breach, undecided_fraction=0.0,
                    extra={"margin": None, "w_bound": None, "horizon": "finite"})
    why = regularity(ctx)
    if why is not None:
        return done("undecided", why, undecided_fraction=1.0,
                    extra={"margin": None, "w_bound": None, "horizon": "finite", "face": None})
    fc = _Faces(ctx)
    F = fc.F
    budget.set_tape(fc.prob.work_per_box())
    r1, r2, note = _initial_ratios(ctx)
    init = d.variant.initial_states()
    kappa = (fc.info["adaptation"] or {}).get("kappa")
    pface = projection_face(d) if d.n_regressor and kappa is None and "projection" in d.parts else None
    if pface is not None and not pface["ok"]:
        return done("undecided", f"the projected adaptive law's ball is not shown invariant: {pface['why']}",
                    undecided_fraction=1.0, extra={"margin": None, "w_bound": None, "horizon": "finite",
                                                   "face": "W_hat"})
    if d.n_regressor and kappa is None and pface is None:
        return done("undecided", "the adaptive law is not W_hat_dot = G(x) - kappa W_hat with kappa > 0 "
                    "(no sigma-modification to bound W_hat with): no W_hat face", undecided_fraction=1.0,
                    extra={"margin": None, "w_bound": None, "horizon": "finite", "face": "W_hat"})
    if "x_esn" in init and np.any(np.abs(np.asarray(init["x_esn"], float)) > 1.0 / float(sc.esn.leak)):
        return done("undecided", "x_esn(0) lies outside the reservoir's invariant box |x| <= 1/leak",
                    undecided_fraction=1.0, extra={"margin": None, "w_bound": None, "horizon": "finite",
                                                   "face": "x_esn"})
    w_what = ("the projected law's invariant ball, proven on its graph" if pface
              else "sup ||G||_F / kappa over S")
    rng = np.random.default_rng(45)
    tried, attempts, boxes = [], 0, 0
    last_undecided = None
    w_of: dict[float, float] = {}          # the W_hat radius per c2 (sup ||G|| over S depends on the e2 margin)
    def screened(m1, m2):
        """The row of (m1, m2) and, when S contains the initial state and the screen finds no outward point, what
        a proof there needs (faces, W_hat radius, the screen's worst sampled values)."""
        nonlocal boxes
        c1, c2 = 1.0 - m1, 1.0 - m2
        row = {"m1": m1, "m2": m2}
        tried.append(row)
        if not (np.all(r1 < c1) and np.all(r2 < c2)):
            row["result"] = f"the initial state is not in S ({note}: |e/F| up to {max(r1.max(), r2.max()):.4g})"
            return None
        states = controller_state_boxes(ctx, (np.zeros_like(init["w_hat"]), np.zeros_like(init["w_hat"]))
                                        if d.n_regressor else None)
        w = None
        if d.n_regressor:
            if c2 not in w_of:
                # ||G|| does not depend on e1's margin beyond the tube: take the widest e1 box of the grid
                lo, hi = fc.box(1.0 - min(M1_GRID), c2, states, fc.gprob)
                split = fc.gprob.split_indices(lo, hi)
                GF = fc.gprob.F
                objs = [(GF.out_off[GF.out_names.index(k)], -1.0) for k in GF.out_names]
                exs = extrema(GF, lo, hi, split, objs, max_boxes=W_BOXES, rel_tol=0.2)
                boxes += exs[0].boxes
                sup = {k: (math.sqrt(max(-e.bound, 0.0)) if np.isfinite(e.bound) else math.inf)
                       for k, e in zip(GF.out_names, exs)}
                # the W_hat face: sigma-modification's ball from sup ||G|| / kappa, or the projection's own ball
                w_of[c2] = (pface["w"] if pface else W_SAFETY * sup["G2"] / kappa, sup.get("P2"))
            w, phi_sup = w_of[c2]
            w0 = float(np.linalg.norm(np.asarray(init["w_hat"], float)))
            row["w"] = w
            if not math.isfinite(w):
                row["result"] = "no finite bound of ||G|| on S"
                return None
            if not w0 < w:
                row["result"] = f"||W_hat(0)|| = {w0:.4g} is not inside the W_hat ball of radius {w:.4g}"
                return None
            W0 = np.zeros_like(np.asarray(init["w_hat"], float))
            if fc.info.get("estimate"):        # W_hat's first row carries the estimate W_hat^T Phi
                lo_w, hi_w = W0.copy(), W0.copy()
                lo_w[0, :], hi_w[0, :] = -w * phi_sup, w * phi_sup
            else:
                lo_w, hi_w = W0 - w, W0 + w
            states = controller_state_boxes(ctx, (lo_w, hi_w))
        lo, hi = fc.box(c1, c2, states)
        faces = fc.faces(lo, hi)
        sampled: dict = {}
        bad = _screen(F, faces, rng, sampled)
        if bad is not None:
            row["result"] = f"outward at a sampled point of face {bad['face']['name']} (sign n = {bad['value']:.4g})"
            row["why"] = _why(fc, bad, w, w_what)
            return None
        return {"m1": m1, "m2": m2, "row": row, "faces": faces, "w": w, "sampled": sampled}

    for m1 in M1_GRID:
        cands = [c for c in (screened(m1, m2) for m2 in M2_GRID) if c is not None]
        if not cands:
            continue
        # the guarantee first: the smallest e2 margin the screen leaves (the faces nearest the funnel's edge, where
        # its gain points the flow inward hardest) with all that is left of the budget; then, with what its proof
        # left, the stronger margins in grid order -- the strongest proven is reported
        easiest = min(cands, key=lambda c: c["m2"])
        order = [easiest] + [c for c in cands if c is not easiest]
        best = None
        for k, c in enumerate(order):
            row = c["row"]
            if best is not None and c["m2"] <= best["m2"]:
                row["result"] = f"not attempted (m2 = {best['m2']:g} is proven)"
                continue
            if attempts >= PROOF_ATTEMPTS or budget.expired() or budget.boxes - boxes < 256:
                row["result"] = "not attempted (budget)"
                continue
            if k > 0 and best is None:
                row["result"] = f"not attempted (the easiest margin m2 = {easiest['m2']:g} is not proven)"
                continue
            attempts += 1
            faces = c["faces"]
            split_of = [fc.split_indices(f["lo"], f["hi"]) for f in faces]
            left = (budget.boxes - boxes) // (1 if k == 0 else max(1, PROOF_ATTEMPTS - attempts + 1))
            res = _decide(F, faces, split_of, left, budget.seconds(0.5))
            boxes += res["boxes"]
            if res["status"] == "failed":
                row["result"] = (f"outward at a point of face {res['face']['name']} found by the search (sign n = "
                                 f"{res['value']:.4g})")
                row["why"] = _why(fc, {"face": res["face"], "x": res["x"], "value": res["value"]}, c["w"], w_what)
                continue
            if res["status"] == "undecided":
                row["result"] = f"undecided: {res['fraction']:.3g} of face {res['face']} left"
                res["sampled_max"] = c["sampled"].get(res["face"])
                if best is None and (last_undecided is None or res["fraction"] < last_undecided[3]["fraction"]):
                    last_undecided = (c["m1"], c["m2"], c["w"], res)      # the attempt that got furthest
                continue
            row["result"] = f"proven ({res['boxes']} boxes)"
            best = dict(c, boxes=res["boxes"], n_faces=len(faces))
            if k > 0:
                break
        if best is None:
            continue
        m1, m2, w = best["m1"], best["m2"], best["w"]
        c1, c2 = 1.0 - m1, 1.0 - m2
        region = {"kind": "proven_invariant", "t": [0.0, float(ctx.t_final)],
                  "e1": f"|e1| <= (1 - {m1:g}) F1(t)", "e2": f"|e2| <= (1 - {m2:g}) F2(t)",
                  "margin": {"e1": m1, "e2": m2}, "parameters": ctx.params.describe(),
                  "w_hat": None if w is None else {"ball": "||W_hat||_F <= w", "w": w},
                  "x_esn": "|x_i| <= 1/leak" if "x_esn" in init else None}
        detail = (f"the funnels are kept with margins m1 = {m1:g}, m2 = {m2:g} on [0, {ctx.t_final:g}] s for every "
                  f"plant of the parameter box: S = {{|e1| <= {c1:g} F1, |e2| <= {c2:g} F2"
                  + (f", ||W_hat||_F <= {w:.4g}" if w is not None else "") + "} is forward invariant "
                  f"(every one of its {best['n_faces']} e-faces points inward, {best['boxes']} boxes) and contains "
                  f"{note}")
        return done("proven", detail, region=region, boxes=boxes, undecided_fraction=0.0,
                    extra={"margin": {"e1": m1, "e2": m2}, "w_bound": w, "horizon": "finite", "tried": tried,
                           "cancelled": fc.info["cancelled"], "f_true": fc.info["f_true"]})
    extra = {"margin": None, "w_bound": None, "horizon": "finite", "tried": tried,
             "cancelled": fc.info["cancelled"], "f_true": fc.info["f_true"]}
    if last_undecided is not None:
        m1, m2, w, res = last_undecided
        extra.update(face=res["face"], margin={"e1": m1, "e2": m2}, w_bound=w, fractions=res["fractions"])
        held = res.get("proven_faces") or []
        ball = (f"; the W_hat ball ||W_hat||_F <= {w:.4g} is proven invariant ({w_what})" if w is not None else "")
        sm = res.get("sampled_max")
        return done("undecided", f"no margin proven; at m1 = {m1:g}, m2 = {m2:g} the face {res['face']} is left "
                    f"({res['fraction']:.3g} of it) within the budget"
                    + (f" (at its {SCREEN} sampled points sign n <= {sm:.4g}: inward there, the interval enclosure "
                       "is what is too wide)" if sm is not None and sm < 0 else "")
                    + (f", while the faces {', '.join(held)} are proven" if held else "") + ball, boxes=boxes,
                    undecided_fraction=float(res["fraction"]), extra=extra)
    # the first margin pair whose failure says which inequality fails, else the first with a failing face
    first = next((r for r in tried if r.get("why")), next((r for r in tried if "why" in r), tried[-1]))
    why = first.get("why")
    extra.update(face=_face_of(first.get("result", "")))
    return done("undecided", "no margin of the grid gives an inward-pointing flow on every face (a failed "
                f"certificate, not a counterexample: the simulated loop keeps its funnels); e.g. at m1 = "
                f"{first['m1']:g}, m2 = {first['m2']:g}: {first.get('result')}" + (f"; {why}" if why else ""),
                boxes=boxes, undecided_fraction=1.0, extra=extra)


def proven_set(ctx: Context) -> dict | None:
    """The set S a proven containment certificate of this context shows invariant: {"m1", "m2", "w" (None without
    adaptive weights)}, or None."""
    c = ctx.results.get(CID)
    if c is None or c.status != "proven":
        return None
    return {"m1": float(c.extra["margin"]["e1"]), "m2": float(c.extra["margin"]["e2"]), "w": c.extra.get("w_bound")}


def _face_of(text: str) -> str | None:
    """The face name in a row's result text."""
    k = text.find("face ")
    return text[k + 5:].split(" (")[0] if k >= 0 else None


def _why(fc: _Faces, bad: dict, w: float | None, w_what: str = "sup ||G||_F / kappa over S") -> str:
    """Which inequality fails at an outward point: with W_hat = 0 there, does the face hold? Then the W_hat ball's
    radius is what breaks it (and by how much)."""
    f = bad["face"]
    if w is None or f["i"] != 2:
        return ""
    F = fc.F
    i = F.in_names.index("w_hat")
    x0 = bad["x"].copy()
    x0[F.in_off[i]:F.in_off[i + 1]] = 0.0
    v0 = float(f["sign"] * F.eval_points(x0[None, :])[0, f["pos"]])
    if v0 < 0:
        return (f"with W_hat = 0 the face {f['name']} points inward there (sign n = {v0:.4g}); the estimate "
                f"W_hat^T Phi over the W_hat ball of radius w = {w:.4g} ({w_what}) moves it by "
                f"{bad['value'] - v0:.4g}: the inequality |W_hat^T Phi| < {-v0:.4g} (the face's inward margin) fails "
                f"by a factor {(bad['value'] - v0) / -v0:.3g}")
    return f"the face {f['name']} points outward even with W_hat = 0 (sign n = {v0:.4g})"

"""What the certificates share: the region problem (the design's signals over R_m as one interval-evaluated
function), its ordinary twin (the same signals of the design without the rewriting, for re-checking points), the
local search that improves a witness, and budgets.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..sx.batch import BatchCenteredForm, BatchIntervalFunction
from ..sx.buffered import Buffered
from ..sx.interval import IntervalError
from .region import ParameterBox, region_signals, true_unknown


@dataclass
class Budget:
    """A deterministic budget of work (tape operations x boxes) and an optional wall-clock expiry
    (time.monotonic()); `boxes` is set from the work once the certificate knows the size of its tape."""

    work: float
    expiry: float | None = None
    boxes: int = 0

    def set_tape(self, ops: int, minimum: int = 256) -> int:
        """The box budget for a tape of `ops` operations (at least `minimum`)."""
        self.boxes = max(int(minimum), int(self.work // max(int(ops), 1)))
        return self.boxes

    def seconds(self, share: float = 1.0) -> float | None:
        """Seconds a search may take now: `share` of what is left before the expiry (None: unbounded)."""
        if self.expiry is None:
            return None
        return max(0.0, (self.expiry - time.monotonic()) * share)

    def expired(self) -> bool:
        """Whether the wall-clock limit is reached."""
        return self.expiry is not None and time.monotonic() >= self.expiry


@dataclass
class Context:
    """The scenario's design, horizon, parameter box, fitted W* and state boxes, shared by every certificate."""

    scenario: object
    design: object
    t_final: float
    params: ParameterBox
    W_star: np.ndarray | None                 # n_regressor x n, fitted along the simulated run (None: not known)
    w_hat_range: tuple[np.ndarray, np.ndarray] | None     # min / max of W_hat along the run
    w_star_info: dict = field(default_factory=dict)
    backend: str = "arb"
    results: dict = field(default_factory=dict)   # certificates computed so far (invariance feeds bounds)
    breach: dict | None = None                    # the simulated run's breach from the initial state, if any


def check_rules(f: ca.Function, what: str, file: str, wrt=None, order: int = 1):
    """The batched interval evaluator of f (centered in `wrt` when given, of that `order`), or exit 2 naming the
    signal and the operation without an interval rule."""
    try:
        return BatchCenteredForm(f, wrt, order) if wrt is not None else BatchIntervalFunction(f)
    except IntervalError as exc:
        raise InputError(f"cannot be certified: {exc}", file=file, key=what,
                         expected="signals built from operations with interval rules") from None


class RegionProblem:
    """Named signals over the funnel region R_m: inputs t, s1, s2, m (a point), p (the uncertain parameters only;
    the others are the scenario's numbers) and the controller states."""

    def __init__(self, ctx: Context, exprs: dict[str, ca.SX], p: ca.SX, name: str = "region",
                 centered: tuple[str, ...] = (), extra: dict[str, ca.SX] | None = None, order: int = 1):
        """`centered`: inputs the mean-value form is taken in too (besides t, s1, s2, p); `extra`: symbols of the
        expressions that are inputs of their own, after the controller states (e.g. Coulomb friction's Filippov
        value in place of sign(dq)); `order` 2: the form's Jacobian enclosed by its own mean-value form."""
        d = ctx.design
        self.ctx = ctx
        self.design = d
        P = ctx.params
        self.wide = np.flatnonzero(P.lo < P.hi)
        pu = ca.SX.sym("p", int(self.wide.size))
        full = [ca.SX(float(v)) for v in P.nominal]
        for i, j in enumerate(self.wide):
            full[j] = pu[i]
        exprs = dict(zip(exprs, ca.substitute(list(exprs.values()), [p], [ca.vertcat(*full)])))
        ins, outs, names, states, rewritten = region_signals(d, exprs)
        self.state_names = [k for k, _ in d.states]
        extra = dict(extra or {})
        self.in_names = ["t", "s1", "s2", "m", "p", *self.state_names, *extra]
        self.names = names
        self.rewritten = rewritten
        self.function = ca.Function(name, ins + [pu] + states + list(extra.values()), outs, self.in_names, names,
                                    {"cse": True, "allow_duplicate_io_names": True})
        self.F = check_rules(self.function, f"signal {', '.join(names)}", ctx.scenario.file,
                             wrt=["t", "s1", "s2", "p", *centered], order=order)
        # the ordinary twin: the same expressions in the design's own symbols (no rewriting), for re-checks
        sym = d.sym
        base = [sym[k] for k in ("t", "q", "dq", "qd", "dqd", "ddqd")] + [pu] + states
        self.extra_names = list(extra)
        self.ordinary = ca.Function(name + "_ordinary", base + list(extra.values()), [exprs[k] for k in names],
                                    ["t", "q", "dq", "qd", "dqd", "ddqd", "p", *self.state_names, *extra], names,
                                    {"allow_duplicate_io_names": True})
        self._alpha2 = d.function("alpha2", ["t", "q", "qd", "dqd"])
        self._F = d.function("funnel_bounds", ["t"], ["F1", "F2"])

    def region(self, m: float, states: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
        """The region (input name -> (lo, hi)) for margin m with the given controller-state boxes."""
        n = self.design.n
        P = self.ctx.params
        out = {"t": (0.0, float(self.ctx.t_final)), "s1": (-np.ones(n), np.ones(n)), "s2": (-np.ones(n), np.ones(n)),
               "m": (float(m), float(m)), "p": (P.lo[self.wide].copy(), P.hi[self.wide].copy())}
        out.update(states)
        return out

    def flat(self, region: dict) -> tuple[np.ndarray, np.ndarray]:
        """Flat (lo, hi) of a region dict in the function's input layout."""
        lo, hi = self.F.flatten_box({k: region[k] for k in self.in_names})
        return np.asarray(lo, float), np.asarray(hi, float)

    def split_indices(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Flat indices that are bisected: t, s1, s2 and the uncertain parameters (never m or the states)."""
        F = self.F
        idx = []
        for name in ("t", "s1", "s2", "p"):
            i = F.in_names.index(name)
            idx += [j for j in range(F.in_off[i], F.in_off[i + 1]) if lo[j] < hi[j]]
        return np.array(idx, dtype=int)

    def work_per_box(self) -> int:
        """Tape operations one box costs the centered form: the function twice (box, center) and its Jacobian (of
        a second-order form: the Jacobian twice and its own Jacobian), and a refine hook's tape per pass."""
        from ..sx.tape import count_ops
        from ..sx.batch import BatchCenteredForm

        def ops(G):
            # counted when G's tape was read (BatchIntervalFunction.operations), else by reading it
            n = getattr(G, "operations", None)
            return n if isinstance(n, int) else count_ops(G.function)["operations"]

        def cost(F):
            f = ops(F.natural)
            jac = getattr(F.jac, "inner", F.jac)
            # a refine hook's own tape (e.g. the regressor columns) per pass
            hook = getattr(getattr(F, "refine", None), "F", None)
            extra = F.refine_passes * ops(hook) if hook is not None else 0
            return 2 * f + extra + (cost(jac) if isinstance(jac, BatchCenteredForm) else ops(jac))
        return cost(self.F)

    def initial_boxes(self, lo: np.ndarray, hi: np.ndarray, limit: int = 4096):
        """(LO, HI) of the first boxes: the region cut at the normalised errors where the transformation switches
        formula (its BREAKPOINTS, e.g. the log transformation's series for s/atanh(s)), while at most `limit`."""
        import itertools
        T = self.design.variant.transform
        cuts = [b for b in getattr(T, "BREAKPOINTS", ()) if b > 0]
        m = float(lo[self.F.in_off[self.F.in_names.index("m")]])
        pieces = []
        for name in ("s1", "s2"):
            i = self.F.in_names.index(name)
            for j in range(self.F.in_off[i], self.F.in_off[i + 1]):
                # just inside the switch, so the middle piece decides the transformation's condition for sure
                cs = [0.999 * c / (1 - m) for c in cuts]
                pts = sorted({float(c) for c in cs if c < hi[j]} | {float(-c) for c in cs if -c > lo[j]})
                edges = [lo[j], *pts, hi[j]]
                pieces.append((j, list(zip(edges[:-1], edges[1:]))))
        count = int(np.prod([len(p) for _, p in pieces])) if pieces else 1
        if count == 1 or count > limit:
            return lo[None, :].copy(), hi[None, :].copy()
        LO, HI = [], []
        for combo in itertools.product(*[p for _, p in pieces]):
            a, b = lo.copy(), hi.copy()
            for (j, _), (x, y) in zip(pieces, combo):
                a[j], b[j] = x, y
            LO.append(a)
            HI.append(b)
        return np.array(LO), np.array(HI)

    def point(self, x: np.ndarray) -> dict:
        """A flat point as per-input arrays."""
        return self.F.unflatten_point(np.asarray(x, float))

    def state_point(self, point: dict) -> dict:
        """The design-input point (t, q, dq, reference, states, p) of a region point (t, s1, s2, m, p, states)."""
        t = float(np.ravel(point["t"])[0])
        m = float(np.ravel(point["m"])[0])
        qd, dqd, ddqd = (np.asarray(v, float).ravel() for v in self.design.reference(t))
        F1, F2 = (np.asarray(v, float).ravel() for v in self._F(t))
        q = qd + np.ravel(point["s1"]) * (1 - m) * F1
        a2 = np.asarray(self._alpha2(t, q, qd, dqd), float).ravel()
        dq = a2 + np.ravel(point["s2"]) * (1 - m) * F2
        out = {"t": t, "q": q, "dq": dq, "qd": qd, "dqd": dqd, "ddqd": ddqd, "p": np.ravel(point["p"])}
        for k in self.state_names:
            out[k] = np.asarray(point[k], float)
        return out

    def ordinary_values(self, point: dict) -> dict[str, np.ndarray]:
        """Every signal at a region point by the ordinary CasADi Function of the design (not the rewritten one)."""
        sp = self.state_point(point)
        sp.update({k: np.asarray(point[k], float) for k in self.extra_names})
        vals = self.ordinary(*[sp[k] for k in ["t", "q", "dq", "qd", "dqd", "ddqd", "p", *self.state_names,
                                               *self.extra_names]])
        vals = [vals] if len(self.names) == 1 else vals
        return {k: np.asarray(v, float).ravel() for k, v in zip(self.names, vals)}

    def counterexample(self, point: dict) -> dict:
        """The contract's counterexample dict of a region point: t, q, dq, the uncertain parameters, the states."""
        sp = self.state_point(point)
        P = self.ctx.params
        m = float(np.ravel(point["m"])[0])
        out = {"t": sp["t"], "q": sp["q"].tolist(), "dq": sp["dq"].tolist(),
               "e_over_F": {"e1": (np.ravel(point["s1"]) * (1 - m)).tolist(),
                            "e2": (np.ravel(point["s2"]) * (1 - m)).tolist()},
               "parameters": {P.names[j]: float(v) for j, v in zip(self.wide, sp["p"])}}
        for k in self.state_names:
            out[k] = np.asarray(sp[k]).tolist()
        return out


_WITNESS: dict = {}


def improve(f: ca.Function, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, pos: int, sign: float,
            iterations: int = 40) -> tuple[np.ndarray, float]:
    """A better witness for max sign * g[pos] near the flat point x of the flat box: sign-gradient steps of
    shrinking size on every input (controller states included), each kept only if CasADi's double value improves.
    `f` is the region Function (flat inputs concatenated in order)."""
    xin = f.sx_in()
    key = (id(f), pos)
    if key not in _WITNESS or _WITNESS[key][0] is not f:
        outs = f.call(xin)
        y = ca.vertcat(*[ca.SX(o).nz[:] for o in outs])[pos]
        xs = ca.vertcat(*[v.nz[:] for v in xin])
        _WITNESS[key] = (f, ca.Function("witness", xin, [ca.densify(y), ca.densify(ca.jacobian(y, xs))]))
        while len(_WITNESS) > 64:
            _WITNESS.pop(next(iter(_WITNESS)))
    # on numpy buffers: a DM per input and call cost more than the evaluation (the inputs' nonzeros are the
    # slices of the flat point, the dense gradient's nonzeros the gradient)
    fx = Buffered(_WITNESS[key][1])
    offs = np.cumsum([0] + [v.nnz() for v in xin])

    def call(z):
        for i, a in enumerate(fx.args):
            a[:] = z[offs[i]:offs[i + 1]]
        fx.evaluate()
        return float(fx.res[0][0]), fx.res[1].copy()
    x = np.clip(np.asarray(x, float).copy(), lo, hi)
    v, g = call(x)
    best = sign * v
    if not np.isfinite(best):
        return x, best
    step = 0.5
    width = hi - lo
    for _ in range(iterations):
        g = g * sign
        if not np.all(np.isfinite(g)) or not np.any(g):
            break
        cand = np.clip(x + step * width * np.sign(g), lo, hi)
        vc, gc = call(cand)
        if np.isfinite(vc) and sign * vc > best:
            x, best, g = cand, sign * vc, gc
        else:
            step *= 0.5
            if step < 1e-6:
                break
    return x, best


def controller_state_boxes(ctx: Context, w_box: tuple[np.ndarray, np.ndarray] | None) -> dict:
    """Boxes of the controller states: each approximator state in its invariant box, W_hat in `w_box`."""
    d = ctx.design
    box = d.approximator.box()
    out = {}
    for name, (r, c) in d.states:
        if name == "w_hat":
            if w_box is None:
                raise ValueError("a W_hat box is needed")
            out[name] = w_box
        else:
            h = float(box[name])
            shape = (r,) if c == 1 else (r, c)
            out[name] = (-h * np.ones(shape), h * np.ones(shape))
    return out


def unknown_exprs(ctx: Context, p: ca.SX, W_star) -> dict[str, ca.SX]:
    """eps = f_true - W*^T Phi (the design's Phi, the plant's exact nonlinearities), f_true and the applied torque."""
    d = ctx.design
    tu = true_unknown(d, p)
    if d.n_regressor:
        eps = tu["f_true"] - ca.mtimes(ca.DM(np.asarray(W_star, float)).T, d.signals["Phi"])
    else:
        eps = tu["f_true"]
    return {"eps": eps, "f_true": tu["f_true"]}

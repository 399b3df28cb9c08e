"""`certify.sampled`: the deployed controller's funnels over one sampling period, proven for a rate f = 1/h.

The set S of states at a sampling instant t_k in [0, T]: |e1_j| <= (1 - m1) F1_j(t_k), |e2_j| <= (1 - m2) F2_j(t_k),
x_esn in its invariant box |x_i| <= 1/leak, W_hat in a box (declared, or the simulated run's range widened), every
parameter of the box (the dead zone's breakpoints and scales included). `SampledSet` is the seam: S is declared
(margins by option) or `containment_set`, the set a proven `certify.containment` shows invariant (W_hat then in its
ball ||W_hat||_F <= w).

In the normalised errors sigma_i = e_i / F_i (the region coordinates s of `region.region_signals` at m = 0) the plant
under the held torque u_k is the non-autonomous ODE

    sigma_i' = (e_i' - sigma_i F_i') / F_i,   e1' = dq - dqd,   e2' = ddq_plant(t, q, dq, u_k, p) - alpha2_dot,

written on the design's own graph (rewritten over the region, so F - |e| is never a cancellation). For a box K of
sample states (t_k, sigma_k, p, controller states) and h:

1. u_k: the enclosure of the C step's torque over K (`emit.step.step_core`'s tau: the design's torque, saturated at
   tau_max; the step's projection onto the funnels is the identity on S since m >= 1 - CLIP);
2. a-priori enclosure: in Taylor form around the rates at the sample (`OnePeriod._taylor`), else first-order
   Picard -- a box Sigma with K_sigma + [0, h] sigma'([t_k, t_k + h], Sigma, u_k, p) inside Sigma; either encloses
   sigma(t) on the whole period;
3. (a) the funnels with the rate's margin M between the samples -- implied by (b) when S lies within them (the
   convexity argument below), else Sigma within |sigma| <= 1 - M -- and (b) the next sample sigma_k + h sigma'(...)
   (+ h^2/2 sigma'', on monotone faces where that pays) within S's margins; W_hat's exponential-Euler update stays in
   its set (an affine update: W+ = b W + phi A, b = 1 - phi c in [0, 1], so A's enclosure inside c times the box, or
   ||A||_F <= c w for containment's ball, suffices, whatever h);
   x_esn's update is the convex combination exp(-lambda h) x + (1 - exp(-lambda h)) tanh(.)/leak (emit.step's ETD
   lemma), inside its box at every h. With a projected law (`[adaptation] projection`) the step clips W_hat onto the
   ball ||W_hat||_F <= R (1 + eps) after its update, so a W_hat box containing that ball is kept at every h (S then
   takes that box, unless one is declared; one that does not contain the ball is undecided).

`sampled_rate` bisects in h and brackets the result with the simulated rate and the theory bound.

Boxes failing a check are bisected (t, sigma and the uncertain parameters; the controller states are never split);
the interior of S passes in large boxes, the layer within one period's reach of its faces is refined. Proven at h
is proven at every h' <= h: the a-priori box covers [t_k, t_k + h'], and (b)'s bound of sigma(t_k + s) for one sample
state, x + s sigma'(x) + s^2/2 max(sigma''_hi, 0) (or x + s max(D_hi, 0)), is convex in s and inside S at s = 0 and
s = h, so on all of [0, h]: the state stays in S during the whole period. So bisection in h gives f_proven.
A point of S whose degenerate box fails ends the search at that h early (the method cannot prove it there; that is
not a refutation: only a sampled run that breaches refutes a rate).
"""

from __future__ import annotations

import copy
import time

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..family.projection import outer_radius
from ..plant.equations import plant_acceleration, plant_parameters
from ..sx.batch import BatchCenteredForm, BatchIntervalFunction
from ..sx.interval import IntervalError
from .problem import Context
from .ball_form import BallForm
from .face_forms import normal_components, with_alpha2_dot_through_e1
from .region import region_signals
from .sampled_set import SampledSet, containment_set, declared_set  # noqa: F401 (their home before)
from .sampled_graph import _add_dn, _add_up, _continuous_rates, _dn, _switching_on, _up, coulomb_signs_as
from .sampled_taylor import PICARD_ITERATIONS, taylor

CID = "certify.sampled"
#: S's margins (e1, e2) when none are given
DEFAULT_SET_MARGIN = (0.5, 0.5)
#: boxes evaluated per batch
BATCH = 256
#: the sensitivity's split variable is used while its relative width is at least the widest's / HINT_RATIO
HINT_RATIO = 4.0
#: why a box fails, by the first check it fails: no finite torque enclosure, no finite rate, no a-priori box within the
#: funnels with margin M (the Picard iteration left them), (a) the funnels with margin M on the period, (b) the next
#: sample outside S, W_hat's update outside its box
WHY = ("", "torque", "rates", "enclosure", "funnel", "next sample", "w_hat")
#: a failing box thinner than this (relative to S) in every split variable ends the search at that h
THIN = 1e-4
#: containment's exact rewrites applied to the one-period map (`face_forms.normal_components`); each falls back to
#: the design's own form where the graph does not have the form it needs
REWRITES = ("alpha2_dot through e1", "adjugate", "pivot order", "tau through e1")
#: random sample points screened (as degenerate boxes) before a branch and bound at one h
SCREEN_POINTS = 128


def _check(f: ca.Function, file: str, what: str, wrt=None):
    try:
        return BatchCenteredForm(f, wrt) if wrt else BatchIntervalFunction(f)
    except IntervalError as exc:
        raise InputError(f"cannot be certified: {exc}", file=file, key=what,
                         expected="signals built from operations with interval rules") from None


class OnePeriod:
    """The one-period map's interval pieces for one design and parameter box: the held torque over a box of sample
    states, the normalised errors' rates under a held torque, and W_hat's update (see the module doc)."""

    def __init__(self, ctx: Context, S: SampledSet, tau_max=None, rewrites=REWRITES):
        d, sc = ctx.design, ctx.scenario
        n = d.n
        self.ctx, self.S, self.n = ctx, S, n
        P = ctx.params
        self.wide = np.flatnonzero(P.lo < P.hi)
        names, _ = plant_parameters(sc)
        pu = ca.SX.sym("p", int(self.wide.size))
        full = [ca.SX(float(v)) for v in P.nominal]
        for i, j in enumerate(self.wide):
            full[j] = pu[i]
        # the parameters enter as constants where they are points, so a term multiplied by a zero parameter (e.g.
        # Coulomb friction's sign(dq) at coulomb = 0) folds away at construction instead of flagging a switch
        p = ca.vertcat(*full)
        assert p.numel() == len(names)
        Sg, sym = d.signals, d.sym
        tau = Sg["tau"]
        if tau_max is not None:
            tm = ca.DM(np.broadcast_to(np.asarray(tau_max, float), (n,)).copy())
            tau = ca.fmin(ca.fmax(tau, -tm), tm)
        u = ca.SX.sym("u", n)
        ddq = plant_acceleration(sc, sym["q"], sym["dq"], sym["t"], u, 0.0, p=p)["ddq"]
        self.continuous, self.continuity = _continuous_rates(
            d, [sym["t"], sym["q"], sym["dq"], u, pu], [sym["t"], sym["q"], sym["dq"]], ddq)
        # the normal components in containment's exact rewrites (`face_forms.normal_components`: dq_d dropped from
        # de1, alpha2_dot through e1, M_p^-1 by the adjugate for two joints, and for more the LDL^T elimination
        # order with the larger pivots), each checked on the graph
        adj, e1, piv = ("adjugate" in rewrites, "alpha2_dot through e1" in rewrites,
                        "pivot order" in rewrites)
        # for three or more joints M_p^-1 may be preconditioned at a point per box (its centre's q: `_full`)
        qc = ca.SX.sym("qc", n) if n >= 3 and piv else None
        n1, n2u, self.forms = normal_components(d, p, adj, u=u, through_e1=e1, pivots=piv, qc=qc)
        qc = qc if self.forms["solve"].startswith("preconditioned") else None
        rates = ca.vertcat(n1 / Sg["F1"], n2u / Sg["F2"])
        # the rates at the sample itself, under the step's own torque: there the plant's acceleration minus
        # alpha2_dot is f_true + de2 (f_true in the inverse-dynamics residual form where the design's torque is the
        # model's inverse dynamics: no M_p^-1 tau - alpha2_dot cancellation); with saturation the held form at the
        # saturated torque
        _, n2k, self.forms_k = normal_components(d, p, adj, u=None if tau_max is None else tau, through_e1=e1,
                                                 pivots=piv, qc=qc)
        rates_k = ca.vertcat(n1 / Sg["F1"], n2k / Sg["F2"])
        # the held torque's enclosure with alpha2_dot through e1 too (the same function: the C step's torque)
        tau_e = with_alpha2_dot_through_e1(d, tau)[0] if "tau through e1" in rewrites else tau
        exprs = {"tau": tau_e, "rate": rates, "rate_k": rates_k}
        # Coulomb friction's sign(dq) as inputs sw: where it is what makes sigma' jump along a period, the rates with
        # sw held are smooth in (t, sigma), and the Taylor a-priori form takes sw in its hull over the box (`_taylor`)
        self.n_sw = 0
        swv = ca.SX.sym("sw", n)
        if not self.continuous:
            ddq_s = coulomb_signs_as(ddq, sym["dq"], swv)[0]
            state = [sym["t"], sym["q"], sym["dq"]]
            ins = state + [u, pu]
            rs, rks = coulomb_signs_as([rates, rates_k], sym["dq"], swv)
            before, after = ([ca.vec(x) for x in xs] for xs in ((rates, rates_k), (rs, rks)))
            if _continuous_rates(d, ins + [swv], state, ddq_s)[0] and \
                    _switching_on(ca.symvar(ca.vertcat(*after, swv)), state, after) < \
                    _switching_on(ca.symvar(ca.vertcat(*before)), state, before):
                exprs.update(rate_s=rs, rate_k_s=rks, sw_arg=sym["dq"])
                self.n_sw, self._swv = n, swv
        self.w_rate = None
        # a projected law: the deployed step clips W_hat radially onto ||W_hat||_F <= R (1 + eps) after its update
        # (emit.step), so W_hat's next sample lies in that ball whatever the period -- a box containing the ball is
        # kept without the affine argument
        proj = d.parts.get("projection")
        self.w_ball = outer_radius(proj["R"], proj["eps"]) if proj is not None else None
        if "w_hat" in sym:
            W = sym["w_hat"]
            wdot = Sg["w_hat_dot"]
            J = ca.jacobian(ca.vec(wdot), ca.vec(W))
            c = None
            try:
                Jd = np.asarray(ca.evalf(J), float)
            except RuntimeError:        # W_hat's rate is not affine in W_hat with a constant Jacobian
                Jd = None
            if Jd is not None:
                diag = np.diag(Jd)
                # the step's exponential-Euler weight decays at Gamma sigma: W+ = (1 - phi c) W + phi A is a convex
                # combination only when the rate's own decay c is that one
                lam = float(sc.gamma) * float(sc.sigma)
                if np.all(Jd - np.diag(diag) == 0) and np.all(diag == diag[0]) and diag[0] < 0 \
                        and abs(-float(diag[0]) - lam) <= 1e-12 * lam:
                    c = -float(diag[0])
            if c is not None:
                exprs["w_affine"] = ca.vec(ca.substitute(wdot, W, ca.SX.zeros(*W.shape)))
                self.w_rate = c
        ins, outs, onames, states, _ = region_signals(d, exprs)
        self.state_names = [k for k, _ in d.states]
        t, s1, s2, m = ins
        self.qc_f = None
        if qc is not None:
            # the preconditioner's point, carried like a controller state (last), set per box by `_full`
            states = states + [qc]
            self.state_names = self.state_names + ["qc"]
            self.qc_f = ca.Function("qc", [t, s1], [d.reference_t["qd"] + s1 * Sg["F1"]])
            self._qc_maps = {}
        opts = {"cse": True, "allow_duplicate_io_names": True}
        o = dict(zip(onames, outs))
        base = [t, s1, s2, m, pu]
        bnames = ["t", "s1", "s2", "m", "p"]
        self.tau_f = ca.Function("held_tau", base + states, [o["tau"]], bnames + self.state_names, ["tau"], opts)
        self.tau = _check(self.tau_f, sc.file, "signal tau", ["t", "s1", "s2", "p"])
        self.rate_f = ca.Function("sigma_rate", base + [u] + states, [o["rate"]],
                                  bnames + ["u"] + self.state_names, ["rate"], opts)
        self.rate = _check(self.rate_f, sc.file, "the normalised errors' rates", ["t", "s1", "s2", "p", "u"])
        # the next sample to second order: sigma_k + h sigma'(t_k, sigma_k, u_k) (one function of the sample
        # state, so its centered form keeps the correlation of sigma_k with its own rate) plus h^2/2 sigma'' over
        # the period's enclosure, sigma'' = d sigma'/dt + d sigma'/d sigma sigma' (u held)
        hs = ca.SX.sym("h")
        sig = ca.vertcat(s1, s2)
        nxt = sig + hs * o["rate_k"]
        self.next_f = ca.Function("next_sample", base + [hs] + states, [nxt], bnames + ["h"] + self.state_names,
                                  ["next"], opts)
        self.next = _check(self.next_f, sc.file, "the next sample", ["t", "s1", "s2", "p"])
        # the rates at the sample under the step's own torque, alone (the Taylor a-priori enclosure's centre)
        self.ratek_f = ca.Function("sigma_rate_k", base + states, [o["rate_k"]], bnames + self.state_names,
                                   ["rate_k"], opts)
        self.ratek = _check(self.ratek_f, sc.file, "the normalised errors' rates at the sample",
                            ["t", "s1", "s2", "p"])
        acc = ca.jacobian(o["rate"], t) + ca.mtimes(ca.jacobian(o["rate"], sig), o["rate"])
        self.acc_f = ca.Function("sigma_acc", base + [u] + states, [acc], bnames + ["u"] + self.state_names,
                                 ["acc"], opts)
        self.acc = _check(self.acc_f, sc.file, "the normalised errors' second derivative", None)
        self._switch_free(base, bnames, u, states, o, opts)
        self.w_f = None
        if self.w_rate is not None:
            self.w_f = ca.Function("w_affine", base + states, [o["w_affine"]], bnames + self.state_names, ["A"],
                                   opts)
            self.w_aff = _check(self.w_f, sc.file, "signal w_hat_dot", None)
        # flat layout: [t, s1 (n), s2 (n), m, p (np), states...]; the rate function has u (n) after p
        self.np = int(self.wide.size)
        self.i_p = 2 * n + 2
        self.i_st = self.i_p + self.np
        self.dim = self.i_st                      # the split part: t, s1, s2, m, p (m is a point)
        self._on(S)

    def on_set(self, S: SampledSet) -> "OnePeriod":
        """The same one-period map over another set S: its interval forms (which do not depend on S) shared, what
        depends on S (the controller states' boxes, S's limits, W_hat's ball) set anew -- what OnePeriod(ctx, S,
        tau_max) with this one's ctx and tau_max builds, without building its forms a second time."""
        other = copy.copy(self)
        other._on(S)
        return other

    def _on(self, S: SampledSet) -> None:
        """The parts that depend on S: the set itself, W_hat's ball forms, the controller states' boxes, the limits."""
        n = self.n
        self.S = S
        # W_hat in containment's ball: the torque and the rates at the sample enclosed over the ball, not its box
        self.ball = S.w_ball if (S.w_ball is not None and "w_hat" in self.state_names) else None
        if self.ball is not None:
            self.tau_ball, self.ratek_ball = BallForm(self.tau), BallForm(self.ratek)
            self.ratek_s_ball = BallForm(self.ratek_s) if self.n_sw else None
        st_lo, st_hi = [], []
        F = self.tau.natural
        for k in self.state_names:
            if k == "qc":           # any point serves (the solve is exact for every C): the reference's start
                q0 = np.asarray(self.qc_f(0.0, np.zeros(n)), float).ravel()
                st_lo.append(q0)
                st_hi.append(q0)
                continue
            lo, hi = S.states[k]
            i = F.in_names.index(k)
            a, b = np.asarray(lo, float).reshape(-1, order="F"), np.asarray(hi, float).reshape(-1, order="F")
            assert a.size == F.in_off[i + 1] - F.in_off[i]
            st_lo.append(a)
            st_hi.append(b)
        self.st_lo = np.concatenate(st_lo) if st_lo else np.zeros(0)
        self.st_hi = np.concatenate(st_hi) if st_hi else np.zeros(0)
        self.taylor = True                        # the Taylor a-priori enclosure first (`_taylor`)
        self.monotone = True                      # the next sample's bounds on monotone faces (`_monotone`)
        self.lim_S = np.concatenate([np.full(n, 1 - S.m1), np.full(n, 1 - S.m2)])

    def _switch_free(self, base, bnames, u, states, o, opts):
        """The rates with Coulomb friction's sign(dq) as inputs `sw` and the signs' arguments (dq in the region's
        coordinates), where the constructor found that replacing them leaves sigma' continuous along a period."""
        if not self.n_sw:
            return
        sw, rs, rks = self._swv, o["rate_s"], o["rate_k_s"]
        F = ca.Function("sigma_rate_sw", base + [u] + states + [sw], [rs], bnames + ["u"] + self.state_names +
                        ["sw"], ["rate"], opts)
        self.rate_s = _check(F, self.ctx.scenario.file, "the normalised errors' rates",
                             ["t", "s1", "s2", "p", "u", "sw"])
        F = ca.Function("sigma_rate_k_sw", base + states + [sw], [rks], bnames + self.state_names + ["sw"],
                        ["rate_k"], opts)
        self.ratek_s = _check(F, self.ctx.scenario.file, "the normalised errors' rates at the sample",
                              ["t", "s1", "s2", "p"])
        F = ca.Function("switch_arguments", base + [u] + states, [o["sw_arg"]], bnames + ["u"] + self.state_names,
                        ["x"], opts)
        self.sw_args = _check(F, self.ctx.scenario.file, "the rates' sign arguments", None)

    def _signs(self, L, H):
        """The hull of each switched sign over boxes of its arguments' inputs (rows laid out as the held-torque
        rates' inputs, u included): [1, 1] where its argument is > 0, [-1, -1] where < 0, else [-1, 1]."""
        AL, AH, _ = self.sw_args.eval_batch(L, H)
        lo = np.where(np.isfinite(AL) & (AL > 0), 1.0, -1.0)
        hi = np.where(np.isfinite(AH) & (AH < 0), -1.0, 1.0)
        return lo, hi

    def box(self, t_final: float) -> tuple[np.ndarray, np.ndarray]:
        """The flat box of S (without the controller states)."""
        n = self.n
        P = self.ctx.params
        lo = np.concatenate([[0.0], -self.lim_S, [0.0], P.lo[self.wide]])
        hi = np.concatenate([[float(t_final)], self.lim_S, [0.0], P.hi[self.wide]])
        assert lo.size == self.dim and n >= 1
        return lo, hi

    def split_vars(self, lo, hi) -> np.ndarray:
        """Flat indices bisected: t, s1, s2 and the uncertain parameters."""
        return np.array([j for j in range(self.dim) if j != 2 * self.n + 1 and lo[j] < hi[j]], dtype=int)

    def _full(self, LO, HI):
        K = LO.shape[0]
        FL = np.concatenate([LO, np.repeat(self.st_lo[None, :], K, 0)], axis=1)
        FH = np.concatenate([HI, np.repeat(self.st_hi[None, :], K, 0)], axis=1)
        if self.qc_f is not None and K:
            # the preconditioner's point: q at the box's centre (t and s1 at their midpoints), the same in FL, FH
            n = self.n
            if K not in self._qc_maps:
                self._qc_maps[K] = self.qc_f.map(K)
            c = 0.5 * LO + 0.5 * HI
            q = np.asarray(self._qc_maps[K](c[:, 0][None, :], c[:, 1:n + 1].T), float).T
            FL[:, -n:] = q
            FH[:, -n:] = q
        return FL, FH

    def check(self, LO: np.ndarray, HI: np.ndarray, h: float, M: float) -> tuple[np.ndarray, dict]:
        """Per box (rows of the flat split part), whether both funnels with margin M on the period and the return
        to S are proven at period h; and the enclosures (sigma' box, a-priori Sigma) for the record."""
        n = self.n
        K = LO.shape[0]
        FL, FH = self._full(LO, HI)
        UL, UH, _ = self.tau_ball.eval_batch(FL, FH, self.ball) if self.ball is not None else \
            self.tau.eval_batch(FL, FH)
        ok = np.all(np.isfinite(UL) & np.isfinite(UH), axis=1)
        why = np.where(ok, 0, WHY.index("torque"))           # the first check a box fails (WHY), 0 = none
        hint = np.full(K, -1, dtype=int)
        switched = np.ones(K, dtype=bool)         # a discontinuous operation (sign, if_else) may switch on the period
        sl = slice(1, 2 * n + 1)
        kl, kh = LO[:, sl], HI[:, sl]
        lim_M = 1.0 - M
        # (a) follows from (b) when S lies within the funnels with margin M (`implied`, the module doc): then the
        # a-priori box need only stay where the rates are defined (|sigma| < 1), not within the margin M
        implied = bool(np.all(self.lim_S <= lim_M))
        lim_P = 1.0 if implied else lim_M
        # Picard: Sigma_{j+1} = K + [0, h] f(T, Sigma_j); valid once Sigma_{j+1} is inside Sigma_j
        wl, wh = kl.copy(), kh.copy()
        valid = np.zeros(K, dtype=bool)
        DL = np.full((K, 2 * n), -np.inf)
        DH = np.full((K, 2 * n), np.inf)
        SL, SH = wl.copy(), wh.copy()
        tl, th = LO[:, 0], _up(HI[:, 0] + h)
        if self.taylor and ok.any():
            # the Taylor form first (the rates' correlation with the held torque kept), the first-order form where
            # it fails
            idx = np.flatnonzero(ok)
            tv, tDL, tDH, tSL, tSH, tsw = self._taylor(FL[idx], FH[idx], kl[idx], kh[idx], tl[idx], th[idx],
                                                       UL[idx], UH[idx], h, lim_P)
            good = idx[tv]
            valid[good] = True
            DL[good], DH[good], SL[good], SH[good] = tDL[tv], tDH[tv], tSL[tv], tSH[tv]
            switched[good] = tsw[tv]
        for it in range(PICARD_ITERATIONS):
            live = ok & ~valid
            if not live.any():
                break
            idx = np.flatnonzero(live)
            RL, RH, RS = self._rate_in(FL[idx], FH[idx], tl[idx], th[idx], wl[idx], wh[idx], UL[idx], UH[idx])
            fin = np.all(np.isfinite(RL) & np.isfinite(RH), axis=1)
            nl = _add_dn(kl[idx], h * np.minimum(RL, 0.0))
            nh = _add_up(kh[idx], h * np.maximum(RH, 0.0))
            inside = fin & np.all((nl >= wl[idx]) & (nh <= wh[idx]), axis=1)
            good = idx[inside]
            valid[good] = True
            DL[good], DH[good] = RL[inside], RH[inside]
            switched[good] = RS[inside]
            SL[good], SH[good] = wl[good], wh[good]
            bad = idx[~fin]
            why[bad[ok[bad]]] = WHY.index("rates")
            ok[bad] = False
            grow = idx[fin & ~inside]
            g = np.flatnonzero(fin & ~inside)
            # inflate, on the sides the new bounds leave only: widened by a tenth of their width and an absolute
            # 1e-9 (a side that is contained stays where it is: at a face of S where the rate points inward the
            # box then keeps the face's value exactly instead of crossing the margin by the inflation)
            w = nh[g] - nl[g]
            wl[grow] = np.where(nl[g] < wl[grow], _dn(nl[g] - 0.1 * w - 1e-9), wl[grow])
            wh[grow] = np.where(nh[g] > wh[grow], _up(nh[g] + 0.1 * w + 1e-9), wh[grow])
            # an enclosure that leaves the funnels with margin M cannot pass (a): stop inflating it
            out = np.any((wl[grow] < -lim_P) | (wh[grow] > lim_P) if not implied else
                         (wl[grow] <= -lim_P) | (wh[grow] >= lim_P), axis=1)
            why[grow[out][ok[grow[out]]]] = WHY.index("funnel")
            ok[grow[out]] = False
        why[ok & ~valid] = WHY.index("enclosure")
        # a box whose enclosure left the funnels with margin M: split the normalised error that leaves (the layer
        # of S at that face is what needs refining), unless the B&B finds it much thinner than the widest variable
        out = np.flatnonzero(why == WHY.index("funnel"))
        if out.size:
            viol = np.maximum(wh[out] - lim_P, -lim_P - wl[out])
            hint[out] = 1 + np.argmax(viol, axis=1)
        ok &= valid
        # (a) the funnels with margin M over the whole period
        a = implied | np.all((SL >= -lim_M) & (SH <= lim_M), axis=1)
        fa = np.flatnonzero(ok & ~a)
        why[fa] = WHY.index("funnel")
        hint[fa] = 1 + np.argmax(np.maximum(SH[fa] - lim_M, -lim_M - SL[fa]), axis=1)
        ok &= a
        # (b) the next sample in S: first order K + h D, and where that fails the second-order form
        el = _dn(kl + _dn(h * DL))
        eh = _up(kh + _up(h * DH))
        first = np.all((el >= -self.lim_S) & (eh <= self.lim_S), axis=1)
        # the second-order form needs sigma' Lipschitz along the period: not where a discontinuity (Coulomb's sign,
        # a branch) may switch inside the a-priori box (interval AD of |.|, min, max encloses Clarke's Jacobian)
        need = np.flatnonzero(ok & ~first & (self.continuous | ~switched))
        if need.size:
            i = need
            XL, XH = self._with_h(FL[i], FH[i], h)
            NL, NH, nsw, J = self.next.eval_batch(XL, XH, with_jacobian=True)
            if self.monotone:
                NL, NH = self._monotone(XL, XH, NL, NH, np.asarray(nsw, bool))
            AL, AH = self._acc_in(FL[i], FH[i], tl[i], th[i], SL[i], SH[i], UL[i], UH[i])
            r = _up(_up(h * h) * 0.5)
            el2 = _dn(NL + _dn(r * np.minimum(AL, 0.0)))
            eh2 = _up(NH + _up(r * np.maximum(AH, 0.0)))
            second = np.all(np.isfinite(el2) & np.isfinite(eh2) & (el2 >= -self.lim_S) & (eh2 <= self.lim_S), axis=1)
            first[i] = second
            hint[i] = self._hint(LO[i], HI[i], el2, eh2, J)
        why[ok & ~first] = WHY.index("next sample")
        ok &= first
        if self.w_f is not None and ok.any():
            idx = np.flatnonzero(ok)
            good = self.w_kept(FL[idx], FH[idx])
            why[idx[~good]] = WHY.index("w_hat")
            ok[idx[~good]] = False
        return ok, {"why": why, "DL": DL, "DH": DH, "SL": SL, "SH": SH, "UL": UL, "UH": UH, "hint": hint}

    def _taylor(self, FL, FH, kl, kh, tl, th, UL, UH, h, lim):
        """The a-priori enclosure in Taylor form per box of sample states (`sampled_taylor.taylor`): (valid, DL,
        DH, SL, SH, switched)."""
        return taylor(self, FL, FH, kl, kh, tl, th, UL, UH, h, lim)

    def _monotone(self, XL, XH, NL, NH, sw):
        """The next sample's bounds tightened by monotonicity: where next_o is provably nondecreasing in a variable
        on the box (its Jacobian's interval >= 0, interval AD on a box where no discontinuity switches), its upper
        bound is taken on the box's upper face in that variable (nonincreasing: the lower face), and conversely for
        the lower bound; each output's bound is the centered form on its own reduced box."""
        keep = np.flatnonzero(~sw)
        if not keep.size:
            return NL, NH
        XL, XH = XL[keep], XH[keep]
        m, n2 = XL.shape[0], 2 * self.n
        wf = self.next.w_flat
        JL, JH, _ = self.next.jac.eval_batch(XL, XH)
        JL = JL.reshape(m, wf.size, n2).transpose(0, 2, 1)
        JH = JH.reshape(m, wf.size, n2).transpose(0, 2, 1)
        lo_w, hi_w = XL[:, wf][:, None, :], XH[:, wf][:, None, :]
        up_pick = np.where(JL >= 0, hi_w, np.where(JH <= 0, lo_w, np.nan))       # (m, n2, nw): where max is
        dn_pick = np.where(JL >= 0, lo_w, np.where(JH <= 0, hi_w, np.nan))
        boxes_l, boxes_h = [], []
        for pick in (up_pick, dn_pick):
            BL = np.repeat(XL[:, None, :], n2, 1)
            BH = np.repeat(XH[:, None, :], n2, 1)
            BL[:, :, wf] = np.where(np.isnan(pick), BL[:, :, wf], pick)
            BH[:, :, wf] = np.where(np.isnan(pick), BH[:, :, wf], pick)
            boxes_l.append(BL.reshape(m * n2, -1))
            boxes_h.append(BH.reshape(m * n2, -1))
        L, H, _ = self.next.eval_batch(np.concatenate(boxes_l), np.concatenate(boxes_h))
        o = np.tile(np.arange(n2), m)
        r = np.arange(m * n2)
        up = H[:m * n2][r, o].reshape(m, n2)
        dn = L[m * n2:][r, o].reshape(m, n2)
        NL, NH = NL.copy(), NH.copy()
        NH[keep] = np.where(np.isfinite(up), np.minimum(NH[keep], up), NH[keep])
        NL[keep] = np.where(np.isfinite(dn), np.maximum(NL[keep], dn), NL[keep])
        return NL, NH

    def w_kept(self, FL: np.ndarray, FH: np.ndarray) -> np.ndarray:
        """Per box (full rows: the split part and the controller states), whether W_hat's exponential-Euler update
        W+ = b W + (1 - b) A / c (b = 1 - phi c in [0, 1]) provably stays in S's W_hat set: its box when
        c lo <= A <= c hi, its ball ||W_hat||_F <= w when ||A||_F <= c w (outward rounded)."""
        AL, AH, _ = self.w_aff.eval_batch(FL, FH)
        c = self.w_rate
        if self.S.w_ball is not None:
            a = np.maximum(np.abs(AL), np.abs(AH))
            sq = _up(_up(np.sum(_up(a * a), axis=1)) * (1 + 4 * a.shape[1] * 2.0 ** -52))
            return np.all(np.isfinite(a), axis=1) & (sq <= _dn(_dn(c * self.S.w_ball) ** 2))
        wlo, whi = (np.asarray(v, float).reshape(-1, order="F") for v in self.S.states["w_hat"])
        return np.all((AL >= _up(c * wlo)) & (AH <= _dn(c * whi)), axis=1)

    def _hint(self, LO, HI, el2, eh2, J) -> np.ndarray:
        """Per box, the split variable for the next sample's most violated component: the largest
        |d next_i / d x_j| x width_j among the other variables (the own sigma_i's term is the contraction itself,
        not an overestimation: it weighs a tenth); -1 where the Jacobian is not finite."""
        n2 = 2 * self.n
        viol = np.maximum(eh2 - self.lim_S, -self.lim_S - el2)
        viol = np.where(np.isfinite(viol), viol, np.inf)
        comp = np.argmax(viol, axis=1)
        wf = self.next.w_flat
        width = HI[:, wf] - LO[:, wf]
        rows = np.arange(LO.shape[0])
        with np.errstate(invalid="ignore"):          # an unbounded Jacobian entry times a zero width
            c = J[rows, comp, :] * width
        for k, j in enumerate(wf):
            if 1 <= j <= n2:
                c[:, k] = np.where(comp == j - 1, 0.1 * c[:, k], c[:, k])
        c = np.where(np.isfinite(c) & (width > 0), c, -1.0)
        best = np.argmax(c, axis=1)
        return np.where(c[rows, best] > 0, wf[best], -1)

    def _with_h(self, FL, FH, h):
        i = self.i_st
        col = np.full((FL.shape[0], 1), float(h))
        return (np.concatenate([FL[:, :i], col, FL[:, i:]], axis=1), np.concatenate([FH[:, :i], col, FH[:, i:]], axis=1))

    def _acc_in(self, FL, FH, tl, th, sl, sh, UL, UH):
        """sigma'' over the period's enclosure (the same inputs as `_rate_in`)."""
        n = self.n
        RLo = np.concatenate([tl[:, None], sl, FL[:, 2 * n + 1:self.i_st], UL, FL[:, self.i_st:]], axis=1)
        RHi = np.concatenate([th[:, None], sh, FH[:, 2 * n + 1:self.i_st], UH, FH[:, self.i_st:]], axis=1)
        L, H, _ = self.acc.eval_batch(RLo, RHi)
        return L, H

    def _rate_in(self, FL, FH, tl, th, sl, sh, UL, UH):
        """sigma' over (time [tl, th], sigma box, the parameters, u box, the states)."""
        n = self.n
        RLo = np.concatenate([tl[:, None], sl, FL[:, 2 * n + 1:self.i_st], UL, FL[:, self.i_st:]], axis=1)
        RHi = np.concatenate([th[:, None], sh, FH[:, 2 * n + 1:self.i_st], UH, FH[:, self.i_st:]], axis=1)
        L, H, sw = self.rate.eval_batch(RLo, RHi)
        return L, H, np.asarray(sw, bool)


def prove_period(op: OnePeriod, h: float, M: float, t_final: float, *, max_boxes: int, expiry=None,
                 rng_seed: int = 20241205, warm: dict | None = None) -> dict:
    """Branch and bound over S at period h: {"proven": bool, "boxes", "left": undecided volume fraction, "reason",
    "queue": the boxes left when the budget ended it}. `warm`: such a result at a period >= h (a lower rate) -- its
    boxes outside the queue are proven at that period, so at every shorter one (the module doc: the property is per
    sample state), and the search starts from its queue."""
    lo, hi = op.box(t_final)
    split = op.split_vars(lo, hi)
    scale = np.where(hi - lo > 0, hi - lo, 1.0)
    # screen: points of S (random, and on its faces) as degenerate boxes
    rng = np.random.default_rng(rng_seed)
    X = lo + rng.random((SCREEN_POINTS, lo.size)) * (hi - lo)
    sl = slice(1, 2 * op.n + 1)
    X[: SCREEN_POINTS // 2, sl] = np.where(rng.random((SCREEN_POINTS // 2, 2 * op.n)) < 0.5, lo[sl], hi[sl])
    okp, infop = op.check(X, X, h, M)
    if not okp.all():
        k = int(np.argmin(okp))
        return {"proven": False, "boxes": SCREEN_POINTS, "left": 1.0, "reason": "point", "point": X[k],
                "failed": WHY[int(infop["why"][k])]}
    # breadth-first: the oldest (largest) boxes first, so what is left shrinks evenly over S
    LO, HI, V = lo[None, :].copy(), hi[None, :].copy(), np.array([1.0])
    if warm is not None and warm.get("queue") is not None:
        if not warm["h"] >= h:
            raise ValueError(f"a warm start from period {warm['h']:g} s cannot serve the longer period {h:g} s")
        LO, HI, V = (np.array(a, copy=True) for a in warm["queue"])
    boxes = 0
    while LO.shape[0]:
        take = min(BATCH, LO.shape[0])
        cur_lo, cur_hi, cur_v = LO[:take], HI[:take], V[:take]
        LO, HI, V = LO[take:], HI[take:], V[take:]
        ok, info = op.check(cur_lo, cur_hi, h, M)
        boxes += take
        bad = ~ok
        if not bad.any():
            continue
        BL, BH, BV = cur_lo[bad], cur_hi[bad], cur_v[bad]
        rel = (BH[:, split] - BL[:, split]) / scale[split]
        left = float(BV.sum() + V.sum())
        if np.any(np.max(rel, axis=1) < THIN):
            return {"proven": False, "boxes": boxes, "left": left, "reason": "thin"}
        if boxes >= max_boxes or (expiry is not None and time.monotonic() >= expiry):
            return {"proven": False, "boxes": boxes, "left": left, "h": h,
                    "reason": "boxes" if boxes >= max_boxes else "seconds",
                    "queue": (np.concatenate([BL, LO]), np.concatenate([BH, HI]), np.concatenate([BV, V]))}
        k = split[np.argmax(rel, axis=1)]
        # the sensitivity's choice, unless that variable is already much thinner (relative to S) than the widest
        hint = info["hint"][bad]
        r = np.arange(BL.shape[0])
        hrel = (BH[r, np.maximum(hint, 0)] - BL[r, np.maximum(hint, 0)]) / scale[np.maximum(hint, 0)]
        k = np.where((hint >= 0) & (hrel * HINT_RATIO >= np.max(rel, axis=1)), hint, k)
        r = np.arange(BL.shape[0])
        mid = 0.5 * BL[r, k] + 0.5 * BH[r, k]
        h1 = BH.copy()
        h1[r, k] = mid
        l2 = BL.copy()
        l2[r, k] = mid
        LO = np.concatenate([LO, BL, l2])
        HI = np.concatenate([HI, h1, BH])
        V = np.concatenate([V, BV / 2, BV / 2])
    return {"proven": True, "boxes": boxes, "left": 0.0, "reason": None}

"""`certify.input_gain`: sym(M_p(q)^-1 D M(q)) positive definite over the joint region x the parameter box x the
dead-zone slope box, with a rigorous lower bound of its smallest eigenvalue.

M is the controller's model, M_p the plant's inertia (the closed loop's own SX, with the plant's parameters p as
symbols), D = diag(d) the dead-zone slopes; S = sym(M_p^-1 D M) is built once as SX (M_p^-1 by the LDL^T solve the
plant uses). S is linear in d, and lambda_min is concave on symmetric matrices, so for every (q, p) the smallest
eigenvalue over the slope box is attained at one of its vertices: with at most VERTEX_LIMIT vertices each vertex is a
branch and bound over (q, p) alone (`search.prove_positive_definite`), otherwise d is bisected like q and p.
Each problem is first probed at PROBE_POINTS seeded points in double (a refutation needs no search when a sample
already fails). A counterexample is reported only after the ordinary CasADi Functions of M and M_p (not the tape the proof used)
reproduce lambda_min <= 0 there with numpy's eigenvalues.
"""

from __future__ import annotations

import itertools
import math
import time

import casadi as ca
import numpy as np

from .problem import Budget, Context, check_rules
from .region import input_gain_function, inertia_functions, joint_box, slope_ranges
from .result import Certificate
from .selfcheck import check_contains
from ..sx.search import prove_positive_definite

CID = "certify.input_gain"
#: at most this many slope-box vertices are enumerated (else the slopes are bisected)
VERTEX_LIMIT = 16
#: the lower bound is refined until it is within this fraction of the smallest eigenvalue seen
REL_TOL = 2e-2
#: seeded uniform points per problem evaluated in double before the branch and bound (a counterexample search only)
PROBE_POINTS = 256


def _probe(Sx: ca.Function, lo: np.ndarray, hi: np.ndarray, k: int = PROBE_POINTS) -> tuple[np.ndarray, float]:
    """The point of k seeded uniform points in [lo, hi] (and the box's midpoint) where lambda_min(sym S) is
    smallest, and that value: a cheap first look for a counterexample, which `confirm` must still reproduce."""
    n = Sx.size1_out(0)
    X = np.vstack([0.5 * lo + 0.5 * hi, lo + (hi - lo) * np.random.default_rng(0).random((k, lo.size))])
    A = np.asarray(Sx.map(X.shape[0])(X.T), float).reshape(n, X.shape[0], n).transpose(1, 0, 2)
    ok = np.all(np.isfinite(A), axis=(1, 2))
    if not ok.any():
        return X[0], np.inf
    lam = np.full(X.shape[0], np.inf)
    lam[ok] = np.linalg.eigvalsh(0.5 * (A[ok] + A[ok].transpose(0, 2, 1)))[:, 0]
    i = int(np.argmin(lam))
    return X[i], float(lam[i])


def certify_input_gain(ctx: Context, budget: Budget) -> Certificate:
    """certify.input_gain over the scenario's region."""
    t0 = time.monotonic()
    d, sc = ctx.design, ctx.scenario
    n = d.n
    P = ctx.params
    sr = slope_ranges(sc, P)
    dl, dh, constant = sr["lo"], sr["hi"], sr["constant"]
    seen_lo, seen_hi = sr["lo_seen"], sr["hi_seen"]

    def attained(slopes) -> np.ndarray:
        """The slopes the dead zone attains nearest the box's: each joint's slope moved to the attained end of its
        side (the rigorous hull may be wider than what any u gives; a refutation is re-checked where it is real)."""
        s_ = np.asarray(slopes, float)
        return np.where(s_ <= 0.5 * (dl + dh), seen_lo, seen_hi)
    ql, qh, jinfo = joint_box(d, ctx.t_final)
    S = input_gain_function(d)
    check_rules(S, "signal input_gain (sym(M_p^-1 D M))", sc.file)
    npar = len(P.names)
    fM, fMp = inertia_functions(d)

    def confirm(q, p, slopes) -> float:
        M = np.asarray(fM(q), float)
        Mp = np.asarray(fMp(q, p), float)
        if not (np.all(np.isfinite(M)) and np.all(np.isfinite(Mp))):
            return math.nan                  # numpy's eigvalsh of a NaN matrix returns numbers: no verdict on them
        G = np.linalg.solve(Mp, np.diag(slopes) @ M)
        if not np.all(np.isfinite(G)):
            return math.nan
        return float(np.linalg.eigvalsh(0.5 * (G + G.T))[0])

    wide_d = [j for j in range(n) if dl[j] < dh[j]]
    vertices = list(itertools.product(*[(dl[j], dh[j]) if j in wide_d else (dl[j],) for j in range(n)])) \
        if 2 ** len(wide_d) <= VERTEX_LIMIT else None
    region = {"q": [ql.tolist(), qh.tolist()], "q_source": "hull of the e1 funnel tube over [0, T]" +
              (" within the joint limits" if jinfo["limits"] else ""), "parameters": P.describe(),
              "slopes": [dl.tolist(), dh.tolist()], "slopes_attained": [seen_lo.tolist(), seen_hi.tolist()],
              "slopes_source": "hull of both branches' slopes" + (" (constant)" if constant else
                                                                   f" over {SLOPE_NOTE}")}
    x = ca.SX.sym("x", n + npar + (0 if vertices is not None else n))
    problems = []
    if vertices is None:
        Sx = ca.Function("S", [x], [S(x[:n], x[n:n + npar], x[n + npar:])])
        lo = np.concatenate([ql, P.lo, dl])
        hi = np.concatenate([qh, P.hi, dh])
        problems.append((None, Sx, lo, hi))
    else:
        lo = np.concatenate([ql, P.lo])
        hi = np.concatenate([qh, P.hi])
        for v in vertices:
            problems.append((np.array(v, float), ca.Function("S", [x], [S(x[:n], x[n:], ca.DM(v))]), lo, hi))
    # vertices with the smallest eigenvalue at the box midpoint first: a refutation, if any, comes early
    def mid_lambda(pr):
        A = np.asarray(pr[1](0.5 * pr[2] + 0.5 * pr[3]), float)
        return float(np.linalg.eigvalsh(0.5 * (A + A.T))[0]) if np.all(np.isfinite(A)) else -np.inf
    problems.sort(key=mid_lambda)
    from ..sx.tape import count_ops
    budget.set_tape((count_ops(problems[0][1])["operations"] + 2 * n ** 3) * 4)
    boxes, lowers, uppers, fractions, first, nan_note = 0, [], [], [], [], []
    for i, (vert, Sx, lo_, hi_) in enumerate(problems):
        xs = ca.SX.sym("x", lo_.size)
        dep = set(ca.jacobian_sparsity(ca.vec(Sx(xs)), xs).get_triplet()[1])
        split = np.array([j for j in range(lo_.size) if j in dep and hi_[j] > lo_[j]], dtype=int)

        def conf(xx, vert=vert):
            slopes = vert if vert is not None else xx[n + npar:]
            return confirm(xx[:n], xx[n:n + npar], attained(slopes))
        left = len(problems) - i
        xp, lp = _probe(Sx, lo_, hi_)
        if lp <= 0 and conf(xp) <= 0:       # refuted by a sample, reproduced independently: no search needed
            r = _Refuted(xp)
        else:
            r = prove_positive_definite(Sx, lo_, hi_, split, confirm=conf, max_boxes=max(200, budget.boxes // left),
                                        seconds=budget.seconds(1.0 / left), rel_tol=REL_TOL)
        budget.boxes -= r.boxes
        boxes += r.boxes
        if r.status == "refuted":
            xx = r.argmin
            slopes = attained(vert if vert is not None else xx[n + npar:])
            lam = confirm(xx[:n], xx[n:n + npar], slopes)
            if not (np.isfinite(lam) and lam <= 0):       # a refutation needs a finite violating value
                lowers.append(None)
                uppers.append(None)
                fractions.append(1.0)
                first.append(None)
                nan_note.append(f"a candidate counterexample at q = {np.round(xx[:n], 6).tolist()} has "
                                f"lambda_min = {lam:.6g} at the attained slopes (not a finite violation)")
                continue
            ce = {"t": None, "q": xx[:n].tolist(), "dq": None,
                  "parameters": {k: float(v) for k, v, a, b in zip(P.names, xx[n:n + npar], P.lo, P.hi) if a < b},
                  "slopes": np.asarray(slopes, float).tolist(), "lambda_min": lam,
                  "slopes_attained_at": [sr["where"][j].get("lo" if slopes[j] == seen_lo[j] else "hi")
                                         for j in range(n)]}
            return Certificate(CID, "refuted", f"sym(M_p^-1 D M) is not positive definite: lambda_min = {lam:.6g} "
                               f"at q = {np.round(xx[:n], 6).tolist()}, slopes {np.asarray(slopes).tolist()} "
                               f"(re-evaluated with the ordinary CasADi Functions of M and M_p"
                               + ("; found among the seeded sample points, before any box was searched)"
                                  if isinstance(r, _Refuted) else ")"),
                               upper=lam, counterexample=ce, region=region, boxes=boxes,
                               undecided_fraction=r.undecided_fraction, seconds=time.monotonic() - t0,
                               method=_method(vertices), extra={"vertices": len(problems)})
        if r.lower is not None and r.argmin is not None:        # self-check: the bound holds at its own witness
            xx = r.argmin
            check_contains("lambda_min(sym(M_p^-1 D M))", r.lower, None,
                           confirm(xx[:n], xx[n:n + npar], vert if vert is not None else xx[n + npar:]), xx)
        lowers.append(r.lower)
        uppers.append(r.upper)
        fractions.append(r.undecided_fraction)
        first.append(r.first_proof)
    upper = min(u for u in uppers if u is not None) if any(u is not None for u in uppers) else None
    upper = upper if upper is None or np.isfinite(upper) else None
    extra = {"vertices": len(problems), "first_proof": [None if f is None else {"boxes": f[0], "seconds": f[1]}
                                                        for f in first]}
    if all(lw is not None for lw in lowers):
        lower = min(lowers)
        return Certificate(CID, "proven", f"sym(M_p^-1 D M) is positive definite on the region: lambda_min >= "
                           f"{lower:.6g} (smallest value found {upper:.6g})", lower=lower, upper=upper,
                           region=region, boxes=boxes, seconds=time.monotonic() - t0, method=_method(vertices),
                           extra=extra)
    frac = float(max(fractions))
    why = ("; " + "; ".join(nan_note)) if nan_note else ""
    return Certificate(CID, "undecided", f"no counterexample, but {frac:.3g} of the (q, p) volume of the worst slope "
                       f"vertex is not proven within the budget (smallest lambda_min found "
                       f"{'none' if upper is None else f'{upper:.6g}'}){why}",
                       upper=upper, region=region, boxes=boxes, undecided_fraction=frac,
                       seconds=time.monotonic() - t0, method=_method(vertices), extra=extra)


class _Refuted:
    """A probe's counterexample in the shape of a search result (no box was searched)."""

    status, boxes, undecided_fraction = "refuted", 0, 1.0

    def __init__(self, argmin: np.ndarray):
        self.argmin = argmin


SLOPE_NOTE = "torques within 10 N m (plant.dead_zone) of the breakpoints"


def _method(vertices) -> str:
    head = "preconditioned Gershgorin discs on interval enclosures (mean-value form) of sym(M_p^-1 D M)"
    if vertices is None:
        return head + ", slopes bisected with q and p"
    return head + f" at each of the {len(vertices)} slope-box vertices (lambda_min is concave in the slopes)"

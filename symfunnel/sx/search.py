"""Batched, deterministic interval branch and bound on `sx.batch`: the range of one output over a box, and a
symmetric matrix function positive definite over a box (with a rigorous lower bound of its smallest eigenvalue).

Both pop up to `batch` boxes at a time in a fixed order (best-first on the bound, ties in creation order), split each
at the midpoint of the variable with the largest max|df/dx_j| x width over the box (the centered form's interval
Jacobian: splitting by sensitivity; relative width where the Jacobian is unknown), and evaluate all children in one
call; midpoints are evaluated by CasADi in double. The same input gives the same boxes and the same result; a wall
clock limit can only stop a search early (its answer then says so).

Positive definiteness (`prove_positive_definite`). Per box, with m its midpoint and S(m) = V diag(w) V^T (floating
point), L = V^T: the centered enclosures of P(x) = L S(x) L^T and Q = L L^T, then for every row i
num_i = min P_ii - sum_{j != i} max|P_ij| and den_i = max Q_ii + sum_{j != i} max|Q_ij| (rounded outward). If every
num_i > 0, then for each lambda < min_i num_i / den_i the matrix L (S - lambda I) L^T is diagonally dominant with a
positive diagonal, hence positive definite (so L is invertible) and so is S - lambda I: lambda_min(S) >= min_i
num_i / den_i on the whole box. A midpoint with w_0 <= 0 is a candidate counterexample, reported only when the
`confirm` callback (an independent evaluation) reproduces lambda_min <= 0 there.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .batch import BatchCenteredForm, BatchIntervalFunction

_INF = math.inf
_EPS = 2.0 ** -52
#: boxes a proven positive-definiteness search may spend refining its lower bound (at least; else as many as the proof took)
REFINE_MIN = 1000


def _split_children(LO, HI, k):
    """The two halves of each box (rows) along variable k[i]: (2K, n) lower and upper bounds."""
    K = LO.shape[0]
    idx = np.arange(K)
    mid = 0.5 * LO[idx, k] + 0.5 * HI[idx, k]
    hi1 = HI.copy()
    hi1[idx, k] = mid
    lo2 = LO.copy()
    lo2[idx, k] = mid
    return np.concatenate([LO, lo2]), np.concatenate([hi1, HI])


def _choose(LO, HI, sens, split, scale):
    """Per box, the split variable: largest sensitivity among `split` (flat indices), else largest relative width;
    -1 where no variable can be halved."""
    width = HI[:, split] - LO[:, split]
    s = np.where(np.isfinite(sens), sens, np.nan) if sens is not None else None
    use = s is not None and np.all(np.isfinite(s)) and True
    rel = width / scale[split]
    if s is not None:
        s = np.where(np.isfinite(s), s, -1.0)
        good = np.any(s > 0, axis=1)
        pick = np.where(good, np.argmax(s, axis=1), np.argmax(rel, axis=1))
    else:
        pick = np.argmax(rel, axis=1)
    del use
    k = split[pick]
    rows = np.arange(LO.shape[0])
    m = 0.5 * LO[rows, k] + 0.5 * HI[rows, k]
    ok = (LO[rows, k] < m) & (m < HI[rows, k])
    return np.where(ok, k, -1)


def _sensitivities(J, wpos, width, pos, K, nsplit):
    """(K, len(pos), nsplit): |J|'s entry of output pos[o] in split variable i times the box's width in it (nan
    where the form has no derivative in that variable, or no Jacobian at all)."""
    if J is None:
        return np.full((K, len(pos), nsplit), np.nan)
    return np.where(wpos >= 0, J[:, pos][:, :, np.maximum(wpos, 0)] * width[:, None, :], np.nan)


def _mid(LO, HI):
    return np.where(LO == HI, LO, 0.5 * LO + 0.5 * HI)


def _blame(F, culprit, invalid, LO, HI, split, scale, sens):
    """For boxes whose enclosure is invalid because of a domain error (a division by an interval around 0, a
    removable singularity such as s/atanh(s) at 0...), splitting priority goes to the variables that failing
    operation depends on, widest (relative) first: the sensitivity rows of those boxes are replaced."""
    natural = getattr(F, "natural", F)
    cache: dict[int, np.ndarray] = {}
    pos = {int(j): c for c, j in enumerate(split)}
    out = None if sens is None else sens.copy()
    for r in np.flatnonzero(invalid & (culprit >= 0)):
        c = int(culprit[r])
        if c not in cache:
            cache[c] = np.array([pos[int(j)] for j in natural.culprit_inputs(c) if int(j) in pos], dtype=int)
        cols = cache[c]
        if cols.size == 0:
            continue
        if out is None:
            out = np.full((LO.shape[0], split.size), np.nan)
        row = np.full(split.size, -1.0)
        row[cols] = (HI[r, split[cols]] - LO[r, split[cols]]) / scale[split[cols]]
        out[r] = row
    return out


# --- the range of one output --------------------------------------------------------------------------------

@dataclass
class Extremum:
    """min over the box of sign * g[pos]: a rigorous lower bound, the best value seen (double) and where."""

    bound: float
    best: float
    argbest: np.ndarray
    boxes: int
    converged: bool
    stopped: str | None


def extremum(F: BatchCenteredForm | BatchIntervalFunction, lo: np.ndarray, hi: np.ndarray, split: np.ndarray,
             pos: int, sign: float, **kw) -> Extremum:
    """min of sign * F[pos] over the flat box [lo, hi] (one objective of `extrema`)."""
    return extrema(F, lo, hi, split, [(pos, sign)], **kw)[0]


def extrema(F: BatchCenteredForm | BatchIntervalFunction, lo: np.ndarray, hi: np.ndarray, split: np.ndarray,
            objectives: list[tuple[int, float]], *, max_boxes: int = 4000, seconds: float | None = None,
            rel_tol: float = 1e-3, abs_tol: float = 0.0, per_round: int = 16,
            initial: tuple | None = None) -> list[Extremum]:
    """min of sign * F[pos] over the flat box [lo, hi] for every objective (pos, sign) at once, bisecting only the
    flat indices `split`: one pool of boxes whose every evaluation serves all objectives; each round every open
    objective picks its `per_round` best boxes (best-first on its bound), they are split at their most sensitive
    variable for that objective and all children are evaluated in one batch. `initial` (LO, HI): the first boxes
    (a partition of the box) instead of the box itself."""
    t0 = time.monotonic()
    split = np.asarray(split, dtype=int)
    scale = np.where(hi - lo > 0, hi - lo, 1.0)
    centered = isinstance(F, BatchCenteredForm)
    wpos = np.array([{int(j): i for i, j in enumerate(F.w_flat)}.get(int(j), -1) for j in split]) if centered \
        else np.full(split.size, -1)
    nobj = len(objectives)
    pos = np.array([o[0] for o in objectives], dtype=int)
    sgn = np.array([o[1] for o in objectives], dtype=float)
    store_lo, store_hi, store_b, store_sens, alive = [], [], [], [], []
    heaps: list[list] = [[] for _ in range(nobj)]
    thin: list[list[float]] = [[] for _ in range(nobj)]
    best = np.full(nobj, _INF)
    arg = [_mid(lo[None, :], hi[None, :])[0] for _ in range(nobj)]
    counter = 0
    boxes = 0

    def evaluate(LO, HI):
        nonlocal counter, boxes
        if centered:
            L, H, _, J = F.eval_batch(LO, HI, with_jacobian=True)
            culprit = F.last_culprit
        else:
            L, H, _, culprit = F.eval_batch_culprit(LO, HI)
            J = None
        boxes += LO.shape[0]
        B = np.where(sgn > 0, sgn * L[:, pos], sgn * H[:, pos])              # (K, nobj) lower bounds of sign*g
        B = np.where(np.isnan(B), -_INF, B)
        M = _mid(LO, HI)
        V = sgn * F.eval_points(M)[:, pos]
        V = np.where(np.isfinite(V), V, _INF)
        for o in range(nobj):
            i = int(np.argmin(V[:, o]))
            if V[i, o] < best[o]:
                best[o], arg[o] = float(V[i, o]), M[i]
        # every box's split sensitivities (K, nobj, nsplit) in one product: |J| times the box's width per split
        # variable (nan where the form has no derivative in it), each entry the same product as box by box
        SS = _sensitivities(J, wpos, HI[:, split] - LO[:, split], pos, LO.shape[0], split.size)
        for r in range(LO.shape[0]):
            S = SS[r]
            invalid = ~np.isfinite(B[r])
            if invalid.any() and culprit[r] >= 0:
                blamed = _blame(F, culprit[r:r + 1], np.array([True]), LO[r:r + 1], HI[r:r + 1], split, scale,
                                None)
                if blamed is not None:
                    S[invalid] = blamed[0]
            k = len(store_lo)
            store_lo.append(LO[r])
            store_hi.append(HI[r])
            store_b.append(B[r])
            store_sens.append(S)
            alive.append(True)
            for o in range(nobj):
                heapq.heappush(heaps[o], (float(B[r, o]), counter, k))
            counter += 1

    if initial is None:
        evaluate(lo[None, :].copy(), hi[None, :].copy())
    else:
        for a in range(0, initial[0].shape[0], 512):
            evaluate(initial[0][a:a + 512], initial[1][a:a + 512])
    converged = np.zeros(nobj, dtype=bool)
    stopped = None
    while True:
        chosen: dict[int, int] = {}             # box -> the objective that splits it
        for o in range(nobj):
            h = heaps[o]
            while h and not alive[h[0][2]]:
                heapq.heappop(h)
            if not h:
                converged[o] = not thin[o] or best[o] - min(thin[o]) <= max(abs_tol, rel_tol * abs(best[o]))
                continue
            tol = max(abs_tol, rel_tol * abs(best[o])) if np.isfinite(best[o]) else 0.0
            if best[o] - h[0][0] <= tol:
                converged[o] = True
                continue
            converged[o] = False
            taken, keep = 0, []
            while h and taken < per_round:
                item = heapq.heappop(h)
                if not alive[item[2]]:
                    continue
                keep.append(item)
                if item[2] not in chosen:
                    chosen[item[2]] = o
                    taken += 1
            for item in keep:
                heapq.heappush(h, item)
        if not chosen:
            break
        if boxes >= max_boxes or (seconds is not None and time.monotonic() - t0 > seconds):
            stopped = "boxes" if boxes >= max_boxes else "seconds"
            break
        ids = list(chosen)
        LO = np.array([store_lo[i] for i in ids])
        HI = np.array([store_hi[i] for i in ids])
        sens = np.array([store_sens[i][chosen[i]] for i in ids])
        k = _choose(LO, HI, sens, split, scale) if split.size else np.full(len(ids), -1)
        for i, kk in zip(ids, k):
            alive[i] = False
            if kk < 0:                          # too thin to split: its bounds stay in the result
                for o in range(nobj):
                    thin[o].append(float(store_b[i][o]))
        keep = k >= 0
        if keep.any():
            LO2, HI2 = _split_children(LO[keep], HI[keep], k[keep])
            evaluate(LO2, HI2)
    out = []
    for o in range(nobj):
        live = [it[0] for it in heaps[o] if alive[it[2]]]
        bound = min(live + thin[o]) if (live or thin[o]) else best[o]
        out.append(Extremum(float(bound), float(best[o]), arg[o], boxes, bool(converged[o]), stopped))
    return out


# --- a matrix positive definite ---------------------------------------------------------------------------

@dataclass
class PDResult:
    """Outcome of `prove_positive_definite`."""

    status: str                       # proven | refuted | undecided
    lower: float | None               # rigorous lower bound of min lambda_min over the box (when proven)
    upper: float | None               # smallest lambda_min seen at a midpoint (an upper bound of the minimum)
    argmin: np.ndarray | None         # where it was seen (the counterexample when refuted)
    boxes: int
    undecided_fraction: float
    seconds: float
    stopped: str | None
    first_proof: tuple | None = None  # (boxes, seconds, bound) when every box was first proven


def gershgorin(PL, PH, QL, QH) -> tuple[np.ndarray, np.ndarray]:
    """Per box (rigorous lower bound of lambda_min or -inf, ranking key) from (K, n, n) enclosures of P and Q."""
    n = PL.shape[1]
    eye = np.eye(n, dtype=bool)
    fin = (np.all(np.isfinite(PL), axis=(1, 2)) & np.all(np.isfinite(PH), axis=(1, 2)) &
           np.all(np.isfinite(QL), axis=(1, 2)) & np.all(np.isfinite(QH), axis=(1, 2)))
    A = np.where(eye, 0.0, np.maximum(np.abs(PL), np.abs(PH)))
    AQ = np.where(eye, 0.0, np.maximum(np.abs(QL), np.abs(QH)))
    grow = 1.0 + 2.0 * n * _EPS
    with np.errstate(all="ignore"):
        off = np.nextafter(A.sum(axis=2) * grow, _INF)
        num = np.nextafter(np.diagonal(PL, axis1=1, axis2=2) - off, -_INF)
        den = np.nextafter((np.diagonal(QH, axis1=1, axis2=2) + AQ.sum(axis=2)) * grow, _INF)
        ratio = np.nextafter(num / den, -_INF)
    key = np.where(fin & np.all(den > 0, axis=1), np.min(ratio, axis=1), -_INF)
    proven = fin & np.all(num > 0, axis=1) & np.all(den > 0, axis=1)
    return np.where(proven, np.min(ratio, axis=1), -_INF), key


def prove_positive_definite(S: ca.Function, lo: np.ndarray, hi: np.ndarray, split: np.ndarray, *,
                            confirm: Callable[[np.ndarray], float] | None = None, max_boxes: int = 20000,
                            seconds: float | None = None, rel_tol: float = 1e-3, batch: int = 64) -> PDResult:
    """Prove S(x) positive definite for x in [lo, hi] (S: one flat input x -> n x n symmetric), splitting only the
    flat indices `split`; `confirm(x)` gives lambda_min at x by an independent evaluation."""
    t0 = time.monotonic()
    n = S.size1_out(0)
    nx = S.size1_in(0)
    x = ca.SX.sym("x", nx)
    Ls = ca.SX.sym("L", n, n)
    Sx = S(x)
    g = ca.Function("preconditioned", [x, Ls], [ca.densify(ca.vec(ca.mtimes([Ls, Sx, Ls.T]))),
                                                 ca.densify(ca.vec(ca.mtimes(Ls, Ls.T)))],
                    ["x", "L"], ["P", "Q"], {"cse": True})
    form = BatchCenteredForm(g, ["x"])
    Sb = BatchIntervalFunction(ca.Function("S", [x], [ca.densify(ca.vec(Sx))], ["x"], ["S"]))
    split = np.asarray(split, dtype=int)
    scale = np.where(hi - lo > 0, hi - lo, 1.0)
    nn = n * n
    heap: list = []
    parked: list[float] = []
    final: list[float] = []
    counter = 0
    boxes = 0
    seen, argmin = _INF, None

    def evaluate(LO, HI, vols):
        """Evaluate K boxes; returns a refutation (x, lambda) or None."""
        nonlocal counter, boxes, seen, argmin
        K = LO.shape[0]
        boxes += K
        M = _mid(LO, HI)
        Sm = Sb.eval_points(M).reshape(K, n, n, order="C").transpose(0, 2, 1)      # column-major vec
        Sm = 0.5 * (Sm + np.swapaxes(Sm, 1, 2))
        good = np.all(np.isfinite(Sm), axis=(1, 2))
        w = np.full((K, n), np.nan)
        V = np.tile(np.eye(n), (K, 1, 1))
        if good.any():
            w[good], V[good] = np.linalg.eigh(Sm[good])
        for r in np.flatnonzero(~(w[:, 0] > 0)):
            lam = confirm(M[r]) if confirm is not None else float(w[r, 0])
            if np.isfinite(lam) and lam <= 0:       # a refutation needs a finite violating value (NaN: no verdict)
                return M[r], lam
        i = int(np.nanargmin(w[:, 0])) if np.any(np.isfinite(w[:, 0])) else 0
        if w[i, 0] < seen:
            seen, argmin = float(w[i, 0]), M[i]
        Lf = V.reshape(K, nn)              # L = V^T; its column-major nonzeros are V's entries row by row
        FLO = np.concatenate([LO, Lf], axis=1)
        FHI = np.concatenate([HI, Lf], axis=1)
        Lb, Hb, _, J = form.eval_batch(FLO, FHI, with_jacobian=True)
        PL = Lb[:, :nn].reshape(K, n, n).transpose(0, 2, 1)
        PH = Hb[:, :nn].reshape(K, n, n).transpose(0, 2, 1)
        QL = Lb[:, nn:].reshape(K, n, n).transpose(0, 2, 1)
        QH = Hb[:, nn:].reshape(K, n, n).transpose(0, 2, 1)
        bound, key = gershgorin(PL, PH, QL, QH)
        with np.errstate(all="ignore"):
            sens = (J[:, :nn, :nx].sum(axis=1) * (HI - LO))[:, split]
        blamed = _blame(form, form.last_culprit, ~np.isfinite(key), FLO[:, :nx], FHI[:, :nx], split, scale, sens)
        sens = blamed if blamed is not None else sens
        for r in range(K):
            s = sens[r]
            item_sens = s if np.all(np.isfinite(s)) else None
            if bound[r] > -_INF:
                heapq.heappush(heap, (0, float(bound[r]), counter, vols[r], LO[r], HI[r], item_sens, float(bound[r])))
            else:
                heapq.heappush(heap, (-1, -vols[r], counter, vols[r], LO[r], HI[r], item_sens, -_INF))
            counter += 1
        return None

    def finish(status, lower=None, extra=0.0):
        left = sum(it[3] for it in heap if it[7] == -_INF) + sum(parked) + extra
        return PDResult(status, lower, None if seen == _INF else seen, argmin, boxes,
                        0.0 if status == "proven" else float(min(1.0, left)), time.monotonic() - t0, stopped,
                        first_proof)

    stopped, first_proof = None, None
    r = evaluate(lo[None, :].copy(), hi[None, :].copy(), [1.0])
    if r is not None:
        return PDResult("refuted", None, r[1], r[0], boxes, 1.0, time.monotonic() - t0, None)
    while True:
        all_proven = (not heap or heap[0][0] == 0) and not parked
        lower = min(([heap[0][7]] if heap else []) + final) if all_proven and (heap or final) else None
        if all_proven and first_proof is None:
            first_proof = (boxes, time.monotonic() - t0, lower)
        if all_proven and (not heap or seen - lower <= rel_tol * abs(seen)):
            return finish("proven", lower)
        if not heap:
            return finish("undecided")
        # refining a proven bound gets as many boxes again as the proof took (at least REFINE_MIN)
        limit = max_boxes if first_proof is None else min(max_boxes, first_proof[0] + max(first_proof[0], REFINE_MIN))
        if boxes >= limit or (seconds is not None and time.monotonic() - t0 > seconds):
            stopped = "boxes" if boxes >= limit else "seconds"
            return finish("proven", lower) if all_proven else finish("undecided")
        # a batch of the same kind as the head (unproven boxes, largest first; else the smallest bounds)
        kind = heap[0][0]
        items = []
        while heap and len(items) < batch and heap[0][0] == kind:
            items.append(heapq.heappop(heap))
        LO = np.array([it[4] for it in items])
        HI = np.array([it[5] for it in items])
        sens = None if any(it[6] is None for it in items) else np.array([it[6] for it in items])
        k = _choose(LO, HI, sens, split, scale) if split.size else np.full(len(items), -1)
        for it, kk in zip(items, k):
            if kk < 0:
                stopped = "min_width"
                (final if it[7] > -_INF else parked).append(it[7] if it[7] > -_INF else it[3])
        keep = k >= 0
        if not keep.any():
            continue
        vols = [it[3] * 0.5 for it, kk in zip(items, keep) if kk]
        LO2, HI2 = _split_children(LO[keep], HI[keep], k[keep])
        r = evaluate(LO2, HI2, vols + vols)
        if r is not None:
            res = finish("refuted", extra=0.0)
            return PDResult("refuted", None, r[1], r[0], boxes, res.undecided_fraction + sum(vols),
                            time.monotonic() - t0, None)

"""Deterministic interval branch and bound on an IntervalFunction: prove g(x) > 0 (>=, <, <=) on a box, or enclose
the range of a scalar output to a tolerance.

Boxes are bisected at the midpoint of the split variable widest relative to its initial width; a box is proven when
the interval enclosure decides the predicate there, and a counterexample is only reported once CasADi's own double
evaluation of the function at the point confirms it. The search is best-first on the enclosure's margin with ties
broken in creation order, so the same input gives the same boxes and the same result; the wall-clock limit only
turns an answer into `undecided`. Proving goes largest box first (breadth-first); the range search goes best-first
on the bound.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import casadi
import numpy as np

from .interval import IntervalFunction

__all__ = ["ProofResult", "RangeResult", "prove", "rigorous_range", "RELATIONS"]

#: relation -> (uses the lower bound?, strict?)
RELATIONS = {">": (True, True), ">=": (True, False), "<": (False, True), "<=": (False, False)}

#: a box whose every split variable is narrower than this fraction of its initial width is not split further
MIN_RELATIVE_WIDTH = 1e-12


@dataclass
class ProofResult:
    """Outcome of `prove`: proven / refuted / undecided, with rigorous bounds over the proven boxes."""

    status: str                         # "proven" | "refuted" | "undecided"
    #: min of the lower / max of the upper enclosure bounds over the proven boxes (over every selected entry): a
    #: rigorous enclosure of g on the proven part, on the whole region when proven; None when nothing was proven
    lower: float | None
    upper: float | None
    counterexample: dict[str, np.ndarray] | None   # input values where CasADi's double g violates the predicate
    counterexample_value: np.ndarray | None        # the selected entries of g there (double)
    #: the interval enclosure at the counterexample point violates too: the exact real value does, not just double
    rigorous_counterexample: bool
    boxes: int                          # enclosures evaluated
    undecided_fraction: float           # unresolved volume / region volume, over the split variables
    seconds: float
    stopped: str | None = None          # why an undecided search stopped: "boxes", "seconds" or "min_width"

    def to_dict(self) -> dict:
        """JSON-friendly form."""
        ce = None if self.counterexample is None else {k: np.asarray(v).tolist() for k, v in self.counterexample.items()}
        return {"status": self.status, "lower": self.lower, "upper": self.upper, "counterexample": ce,
                "counterexample_value": None if self.counterexample_value is None
                else self.counterexample_value.tolist(), "rigorous_counterexample": self.rigorous_counterexample,
                "boxes": self.boxes, "undecided_fraction": self.undecided_fraction, "seconds": self.seconds,
                "stopped": self.stopped}


@dataclass
class RangeResult:
    """Outcome of `rigorous_range`: [lo, hi] encloses the scalar over the whole region; *_seen are attained (double)."""

    lo: float
    hi: float
    lo_seen: float                      # smallest double value found, at argmin
    hi_seen: float
    argmin: dict[str, np.ndarray] = field(repr=False)
    argmax: dict[str, np.ndarray] = field(repr=False)
    converged: bool                     # both gaps (lo_seen - lo, hi - hi_seen) are within the tolerance
    boxes: int
    seconds: float

    def to_dict(self) -> dict:
        """JSON-friendly form."""
        return {"lo": self.lo, "hi": self.hi, "lo_seen": self.lo_seen, "hi_seen": self.hi_seen,
                "argmin": {k: np.asarray(v).tolist() for k, v in self.argmin.items()},
                "argmax": {k: np.asarray(v).tolist() for k, v in self.argmax.items()},
                "converged": self.converged, "boxes": self.boxes, "seconds": self.seconds}


# --- the region -------------------------------------------------------------------------------------------------

@dataclass
class _Region:
    lo: np.ndarray
    hi: np.ndarray
    split: np.ndarray          # flat indices of the variables that are bisected
    scale: np.ndarray          # their initial widths


def _as_interval_function(g, backend: str, form: str) -> IntervalFunction:
    if isinstance(g, IntervalFunction):
        return g
    if isinstance(g, casadi.Function):
        return IntervalFunction(g, backend=backend, form=form)
    raise TypeError(f"expected an IntervalFunction or a casadi.Function, got {type(g).__name__}")


def _box_of(value):
    """(lo, hi) of one input's region entry: a 2-tuple is a box (lo, hi), anything else a point value."""
    if isinstance(value, tuple) and len(value) == 2:
        return value
    return value, value


def _region(F: IntervalFunction, region, split: Iterable[str] | None, no_split: Iterable[str],
            out_index: int) -> _Region:
    if not isinstance(region, Mapping):
        region = list(region)
        if len(region) != len(F.in_names):
            raise ValueError(f"{F.name!r} has {len(F.in_names)} inputs ({', '.join(F.in_names)}); the region gives "
                             f"{len(region)}")
        region = dict(zip(F.in_names, region))
    unknown = [k for k in region if k not in F.in_names]
    if unknown:
        raise ValueError(f"{F.name!r} has no input {', '.join(map(repr, unknown))} (inputs: {', '.join(F.in_names)})")
    missing = [k for k in F.in_names if k not in region]
    if missing:
        raise ValueError(f"the region of {F.name!r} gives no value or box for {', '.join(missing)}")
    lo, hi = F.flatten_box({k: _box_of(region[k]) for k in F.in_names})
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"the region of {F.name!r} must be bounded")
    names = set(F.in_names if split is None else split)
    bad = names.union(no_split) - set(F.in_names)
    if bad:
        raise ValueError(f"{F.name!r} has no input {', '.join(sorted(bad))}")
    names -= set(no_split)
    relevant = _relevant(F, out_index)
    idx = [j for i, name in enumerate(F.in_names) if name in names
           for j in range(F.in_off[i], F.in_off[i + 1]) if lo[j] < hi[j] and j in relevant]
    split_idx = np.array(idx, dtype=int)
    return _Region(lo, hi, split_idx, (hi - lo)[split_idx])


def _relevant(F: IntervalFunction, out_index: int) -> set[int]:
    """Flat input nonzeros that the output structurally depends on (others are never worth splitting)."""
    f = F.function
    xin = f.sx_in()
    y = casadi.SX(f.call(xin)[out_index])
    x = casadi.vertcat(casadi.SX(0, 1), *[v.nz[:] for v in xin])
    sp = casadi.jacobian_sparsity(y.nz[:] if y.nnz() else casadi.SX(0, 1), x)
    return set(int(c) for c in sp.get_triplet()[1])


def _out_index(F: IntervalFunction, output) -> int:
    if isinstance(output, str):
        if output not in F.out_names:
            raise ValueError(f"{F.name!r} has no output {output!r} (outputs: {', '.join(F.out_names)})")
        return F.out_names.index(output)
    if not 0 <= output < len(F.out_names):
        raise ValueError(f"{F.name!r} has {len(F.out_names)} outputs; no output {output}")
    return int(output)


def _point_dict(F: IntervalFunction, x: np.ndarray) -> dict[str, np.ndarray]:
    return F.unflatten_point(x)


def _confirm(F: IntervalFunction, x: np.ndarray, out_index: int) -> np.ndarray:
    """The selected output's nonzeros at x by the ordinary CasADi call (dense arguments), independent of the
    flat path that found the point."""
    vals = F.eval_point(_point_dict(F, x))[out_index]
    r, c = F.out_sx_shapes[out_index]
    dense = np.asarray(vals, dtype=float).reshape((r, c)).ravel(order="F")
    return dense[list(F.out_nz[out_index])]


def _split(box_lo: np.ndarray, box_hi: np.ndarray, reg: _Region):
    """The two halves of a box along its widest split variable (relative to scale), or None if all are too thin."""
    if reg.split.size == 0:
        return None
    rel = (box_hi[reg.split] - box_lo[reg.split]) / reg.scale
    k = int(np.argmax(rel))                       # first maximum: deterministic tie-break by input order
    if rel[k] <= MIN_RELATIVE_WIDTH:
        return None
    j = int(reg.split[k])
    m = 0.5 * box_lo[j] + 0.5 * box_hi[j]
    if not box_lo[j] < m < box_hi[j]:            # adjacent doubles: cannot bisect further
        return None
    lo1, hi1 = box_lo, box_hi.copy()
    hi1[j] = m
    lo2, hi2 = box_lo.copy(), box_hi
    lo2[j] = m
    return (lo1, hi1), (lo2, hi2)


# --- proving a predicate ----------------------------------------------------------------------------------------

def prove(g, region, *, relation: str = ">", bound: float = 0.0, output: int | str = 0,
          split: Iterable[str] | None = None, no_split: Iterable[str] = (), max_boxes: int = 10_000,
          seconds: float | None = None, backend: str = "codac", form: str = "natural") -> ProofResult:
    """Prove `g(x) relation bound` for every x in the region and every structural nonzero of the output.

    `g` is an IntervalFunction (or a casadi.Function, wrapped on `backend` in `form`); `region` maps every input name to a
    value or a (lo, hi) box (or is a sequence in input order). Only the inputs in `split` (default: all) minus
    `no_split` are bisected -- e.g. controller states that enter as boxes stay whole. A double value that is NaN at
    a midpoint violates the predicate (g is undefined there). Stops at `max_boxes` enclosures or after `seconds`.
    """
    if relation not in RELATIONS:
        raise ValueError(f"unknown relation {relation!r} (expected one of {', '.join(RELATIONS)})")
    use_lower, strict = RELATIONS[relation]
    F = _as_interval_function(g, backend, form)
    oi = _out_index(F, output)
    reg = _region(F, region, split, no_split, oi)
    sel = slice(F.out_off[oi], F.out_off[oi + 1])
    c = float(bound)
    t0 = time.monotonic()

    def holds(L, H) -> bool:                     # the enclosure decides the predicate on the whole box
        if use_lower:
            return bool(np.all(L > c)) if strict else bool(np.all(L >= c))
        return bool(np.all(H < c)) if strict else bool(np.all(H <= c))

    def violated(v) -> bool:                      # a double value breaks it (NaN included)
        ok = (v > c if strict else v >= c) if use_lower else (v < c if strict else v <= c)
        return not bool(np.all(ok))

    n_boxes = 0
    lower = upper = None
    heap: list = []
    counter = 0
    unresolved = 0.0        # volume fraction of boxes left too thin to split
    stopped = None

    def result(status, ce=None, ce_val=None, rigorous=False) -> ProofResult:
        left = unresolved + sum(item[2] for item in heap)
        return ProofResult(status, lower, upper, ce, ce_val, rigorous, n_boxes,
                           0.0 if status == "proven" else float(min(1.0, left)), time.monotonic() - t0, stopped)

    def refutation(x):
        v = _confirm(F, x, oi)
        if not violated(v):
            return None
        L, H = F.eval_flat(x, x)
        return result("refuted", _point_dict(F, x), v, decided_against(L[sel], H[sel]))

    def decided_against(L, H) -> bool:            # the exact value at a point violates it for sure
        if use_lower:
            return bool(np.any(H <= c)) if strict else bool(np.any(H < c))
        return bool(np.any(L >= c)) if strict else bool(np.any(L > c))

    if len(F.out_nz[oi]) < F.out_sx_shapes[oi][0] * F.out_sx_shapes[oi][1] and violated(np.zeros(1)):
        mid = np.where(reg.lo == reg.hi, reg.lo, 0.5 * reg.lo + 0.5 * reg.hi)
        n_boxes = 0
        return result("refuted", _point_dict(F, mid), np.zeros(1), True)

    def evaluate(lo, hi, vol):
        nonlocal n_boxes, lower, upper, counter
        L, H = F.eval_flat(lo, hi)
        n_boxes += 1
        L, H = L[sel], H[sel]
        if holds(L, H):
            lmin, hmax = float(np.min(L)), float(np.max(H))
            lower = lmin if lower is None else min(lower, lmin)
            upper = hmax if upper is None else max(upper, hmax)
            return None
        mid = np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
        if violated(F.eval_point_flat(mid)[sel]):
            r = refutation(mid)
            if r is not None:
                return r
        # largest box first, then creation order: every level of bisection is finished before the next, so the
        # easy part of the region is proven early and the undecided fraction at a budget stop means something
        heapq.heappush(heap, (-vol, counter, vol, lo, hi))
        counter += 1
        return None

    r = evaluate(reg.lo.copy(), reg.hi.copy(), 1.0)
    if r is not None:
        return r
    while heap:
        if n_boxes >= max_boxes:
            stopped = "boxes"
            return result("undecided")
        if seconds is not None and time.monotonic() - t0 > seconds:
            stopped = "seconds"
            return result("undecided")
        _, _, vol, lo, hi = heapq.heappop(heap)
        halves = _split(lo, hi, reg)
        if halves is None:
            unresolved += vol
            stopped = "min_width"
            continue
        for blo, bhi in halves:
            r = evaluate(blo, bhi, 0.5 * vol)
            if r is not None:
                # the undecided fraction of a refutation counts what was still open when it was found
                return r
    if unresolved > 0:
        return result("undecided")
    return result("proven")


# --- a rigorous range -------------------------------------------------------------------------------------------

def rigorous_range(g, region, *, output: int | str = 0, element: int = 0, tol: float = 1e-6,
                   rel_tol: float = 0.0, split: Iterable[str] | None = None, no_split: Iterable[str] = (),
                   max_boxes: int = 20_000, seconds: float | None = None, backend: str = "codac",
                   form: str = "mean_value") -> RangeResult:
    """The tightest enclosure [lo, hi] of one scalar entry of g over the region that the budget allows.

    Best-first on each side: the box with the smallest lower bound is split until that bound is within
    max(tol, rel_tol |value|) of the smallest double value found at a box midpoint (the same for the maximum).
    `lo` and `hi` are rigorous whatever the budget; `converged` says whether both gaps closed. `element` is the
    index of the entry in the output's dense column-major order; a structural zero gives [0, 0] at once. A
    casadi.Function is wrapped in the mean-value form by default: near an extremum boxes are narrow and the natural
    form's overestimation (linear in the width) would need ~1/sqrt(width) boxes side by side.
    """
    F = _as_interval_function(g, backend, form)
    oi = _out_index(F, output)
    r_, c_ = F.out_sx_shapes[oi]
    if not 0 <= element < r_ * c_:
        raise ValueError(f"output {F.out_names[oi]!r} of {F.name!r} has {r_ * c_} entries; no entry {element}")
    reg = _region(F, region, split, no_split, oi)
    t0 = time.monotonic()
    mid0 = np.where(reg.lo == reg.hi, reg.lo, 0.5 * reg.lo + 0.5 * reg.hi)
    nz = list(F.out_nz[oi])
    if element not in nz:
        p = _point_dict(F, mid0)
        return RangeResult(0.0, 0.0, 0.0, 0.0, p, p, True, 0, time.monotonic() - t0)
    pos = F.out_off[oi] + nz.index(element)
    per_side = max(1, max_boxes // 2)
    deadline = None if seconds is None else t0 + seconds
    lo_b, lo_seen, xmin, n1, ok1 = _extremum(F, reg, pos, +1.0, tol, rel_tol, per_side, deadline)
    hi_b, hi_seen, xmax, n2, ok2 = _extremum(F, reg, pos, -1.0, tol, rel_tol, per_side, deadline)
    return RangeResult(lo_b, -hi_b, lo_seen, -hi_seen, _point_dict(F, xmin), _point_dict(F, xmax), ok1 and ok2,
                       n1 + n2, time.monotonic() - t0)


def _extremum(F: IntervalFunction, reg: _Region, pos: int, s: float, tol: float, rel_tol: float, budget: int,
              deadline: float | None):
    """min of s*g[pos] over the region: (rigorous lower bound, best double value, its point, boxes, converged)."""
    heap: list = []
    counter = 0
    n = 0
    best, best_x = math.inf, None
    thin: list[float] = []          # lower bounds of boxes that cannot be split further

    def evaluate(lo, hi):
        nonlocal n, counter, best, best_x
        L, H = F.eval_flat(lo, hi)
        n += 1
        b = s * L[pos] if s > 0 else s * H[pos]
        mid = np.where(lo == hi, lo, 0.5 * lo + 0.5 * hi)
        v = s * F.eval_point_flat(mid)[pos]
        if v < best:                # NaN never improves
            best, best_x = float(v), mid
        heapq.heappush(heap, (float(b) if b == b else -math.inf, counter, lo, hi))
        counter += 1

    evaluate(reg.lo.copy(), reg.hi.copy())
    converged = False
    while heap:
        b, _, lo, hi = heap[0]
        if best - b <= max(tol, rel_tol * abs(best)):
            converged = True
            break
        if n >= budget or (deadline is not None and time.monotonic() > deadline):
            break
        heapq.heappop(heap)
        halves = _split(lo, hi, reg)
        if halves is None:
            thin.append(b)
            continue
        for blo, bhi in halves:
            evaluate(blo, bhi)
    # the heap's first item is its minimum; thin boxes were popped as minima and stay in the bound
    bound = min([item[0] for item in heap[:1]] + thin)
    if best_x is None:
        best_x = np.where(reg.lo == reg.hi, reg.lo, 0.5 * reg.lo + 0.5 * reg.hi)
    if thin:
        converged = converged and best - min(thin) <= max(tol, rel_tol * abs(best))
    return float(bound), best, best_x, n, converged

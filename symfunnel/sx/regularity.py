"""Regularity of a function of time proven over [0, T] by interval arithmetic, not sampled.

`nonsmooth_arguments(exprs, t)` lists each operation of the expressions' graph that has a kink or a jump (abs, sign,
min, max, floor, ceil, a comparison, a logic operation, if-else, atan2) with the argument whose switch is the kink
or jump (abs(x), sign(x): x; min(x, y), max(x, y), x < y: x - y; floor(x): x against the integers; atan2(y, x): y).
`prove_on_horizon(f, kinds, T)` proves, by bisection of [0, T] with the batched endpoint interval backend
(`sx.batch`, outward rounded), a predicate of each output on the whole horizon: "positive" (lo > 0), "nonzero"
(the enclosure excludes 0), "finite", "same_floor" / "same_ceil" (no integer crossed). A box where an enclosure
does not decide is bisected down to a minimum width; what is left is returned with the double value at its midpoint
(a definite failure when that value already violates the predicate). A function whose switching arguments are all
proven nonzero, and whose enclosures (of the function and of the derivatives asked for) are finite on every box, is
built from operations that are smooth where they are evaluated: it is as often continuously differentiable as it
was differentiated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

#: operation name -> how its switching argument is formed from its dependencies (None: not an operation of time)
_SWITCH = {
    "FABS": "x", "SIGN": "x", "NOT": "x", "FLOOR": "floor", "CEIL": "ceil",
    "FMIN": "x-y", "FMAX": "x-y", "LT": "x-y", "LE": "x-y", "EQ": "x-y", "NE": "x-y",
    "AND": "both", "OR": "both", "IF_ELSE_ZERO": "x", "ATAN2": "x", "FMOD": "x", "COPYSIGN": "y",
}
_OPS = {getattr(ca, "OP_" + k): k for k in _SWITCH if hasattr(ca, "OP_" + k)}
#: a box narrower than this fraction of max(T, 1) is not bisected further
MIN_WIDTH = 2.0 ** -40
#: at most this many boxes per proof
MAX_BOXES = 40_000


@dataclass
class Switch:
    """One non-smooth operation: its name, the argument whose switch is the kink/jump, and the predicate that rules
    the switch out."""

    op: str
    argument: ca.SX
    kind: str            # "nonzero" | "same_floor" | "same_ceil"


def nonsmooth_arguments(exprs: ca.SX, t: ca.SX) -> list[Switch]:
    """Every non-smooth operation of the graph of `exprs` whose argument depends on t (once per node)."""
    out: list[Switch] = []
    seen: set = set()
    stack = [exprs.nz[k] for k in range(exprs.nnz())]
    while stack:
        e = stack.pop()
        if e.is_constant() or e.is_symbolic():
            continue
        h = e.element_hash()
        if h in seen:
            continue
        seen.add(h)
        deps = [e.dep(i) for i in range(e.n_dep())]
        stack.extend(deps)
        name = _OPS.get(e.op())
        if name is None or not ca.depends_on(e, t):
            continue
        form = _SWITCH[name]
        if form == "x":
            args = [(deps[0], "nonzero")]
        elif form == "y":
            args = [(deps[1], "nonzero")]
        elif form == "x-y":
            args = [(deps[0] - deps[1], "nonzero")]
        elif form == "both":
            args = [(d, "nonzero") for d in deps]
        else:
            args = [(deps[0], "same_" + form)]
        out += [Switch(name, a, k) for a, k in args if ca.depends_on(a, t)]
    return out


@dataclass
class Failure:
    """Where a predicate could not be proven: the output, the time box, the double value at its midpoint and
    whether that value violates the predicate (definite) or the enclosure only did not decide."""

    output: int
    t_lo: float
    t_hi: float
    value: float
    definite: bool


def _holds(kind: str, lo, hi):
    fin = np.isfinite(lo) & np.isfinite(hi)
    if kind == "positive":
        return fin & (lo > 0)
    if kind == "nonzero":
        return fin & ((lo > 0) | (hi < 0))
    if kind == "finite":
        return fin
    if kind == "same_floor":
        return fin & (np.floor(lo) == np.floor(hi))
    if kind == "same_ceil":
        return fin & (np.ceil(lo) == np.ceil(hi))
    raise ValueError(f"unknown predicate {kind!r}")


def _holds_at(kind: str, v: float) -> bool:
    if not math.isfinite(v):
        return False
    return {"positive": v > 0, "nonzero": v != 0, "finite": True}.get(kind, True)


def prove_on_horizon(f: ca.Function, kinds: list[str], t_final: float, max_boxes: int = MAX_BOXES,
                     evaluator=None) -> list[Failure]:
    """Prove kinds[k] of output nonzero k of f(t) (one scalar input) for every t in [0, t_final]; the failures (at
    most one per output, its first box in time) -- empty when every predicate is proven."""
    from .batch import BatchIntervalFunction
    F = evaluator or BatchIntervalFunction(f)
    n_out = F.out_off[-1]
    if len(kinds) != n_out:
        raise ValueError(f"{len(kinds)} predicates for {n_out} outputs")
    T = float(t_final)
    min_w = MIN_WIDTH * max(T, 1.0)
    todo = np.ones(n_out, dtype=bool)              # outputs not yet failed
    pending = [(0.0, T)]
    fails: dict[int, Failure] = {}
    boxes = 0
    while pending and todo.any():
        LO = np.array([[a] for a, _ in pending])
        HI = np.array([[b] for _, b in pending])
        boxes += len(pending)
        L, H, _ = F.eval_batch(LO, HI)
        ok = np.ones((len(pending), n_out), dtype=bool)
        for k in range(n_out):
            ok[:, k] = _holds(kinds[k], L[:, k], H[:, k]) | ~todo[k]
        nxt = []
        for i, (a, b) in enumerate(pending):
            if ok[i].all():
                continue
            if b - a <= min_w or boxes + 2 * len(nxt) >= max_boxes:
                mid = 0.5 * (a + b)
                vals = np.asarray(F.eval_points(np.array([[mid]])), float).ravel()
                for k in np.flatnonzero(~ok[i]):
                    if k not in fails:
                        fails[k] = Failure(int(k), a, b, float(vals[k]), not _holds_at(kinds[k], float(vals[k])))
                        todo[k] = False
                continue
            m = 0.5 * (a + b)
            nxt += [(a, m), (m, b)]
        # a definite violation at a box's midpoint needs no further bisection
        if nxt:
            mids = np.array([[0.5 * (a + b)] for a, b in nxt])
            vals = np.asarray(F.eval_points(mids), float).reshape(len(nxt), n_out)
            for k in np.flatnonzero(todo):
                bad = [i for i in range(len(nxt)) if not _holds_at(kinds[k], float(vals[i, k]))]
                if bad:
                    i = bad[0]
                    fails[k] = Failure(int(k), nxt[i][0], nxt[i][1], float(vals[i, k]), True)
                    todo[k] = False
        pending = nxt
    return [fails[k] for k in sorted(fails)]

"""The mean-value (centered) form in a chosen subset of an SX Function's inputs, on the interval evaluator.

For inputs split into w (the ones the form is centered in) and u (the others, entering as their boxes):

    f(W, U)  is enclosed by  f(w_m, U) + J_w(W, U) (W - w_m),     w_m the midpoint of W,

with J_w = df/dw by CasADi's AD of the same graph, interval-evaluated over the whole box; the result is intersected
with the natural enclosure f(W, U). It is valid where f is continuous in w on the box: boxes on which a
discontinuous operation of the tape switches (sign, a comparison, an undecided if-else) get the natural enclosure
alone. Its overestimation shrinks with the square of the box width in w (the natural form's only linearly), which
is what a narrow box in a long dependency chain (an inverse, a Cholesky pivot, z = e/(F - |e|)) needs.

`bounds_and_jacobian` also returns the enclosure of J_w over the box, which the branch and bound of
`symfunnel.certificates` uses to split the variable with the largest |J| x width (splitting by sensitivity).
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi
import numpy as np

from .interval import IntervalError, IntervalFunction

__all__ = ["CenteredForm"]

_INF = float("inf")


class CenteredForm:
    """Enclosures of an SX Function's output nonzeros (flat) over boxes, centered in the inputs `wrt`."""

    def __init__(self, f: casadi.Function, wrt: Sequence[str], backend: str = "arb"):
        self.natural = IntervalFunction(f, backend=backend, form="natural")
        F = self.natural
        f = F.function
        unknown = [k for k in wrt if k not in F.in_names]
        if unknown:
            raise ValueError(f"{f.name()!r} has no input {', '.join(unknown)}")
        self.wrt = [k for k in F.in_names if k in wrt]
        xin = f.sx_in()
        outs = f.call(xin)
        y = casadi.vertcat(casadi.SX(0, 1), *[casadi.SX(o).nz[:] for o in outs])
        w = casadi.vertcat(casadi.SX(0, 1), *[xin[F.in_names.index(k)].nz[:] for k in self.wrt])
        J = casadi.jacobian(y, w)
        rows, cols = J.sparsity().get_triplet()
        self.jac = IntervalFunction(casadi.Function(f.name() + "_dw", xin, [J], list(F.in_names), ["J"],
                                                    {"cse": True, "allow_duplicate_io_names": True}),
                                    backend=backend)
        self.entries = list(zip(rows, cols))
        #: flat input index (of the natural function's layout) of each column of J
        self.w_flat = np.concatenate([np.arange(F.in_off[F.in_names.index(k)], F.in_off[F.in_names.index(k) + 1])
                                      for k in self.wrt]).astype(int) if self.wrt else np.zeros(0, int)
        self.n_out = F.n_out_nz
        self.backend = F.backend

    def __getattr__(self, name):
        # everything else (shapes, layouts, eval_point_flat...) is the natural evaluator's: branch and bound takes
        # a CenteredForm wherever it takes an IntervalFunction
        if name == "natural":
            raise AttributeError(name)
        return getattr(self.natural, name)

    def eval_flat(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The enclosures of the output nonzeros over a flat box (as `IntervalFunction.eval_flat`)."""
        return self.bounds(np.asarray(lo, float), np.asarray(hi, float))

    def bounds(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous (lo, hi) of every output nonzero over the flat box."""
        L, H, _ = self.bounds_and_jacobian(lo, hi)
        return L, H

    def bounds_and_jacobian(self, lo: np.ndarray, hi: np.ndarray):
        """(lo, hi) of the outputs and the (n_out, n_wrt) magnitude bound max|J| over the box (inf where unknown)."""
        F, be = self.natural, self.backend
        vals, continuous = F.eval_values(lo, hi)
        L = np.empty(len(vals))
        H = np.empty(len(vals))
        for k, v in enumerate(vals):
            L[k], H[k] = be.bounds(v)
        Jv, _ = self.jac.eval_values(lo, hi)
        Jabs = np.zeros((self.n_out, self.w_flat.size))
        Jb = []
        for k, (i, j) in enumerate(self.entries):
            a, b = be.bounds(Jv[k])
            Jabs[i, j] = max(abs(a), abs(b))
            Jb.append((i, j, Jv[k]))
        if not continuous or self.w_flat.size == 0:
            return L, H, Jabs
        wl, wh = lo[self.w_flat], hi[self.w_flat]
        wm = np.where(wl == wh, wl, 0.5 * wl + 0.5 * wh)
        mlo, mhi = lo.copy(), hi.copy()
        mlo[self.w_flat] = wm
        mhi[self.w_flat] = wm
        # f(w_m, U): a separate IntervalFunction state (the natural one caches its last inputs)
        fm, _ = F.eval_values(mlo, mhi)
        make, sub, mul, add = be.interval, be.rules["SUB"], be.rules["MUL"], be.rules["ADD"]
        dx = [sub(make(float(wl[j]), float(wh[j])), be.point(float(wm[j]))) for j in range(wl.size)]
        acc = list(fm)
        for i, j, Jij in Jb:
            if wl[j] < wh[j]:
                acc[i] = add(acc[i], mul(Jij, dx[j]))
        for i, v in enumerate(acc):
            a, b = be.bounds(v)
            # only a valid natural enclosure is tightened: it is what shows f defined on the whole box
            if a > -_INF and L[i] > -_INF:
                L[i], H[i] = max(L[i], a), min(H[i], b)
                if L[i] > H[i]:
                    raise IntervalError(f"{F.name!r}: the centered and natural enclosures of output nonzero {i} "
                                        f"are disjoint -- an interval rule is wrong")
        return L, H, Jabs

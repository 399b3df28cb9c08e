"""The W_hat face of `certify.containment` for a projected adaptive law (`[adaptation] projection = R`): the ball
||W_hat||_F <= w is invariant, shown on the design's own graph rather than assumed from the operator's theory.

The argument, each step checked here:

1. on the graph, W_hat_dot is Y - c W_hat entry by entry, c is max(a, 0) k, a = <W_hat, Y>_F and b = ||W_hat||_F^2
   are those expressions, and k depends on (t, x, W_hat) only through b (b's node replaced by a symbol B leaves k
   free of every design input) -- structural identities of the SX graph (`casadi.is_equal`), no numbers;
2. so d/dt ||W_hat||^2 / 2 = <W_hat, Y - c W_hat> = a - max(a, 0) k(b) b: this is a <= 0 where a <= 0, and
   a (1 - k(b) b) where a > 0;
3. 1 - k(B) B <= 0 for every B in [w^2, 4 w^2], proven by interval evaluation of k's graph (outward rounded) over a
   geometric subdivision of that interval, with w = R (1 + eps) (1 + W_MARGIN).

Then ||W_hat|| cannot pass w: on any interval after it would reach w and before it reaches 2 w, d/dt ||W_hat||^2 <= 0
(3 with 2), so it stays <= w (continuity). The e2 faces then carry W_hat in the ball of radius w.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..family.projection import outer_radius
from ..sx.batch import BatchIntervalFunction
from ..sx.rewrite import replace_nodes

#: the proven radius is this fraction above the layer's outer radius R (1 + eps): there k(b) b > 1 with room for
#: the interval subdivision (at R (1 + eps) itself k b = 1 exactly, and rounding cannot prove <= 0)
W_MARGIN = 0.01
#: pieces of [w^2, 4 w^2] at most
MAX_PIECES = 4096
#: depth of the structural comparisons (a sum over every weight: one level per entry)
DEPTH = 100000


def projection_face(design) -> dict:
    """{"ok": True, "w": the proven radius, "pieces"} or {"ok": False, "why": which step fails}."""
    P = design.parts.get("projection")
    if P is None:
        return {"ok": False, "why": "the design has no projected adaptive law"}
    W = design.sym["w_hat"]
    Wd = design.signals["w_hat_dot"]
    Y, a, b, k, c = (P[x] for x in ("raw", "a", "b", "k", "c"))
    expect = Y - c * W
    if not all(ca.is_equal(Wd[i, j], expect[i, j], 3) for i in range(W.shape[0]) for j in range(W.shape[1])):
        return {"ok": False, "why": "W_hat_dot is not Y - c W_hat on the graph (the projection's correction is not "
                "radial)"}
    if not ca.is_equal(a, ca.dot(ca.vec(W), ca.vec(Y)), DEPTH):
        return {"ok": False, "why": "the projection's boundary test is not <W_hat, Y> on the graph"}
    if not ca.is_equal(b, ca.sumsqr(W), DEPTH):
        return {"ok": False, "why": "the projection's b is not ||W_hat||^2 on the graph"}
    if not ca.is_equal(c, ca.fmax(a, 0) * k, 2):
        return {"ok": False, "why": "the projection's c is not max(<W_hat, Y>, 0) k(||W_hat||^2) on the graph"}
    B = ca.SX.sym("B")
    kB = replace_nodes([k], b, B)[0]
    inputs = ca.vertcat(*[ca.vec(design.sym[name]) for name in design.inputs])
    if ca.depends_on(kB, inputs):
        return {"ok": False, "why": "the projection's gain k depends on the state beyond ||W_hat||^2"}
    w = outer_radius(P["R"], P["eps"]) * (1.0 + W_MARGIN)
    F = BatchIntervalFunction(ca.Function("projection_gain", [B], [1 - kB * B]))
    lo, hi = w * w, 4.0 * w * w
    pieces = 1
    while pieces <= MAX_PIECES:
        edges = lo * (hi / lo) ** (np.arange(pieces + 1) / pieces)
        edges[0], edges[-1] = lo, hi
        _, H, _ = F.eval_batch(edges[:-1, None], edges[1:, None])
        if np.all(H[:, 0] <= 0.0):
            return {"ok": True, "w": float(w), "pieces": pieces}
        pieces *= 2
    return {"ok": False, "why": f"1 - k(B) B <= 0 on [{lo:.4g}, {hi:.4g}] not proven in {MAX_PIECES} pieces "
            "(the projection does not remove the outward part of the law at the layer's outer radius)"}


__all__ = ["projection_face", "W_MARGIN"]

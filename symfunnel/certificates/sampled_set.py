"""S, the set of states at a sampling instant that `certify.sampled` starts from and returns to: a declared one (the
funnels at margins m1, m2, the controller states in their boxes) or the set a proven `certify.containment` gives."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import InputError
from ..emit.step import CLIP
from ..family.projection import outer_radius
from .problem import Context, controller_state_boxes


@dataclass
class SampledSet:
    """S: the states at a sampling instant the certificate starts from and returns to (the seam for a containment
    certificate's set: `source` says where it comes from)."""

    m1: float
    m2: float
    states: dict = field(default_factory=dict)        # controller-state boxes {name: (lo, hi)}
    source: str = "declared"
    notes: dict = field(default_factory=dict)
    w_ball: float | None = None     # W_hat in the ball ||W_hat||_F <= w_ball (states["w_hat"] its bounding box)

    def describe(self, t_final: float) -> dict:
        """The contract's region dict of S."""
        return {"t": [0.0, float(t_final)], "margin": {"e1": self.m1, "e2": self.m2}, "source": self.source,
                **self.notes}


def normalised_errors(design):
    """sigma(t, q, dq) = (e1 / F1, (dq - alpha2) / F2) from the design's reference, funnels and alpha2: where a
    joint state lies relative to S's margins."""
    F = design.function("funnel_bounds", ["t"], ["F1", "F2"])
    a2 = design.function("alpha2", ["t", "q", "qd", "dqd"])

    def sigma(t, q, dq):
        qd, dqd, _ = (np.asarray(v, float).ravel() for v in design.reference(t))
        F1, F2 = (np.asarray(v, float).ravel() for v in F(t))
        q, dq = np.asarray(q, float).ravel(), np.asarray(dq, float).ravel()
        return np.concatenate([(q - qd) / F1, (dq - np.asarray(a2(t, q, qd, dqd), float).ravel()) / F2])
    return sigma


def declared_set(ctx: Context, m1: float, m2: float, w_box=None, w_source: str | None = None) -> SampledSet:
    """S with margins (m1, m2), x_esn in its invariant box and W_hat in `w_box` (else the bounds certificate's box:
    the run's range widened by its own width)."""
    for k, m in (("e1", m1), ("e2", m2)):
        if not (isinstance(m, (int, float)) and math.isfinite(m) and 1.0 - CLIP <= m < 1.0):
            raise InputError(f"is {m!r}", file=ctx.scenario.file, key=f"--set-margin ({k})",
                             expected=f"a margin in [{1 - CLIP:g}, 1) (the step projects at {CLIP:g} F)")
    notes = {}
    w = None
    proj = ctx.design.parts.get("projection")
    if ctx.design.n_regressor and w_box is None and proj is not None:
        r = outer_radius(proj["R"], proj["eps"])
        shape = tuple(int(v) for v in ctx.design.sym["w_hat"].shape)
        w_box = (np.full(shape, -r), np.full(shape, r))
        w_source = (f"the box of the projection's ball ||W_hat||_F <= {r:.6g}, which the deployed step clips W_hat "
                    "onto")
    if ctx.design.n_regressor:
        if w_box is None:
            from .bounds import w_hat_box
            w_box, w_source = w_hat_box(ctx)
        w = w_box
        notes["w_hat"] = w_source
    if "x_esn" in dict(ctx.design.states):
        notes["x_esn"] = "the reservoir's invariant box |x_i| <= 1/leak"
    states = controller_state_boxes(ctx, w) if (w is not None or not ctx.design.n_regressor) else {}
    return SampledSet(float(m1), float(m2), states, "declared", notes)


def containment_set(ctx: Context, M: float) -> SampledSet | None:
    """S from a proven `certify.containment` of this context (None otherwise): its margins (each raised to the
    rate's margin M where it is below: the period's funnel check needs S within the margin M), W_hat in its ball
    ||W_hat||_F <= w (boxes evaluate over the bounding box; the update is checked to keep the ball) and x_esn in its
    invariant box. The sampled proof re-proves the return to this S itself; containment only proposes it."""
    from .containment import proven_set
    P = proven_set(ctx)
    if P is None:
        return None
    m1, m2 = max(P["m1"], float(M)), max(P["m2"], float(M))
    notes = {"containment_margin": {"e1": P["m1"], "e2": P["m2"]}}
    if (m1, m2) != (P["m1"], P["m2"]):
        notes["raised_to_rate_margin"] = float(M)
    w = P["w"]
    if ctx.design.n_regressor:
        if w is None:
            return None
        W0 = np.zeros_like(np.asarray(ctx.design.variant.initial_states()["w_hat"], float))
        states = controller_state_boxes(ctx, (W0 - w, W0 + w))
        notes["w_hat"] = f"the containment certificate's ball ||W_hat||_F <= {w:.6g} (kept by the update: checked)"
    else:
        states = controller_state_boxes(ctx, None)
    if "x_esn" in dict(ctx.design.states):
        notes["x_esn"] = "the reservoir's invariant box |x_i| <= 1/leak"
    return SampledSet(float(m1), float(m2), states, "certify.containment", notes,
                      w_ball=None if w is None else float(w))

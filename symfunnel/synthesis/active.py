"""What a tuned design gave up, said: the parameters that ended at a bound of `[tune.bounds]` and the tracking or
smoothness it lost against the user's design. An active bound is a finding `tune` states (the search
was stopped by the bound, not by the constraints or the objective: on the paper k1 went from 5 to its lower bound
0.1, and the tracking error grew with it)."""

from __future__ import annotations

import math

__all__ = ["AT_BOUND", "at_bounds", "DEGRADED", "degradations"]

#: a tuned design whose tracking error or chattering grew by more than this factor is flagged
DEGRADED = 2.0

#: a value this close to a bound on the search's log scale (a share of log(hi/lo)) is at that bound
AT_BOUND = 1e-3


def at_bounds(vars_, xs) -> list[dict]:
    """The coordinates (`synthesis.candidates.Variable`) whose value ended at a bound of [tune.bounds] (an active
    bound: the search was stopped by it, not by the constraints or the objective), with the bound and the user's
    value."""
    out = []
    for v, x in zip(vars_, xs):
        z = math.log(x / v.lo) / math.log(v.hi / v.lo) if v.hi > v.lo and x > 0 else 0.5
        side = "lower" if z <= AT_BOUND else "upper" if z >= 1 - AT_BOUND else None
        if side is not None:
            out.append({"key": v.name, "value": float(x), "bound": side,
                        "bound_value": float(v.lo if side == "lower" else v.hi), "before": float(v.user_x())})
    return out


def degradations(before: dict, after: dict, factor: float = DEGRADED) -> list[str]:
    """Notes for the figures (`synthesis.candidates._tracking`) that grew by more than `factor` from the user's design
    to the tuned one: the e1 RMS after the transient and the chattering index (docs/metrics.md)."""
    out = []
    for key, what in (("e1_rms_after_transient", "the e1 RMS after the transient (tracking)"),
                      ("chattering", "the chattering index (total variation of tau per s)")):
        a, b = before.get(key), after.get(key)
        if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or a <= 0:
            continue
        if b > factor * a:
            out.append(f"{what} grew {b / a:.3g}x ({a:.4g} -> {b:.4g}): the tuned design trades it for the "
                       "objective; add it to your judgement, or narrow [tune.bounds]")
    return out

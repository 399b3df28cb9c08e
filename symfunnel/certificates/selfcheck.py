"""The certificates' run-time self-check: every enclosure must contain the values attained at its own witnesses.

A branch and bound's rigorous bound and the value at the point it found are computed by two different paths (the
interval tape, outward rounded, and the same Function evaluated in double by plain CasADi -- the design's ordinary
Functions where the certificate has no region graph, e.g. M and M_p of the input gain); `lo <= attained <= hi` must
hold at every witness. A violation means an interval rule (or the region's construction) is unsound, so the run
stops with an internal error (exit 3) -- never a verdict built on it. The double value may differ from the exact one
by its round-off, hence the tolerance REL_TOL relative to the value's magnitude.
"""

from __future__ import annotations

import math

import numpy as np

#: relative tolerance of the comparison (the double evaluation's round-off; a rule off by more is caught)
REL_TOL = 1e-8


class EnclosureViolation(RuntimeError):
    """An enclosure that does not contain a value attained inside its own region: an unsound interval rule."""


def check_contains(what: str, lo: float | None, hi: float | None, value: float, where=None,
                   slack: float = 0.0) -> None:
    """Raise EnclosureViolation unless lo <= value <= hi (within REL_TOL, plus `slack`: the width of the interval
    evaluation at the witness point itself, which bounds the double value's own round-off where a signal cancels);
    a non-finite value attains nothing."""
    v = float(value)
    if not math.isfinite(v):
        return
    tol = REL_TOL * max(1.0, abs(v)) + (float(slack) if math.isfinite(float(slack)) else math.inf)
    below = lo is not None and math.isfinite(float(lo)) and v < float(lo) - tol
    above = hi is not None and math.isfinite(float(hi)) and v > float(hi) + tol
    if below or above:
        at = "" if where is None else f" at {np.round(np.asarray(where, float), 9).tolist()}"
        raise EnclosureViolation(f"certificate self-check failed: the enclosure [{lo!r}, {hi!r}] of {what} does not "
                                 f"contain {v!r}, the value the ordinary CasADi Function attains{at} inside its "
                                 "region (an interval rule or the region is unsound; no verdict is given)")

"""The smoothing study: how far the trajectory moves with the non-smooth terms' smoothing width."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ..core.errors import InputError
from ..core.io import json_safe
from .run import simulate

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from ..design import Design
    from ..scenario import Scenario


def convergence_study(scenario: Scenario, design: Design, widths: Sequence[float] | None = None, *,
                      t_final: float | None = None, integrator: str | None = None,
                      progress: Callable[[str], None] | None = None) -> dict:
    """Max |q difference| against a reference run at a tenth of the smallest width, with the observed rate.

    Every studied width (the scenario's convergence_widths and its smoothing_width) is compared with the finer
    reference, never with itself; the rate between consecutive widths is log(d_a/d_b)/log(w_a/w_b) (1 for O(w)).
    """
    say = progress or (lambda s: None)
    ws = list(widths if widths is not None else scenario.simulation.convergence_widths)
    ws.append(scenario.simulation.smoothing_width)
    ws = sorted({float(w) for w in ws if w > 0}, reverse=True)
    if len(ws) < 2:
        raise InputError("needs at least two positive widths", key="simulation.convergence_widths",
                         expected="widths > 0 different from the run's smoothing_width")
    ref_w = ws[-1] / 10
    runs = {}
    for w in ws + [ref_w]:
        say(f"convergence study: width {w:g}" + (" (reference)" if w == ref_w else ""))
        runs[w] = simulate(scenario, design, t_final=t_final, integrator=integrator, width=w)
    ref = runs[ref_w]
    rows = []
    for w in ws:
        r = runs[w]
        T = min(r.t.size, ref.t.size)
        diff = float(np.max(np.abs(r.signals["q"][:T] - ref.signals["q"][:T])))
        rows.append({"width": w, "status": r.status, "max_abs_q_diff_vs_smallest": diff,
                     "steps": r.stats.get("steps"), "wall_time": r.stats.get("wall_time"),
                     "min_margin_e1": [float(v) for v in np.min(r.signals["m1"], axis=0)]})
    rates = []
    for a, b in zip(rows[:-1], rows[1:]):
        if a["max_abs_q_diff_vs_smallest"] > 0 and b["max_abs_q_diff_vs_smallest"] > 0:
            rates.append(math.log(a["max_abs_q_diff_vs_smallest"] / b["max_abs_q_diff_vs_smallest"])
                         / math.log(a["width"] / b["width"]))
    return json_safe({"reference_width": ref_w, "runs": rows, "observed_rates": rates,
                         "note": "q difference against a reference run at a tenth of the smallest width; "
                                 "the smoothing error is O(w), so the rate should be near 1"})


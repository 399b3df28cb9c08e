"""Data and figures of the deployed controller for the report: minimum rate, design help, torque beside the limits.

`implementation_report(scenario, design)` returns plain data; `torque_figure` (sampled torque as stairs over the
continuous one) and `deployed.rate.margin_rate_figure` (min margin against rate) draw it. The report's wiring is left to reporting/.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["implementation_report", "torque_figure"]


def implementation_report(scenario: Scenario, design: Design, *, margin: float = 0.05, sensitivity: bool = True,
                          t_final: float | None = None, progress: Callable[[str], None] | None = None,
                          engine: str = "symfunnel") -> dict:
    """{"min_rate": rate.min_rate(...), "sensitivity": rate.rate_sensitivity(...) | None, "run": the sampled run's
    summary at the scenario's rate (twice the minimum without [implementation]), "peak_tau", "tau_max",
    "effort_limits" (a URDF model's <limit effort>, else None)}: the peak torque beside the actuator limits, on the
    plant `engine` (symfunnel's by default; `deployed.compare` puts a physics engine beside it)."""
    from .rate import min_rate, rate_sensitivity
    from .loop import simulate_sampled
    say = progress or (lambda s: None)
    r = min_rate(scenario, design, margin=margin, t_final=t_final, progress=say, engine=engine)
    impl = getattr(scenario, "implementation", None)
    rate = impl.rate_hz if impl is not None else (2 * r["min_rate_hz"] if r["min_rate_hz"] else None)
    run = None
    if rate is not None:
        res = simulate_sampled(scenario, design, rate_hz=rate, t_final=t_final, engine=engine)
        run = res.summary()
        run["result"] = res
    sens = (rate_sensitivity(scenario, design, margin=margin, t_final=t_final, baseline=r, progress=say,
                             engine=engine)
            if sensitivity else None)
    effort = None
    model = scenario.raw.get("model", {})
    if model.get("type") == "urdf":
        from ..model.urdf import effort_limits
        effort = effort_limits(scenario.path.parent / model["path"])
    return {"min_rate": r, "sensitivity": sens, "run": run,
            "peak_tau": None if run is None else run["max_abs_tau"],
            "tau_max": None if impl is None or impl.tau_max is None else list(impl.tau_max),
            "effort_limits": effort}


def torque_figure(sampled, continuous=None, t_max: float | None = None, units=None):
    """A matplotlib Figure per joint: the sampled run's held torque as stairs, the continuous run's torque over it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = sampled.q.shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(6, 1.8 * n + 0.6), sharex=True, squeeze=False)
    t = sampled.t
    m = sampled.tau.shape[0] if t_max is None else int(min(sampled.tau.shape[0], np.searchsorted(t, t_max)))
    for j, ax in enumerate(axes[:, 0]):
        ax.stairs(sampled.tau[:m, j], t[:m + 1], baseline=None, label=f"sampled at {sampled.rate_hz:g} Hz (held)")
        if continuous is not None:
            tc = continuous.t if t_max is None else continuous.t[continuous.t <= t_max]
            ax.plot(tc, continuous.signals["tau"][:tc.size, j], lw=0.8, label="continuous-time controller")
        if sampled.tau_max is not None:
            for s in (1, -1):
                ax.axhline(s * sampled.tau_max[j], color="k", ls=":", lw=0.8)
        ax.set_ylabel(f"tau{j + 1} [{units[j]['tau'] if units else 'N m'}]")
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    return fig

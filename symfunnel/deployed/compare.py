"""The deployed controller on two plants side by side: symfunnel's own and a physics engine's, for the report.

`engine_comparison(scenario, design, rate_hz=...)` runs the sampled loop around the same compiled C step on both
plants at the same rate, with the same measurements, and returns plain data: each run's margins and torque, the
difference of the two trajectories, the minimum rate on each plant, and the engine's notes. `comparison_figures`
draws the margins and the trajectory difference over time.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["engine_comparison", "comparison_figures"]


def _row(res) -> dict:
    n = res.q.shape[1]
    s = res.summary()
    return {"status": res.status, "message": res.message, "t_end": float(res.t[-1]),
            "min_margin": res.min_margin if math.isfinite(res.min_margin) else None,
            "min_margin_e1": min(s["min_margin_e1"]) if s["min_margin_e1"] else None,
            "min_margin_e2": min(s["min_margin_e2"]) if s["min_margin_e2"] else None,
            "max_abs_tau": s["max_abs_tau"], "saturated_fraction": s["saturated_fraction"],
            "wall_time": res.wall_time, "realtime_factor": s["realtime_factor"], "substeps": res.stats.get(
                "plant_substeps"), "n": n}


def engine_comparison(scenario: Scenario, design: Design, *, rate_hz: float, engine: str = "mujoco",
                      t_final: float | None = None, symfunnel_run=None, symfunnel_min_rate: dict | None = None,
                      margin: float = 0.05, min_rates: bool = True,
                      progress: Callable[[str], None] | None = None) -> dict:
    """Both plants at `rate_hz` (symfunnel's run may be passed in, e.g. the report's), the trajectory difference,
    the minimum rate on each (symfunnel's may be passed in), and the engine's notes and engine-only dynamics."""
    from .loop import simulate_sampled
    from .rate import min_rate
    say = progress or (lambda s: None)
    if symfunnel_run is None:
        say("sampled run on symfunnel's plant")
        symfunnel_run = simulate_sampled(scenario, design, rate_hz=rate_hz, t_final=t_final, engine="symfunnel")
    say(f"sampled run on the {engine} plant at {rate_hz:g} Hz")
    er = simulate_sampled(scenario, design, rate_hz=rate_hz, t_final=t_final, engine=engine, progress=say)
    sr = symfunnel_run
    k = min(sr.t.size, er.t.size)
    dq = np.abs(er.q[:k] - sr.q[:k])
    ddq = np.abs(er.dq[:k] - sr.dq[:k])
    kt = min(sr.tau.shape[0], er.tau.shape[0])
    dtau = np.abs(er.tau[:kt] - sr.tau[:kt])
    rates = {}
    if min_rates:
        rates["symfunnel"] = symfunnel_min_rate or min_rate(scenario, design, margin=margin, t_final=t_final,
                                                            progress=say, engine="symfunnel")
        start = rates["symfunnel"].get("min_rate_hz") or rate_hz
        rates[engine] = min_rate(scenario, design, margin=margin, t_final=t_final, progress=say, engine=engine,
                                 start=start)
    st = er.stats
    return {"engine": engine, "rate_hz": rate_hz, "plants": {"symfunnel": _row(sr), engine: _row(er)},
            "difference": {"max_abs_q": dq.max(axis=0).tolist() if k else None,
                           "max_abs_dq": ddq.max(axis=0).tolist() if k else None,
                           "max_abs_tau": dtau.max(axis=0).tolist() if kt else None,
                           "max_q": float(dq.max()) if k else None, "over_s": float(sr.t[k - 1]) if k else 0.0},
            "min_rate": {name: {"min_rate_hz": r["min_rate_hz"], "margin": r["margin"], "runs": len(r["tried"])}
                         for name, r in rates.items()},
            "engine_stats": {key: st.get(key) for key in ("engine_timestep", "plant_substeps", "engine_substeps_rule",
                                                          "engine_integrator", "engine_only", "engine_mass_scale",
                                                          "engine_notes", "engine_warnings",
                                                          "engine_last_warning")},
            "results": {"symfunnel": sr, engine: er}}


def comparison_figures(data: dict):
    """Matplotlib Figures: (min margin over the joints against time on each plant, |q_engine - q_symfunnel| per
    joint against time)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    res = data["results"]
    engine = data["engine"]
    fig1, ax = plt.subplots(figsize=(6, 3.2))
    for name, r in res.items():
        m = np.nanmin(r.margins, axis=1) if r.margins.size else np.zeros(0)
        ax.plot(r.t[:m.size], m, lw=0.9, ls="-" if name == "symfunnel" else "--",
                label=f"{'symfunnel' if name == 'symfunnel' else engine} plant")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("min margin 1 - |e|/F (all joints)")
    ax.legend(fontsize=8)
    fig1.tight_layout()
    sr, er = res["symfunnel"], res[engine]
    k = min(sr.t.size, er.t.size)
    fig2, ax2 = plt.subplots(figsize=(6, 3.2))
    d = np.abs(er.q[:k] - sr.q[:k])
    for j in range(d.shape[1]):
        ax2.semilogy(sr.t[:k], np.maximum(d[:, j], 1e-17), lw=0.7, label=f"joint {j + 1}")
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel(f"|q_{engine} - q_symfunnel| [rad or m]")
    ax2.legend(fontsize=6, ncol=4)
    fig2.tight_layout()
    return fig1, fig2

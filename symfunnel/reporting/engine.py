"""The report's physics-engine section: the engine's agreement with the controller's model, what the engine has that
the model does not, and the deployed controller on both plants side by side (margins, torque, the difference of
the two trajectories, the minimum rate on each)."""

from __future__ import annotations

from . import figures as FIG
from .text import fmt


def engine_section(run, progress) -> dict:
    """Plain data of the section (`available` False with a reason when the scenario runs on symfunnel's plant only)."""
    engine = run.options.engine or run.scenario.plant.engine
    if engine == "symfunnel":
        return {"available": False, "reason": "the deployed controller runs on symfunnel's plant only "
                                              "([plant] engine = \"mujoco\" or --plant mujoco adds this section)"}
    try:
        data = run.engine_comparison
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"available": False, "engine": engine, "reason": f"{type(exc).__name__}: {exc}"}
    if data is None:
        return {"available": False, "engine": engine,
                "reason": "no sample rate to compare at (the rate search found none that holds)"}
    progress(f"report: the deployed controller on symfunnel's and the {engine} plant")
    agree = next((c for c in run.verification.checks if c.id == "plant.engine_agreement"), None)
    rows = []
    for name, r in data["plants"].items():
        mr = data["min_rate"].get(name, {})
        integ = data["engine_stats"].get("engine_integrator") or "RK4"
        rows.append({"plant": "symfunnel (CasADi RK4)" if name == "symfunnel" else f"{name} (its {integ})",
                     "status": r["status"], "m1": fmt(r["min_margin_e1"]), "m2": fmt(r["min_margin_e2"]),
                     "tau": fmt(r["max_abs_tau"], 3), "sat": fmt(r["saturated_fraction"], 3),
                     "substeps": fmt(r["substeps"]), "min_rate": fmt(mr.get("min_rate_hz")),
                     "rtf": fmt(r["realtime_factor"], 3)})
    d = data["difference"]
    st = data["engine_stats"]
    fig_m, fig_d = comparison_figures_of(data)
    figs = [("engine-margins", f"Minimum funnel margin at the samples on both plants ({fmt(data['rate_hz'])} Hz)",
             FIG.to_svg(fig_m))]
    figs.append(("engine-difference", f"|q_{engine} - q_symfunnel| per joint: the two plants' trajectories under the "
                                      "same compiled controller", FIG.to_svg(fig_d)))
    only = st.get("engine_only") or {}
    return {"available": True, "engine": engine, "rate": fmt(data["rate_hz"]),
            "agreement": None if agree is None else {"status": agree.status, "detail": agree.detail,
                                                     "value": fmt(agree.value, 3)},
            "notes": st.get("engine_notes") or [], "rows": rows,
            "engine_only": [(k, fmt(v)) for k, v in only.items()],
            "mass_scale": fmt(st.get("engine_mass_scale")),
            "step": f"{fmt(st.get('plant_substeps'))} step(s) of {fmt(st.get('engine_timestep'))} s per period "
                    f"({st.get('engine_substeps_rule')})",
            "diff_q": fmt(d["max_abs_q"], 3), "diff_dq": fmt(d["max_abs_dq"], 3), "diff_tau": fmt(d["max_abs_tau"], 3),
            "diff_max": fmt(d["max_q"], 3), "over": fmt(d["over_s"]),
            "warnings": st.get("engine_warnings") or 0, "last_warning": st.get("engine_last_warning"),
            "figures": figs}


def comparison_figures_of(data: dict):
    """The section's two figures (drawn by deployed.compare)."""
    from ..deployed.compare import comparison_figures
    return comparison_figures(data)

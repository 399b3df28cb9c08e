"""The checks of the deployed controller: `implementation.containment` and `implementation.saturation`, on a run of
the sampled-data loop around the compiled generated C step (`symfunnel.deployed.loop`)."""

from __future__ import annotations

import numpy as np

from typing import TYPE_CHECKING

from ..deployed.loop import SampledResult, simulate_sampled
from .result import CheckResult

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["implementation_checks"]


def implementation_checks(scenario: Scenario, design: Design | None, *, rate_hz: float | None = None,
                          t_final: float | None = None, result: SampledResult | None = None,
                          progress: Callable[[str], None] | None = None,
                          engine: str | None = None) -> list[CheckResult]:
    """`implementation.containment` and (with tau_max) `implementation.saturation`; [] without an implementation.

    containment: the sampled loop around the compiled C step reaches t_final with every true margin > 0 at the
    samples. saturation: the torque never sits at tau_max (the design's guarantees assume the torque it asks
    for is applied); detail and evidence give the time fraction saturated per joint. `design` may be None when
    `result` (the sampled run) is given. `engine` is the plant (default the scenario's `[plant] engine`); on a
    physics engine without a rate (no rate_hz, no [implementation]) the run is at twice the minimum rate found
    on that engine, as the report does.
    """
    found = None
    if result is None:
        engine = engine or getattr(scenario.plant, "engine", "symfunnel")
        if getattr(scenario, "implementation", None) is None and rate_hz is None:
            if engine == "symfunnel":
                return []
            from ..deployed.rate import min_rate
            found = min_rate(scenario, design, t_final=t_final, progress=progress, engine=engine)
            if found["min_rate_hz"] is None:
                return [CheckResult("implementation.containment", "fail", f"on the {engine} plant no sample rate up "
                                    "to 1 MHz keeps both funnels with margin 0.05", method="sampled-data simulation",
                                    evidence={"engine": engine, "tried": found["tried"]})]
            rate_hz = 2.0 * found["min_rate_hz"]
        (progress or (lambda s: None))("sampled-data run of the generated C step function"
                                       + ("" if engine == "symfunnel" else f" on the {engine} plant"))
        result = simulate_sampled(scenario, rate_hz=rate_hz, t_final=t_final, design=design, progress=progress,
                                  engine=engine)
    r = result
    how = (f"sampled at {r.rate_hz:g} Hz" + (f" (twice the minimum rate {found['min_rate_hz']:.5g} Hz on this plant)"
                                             if found else "")
           + f", zero-order hold, delay {r.stats.get('delay_samples', 0)} sample(s), "
           f"controller = compiled generated C step" + _plant_text(r))
    ev = r.summary()
    ev.pop("breach", None)
    if found:
        ev["min_rate"] = {"min_rate_hz": found["min_rate_hz"], "margin": found["margin"], "runs": len(found["tried"])}
    if r.ok:
        c = CheckResult("implementation.containment", "pass" if r.min_margin > 0 else "fail",
                        f"{how}: {r.message}; min margin {r.min_margin:.4g} at the samples",
                        method="sampled-data simulation", margin=r.min_margin, evidence=ev)
    else:
        c = CheckResult("implementation.containment", "fail", f"{how}: {r.message}", method="sampled-data simulation",
                        margin=r.breach["margin"] if r.breach else None, where=r.breach, evidence=ev)
    out = [c]
    if r.tau_max is not None:
        frac = r.saturated_fraction or [0.0] * r.q.shape[1]
        worst = max(frac)
        detail = ("time fraction at tau_max per joint: " + ", ".join(f"{f:.3g}" for f in frac)
                  + f" (tau_max = {', '.join(f'{v:g}' for v in r.tau_max)}; over the {r.tau.shape[0]} samples to "
                  f"t = {r.t[-1]:g} s" + ("" if r.ok else ", where the run stopped") + ")")
        if worst > 0 and design is not None:
            tm = np.asarray(r.tau_max, float)
            k, j = (int(a[0]) for a in np.nonzero(np.abs(r.tau) >= tm * (1 - 1e-12)))
            from ..simulation.hints import breach_hint
            from ..simulation.result import scenario_arg
            detail += "; what to do: " + breach_hint(design, t=float(r.t[k]), q=r.q[k], dq=r.dq[k], funnel="saturation",
                                                     joint=j + 1, tau_max=r.tau_max, scenario_arg=scenario_arg(scenario))
        out.append(CheckResult("implementation.saturation", "pass" if worst == 0.0 else "fail", detail,
                               method="sampled-data simulation", margin=-worst,
                               evidence={"saturated_fraction": frac, "tau_max": list(r.tau_max),
                                         "max_abs_tau": ev["max_abs_tau"]}))
    return out


def _plant_text(r: SampledResult) -> str:
    """Which plant the run had, for the detail: symfunnel's (nothing said, as before) or the engine's settings."""
    st = r.stats
    if st.get("engine", "symfunnel") == "symfunnel":
        return ""
    only = st.get("engine_only") or {}
    extra = "; in the engine only: " + ", ".join(f"{k} {v}" for k, v in only.items()) if only else ""
    return (f", plant = MuJoCo {st.get('engine_integrator', 'RK4')} with {st['plant_substeps']} step(s) of "
            f"{st['engine_timestep']:.4g} s per period{extra}")

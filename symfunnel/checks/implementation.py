"""The checks of the deployed controller: `implementation.containment` and `implementation.saturation`, on a run of
the sampled-data loop around the compiled generated C step (`symfunnel.deployed.loop`)."""

from __future__ import annotations

import numpy as np

from typing import TYPE_CHECKING

from ..deployed.loop import SampledResult, simulate_sampled
from .audit import CheckResult

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["implementation_checks"]


def implementation_checks(scenario: Scenario, design: Design | None, *, rate_hz: float | None = None,
                          t_final: float | None = None, result: SampledResult | None = None,
                          progress: Callable[[str], None] | None = None) -> list[CheckResult]:
    """`implementation.containment` and (with tau_max) `implementation.saturation`; [] without an implementation.

    containment: the sampled loop around the compiled C step reaches t_final with every true margin > 0 at the
    samples. saturation: the torque never sits at tau_max (the design's guarantees assume the torque it asks
    for is applied); detail and evidence give the time fraction saturated per joint. `design` may be None when
    `result` (the sampled run) is given.
    """
    if result is None:
        if getattr(scenario, "implementation", None) is None and rate_hz is None:
            return []
        (progress or (lambda s: None))("sampled-data run of the generated C step function")
        result = simulate_sampled(scenario, rate_hz=rate_hz, t_final=t_final, design=design, progress=progress)
    r = result
    how = (f"sampled at {r.rate_hz:g} Hz, zero-order hold, delay {r.stats.get('delay_samples', 0)} sample(s), "
           f"controller = compiled generated C step")
    ev = r.summary()
    ev.pop("breach", None)
    if r.ok:
        c = CheckResult("implementation.containment", "pass" if r.min_margin > 0 else "fail",
                        f"{how}: reached t = {r.t[-1]:g} s; min margin {r.min_margin:.4g} at the samples",
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

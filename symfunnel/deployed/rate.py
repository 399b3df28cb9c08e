"""The minimum sample rate of the deployed controller, and which design parameters set it.

`min_rate(scenario, design)` searches the lowest rate at which the sampled-data loop (`symfunnel.deployed.loop`) keeps
both funnels over the horizon with margin >= M after the transient (`simulation.margins`): it brackets from the scenario's rate by factors of 4, then bisects on a
log scale until the bracket is within `rel_tol`. It assumes that holding is monotone in the rate (every tried rate
is listed, so a non-monotone case shows). A run that starts outside a funnel ends the search after its first rate:
the state at t = 0 is the same at every rate, so the result says why instead (`reason`). `rate_sensitivity` re-runs the search for a few one-parameter changes
of the inner loop (phi_inf and a of funnel e2, k2), to show which parameter sets the minimum rate.
"""

from __future__ import annotations

import copy
import math
from typing import TYPE_CHECKING

from ..core.errors import InputError

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["min_rate", "rate_sensitivity", "margin_rate_figure", "VARIATIONS", "MAX_RATE_HZ"]

MAX_RATE_HZ = 1e6
MIN_RATE_HZ = 1.0
#: (dotted key, factor) of the design-help variations: the e2 loop's parameters (mu2 >= 1/F2 grows to 1/phi_inf).
VARIATIONS = (("funnel.e2.phi_inf", 2.0), ("controller.k2", 0.5), ("funnel.e2.a", 0.5))


def min_rate(scenario: Scenario, design: Design, *, margin: float = 0.05, t_final: float | None = None,
             rel_tol: float = 0.05, start: float | None = None,
             progress: Callable[[str], None] | None = None, engine: str | None = None,
             search_build: bool = True) -> dict:
    """{"min_rate_hz": float | None, "margin", "tried": [{"rate_hz", "status", "min_margin", "holds"}], "engine"}
    on the plant `engine` (default the scenario's `[plant] engine`). `search_build` False builds the shipped step
    at each rate tried instead of the search build compiled once (`deployed.rate_step`; the bench's baseline)."""
    from ..core.text import number
    from .loop import simulate_sampled
    if not (isinstance(margin, (int, float)) and 0 <= margin < 1):
        raise InputError(f"is {margin!r}", file=scenario.file, key="--margin", expected="a number in [0, 1)")
    say = progress or (lambda s: None)
    impl = getattr(scenario, "implementation", None)
    r = float(start or (impl.rate_hz if impl is not None else 1000.0))
    tried: list[dict] = []
    engine = engine or getattr(getattr(scenario, "plant", None), "engine", "symfunnel")
    on_engine = {} if engine == "symfunnel" else {"engine": engine}     # symfunnel's plant: today's call
    if engine != "symfunnel" and scenario.plant.mujoco.timestep is not None:
        raise InputError("fixes MuJoCo's step, but a rate search changes the sample period", file=scenario.file,
                         key="plant.mujoco.timestep", expected="plant.mujoco.substeps (steps per period) for `rate`")

    def holds(rate: float) -> bool:
        # the search build: the generated C once for every rate, the period's weights set per run (rate_step)
        res = simulate_sampled(scenario, design, rate_hz=rate, t_final=t_final, search_build=search_build,
                               **on_engine)
        # holds: the run reaches the horizon inside both funnels with margin >= M after the transient (the margin
        # at t = 0 is the initial condition's, the same at every rate)
        mt = res.min_margin_after_transient
        ok = res.ok and mt >= margin
        m = res.min_margin
        tried.append({"rate_hz": rate, "status": res.status, "min_margin": m if math.isfinite(m) else None,
                      "min_margin_after_transient": mt if math.isfinite(mt) else None,
                      "settle_time": res.stats.get("settle_time"), "holds": bool(ok)})
        say(f"rate {rate:.6g} Hz: {res.status}, min margin after the transient {number(mt, '.3g')} (whole run "
            f"{number(m, '.3g')}) -> "
            f"{'holds' if ok else 'does not hold'}")
        if res.breach is not None and res.breach["time"] == 0.0 and "between_samples" not in res.breach:
            raise _OutsideAtStart(res.breach)
        return ok

    try:
        return _search(holds, r, tried, scenario, t_final, rel_tol, margin, engine)
    except _OutsideAtStart as exc:
        b = exc.args[0]
        return {"min_rate_hz": None, "margin": margin, "tried": tried, "engine": engine,
                "reason": (f"the initial state is outside funnel {b['funnel']} of joint {b['joint']} at t = 0 "
                           f"(margin {b['margin']:.3g}): no sample rate changes it, so no other rate was tried")}


class _OutsideAtStart(Exception):
    """The sampled run starts outside a funnel: the sample rate cannot matter (raised by the search's probe)."""


def _search(holds, r: float, tried: list, scenario, t_final, rel_tol: float, margin: float, engine: str) -> dict:
    """Bracket from r by factors of 4, then bisect on a log scale (see the module doc)."""
    lo = hi = None
    if holds(r):
        hi = r
        while lo is None:
            r2 = hi / 4
            from ..core.validate import MIN_HORIZON_STEPS
            from .loop import min_rate_hz
            T = t_final if t_final is not None else getattr(getattr(scenario, "simulation", None), "t_final", None)
            floor = MIN_HORIZON_STEPS / float(T) if T else 0.0
            # no lower than the plant's own floor, nor than a period the horizon holds MIN_HORIZON_STEPS of
            if r2 < max(MIN_RATE_HZ, min_rate_hz(scenario), floor):
                return {"min_rate_hz": hi, "margin": margin, "tried": tried, "engine": engine}
            if holds(r2):
                hi = r2
            else:
                lo = r2
    else:
        lo = r
        while hi is None:
            r2 = min(lo * 4, MAX_RATE_HZ)
            if holds(r2):
                hi = r2
            elif r2 >= MAX_RATE_HZ:
                return {"min_rate_hz": None, "margin": margin, "tried": tried, "engine": engine}
            else:
                lo = r2
    while hi / lo > 1 + rel_tol:
        mid = math.sqrt(lo * hi)
        if holds(mid):
            hi = mid
        else:
            lo = mid
    return {"min_rate_hz": hi, "margin": margin, "tried": tried, "engine": engine}


def _varied(scenario, key: str, factor: float):
    """The scenario with the number(s) at a dotted key of its TOML multiplied by factor, and the old value."""
    from ..scenario import from_dict
    raw = copy.deepcopy(scenario.raw)
    *path, last = key.split(".")
    table = raw
    for p in path:
        table = table.setdefault(p, {})
    e2 = scenario.funnels["e2"]
    defaults = {"funnel.e2.phi_inf": getattr(e2, "phi_inf", None), "funnel.e2.a": getattr(e2, "a", None),
                "controller.k2": scenario.k2}
    before = table.get(last, defaults[key])
    table[last] = [v * factor for v in before] if isinstance(before, list) else before * factor
    sc = from_dict(raw, file=scenario.file, base_dir=scenario.path.parent, default_name=scenario.name)
    return sc, before, table[last]


def rate_sensitivity(scenario: Scenario, design: Design, *, margin: float = 0.05, t_final: float | None = None,
                     variations=VARIATIONS, baseline: dict | None = None,
                     progress: Callable[[str], None] | None = None, engine: str | None = None) -> dict:
    """The minimum rate of the scenario and of each one-parameter variation, computed by `min_rate`.

    `design` is the scenario's (for the baseline); each variation is a new scenario, derived here.

    Returns {"baseline": min_rate(...), "inner_loop_gain": [k2 / phi_inf of e2 per joint],
    "variations": [{"key", "factor", "before", "after", "min_rate_hz", "ratio"}]}, ratio = variation / baseline.
    """
    from ..design import derive
    say = progress or (lambda s: None)
    base = baseline or min_rate(scenario, design, margin=margin, t_final=t_final, progress=say, engine=engine)
    start = base["min_rate_hz"]
    out = []
    shape = scenario.funnels["e2"]
    for key, factor in variations:
        if key.startswith("funnel.e2.") and not hasattr(shape, key.rsplit(".", 1)[1]):
            out.append({"key": key, "factor": factor, "status": "skip", "before": None, "after": None,
                        "min_rate_hz": None, "ratio": None, "tried": [],
                        "reason": "funnel e2 is an expression F(t): it has no " + key.rsplit(".", 1)[1]})
            continue
        say(f"design help: {key} x {factor:g}")
        sc, before, after = _varied(scenario, key, factor)
        r = min_rate(sc, derive(sc), margin=margin, t_final=t_final, start=start, progress=say, engine=engine)
        ratio = (r["min_rate_hz"] / start) if (r["min_rate_hz"] and start) else None
        out.append({"key": key, "factor": factor, "before": before, "after": after,
                    "min_rate_hz": r["min_rate_hz"], "ratio": ratio, "tried": r["tried"]})
    # mu2 >= 1/F2 grows to 1/inf F2 (phi_inf for the exponential): the inner loop's largest gain
    floor = getattr(shape, "phi_inf", None)
    if floor is None:
        from ..family.funnels import extremes
        floor = extremes(shape, t_final or scenario.simulation.t_final)[0]
    gain = [float(k / p) for k, p in zip(scenario.k2, floor)]
    return {"baseline": base, "inner_loop_gain": gain, "variations": out}


def margin_rate_figure(result: dict):
    """A matplotlib Figure of the min funnel margin against the tried rates (log axis), with M and the minimum."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    tried = sorted(result["tried"], key=lambda d: d["rate_hz"])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    r = [d["rate_hz"] for d in tried]
    key = "min_margin_after_transient" if all("min_margin_after_transient" in d for d in tried) else "min_margin"
    m = [d[key] if d[key] is not None else float("nan") for d in tried]
    ax.semilogx(r, [max(v, -1.0) for v in m], "o-", label="min margin 1 - |e|/F after the transient (clipped at -1)")
    ax.axhline(result["margin"], color="k", ls="--", lw=1, label=f"required margin {result['margin']:g}")
    if result.get("min_rate_hz"):
        ax.axvline(result["min_rate_hz"], color="C3", lw=1, label=f"minimum rate {result['min_rate_hz']:.4g} Hz")
    ax.set_xlabel("sample rate [Hz]")
    ax.set_ylabel("min funnel margin after the transient")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig

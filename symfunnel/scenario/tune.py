"""The `[tune]` scenario section: which design parameters `symfunnel tune` may change, within which bounds, to what end.

The specification (the reference and the e1 funnel) is never tuned. Every tunable key is searched on a log scale,
so its bounds must be > 0. A per-joint key is tuned as one shared value by default (the joint with the largest
value moves within the bounds, the others keep their ratio to it); `per_joint = true` gives each joint its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..core import validate as V
from ..core.errors import InputError

__all__ = ["TuneSpec", "TUNABLE", "OBJECTIVES", "parse_tune", "current_value"]

#: tunable key -> (per joint?, default bounds [low, high], validity of the key)
TUNABLE = {
    "controller.k1": (True, (0.1, 100.0), "k1 > 0"),
    "controller.k2": (True, (0.1, 100.0), "k2 > 0"),
    "adaptation.gamma": (False, (0.01, 1000.0), "gamma > 0"),
    "adaptation.sigma": (False, (1e-4, 10.0), "sigma > 0 on the log scale of the search"),
    "funnel.e2.phi0": (True, (0.01, 10.0), "phi0 > 0 on the log scale of the search"),
    "funnel.e2.phi_inf": (True, (1e-3, 1.0), "phi_inf > 0"),
    "funnel.e2.a": (True, (0.01, 20.0), "a > 0 on the log scale of the search"),
}
#: the specification the user prescribes: never tuned
SPECIFICATION = ("reference", "funnel.e1")
OBJECTIVES = ("peak_torque", "ise", "min_rate")
KEYS = ["parameters", "objective", "margin", "runs", "bounds", "per_joint", "tau_max", "tracking"]
DEFAULT_PARAMETERS = ["controller.k1", "controller.k2", "funnel.e2.phi0", "funnel.e2.phi_inf", "funnel.e2.a"]


@dataclass
class TuneSpec:
    """A validated `[tune]` table."""

    parameters: list[str] = field(default_factory=lambda: list(DEFAULT_PARAMETERS))
    objective: str = "peak_torque"
    margin: float = 0.05
    runs: int = 20
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    per_joint: bool = False
    tau_max: tuple[float, ...] | None = None     # the torque limit of a scenario without [implementation]
    tracking: float | None = None                # e1 RMS after the transient at most this x the user's design's

    def bounds_of(self, key: str) -> tuple[float, float]:
        """The search bounds of a key (the table's, else the documented default)."""
        return self.bounds.get(key, TUNABLE[key][1])


def _check_key(key: Any, file: str, where: str) -> str:
    if not isinstance(key, str):
        raise InputError(f"is {V.a_type(key)}", file=file, key=where, expected="a dotted key string")
    if any(key == s or key.startswith(s + ".") for s in SPECIFICATION):
        raise InputError(f"is '{key}', part of the specification (the reference and funnel e1 are what the user "
                         "prescribes)", file=file, key=where, expected="one of " + ", ".join(TUNABLE))
    if key not in TUNABLE:
        raise InputError(f"is '{key}', not a tunable key{V.did_you_mean(key, TUNABLE)}", file=file, key=where,
                         expected="one of " + ", ".join(TUNABLE))
    return key


def parse_tune(table: Any, *, file: str, has_implementation: bool, funnels: dict | None = None, n: int = 1,
               raw_model: dict | None = None, base_dir=None) -> TuneSpec:
    """Validate `[tune]` (see docs/scenario.md); InputError naming the key on any bad entry."""
    p = "tune"
    V.check_keys(table, KEYS, file=file, prefix=p)
    d = TuneSpec()
    params = V.get_list(table, "parameters", d.parameters, file=file, prefix=p)
    if not params:
        raise InputError("is empty", file=file, key="tune.parameters", expected="at least one tunable key")
    keys = []
    for i, k in enumerate(params):
        k = _check_key(k, file, f"tune.parameters[{i}]")
        if k in keys:
            raise InputError(f"names '{k}' twice", file=file, key="tune.parameters", expected="each key once")
        keys.append(k)
    if funnels is not None and any(k.startswith("funnel.e2.") for k in keys) \
            and not hasattr(funnels.get("e2"), "phi_inf"):
        raise InputError("tunes phi0/phi_inf/a but funnel e2 is not given by them", file=file, key="tune.parameters",
                         expected="[funnel.e2] with phi0, phi_inf, a to tune its shape")
    objective = V.get_str(table, "objective", d.objective, file=file, prefix=p, choices=list(OBJECTIVES))
    if objective == "min_rate" and not has_implementation:
        raise InputError("is 'min_rate' but the scenario has no [implementation]", file=file, key="tune.objective",
                         expected="an [implementation] section (the rate of the deployed controller) or "
                                  "peak_torque / ise")
    margin = V.get_float(table, "margin", d.margin, file=file, prefix=p, minimum=0)
    if not margin < 1:
        raise InputError(f"is {margin:g}", file=file, key="tune.margin", expected="a number in [0, 1)")
    runs = V.get_int(table, "runs", d.runs, file=file, prefix=p, minimum=1, maximum=10000)
    per_joint = V.get_bool(table, "per_joint", d.per_joint, file=file, prefix=p)
    braw = table.get("bounds", {})
    V.check_keys(braw, list(braw) if isinstance(braw, dict) else [], file=file, prefix="tune.bounds")
    bounds = {}
    for k, v in braw.items():
        where = f"tune.bounds.{k}"
        _check_key(k, file, where)
        if k not in keys:
            raise InputError(f"bounds '{k}', which tune.parameters does not list", file=file, key=where,
                             expected="bounds only for tuned keys")
        if not (isinstance(v, list) and len(v) == 2):
            raise InputError(f"is {V.a_type(v)}", file=file, key=where, expected="a pair [low, high]")
        lo = V.as_float(v[0], file=file, key=where + "[0]")
        hi = V.as_float(v[1], file=file, key=where + "[1]")
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError(f"is [{lo:g}, {hi:g}]", file=file, key=where, expected="finite bounds")
        if not lo > 0:
            raise InputError(f"has low = {lo:g}", file=file, key=where,
                             expected=f"low > 0 ({TUNABLE[k][2]}; the search is log-scaled)")
        if not lo < hi:
            raise InputError(f"is [{lo:g}, {hi:g}]", file=file, key=where, expected="low < high")
        bounds[k] = (lo, hi)
    tau_max = None
    if "tau_max" in table:
        if has_implementation:
            raise InputError("is given but the scenario has [implementation]", file=file, key="tune.tau_max",
                             expected="the torque limit in implementation.tau_max (the deployed controller's)")
        from .implementation import parse_tau_max
        tau_max = parse_tau_max(table, p, n=n, file=file, raw_model=raw_model or {}, base_dir=base_dir or ".")
    tracking = None
    if "tracking" in table:
        tracking = V.get_float(table, "tracking", None, file=file, prefix=p, minimum=1)
    return TuneSpec(keys, objective, margin, runs, bounds, per_joint, tau_max, tracking)


def current_value(scenario, key: str) -> list[float]:
    """The scenario's value of a tunable key, per joint (one entry for a scalar key)."""
    if key == "controller.k1":
        return list(scenario.k1)
    if key == "controller.k2":
        return list(scenario.k2)
    if key == "adaptation.gamma":
        return [scenario.gamma]
    if key == "adaptation.sigma":
        return [scenario.sigma]
    return list(getattr(scenario.funnels["e2"], key.rsplit(".", 1)[1]))

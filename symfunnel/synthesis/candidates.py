"""`symfunnel tune`'s candidates: the search coordinates of `[tune]` (log-scaled, per joint or shared), a design
document with their values written in, and the Evaluator that simulates one candidate under tune's constraints on the
nominal plant and the uncertainty samples (the search strategies that choose candidates are `search`'s).
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import InputError
from ..scenario.tune import TUNABLE, TuneSpec, current_value

__all__ = ["Variable", "variables", "apply", "scenario_confidence", "Candidate", "Evaluator"]


@dataclass
class Variable:
    """One search coordinate: a key (all joints, or one joint), its bounds and how it maps to the scenario's values."""

    key: str
    joint: int | None          # None: all joints (shared) or a scalar key
    lo: float
    hi: float
    base: list[float]          # the user's per-joint values of the key
    ratio: list[float]         # shared mode: joint value = x * ratio[i]

    @property
    def name(self) -> str:
        """The key, with [joint] (1-based) when it is one joint's."""
        return self.key if self.joint is None else f"{self.key}[{self.joint + 1}]"

    def x_of(self, z: float) -> float:
        """The value at z in [0, 1] of the log-scaled range."""
        z = min(1.0, max(0.0, float(z)))
        return self.lo * (self.hi / self.lo) ** z

    def z_of(self, x: float) -> float:
        """The log-scale coordinate of a value (clipped into the bounds)."""
        x = min(self.hi, max(self.lo, x))
        return math.log(x / self.lo) / math.log(self.hi / self.lo)

    def user_x(self) -> float:
        """The user's value of this coordinate."""
        return self.base[self.joint] if self.joint is not None else max(self.base)


def variables(scenario, spec: TuneSpec) -> list[Variable]:
    """The search coordinates of a scenario's `[tune]`."""
    out = []
    for key in spec.parameters:
        lo, hi = spec.bounds_of(key)
        base = current_value(scenario, key)
        if len(base) > 1 and spec.per_joint:
            out.extend(Variable(key, i, lo, hi, base, []) for i in range(len(base)))
        else:
            top = max(base)
            ratio = [b / top for b in base] if top > 0 and min(base) > 0 else [1.0] * len(base)
            out.append(Variable(key, None, lo, hi, base, ratio))
    return out


def apply(raw: dict, vars_: list[Variable], xs) -> dict:
    """A copy of the scenario document with the coordinates' values written at their keys."""
    raw = copy.deepcopy(raw)
    values: dict[str, list[float]] = {}
    for v, x in zip(vars_, xs):
        cur = values.setdefault(v.key, list(v.base))
        if v.joint is not None:
            cur[v.joint] = float(x)
        else:
            for i, r in enumerate(v.ratio):
                cur[i] = float(x) * r
    for key, vals in values.items():
        *path, leaf = key.split(".")
        t = raw
        for p in path:
            t = t.setdefault(p, {})
        t[leaf] = vals[0] if (not TUNABLE[key][0] or len(set(vals)) == 1) else vals
    return raw


def scenario_confidence(n: int, eps: float = 0.05) -> float:
    """Scenario approach: with n independent samples and no violation, P(violation) <= eps with this confidence."""
    return 1.0 - (1.0 - eps) ** n


@dataclass
class Candidate:
    """One evaluated design: its values, constraint values (>= 0 holds) and objective figures."""

    xs: list[float]
    constraints: dict[str, float]
    figures: dict[str, float]
    note: str = ""
    worst_run: dict = field(default_factory=dict)

    @property
    def feasible(self) -> bool:
        """Every constraint holds."""
        return bool(self.constraints) and all(g >= 0 for g in self.constraints.values())

    def binding(self, tol: float = 0.02) -> list[str]:
        """The violated constraints, or (when feasible) those within tol of their limit."""
        bad = [k for k, g in self.constraints.items() if g < 0]
        return bad or [k for k, g in self.constraints.items() if g < tol]


class Evaluator:
    """Simulates candidates of one scenario under its `[tune]` constraints (nominal plant + uncertainty samples)."""

    def __init__(self, scenario, spec: TuneSpec, *, t_final: float | None = None, progress=None):
        self.sc = scenario
        self.spec = spec
        self.say = progress or (lambda s: None)
        self.impl = scenario.implementation
        self.tau_max = self.impl.tau_max if self.impl is not None else spec.tau_max
        self.T = float(t_final if t_final is not None else scenario.simulation.t_final)
        self.sample_values = []
        self.samples = self._samples()
        self.count = 0
        self.rechecks = 0               # evaluations of rounded gains (not counted against --max-evals)
        self.tracking_ref = None        # the user's design's e1 RMS after the transient ([tune] tracking)

    def _samples(self) -> list[dict]:
        """Scenario edits of the N uncertainty samples (none without [[uncertainty]])."""
        camp = self.sc.campaign
        if camp is None or not camp.uncertainties:
            return []
        from ..scenario.uncertainty import scenario_edits
        vals = camp.values(range(self.spec.runs), self.spec.runs)
        self.sample_values = vals
        return [scenario_edits(camp, self.sc.n, v) for v in vals]

    def scenario(self, raw: dict):
        """A scenario from a document (the tuned one keeps the original's file and name)."""
        from ..scenario import from_dict
        return from_dict(raw, file=self.sc.file, base_dir=self.sc.path.parent, default_name=self.sc.name)

    def plants(self, raw: dict) -> list[tuple[str, dict]]:
        """(label, document) of the nominal plant and of every uncertainty sample."""
        out = [("nominal", raw)]
        for i, edits in enumerate(self.samples):
            r = copy.deepcopy(raw)
            for key, v in edits.items():
                *path, leaf = key.split(".")
                t = r
                for p in path:
                    t = t.setdefault(p, {})
                t[leaf] = v
            out.append((f"sample {i}", r))
        return out

    def run(self, raw: dict) -> tuple[dict, dict, dict]:
        """(constraints, figures, worst run) of one design document."""
        sc = self.scenario(raw)
        from ..design import derive
        design = derive(sc)
        cons = {"containment": math.inf}
        if self.tau_max is not None:
            cons["saturation"] = math.inf
        figs = {}
        worst = {}
        ctrl = None
        if self.impl is not None:
            from ..emit import generate
            from ..deployed.loop import step_library
            ctrl = step_library(design, generate(design, "c", rate_hz=self.impl.rate_hz, tau_max=self.impl.tau_max))
        violated = 0
        for label, r in self.plants(raw):
            psc = sc if label == "nominal" else self.scenario(r)
            g, f = (self._sampled(psc, design, ctrl) if ctrl is not None else self._continuous(psc, design))
            for k, v in g.items():
                if v < cons[k]:
                    cons[k] = v
                    worst[k] = label
            if label == "nominal":
                figs = f
            else:
                violated += any(v < 0 for v in g.values())
        if self.samples:
            figs["sample_violations"] = violated
        if self.tracking_ref:           # [tune] tracking: the nominal run's e1 RMS within that factor of the user's
            rms = figs.get("e1_rms_after_transient", math.nan)
            cons["tracking"] = (1.0 - rms / (self.spec.tracking * self.tracking_ref)) if math.isfinite(rms) else -1.0
        if self.spec.objective == "min_rate" and cons["containment"] >= 0:
            from ..deployed.rate import min_rate
            r = min_rate(sc, margin=self.spec.margin, design=design, t_final=self.T, rel_tol=0.1,
                         start=self.impl.rate_hz, engine="symfunnel")
            figs["min_rate"] = r["min_rate_hz"] if r["min_rate_hz"] is not None else math.inf
        return cons, figs, worst

    def _containment(self, ok: bool, min_margin: float, t_end: float) -> float:
        """min margin - M; a run that stopped early loses the fraction of the horizon it did not reach."""
        m = max(min_margin, -1.0) if math.isfinite(min_margin) else -1.0     # a diverged run: -1, not -1e6
        if ok:
            return m - self.spec.margin
        return min(m, 0.0) - self.spec.margin - max(0.0, 1.0 - t_end / self.T)

    def _sampled(self, sc, design, ctrl) -> tuple[dict, dict]:
        from ..deployed.loop import simulate_sampled
        res = simulate_sampled(sc, t_final=self.T, design=design, controller=ctrl, engine="symfunnel")
        # ranked by the margin after the transient: the margin at t = 0 is the initial condition's, the same for
        # every candidate (a breach counts wherever it happened)
        g = {"containment": self._containment(res.ok, res.min_margin_after_transient, float(res.t[-1]))}
        peak = float(np.max(np.abs(res.tau))) if res.tau.size else 0.0
        if res.tau_max is not None:
            frac = max(res.saturated_fraction or [0.0])
            use = float(np.max(np.abs(res.tau) / np.asarray(res.tau_max))) if res.tau.size else 0.0
            g["saturation"] = 1.0 - use if frac == 0 else -frac
        n = sc.n
        k = res.tau.shape[0]
        qd = np.asarray(design.reference.map(k + 1)(res.t.reshape(1, -1))[0]).T if k else np.zeros((1, n))
        e1 = res.q[:k + 1] - qd
        ok = np.all(np.isfinite(e1), axis=1)
        h = 1.0 / res.rate_hz
        figs = {"peak_torque": peak, "ise": float(np.sum(e1[ok] ** 2) * h), **_tracking(res)}
        return g, figs

    def _continuous(self, sc, design) -> tuple[dict, dict]:
        from ..simulation import simulate
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = simulate(sc, design, t_final=self.T)
        s = res.signals
        mg = res.margins()          # ranked by the margin after the transient (see _sampled)
        mm = [v for k in ("e1", "e2") for v in mg[f"min_margin_{k}_after_transient"] if v is not None]
        if res.breach is not None:
            mm.append(float(res.breach["margin"]))
        t_end = float(res.t[-1]) if res.t.size else 0.0
        g = {"containment": self._containment(res.ok, min(mm) if mm else -1.0, t_end)}
        tau = np.asarray(s["tau"])
        peak = float(np.max(np.abs(tau))) if tau.size and np.isfinite(tau).all() else math.inf
        if self.tau_max is not None:        # the continuous loop has no saturation: 1 - the largest |tau|/tau_max
            use = (float(np.max(np.abs(tau).reshape(len(res.t), -1) / np.asarray(self.tau_max)))
                   if math.isfinite(peak) and tau.size else math.inf)
            g["saturation"] = 1.0 - use
        e1 = np.asarray(s["e1"]).reshape(len(res.t), -1) if res.t.size else np.zeros((1, 1))
        ise = float(np.trapezoid(np.sum(e1 ** 2, axis=1), res.t)) if res.t.size > 1 else math.inf
        return g, {"peak_torque": peak, "ise": ise, **_tracking(res),
                   # the run's size, by which `--method auto` sizes the sensitivity problem (synthesis.choice)
                   # (a run that stopped early: its steps scaled to the horizon)
                   "steps": (int(round(res.stats["steps"] * self.T / t_end)) if res.stats.get("steps") and t_end > 0
                             else None), "states": int(res.x.shape[1])}

    def evaluate(self, vars_: list[Variable], xs) -> Candidate:
        """Simulate one candidate (a candidate the scenario's validation rejects gets the constraint `valid` < 0)."""
        self.count += 1
        raw = apply(self.sc.raw, vars_, xs)
        try:
            cons, figs, worst = self.run(raw)
        except InputError as exc:       # e.g. a funnel that no longer contains e2(0): not a design at all
            return Candidate(list(xs), {"valid": -1.0}, {}, note=exc.reason)
        return Candidate(list(xs), cons, figs, worst_run=worst)


def _tracking(res) -> dict:
    """A run's tracking and chattering (`simulation.metrics`, the largest over the joints): what tune shows beside
    its objective, so that a design that trades tracking or smoothness for torque says so."""
    from ..simulation.metrics import campaign_row
    m = campaign_row(res.metrics())
    return {"e1_rms_after_transient": m["e1_rms_after_transient"], "chattering": m["chattering"]}

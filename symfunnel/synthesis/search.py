"""`symfunnel tune`: search the design parameters of `[tune]` for a design that keeps the constraints, best objective.

Constraints of a candidate (each a number g >= 0 when it holds, on the nominal plant and on N uncertainty samples):
`containment` (both funnels kept with margin >= M over the horizon: the sampled loop around the compiled C step
when the scenario has `[implementation]`, else the continuous simulation; a run that leaves a funnel early scores
lower the earlier it leaves) and `saturation` (|tau| below tau_max: 1 - max over joints of peak |tau_i|/tau_max_i
when the torque never saturates, else minus the saturated time fraction). The objective (peak torque, integral
squared e1, or the minimum sample rate) is minimised over the feasible candidates. Method: without
`[implementation]` the continuous-time loop is smooth in the parameters, so IPOPT runs over them with exact
sensitivities of the constraints on an output grid (`synthesis.gradient`), from the user's values and a few Sobol points;
each result is judged by the full simulation above. With `[implementation]` the sampled-data loop (zero-order hold,
saturation, the stop at a breach) makes the constraints piecewise constant in the parameters, so gradients are
meaningless; the search is derivative-free: the user's values and a few Sobol points are evaluated, then Nelder-Mead
(on a penalty: any infeasible candidate ranks behind every feasible one) runs from the best starts over log-scaled
parameters until it converges or the wall-clock limit is reached. It is also the fallback when IPOPT is missing or
finds nothing that holds. The best feasible designs then go through verify's gate in turn.
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import InputError
from ..scenario.tune import TUNABLE, TuneSpec, current_value

__all__ = ["tune", "TuneResult", "Candidate", "scenario_confidence", "METHOD", "GRADIENT_METHOD", "tune_records",
           "original_document"]

METHOD = ("derivative-free: Nelder-Mead on a feasibility-first penalty over log-scaled parameters, multi-start from "
          "the user's values and Sobol points")
WHY = ("the constraints come from simulated runs (sampled-data loop: zero-order hold, torque saturation, stop at "
       "the first breach), piecewise constant in the parameters, so their gradients are zero or undefined")
GRADIENT_METHOD = ("gradient: IPOPT (limited-memory Hessian) over log-scaled parameters with CVODES forward "
                   "sensitivities of the grid constraints, multi-start from the user's values and Sobol points")
GRADIENT_WHY = ("no [implementation]: the continuous-time closed loop is smooth in the gains and the e2 funnel, so the "
                "simulated constraints have exact derivatives")
WHY_NO_GRADIENT = "no [implementation], but the gradient path is not available"
#: Sobol starting points besides the user's values
SOBOL_STARTS = 8
#: Sobol starting points of the gradient path besides the user's values
GRADIENT_SOBOL_STARTS = 2
INFEASIBLE = 1e3
#: feasible designs (best first) that go through verify's gate before tune reports infeasible
GATE_TRIES = 3
#: share of --wall-limit the search may use; the rest is kept for the re-check after rounding and verify's gate
#: (the gate of the paper takes 11 s of a 240 s limit here, a new design's first compile adds about 7 s)
SEARCH_SHARE = 0.8
#: the gradient path is chosen (method "auto") only when this many IPOPT iterations fit the search's time, each
#: costing about d + 2 forward solves of the sensitivity problem (one timed forward solve decides, measured in a
#: child process killed at its share of the time: on the paper one forward solve takes 17 s, so 8 iterations of 7
#: solves would need about 950 s, and the derivative-free search is chosen)
MIN_IPOPT_ITERATIONS = 8
#: significant digits of the gains tune writes (re-checked after rounding; more digits when rounding breaks them)
DIGITS = 4
METHODS = ("auto", "gradient", "derivative-free")


class _OutOfTime(Exception):
    """Raised inside the objective when the wall-clock limit or the evaluation budget is reached."""


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
        figs = {"peak_torque": peak, "ise": float(np.sum(e1[ok] ** 2) * h)}
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
        return g, {"peak_torque": peak, "ise": ise}

    def evaluate(self, vars_: list[Variable], xs) -> Candidate:
        """Simulate one candidate (a candidate the scenario's validation rejects gets the constraint `valid` < 0)."""
        self.count += 1
        raw = apply(self.sc.raw, vars_, xs)
        try:
            cons, figs, worst = self.run(raw)
        except InputError as exc:       # e.g. a funnel that no longer contains e2(0): not a design at all
            return Candidate(list(xs), {"valid": -1.0}, {}, note=exc.reason)
        return Candidate(list(xs), cons, figs, worst_run=worst)


def _score(c: Candidate, objective: str, ref: dict) -> float:
    """Feasibility first: any infeasible candidate ranks behind every feasible one; ties broken by the others."""
    if not c.feasible:
        if "valid" in c.constraints:
            return 2 * INFEASIBLE
        return INFEASIBLE + sum(max(0.0, -g) for g in c.constraints.values() if math.isfinite(g))
    val = c.figures.get(objective, math.inf)
    if not math.isfinite(val):
        return INFEASIBLE - 1
    main = val / ref.get(objective, 1.0)
    tie = sum(c.figures[k] / ref.get(k, 1.0) for k in ("peak_torque", "ise") if k != objective
              and math.isfinite(c.figures.get(k, math.inf)))
    return main + 1e-6 * tie


@dataclass
class TuneResult:
    """The outcome of `tune`: status, method, objective before/after, changes, binding constraints, the tuned TOML."""

    status: str
    method: str
    why: str
    objective: dict
    changes: list[dict]
    binding: list[str]
    wall_s: float
    evaluations: int
    constraints: dict
    samples: int
    confidence: float | None
    gate: dict
    tuned_raw: dict
    notes: list[str]
    tuned_text: str = ""
    rechecks: int = 0
    comparison: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """The `--json` output of the contract (plus details)."""
        from ..core.io import json_safe
        return json_safe({"status": self.status, "method": self.method, "why": self.why,
                          "objective": self.objective, "changes": self.changes, "binding": self.binding,
                          "wall_s": self.wall_s, "evaluations": self.evaluations, "rechecks": self.rechecks,
                          "constraints": self.constraints,
                          "uncertainty_samples": self.samples, "confidence_eps_0.05": self.confidence,
                          "gate": self.gate, "notes": self.notes, "comparison": self.comparison})


def tune(scenario, *, wall_limit: float = 240.0, t_final: float | None = None, progress=None,
         max_evaluations: int | None = None, gate: bool = True, method: str = "auto",
         started: float | None = None) -> TuneResult:
    """Search the `[tune]` parameters of a scenario (see the module doc); never changes the specification.

    The whole call keeps `wall_limit` seconds (the search stops at SEARCH_SHARE of it, an evaluation in progress
    is interrupted at the limit, IPOPT runs in a child process that is killed at the limit) and at most
    `max_evaluations` full-simulation evaluations of candidates. `method`: "auto" (the gradient path without
    `[implementation]` when a timed forward solve says MIN_IPOPT_ITERATIONS iterations fit the time, else
    derivative-free), "gradient" or "derivative-free". Gains are rounded to DIGITS significant digits and the
    rounded design is re-checked.
    """
    from scipy.optimize import minimize
    from scipy.stats import qmc
    say = progress or (lambda s: None)
    spec = scenario.tune or TuneSpec()
    if spec.objective == "min_rate" and scenario.implementation is None:
        raise InputError("is 'min_rate' but the scenario has no [implementation]", file=scenario.file,
                         key="tune.objective", expected="an [implementation] section or peak_torque / ise")
    if method not in METHODS:
        raise InputError(f"is {method!r}", key="--method", expected="one of " + ", ".join(METHODS))
    requested = method
    # the limit counts from `started` (time.monotonic() when the command began: its start-up and loading count)
    m0 = time.monotonic() if started is None else min(float(started), time.monotonic())
    t0 = time.perf_counter() - (time.monotonic() - m0)
    search_end = t0 + SEARCH_SHARE * wall_limit
    ev = Evaluator(scenario, spec, t_final=t_final, progress=say)
    vars_ = variables(scenario, spec)
    d = len(vars_)
    loop = (f"sampled loop at {scenario.implementation.rate_hz:g} Hz" if scenario.implementation
            else "continuous-time loop")
    say(f"tune {scenario.name}: {d} coordinate(s) ({', '.join(v.name for v in vars_)}), objective "
        f"{spec.objective}, margin {spec.margin:g}, {len(ev.samples)} uncertainty sample(s) + nominal, horizon "
        f"{ev.T:g} s, {loop}")
    user = [v.user_x() for v in vars_]
    from ..core import deadline as DL
    with _whole(m0, wall_limit, "evaluating the user's design"):
        before = ev.evaluate(vars_, user)
    say("the user's design: " + ("feasible" if before.feasible else "infeasible") + " "
        + ", ".join(f"{k} {g:+.3g}" for k, g in before.constraints.items()))
    ref = {k: (v if math.isfinite(v) and v > 0 else 1.0) for k, v in before.figures.items()}
    seen: dict[tuple, Candidate] = {}
    best: list[Candidate | None] = [None]          # the best candidate inside the bounds

    def record(c: Candidate) -> float:
        s = _score(c, spec.objective, ref)
        if best[0] is None or s < _score(best[0], spec.objective, ref):
            best[0] = c
        return s

    def f(z, final: bool = False) -> float:
        # final: the result of an IPOPT run, always judged (the limits stop the next search, not this check), and
        # judged as it would be written, rounded to DIGITS (each new value is a new closed loop to compile: the
        # exact and then the rounded one cost two compiles for one answer)
        xs = [v.x_of(zi) for v, zi in zip(vars_, z)]
        if final:
            xs = _rounded_values(vars_, xs, DIGITS)
        key = tuple(round(x, 10) for x in xs)
        if key in seen:
            return _score(seen[key], spec.objective, ref)
        now = time.perf_counter()
        if not final and now >= search_end:
            raise _OutOfTime(f"search stopped at the wall-clock limit ({SEARCH_SHARE:.0%} of --wall-limit "
                             f"{wall_limit:g} s; the rest is kept for the checks of the result)")
        if not final and max_evaluations and ev.count >= max_evaluations:
            raise _OutOfTime(f"search stopped after {max_evaluations} evaluations (--max-evals)")
        # an evaluation in progress is interrupted at the limit (a simulation stops there, a compile is killed)
        end = m0 + (search_end - t0) if not final else m0 + wall_limit
        try:
            with DL.until(end, wall_limit, m0):
                c = ev.evaluate(vars_, xs)
        except (DL.WallLimitReached, SystemError, RuntimeError) as exc:
            if not (isinstance(exc, DL.WallLimitReached) or _expired(end, exc)):
                raise
            raise _OutOfTime(f"search stopped at the wall-clock limit ({SEARCH_SHARE:.0%} of --wall-limit "
                             f"{wall_limit:g} s) during an evaluation") from None
        seen[key] = c
        s = record(c)
        b = best[0]
        elapsed = time.perf_counter() - t0
        per = elapsed / max(ev.count, 1)
        left = search_end - time.perf_counter()
        if max_evaluations:
            left = min(left, per * max(max_evaluations - ev.count, 0))
        say(f"eval {ev.count}{f' of at most {max_evaluations}' if max_evaluations else ''}: "
            f"{'feasible' if c.feasible else 'infeasible'} "
            + ", ".join(f"{k} {g:+.3g}" for k, g in c.constraints.items())
            + (f", {spec.objective} {c.figures.get(spec.objective, math.nan):.4g}" if c.figures else f" ({c.note})")
            + f" | best {'feasible' if b.feasible else 'infeasible'} {_score(b, spec.objective, ref):.4g}"
            + f" | {elapsed:.0f} s, ETA {max(left, 0.0):.0f} s")
        return s

    if all(v.lo <= x <= v.hi for v, x in zip(vars_, user)):
        seen[tuple(round(x, 10) for x in user)] = before
        record(before)
    else:
        say("the user's values lie outside the bounds: the search starts from them clipped into the bounds")
    z_user = np.array([v.z_of(x) for v, x in zip(vars_, user)])
    method, why = METHOD, WHY
    stopped = None
    if scenario.implementation is None and requested != "derivative-free":
        use, reason = _gradient_sound()
        gp, timed = None, False
        if use:
            from .gradient import GradientProblem
            try:
                gp = GradientProblem(scenario, spec, vars_, t_final=ev.T, tau_max=ev.tau_max,
                                     sample_values=ev.sample_values)
            except RuntimeError as exc:            # CasADi could not build the sensitivity problem
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)
                use, reason = False, f"the sensitivity problem could not be built ({_last_line(exc)})"
        if use and requested == "auto":
            use, reason = _gradient_fits(gp, z_user, len(vars_), search_end - time.perf_counter(), say)
            timed = not use
        if use:
            method, why = GRADIENT_METHOD, GRADIENT_WHY
            say(f"method: {method} ({why})")
            failed = None
            try:
                _gradient_search(gp, vars_, ev, z_user, f, ref, say, spec, deadline=search_end,
                                 max_evaluations=max_evaluations)
            except _OutOfTime as exc:
                stopped = str(exc)
                say(stopped + ": the best design so far is the result")
            except RuntimeError as exc:            # CasADi/IPOPT failed to build or run the problem
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)
                failed = _last_line(exc)
            b = best[0]
            if stopped is None and (b is None or not b.feasible):
                method = f"{GRADIENT_METHOD}; then {METHOD}"
                why = (f"{GRADIENT_WHY}; " + (f"IPOPT failed ({failed})" if failed else
                                              "no IPOPT result held in the full simulation")
                       + ", so the derivative-free search continued (fallback)")
                say("falling back to the derivative-free search: " + why)
            elif failed:
                why = f"{GRADIENT_WHY}; IPOPT stopped with an error ({failed}) after a design that holds"
        elif timed:
            why = f"no [implementation], but the gradient path was not chosen: {reason}"
        else:
            why = f"{WHY_NO_GRADIENT} ({reason})"
    elif scenario.implementation is None:
        why = "derivative-free search requested (method derivative-free)"
    if method.endswith(METHOD) and stopped is None:
        if method == METHOD:
            say(f"method: {method} ({why})")
        starts = [z_user]
        sob = qmc.Sobol(d, scramble=True, seed=0).random(SOBOL_STARTS)
        starts.extend(sob)
        scored = []
        try:
            for z in starts:
                scored.append((f(z), list(z)))
            scored.sort(key=lambda p: p[0])
            for _, z in scored[:3]:
                step = 0.15
                simplex = [np.array(z)] + [np.clip(np.array(z) + step * np.eye(d)[i] * (1 if z[i] < 0.5 else -1),
                                                   0, 1) for i in range(d)]
                minimize(f, np.array(z), method="Nelder-Mead", bounds=[(0.0, 1.0)] * d,
                         options={"initial_simplex": np.array(simplex), "xatol": 2e-3, "fatol": 1e-4,
                                  "maxfev": 60 * d})
        except _OutOfTime as exc:
            stopped = str(exc)
            say(stopped + ": the best design so far is the result")
    b = best[0] or before
    notes = [stopped] if stopped else []
    gate_info = {"status": "skipped"}
    status = "ok" if b.feasible else "infeasible"
    binding = b.binding()
    if b.feasible and gate:
        # verify's gate on the best feasible designs in turn (at most GATE_TRIES): the search's constraints are
        # the sampled runs; the gate adds the continuous-time checks, whose declared outcomes must still hold
        ranked = sorted((c for c in seen.values() if c.feasible and all(v.lo <= x <= v.hi for v, x in
                                                                         zip(vars_, c.xs))),
                        key=lambda c: _score(c, spec.objective, ref))
        for i, c in enumerate(ranked[:GATE_TRIES]):
            try:
                with DL.until(m0 + wall_limit, wall_limit, m0):
                    c = _rounded(c, vars_, ev, say)
                    say(f"verify's gate on the tuned scenario (design {i + 1} of the ranking)")
                    gate_info = verify_gate(ev.scenario(apply(scenario.raw, vars_, c.xs)), progress=say)
            except (DL.WallLimitReached, SystemError, RuntimeError) as exc:
                if not (isinstance(exc, DL.WallLimitReached) or _expired(m0 + wall_limit, exc)):
                    raise
                gate_info = {"status": "not completed", "unexpected": []}
                notes.append(f"verify's gate on design {i + 1} did not finish within --wall-limit {wall_limit:g} s")
                status = "infeasible"
                binding = binding + ["verify.gate (not completed within --wall-limit)"]
                break
            if c is None:
                notes.append(f"design {i + 1} of the ranking does not hold once its values are rounded")
                continue
            if gate_info["status"] == "pass":
                b = c
                break
            notes.append(f"design {i + 1} of the ranking failed verify's gate: {', '.join(gate_info['unexpected'])}")
        else:
            status = "infeasible"
            binding = binding + [f"verify.{c}" for c in gate_info.get("unexpected", [])]
    if b.feasible and not gate and best[0] is not None:
        with _whole(m0, wall_limit, "re-checking the rounded gains"):
            b = _rounded(b, vars_, ev, say) or b
    elif not b.feasible:               # the closest design, written readably (it does not hold either way)
        b = Candidate([min(v.hi, max(v.lo, round_sig(x, DIGITS))) for v, x in zip(vars_, b.xs)], b.constraints,
                      b.figures, b.note, b.worst_run)
    tuned = apply(scenario.raw, vars_, b.xs)
    changes = []
    for v, x in zip(vars_, b.xs):
        ux = v.user_x()
        if not math.isclose(x, ux, rel_tol=1e-12):
            changes.append({"key": v.name, "before": ux, "after": x})
    _record_deviations(tuned, changes, spec, b, ev, status)
    name = spec.objective
    return TuneResult(
        status=status, method=method, why=why,
        objective={"name": name, "before": before.figures.get(name) if before.feasible or name != "min_rate" else None,
                   "after": b.figures.get(name)},
        changes=changes, binding=binding, wall_s=time.perf_counter() - t0, evaluations=ev.count,
        constraints={"margin": spec.margin, "values": b.constraints, "before": before.constraints,
                     "worst_run": b.worst_run, "before_feasible": before.feasible},
        samples=len(ev.samples), confidence=scenario_confidence(len(ev.samples)) if ev.samples else None,
        gate=gate_info, tuned_raw=tuned, notes=notes,
        tuned_text=tuned_toml(scenario, tuned, sorted({v.key for v in vars_})), rechecks=ev.rechecks,
        comparison={"original": _side(before, spec, ev), "tuned": _side(b, spec, ev)})


def tuned_toml(scenario, tuned: dict, keys: list[str]) -> str:
    """The tuned scenario as TOML: the user's own file edited (tomlkit: comments, order and layout kept), the tuned
    keys set (each keeping its line's comment) and the new `[[deviations]]` entries appended; a scenario without a
    readable file is written whole."""
    import tomlkit
    from ..core.toml_write import dumps
    try:
        doc = tomlkit.parse(scenario.path.read_text(encoding="utf-8"))
    except (OSError, TypeError, AttributeError, tomlkit.exceptions.TOMLKitError):
        return dumps(tuned)
    orig = scenario.raw
    for key in keys:
        *path, leaf = key.split(".")
        new, old = tuned, orig
        for p in path + [leaf]:
            new = new.get(p) if isinstance(new, dict) else None
            old = old.get(p) if isinstance(old, dict) else None
        if new is None or new == old:
            continue
        t = doc
        for p in path:
            if p not in t:
                t[p] = tomlkit.table()
            t = t[p]
        item = tomlkit.item(new)
        prev = t.get(leaf) if hasattr(t, "get") else None
        if prev is not None and hasattr(prev, "trivia") and prev.trivia.comment:
            item.trivia.comment_ws = prev.trivia.comment_ws or "  "
            item.trivia.comment = prev.trivia.comment
        t[leaf] = item
    added = (tuned.get("deviations") or [])[len(orig.get("deviations") or []):]
    if added:
        if "deviations" not in doc:
            doc["deviations"] = tomlkit.aot()
        for d in added:
            doc["deviations"].append(dict(d))
    return tomlkit.dumps(doc)


@contextlib.contextmanager
def _whole(m0: float, wall_limit: float, step: str):
    """The block under the command's whole limit; the alarm seen through a CasADi call is the limit, said so."""
    from ..core import deadline as DL
    try:
        with DL.until(m0 + wall_limit, wall_limit, m0):
            yield
    except (SystemError, RuntimeError) as exc:
        if not _expired(m0 + wall_limit, exc):
            raise
        raise DL.WallLimitReached(wall_limit, step, time.monotonic() - m0) from None


def _expired(end: float, exc: BaseException) -> bool:
    """Whether an error is the wall-clock alarm seen through a C extension: raised inside a CasADi call, the
    deadline's exception comes back as that call's SystemError or RuntimeError once the limit has passed."""
    from ..core.lifecycle import reraise_interrupt
    reraise_interrupt(exc) if isinstance(exc, RuntimeError) else None
    chain = exc
    while chain is not None:
        from ..core import deadline as DL
        if isinstance(chain, DL.WallLimitReached):
            return True
        chain = chain.__cause__ or chain.__context__
    return time.monotonic() >= end


def round_sig(x: float, digits: int) -> float:
    """x rounded to `digits` significant digits."""
    return float(f"{float(x):.{int(digits)}g}")


def _rounded_values(vars_, xs, digits: int) -> list[float]:
    """xs rounded to `digits` significant digits, each kept inside its variable's bounds."""
    return [min(v.hi, max(v.lo, round_sig(x, digits))) for v, x in zip(vars_, xs)]


def _rounded(c: Candidate, vars_, ev: Evaluator, say) -> Candidate | None:
    """The candidate with its values rounded to DIGITS significant digits (more, up to 8, when rounding breaks a
    constraint), re-checked by a full evaluation; None when no rounding holds (the exact values are never
    written: a file with 17 digits is not what a user can read or type)."""
    for digits in range(DIGITS, 9):
        xs = _rounded_values(vars_, c.xs, digits)
        if xs == list(c.xs):
            return c
        n = ev.count
        r = ev.evaluate(vars_, xs)
        ev.count = n                    # a re-check, not one of the search's --max-evals evaluations
        ev.rechecks += 1
        say(f"rounded to {digits} significant digits: {'holds' if r.feasible else 'does not hold'} ("
            + ", ".join(f"{k} {g:+.3g}" for k, g in r.constraints.items()) + ")")
        if r.feasible:
            return r
    return None


def _last_line(exc: Exception) -> str:
    """The last line of an exception's message (CasADi's carry a call trace before it)."""
    text = str(exc).strip()
    return text.splitlines()[-1][:200] if text else type(exc).__name__


def _gradient_sound() -> tuple[bool, str]:
    """Whether IPOPT is there (the installed casadi wheel may lack the plugin), with the reason when not."""
    from .gradient import ipopt_available
    if not ipopt_available():
        return False, "casadi.has_nlpsol('ipopt') is false in the installed casadi"
    return True, ""


def _gradient_fits(gp, z0, d: int, budget: float, say) -> tuple[bool, str]:
    """Whether MIN_IPOPT_ITERATIONS IPOPT iterations (about d + 2 forward solves each) fit `budget` seconds: one
    forward solve is timed in a forked worker (`core.lifecycle.run_killable`) that is killed at its share of the
    budget."""
    from ..core import deadline as DL
    from ..core.lifecycle import reraise_interrupt, run_killable
    share = budget / (MIN_IPOPT_ITERATIONS * (d + 2))
    say(f"timing one forward solve of the sensitivity problem (at most {share:.1f} s, the share that "
        f"{MIN_IPOPT_ITERATIONS} IPOPT iterations may have)")
    try:
        run_killable(_forward_size, gp, np.asarray(z0, float), wall_limit=max(share, 0.05),
                     what="timing one forward solve of the sensitivity problem")
    except DL.WallLimitReached:
        if DL.expired_limit() is not None:            # a limit around tune: it ends the command
            raise
        return False, (f"one forward solve of the sensitivity problem takes more than {share:.1f} s, so "
                       f"{MIN_IPOPT_ITERATIONS} IPOPT iterations of about {d + 2} solves each would not fit the "
                       f"{budget:.0f} s the search has (measured; force it with --method gradient)")
    except RuntimeError as exc:
        reraise_interrupt(exc)
        return False, f"the sensitivity problem does not evaluate at the user's design ({_last_line(exc)})"
    return True, ""


def _forward_size(gp, z0) -> int:
    """One forward solve of the sensitivity problem (its constraint values' count: the result is small to send)."""
    return int(np.asarray(gp.g(z0), float).size)


def _gradient_search(gp, vars_, ev, z_user, f, ref, say, spec, *, deadline: float,
                     max_evaluations: int | None) -> None:
    """IPOPT from the user's values, then from Sobol points, while time remains; every result is judged by `f`
    (the full simulation of the Evaluator), which records the best candidate. Each IPOPT run is a child process
    killed at the deadline (its best grid-feasible iterate so far is then the result)."""
    from scipy.stats import qmc
    say(f"gradient problem: {gp.d} parameter(s), {gp.ng} grid constraints ({gp.nplants} plant(s) x {gp.K + 1} "
        "points)")
    starts = [z_user, *qmc.Sobol(len(vars_), scramble=True, seed=0).random(GRADIENT_SOBOL_STARTS)]
    obj = spec.objective
    for i, z0 in enumerate(starts):
        left = deadline - time.perf_counter()
        if left <= 1.0:
            raise _OutOfTime("search stopped at the wall-clock limit")
        if max_evaluations and ev.count >= max_evaluations:
            raise _OutOfTime(f"search stopped after {max_evaluations} evaluations (--max-evals)")
        say(f"IPOPT start {i + 1} of {len(starts)} (at most {left:.0f} s)")
        # IPOPT gets the time left but what the full simulation of its result needs
        try:
            # in a forked worker: IPOPT inside one C call hears no signal and no limit, the waiting parent does
            from ..core.lifecycle import run_killable
            from ..core import deadline as _deadline
            try:
                r = run_killable(gp.solve, np.asarray(z0, float), objective=obj, ref=ref.get(obj, 1.0),
                                 wall_s=0.9 * left, progress=say, wall_limit=left + 2.0, what="solving with IPOPT")
            except _deadline.WallLimitReached:
                if _deadline.expired_limit() is not None:     # a limit around tune: it ends the command
                    raise
                raise _OutOfTime("search stopped at the wall-clock limit (IPOPT did not stop by itself)") from None
        except RuntimeError as exc:          # e.g. the start itself does not integrate: next start
            from ..core.lifecycle import reraise_interrupt
            reraise_interrupt(exc)
            say(f"IPOPT start {i + 1}: skipped ({_last_line(exc)})")
            continue
        say(f"IPOPT start {i + 1}: {r['status']} after {r['iterations']} iteration(s)")
        f(r["z"], final=True)


def _side(c: Candidate, spec: TuneSpec, ev: Evaluator) -> dict:
    """One column of the original/tuned comparison: torque, margin, saturation, violations among the samples."""
    g = c.constraints
    held = g.get("containment", -1) >= -spec.margin         # reached the horizon inside both funnels
    out = {"feasible": c.feasible, "reached_horizon": held, "peak_torque": c.figures.get("peak_torque"),
           "ise": c.figures.get("ise") if held else None,
           "min_margin": g["containment"] + spec.margin if held else None,
           "saturation": g.get("saturation"), "min_rate_hz": c.figures.get("min_rate")}
    if ev.samples:
        k = c.figures.get("sample_violations")
        out["sample_violations"] = k
        out["samples"] = len(ev.samples)
    return out


def verify_gate(scenario, progress=None) -> dict:
    """verify's gate (the Run's verification) on a scenario: {"status", "unexpected": [check ids]}."""
    from ..pipeline import Run, RunOptions
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        v = Run(scenario, RunOptions(), progress=None).verification
    return {"status": v.status, "unexpected": [c.id for c in v.checks if c.unexpected]}


def _record_deviations(raw: dict, changes: list[dict], spec: TuneSpec, b: Candidate, ev: Evaluator,
                       status: str) -> None:
    """Append a `[[deviations]]` entry per changed key (old -> new, why) to the tuned document."""
    if not changes:
        return
    impl = ev.impl
    what = (f"sampled loop at {impl.rate_hz:g} Hz" + (f", |tau| <= {', '.join(f'{x:g}' for x in impl.tau_max)}"
                                                      if impl.tau_max else "")) if impl else "continuous-time loop"
    unc = f" on the nominal plant and {len(ev.samples)} uncertainty samples" if ev.samples else " on the nominal plant"
    why = (f"symfunnel tune ({status}): both funnels kept with margin >= {spec.margin:g} in the {what}{unc} "
           f"over {ev.T:g} s, objective {spec.objective} = {b.figures.get(spec.objective, math.nan):.6g}")
    devs = raw.setdefault("deviations", [])
    for c in changes:
        # exact (shortest round-trip) numbers, so that `original_document` restores the user's design
        devs.append({"key": c["key"], "paper": "", "value": f"{float(c['before'])!r} -> {float(c['after'])!r}",
                     "reason": why})


TUNE_REASON = "symfunnel tune ("


def tune_records(raw: dict) -> list[dict]:
    """The `[[deviations]]` entries that `symfunnel tune` wrote into a scenario document (key, old, new)."""
    import re
    from ..scenario.tune import TUNABLE
    out = []
    for d in raw.get("deviations", []) or []:
        if not (isinstance(d, dict) and str(d.get("reason", "")).startswith(TUNE_REASON)):
            continue
        m = re.fullmatch(r"\s*(\S+)\s*->\s*(\S+)\s*", str(d.get("value", "")))
        k = re.fullmatch(r"([a-z0-9_.]+)(?:\[(\d+)\])?", str(d.get("key", "")))
        if not (m and k and k.group(1) in TUNABLE):
            continue
        try:
            old, new = float(m.group(1)), float(m.group(2))
        except ValueError:
            continue
        out.append({"key": k.group(1), "joint": int(k.group(2)) - 1 if k.group(2) else None, "before": old,
                    "after": new, "name": d["key"]})
    return out


def original_document(raw: dict, n: int) -> dict | None:
    """The scenario document before `symfunnel tune` (its records undone, old values back), or None when the
    document carries no tune record. A shared per-joint key gets back old/new times each joint's value (tune kept
    the joints' ratios)."""
    recs = tune_records(raw)
    if not recs:
        return None
    from ..scenario.tune import TUNABLE
    doc = copy.deepcopy(raw)
    for r in reversed(recs):           # the last change first: a key tuned twice returns to its first value
        *path, leaf = r["key"].split(".")
        t = doc
        for p in path:
            t = t.setdefault(p, {})
        cur = t.get(leaf)
        if not TUNABLE[r["key"]][0]:
            t[leaf] = r["before"]
        elif r["joint"] is not None:
            vals = list(cur) if isinstance(cur, list) else [cur] * n
            vals[r["joint"]] = r["before"]
            t[leaf] = vals
        else:
            scale = r["before"] / r["after"]
            t[leaf] = [v * scale for v in cur] if isinstance(cur, list) else cur * scale
    doc["deviations"] = [d for d in doc.get("deviations", [])
                         if not str(d.get("reason", "")).startswith(TUNE_REASON)]
    if not doc["deviations"]:
        del doc["deviations"]
    return doc


def compare_designs(tuned, *, tuned_run=None, t_final: float | None = None, sweep_runs: int | None = None,
                    progress=None) -> dict | None:
    """Original (from tune's `[[deviations]]` records) against tuned, side by side: peak |tau|, min margins e1/e2
    of the continuous-time run, the minimum sample rate (with `[implementation]`) and the breach probability of a
    campaign of the scenario's `[[uncertainty]]` (`sweep_runs` runs, default tune's `runs`). None without records.
    """
    import tempfile
    say = progress or (lambda s: None)
    orig_raw = original_document(tuned.raw, tuned.n)
    if orig_raw is None:
        return None
    from ..scenario import from_dict
    original = from_dict(orig_raw, file=tuned.file, base_dir=tuned.path.parent, default_name=tuned.name)
    spec = tuned.tune or TuneSpec()
    sides = {}
    for label, sc in (("original", original), ("tuned", tuned)):
        from ..pipeline import Run, RunOptions
        say(f"tuning comparison: the {label} design")
        run = tuned_run if label == "tuned" and tuned_run is not None else Run(sc, RunOptions(t_final=t_final))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim = run.simulation
        s = sim.signals
        tau = np.abs(np.asarray(s["tau"]))
        side = {"scenario": sc, "simulation": sim, "status": sim.status,
                "peak_torque": float(np.max(tau)) if tau.size else None,
                "min_margin_e1": float(np.min(s["m1"])) if np.size(s["m1"]) else None,
                "min_margin_e2": float(np.min(s["m2"])) if np.size(s["m2"]) else None}
        if sc.implementation is not None:
            from ..deployed.rate import min_rate
            r = min_rate(sc, run.design, margin=spec.margin, t_final=t_final, rel_tol=0.1,
                         start=sc.implementation.rate_hz)
            side["min_rate_hz"] = r["min_rate_hz"]
        if sc.campaign is not None and sc.campaign.uncertainties:
            from ..campaigns.campaign import sweep
            runs = sweep_runs or spec.runs
            with tempfile.TemporaryDirectory(prefix="symfunnel-tune-cmp-") as tmp:
                summ = sweep(sc, runs=runs, workers=1, out=tmp).summary
            side["breach_probability"] = summ["breach_probability"]
            side["breach_ci95"] = summ["ci95"]
            side["runs"] = runs
        sides[label] = side
    return {"original": sides["original"], "tuned": sides["tuned"], "changes": tune_records(tuned.raw)}

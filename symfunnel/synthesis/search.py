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
parameters until it converges or has spent its evaluation budget (--max-evals, by default DERIVATIVE_FREE_EVALUATIONS):
a count, so the same scenario gives the same file on any machine and under any load; the wall-clock limit is only a
safety net, and a search it ends is reported as timing-dependent. It is also the fallback when IPOPT is missing or
finds nothing that holds. The best feasible designs then go through verify's gate in turn.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import InputError
from ..scenario.tune import TuneSpec
from .candidates import Candidate, Evaluator, apply, scenario_confidence, variables
from .choice import DERIVATIVE_FREE_EVALUATIONS
from .records import _record_deviations, original_document, tune_records, tuned_toml

__all__ = ["tune", "TuneResult", "Candidate", "scenario_confidence", "METHOD", "GRADIENT_METHOD", "tune_records",
           "original_document", "DERIVATIVE_FREE_EVALUATIONS"]

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
#: why the search ended (`ended_by` in --json): all its passes ran, the evaluation count, or the wall-clock limit
ENDED_BY = ("completed", "evaluations", "wall-limit")
#: feasible designs (best first) that go through verify's gate before tune reports infeasible
GATE_TRIES = 3
#: share of --wall-limit the search may use; the rest is kept for the re-check after rounding and verify's gate
#: (the gate of the paper takes 11 s of a 240 s limit here, a new design's first compile adds about 7 s)
SEARCH_SHARE = 0.8
#: seconds kept at the very end of --wall-limit (at most this share of it) to assemble and write the result: the
#: gate and the last evaluations end that much before the limit, so a loaded machine's slower unwinding does not
#: meet the watchdog's hard stop (1 s after the limit) and lose a result the search already has
TAIL_S, TAIL_SHARE = 2.0, 0.05
#: significant digits of the gains tune writes (re-checked after rounding; more digits when rounding breaks them)
DIGITS = 4
METHODS = ("auto", "gradient", "derivative-free")


class _OutOfTime(Exception):
    """Raised inside the objective when the wall-clock limit or the evaluation budget is reached (`by`: which,
    one of ENDED_BY)."""

    def __init__(self, message: str, by: str = "wall-limit"):
        super().__init__(message)
        self.by = by


#: the note of a search the wall-clock limit ended: its result is not reproducible
TIMING_NOTE = ("timing-dependent: the wall-clock limit, not an evaluation count, ended {what}, so this result "
               "depends on the machine's speed and load (the same scenario may give another file); raise --wall-limit "
               "or lower --max-evals for a reproducible result")


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
    ended_by: str = "completed"
    timing_dependent: bool = False
    comparison: dict = field(default_factory=dict)
    at_bounds: list[dict] = field(default_factory=list)

    def __repr__(self) -> str:
        """Short: status, method and evaluations (not the tuned file's text)."""
        return (f"TuneResult(status={self.status!r}, method={self.method!r}, {self.evaluations} evaluations, "
                f"changes={[c.get('key') for c in self.changes]})")

    def to_json(self) -> dict:
        """The `--json` output of the contract (plus details)."""
        from ..core.io import json_safe
        return json_safe({"status": self.status, "method": self.method, "why": self.why,
                          "objective": self.objective, "changes": self.changes, "binding": self.binding,
                          "at_bounds": self.at_bounds,
                          "wall_s": self.wall_s, "evaluations": self.evaluations, "rechecks": self.rechecks,
                          "ended_by": self.ended_by, "timing_dependent": self.timing_dependent,
                          "constraints": self.constraints,
                          "uncertainty_samples": self.samples, "confidence_eps_0.05": self.confidence,
                          "gate": self.gate, "notes": self.notes, "comparison": self.comparison})


def tune(scenario, *, wall_limit: float = 240.0, t_final: float | None = None, progress=None,
         max_evaluations: int | None = None, gate: bool = True, method: str = "auto",
         started: float | None = None) -> TuneResult:
    """Search the `[tune]` parameters of a scenario (see the module doc); never changes the specification.

    The whole call keeps `wall_limit` seconds (the search stops at SEARCH_SHARE of it, an evaluation in progress
    is interrupted at the limit, IPOPT runs in a child process that is killed at the limit) and at most
    `max_evaluations` full-simulation evaluations of candidates (the derivative-free search: by default
    DERIVATIVE_FREE_EVALUATIONS, so that a count, not the limit, ends it). `method`: "auto" (the gradient path without
    `[implementation]` when the sensitivity problem's size says enough IPOPT iterations fit the search's share of
    the limit, `synthesis.choice`, else derivative-free), "gradient" or "derivative-free". Gains are rounded to
    DIGITS significant digits and the rounded design is re-checked.
    """
    from scipy.optimize import minimize

    from ..core.sobol import sobol
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
    last = m0 + wall_limit - min(TAIL_S, TAIL_SHARE * wall_limit)     # the gate and final judgements end here
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
    if spec.tracking is not None:
        before = _with_tracking(ev, spec, before, say)
    say("the user's design: " + ("feasible" if before.feasible else "infeasible") + " "
        + ", ".join(f"{k} {g:+.3g}" for k, g in before.constraints.items()))
    ref = {k: (v if math.isfinite(v) and v > 0 else 1.0) for k, v in before.figures.items()}
    seen: dict[tuple, Candidate] = {}
    best: list[Candidate | None] = [None]          # the best candidate inside the bounds
    cap = [max_evaluations]                        # the evaluation budget of the running search (None: none)

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
        if not final and cap[0] and ev.count >= cap[0]:
            raise _OutOfTime(f"search stopped after {cap[0]} evaluations ("
                             + ("--max-evals" if max_evaluations else "the derivative-free search's default budget; "
                                "--max-evals changes it") + ")", by="evaluations")
        # an evaluation in progress is interrupted at the limit (a simulation stops there, a compile is killed)
        end = m0 + (search_end - t0) if not final else last
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
        if cap[0]:
            left = min(left, per * max(cap[0] - ev.count, 0))
        say(f"eval {ev.count}{f' of at most {cap[0]}' if cap[0] else ''}: "
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
    stopped, ended_by = None, "completed"
    ipopt_timed: list[int] = []                    # IPOPT starts whose pass its own wall-time limit ended
    if scenario.implementation is None and requested != "derivative-free":
        use, reason = _gradient_sound()
        gp, sized = None, False
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
            from .choice import gradient_fits
            use, reason = gradient_fits(before.figures.get("steps"), int(before.figures.get("states") or 0),
                                        len(vars_), gp.nplants, SEARCH_SHARE * wall_limit)
            sized = not use
            say(f"method auto: {'IPOPT' if use else 'derivative-free'}: {reason}")
        if use:
            method, why = GRADIENT_METHOD, GRADIENT_WHY + (f"; method auto: {reason}" if requested == "auto" else "")
            say(f"method: {method} ({why})")
            failed = None
            try:
                _gradient_search(gp, vars_, ev, z_user, f, ref, say, spec, deadline=search_end,
                                 max_evaluations=max_evaluations, timed=ipopt_timed)
            except _OutOfTime as exc:
                stopped, ended_by = str(exc), exc.by
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
        elif sized:
            why = f"no [implementation], but the gradient path was not chosen: {reason}"
        else:
            why = f"{WHY_NO_GRADIENT} ({reason})"
    elif scenario.implementation is None:
        why = "derivative-free search requested (method derivative-free)"
    if method.endswith(METHOD) and stopped is None:
        if method == METHOD:
            say(f"method: {method} ({why})")
        cap[0] = max_evaluations or DERIVATIVE_FREE_EVALUATIONS
        starts = [z_user]
        sob = sobol(d, SOBOL_STARTS, 0)
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
            stopped, ended_by = str(exc), exc.by
            say(stopped + ": the best design so far is the result")
    b = best[0] or before
    notes = [stopped] if stopped else []
    timing = ended_by == "wall-limit" or bool(ipopt_timed)
    if ended_by == "wall-limit":
        notes.append(TIMING_NOTE.format(what="the search"))
    elif ipopt_timed:
        notes.append(TIMING_NOTE.format(what="IPOPT's pass of start " + ", ".join(map(str, ipopt_timed))))
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
                with DL.until(last, wall_limit, m0):
                    c = _rounded(c, vars_, ev, say)
                    say(f"verify's gate on the tuned scenario (design {i + 1} of the ranking)")
                    gate_info = verify_gate(ev.scenario(apply(scenario.raw, vars_, c.xs)), progress=say)
            except (DL.WallLimitReached, SystemError, RuntimeError) as exc:
                if not (isinstance(exc, DL.WallLimitReached) or _expired(last, exc)):
                    raise
                gate_info = {"status": "not completed", "unexpected": []}
                notes.append(f"verify's gate on design {i + 1} did not finish within --wall-limit {wall_limit:g} s")
                if not timing:
                    timing = True
                    notes.append(TIMING_NOTE.format(what="verify's gate"))
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
    from .active import at_bounds, degradations
    bounds_hit = at_bounds(vars_, b.xs)
    notes += degradations(before.figures, b.figures)
    for e in bounds_hit:
        notes.append(f"{e['key']} ended at its {e['bound']} bound {e['bound_value']:.4g} (was {e['before']:.4g}): "
                     "the search wanted to go further; check the design's tracking and torque, or widen "
                     "[tune.bounds] if that is intended")
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
        comparison={"original": _side(before, spec, ev), "tuned": _side(b, spec, ev)}, at_bounds=bounds_hit,
        ended_by=ended_by, timing_dependent=timing)


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


def _gradient_search(gp, vars_, ev, z_user, f, ref, say, spec, *, deadline: float,
                     max_evaluations: int | None, timed: list | None = None) -> None:
    """IPOPT from the user's values and from Sobol points, all started at once (each a child process, so the
    starts share the machine's cores instead of queueing), their results judged in the starts' order by `f` (the
    full simulation of the Evaluator), which records the best candidate: the same results, in the same order, as one
    start after the other. Each IPOPT run is killed at the deadline (its best grid-feasible iterate so far is then the
    result). The starts (1-based) whose pass IPOPT's own wall-time limit ended (a timing, not a count) are appended
    to `timed`."""
    from ..core import deadline as _deadline
    from ..core.sobol import sobol
    from ..core.worker import start_killable
    say(f"gradient problem: {gp.d} parameter(s), {gp.ng} grid constraints ({gp.nplants} plant(s) x {gp.K + 1} "
        "points)")
    starts = [z_user, *sobol(len(vars_), GRADIENT_SOBOL_STARTS, 0)]
    obj = spec.objective
    left = deadline - time.perf_counter()
    if left <= 1.0:
        raise _OutOfTime("search stopped at the wall-clock limit")
    side = starts_side_by_side()

    def running(i: int) -> int:
        # how many starts are launched once start i is collected: each start's result costs at most one evaluation
        # (`f`; none when it repeats a design already judged), so a start the evaluations left cannot reach is not
        # launched ahead (its IPOPT run would be killed unheard: --max-evals 2 leaves one, 1 start's CPU, not 3)
        if not side:
            return i + 1
        if not max_evaluations:
            return len(starts)
        return min(len(starts), i + max(max_evaluations - ev.count, 0))
    ahead = running(0)
    say(f"IPOPT: {len(starts)} starts " + ("side by side" if side else "one after the other")
        + (f" ({ahead} at once: the evaluations left judge no more)" if side and ahead < len(starts) else "")
        + f" (at most {left:.0f} s)")

    def launch(i: int):
        # IPOPT gets the time left but what the full simulation of its result needs; in forked workers: IPOPT
        # inside one C call hears no signal and no limit, the waiting parent does
        left = deadline - time.perf_counter()
        job = start_killable(gp.solve, np.asarray(starts[i], float), objective=obj, ref=ref.get(obj, 1.0),
                             wall_s=0.9 * left, progress=_tagged(say, f"IPOPT start {i + 1}: "))
        return job, left
    jobs: list = []
    try:
        for i in range(ahead if side else 0):   # inside the try: a start that fails to launch stops the others
            jobs.append(launch(i))
        for i in range(len(starts)):
            if deadline - time.perf_counter() <= 1.0:
                raise _OutOfTime("search stopped at the wall-clock limit")
            if max_evaluations and ev.count >= max_evaluations:
                raise _OutOfTime(f"search stopped after {max_evaluations} evaluations (--max-evals)",
                                 by="evaluations")
            while len(jobs) <= i or len(jobs) < running(i):
                jobs.append(launch(len(jobs)))
            job, left = jobs[i]
            say(f"IPOPT start {i + 1} of {len(starts)}: waiting for its result")
            try:
                try:
                    r = job.result(wall_limit=left + 2.0, what="solving with IPOPT")
                except _deadline.WallLimitReached:
                    if _deadline.expired_limit() is not None:     # a limit around tune: it ends the command
                        raise
                    raise _OutOfTime("search stopped at the wall-clock limit (IPOPT did not stop by itself)") \
                        from None
            except RuntimeError as exc:          # e.g. the start itself does not integrate: next start
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)
                say(f"IPOPT start {i + 1}: skipped ({_last_line(exc)})")
                continue
            say(f"IPOPT start {i + 1}: {r['status']} after {r['iterations']} iteration(s)")
            if timed is not None and any("WallTime" in str(p.get("status", "")) for p in (r, r.get("coarse") or {})):
                timed.append(i + 1)
            f(r["z"], final=True)
    finally:
        for job, _ in jobs:                      # the starts not collected (a limit, an error) stop here
            job.kill()


def starts_side_by_side() -> bool:
    """Whether the IPOPT starts run side by side (issue 43), or one after the other as before when
    $SYMFUNNEL_TUNE_STARTS is 'sequential' (the bench's baseline, `bench.tune`)."""
    import os
    return os.environ.get("SYMFUNNEL_TUNE_STARTS", "").strip().lower() != "sequential"


def _tagged(say, tag: str):
    """`say` with each line prefixed by `tag` (the IPOPT starts run side by side: their lines interleave)."""
    return lambda s: say(tag + s)


def _with_tracking(ev: Evaluator, spec: TuneSpec, before: Candidate, say) -> Candidate:
    """Set the reference of [tune] tracking from the user's design (its nominal e1 RMS after the transient) and
    give that design its own tracking constraint (1 - 1/factor); without a reference (the user's run does not reach
    its settle time) the constraint is left out, said so."""
    ref = before.figures.get("e1_rms_after_transient")
    if ref is None or not math.isfinite(ref) or ref <= 0:
        say("[tune] tracking: the user's design has no e1 RMS after the transient to compare with; left out")
        return before
    ev.tracking_ref = float(ref)
    say(f"[tune] tracking: e1 RMS after the transient at most {spec.tracking:g} x {ref:.4g}")
    return Candidate(before.xs, {**before.constraints, "tracking": 1.0 - 1.0 / spec.tracking}, before.figures,
                     before.note, before.worst_run)


def _side(c: Candidate, spec: TuneSpec, ev: Evaluator) -> dict:
    """One column of the original/tuned comparison: torque, margin, saturation, violations among the samples."""
    g = c.constraints
    held = g.get("containment", -1) >= -spec.margin         # reached the horizon inside both funnels
    out = {"feasible": c.feasible, "reached_horizon": held, "peak_torque": c.figures.get("peak_torque"),
           "ise": c.figures.get("ise") if held else None,
           "min_margin": g["containment"] + spec.margin if held else None,
           "saturation": g.get("saturation"), "min_rate_hz": c.figures.get("min_rate"),
           "e1_rms_after_transient": c.figures.get("e1_rms_after_transient") if held else None,
           "chattering": c.figures.get("chattering") if held else None}
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



"""The simulation's result: `SimResult` (trajectory, signals, status, statistics; JSON summary and .npz) and
`finish`, which assembles it from the run's segments."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .closedloop import OUTPUT_NAMES, ClosedLoop
from ..core.io import json_safe
from .compiled import Compiled, evaluate_outputs

if TYPE_CHECKING:
    from ..scenario import Scenario
    from .runner import Runner


@dataclass
class SimResult:
    """A simulated trajectory (arrays with time as the first axis), its status and statistics."""

    scenario: str
    t: np.ndarray
    x: np.ndarray                              # (T, n_x), public state order
    signals: dict                              # logged signals (T, ...) plus q, dq, x_esn, w_hat
    status: str                                # 'ok' | 'breach' | 'initial_outside' | 'timeout' | 'failed'
    message: str
    breach: dict | None
    stats: dict
    n: int = 0
    gamma: float = 1.0
    convergence: dict | None = None
    joint_types: list | None = None            # the model's joint types: the metrics' units

    @property
    def ok(self) -> bool:
        """True when the run reached its final time inside both funnels."""
        return self.status == "ok"

    def __getattr__(self, name):
        sig = self.__dict__.get("signals", {})
        if name in sig:
            return sig[name]
        raise AttributeError(name)

    @property
    def between(self) -> dict:
        """What the samples between the output points showed (`simulation.between`; empty without any)."""
        return self.stats.get("between") or {}

    def extreme(self, key: str) -> list[float | None]:
        """Per joint, over the output points and the samples between them: the smallest margin (key 'm1', 'm2') or
        the largest |tau| ('tau', 'tau_applied'); None where neither has a value."""
        a = self.signals.get(key)
        lowest = key in ("m1", "m2")
        b = self.between.get({"m1": "min_margin_e1", "m2": "min_margin_e2", "tau": "max_abs_tau",
                              "tau_applied": "max_abs_tau_applied"}[key]) or [None] * self.n
        out = []
        for j in range(self.n):
            vals = []
            if a is not None and a.shape[0]:
                col = a[:, j] if lowest else np.abs(a[:, j])
                vals.append(float(np.min(col) if lowest else np.max(col)))
            if b[j] is not None:
                vals.append(float(b[j]))
            out.append((min(vals) if lowest else max(vals)) if vals else None)
        return out

    def __repr__(self) -> str:
        """Short: status, horizon and points (not the arrays; `summary()` has every figure)."""
        t_end = float(self.t[-1]) if self.t.size else 0.0
        return (f"SimResult(scenario={self.scenario!r}, status={self.status!r}, t_end={t_end:.6g} s, "
                f"{self.t.size} points)")

    def summary(self) -> dict:
        """The JSON summary: margins, torque (both over the output points and the samples between them), ESN
        estimation error, wall time, integrator statistics."""
        s = self.signals
        T = self.t.size

        def per_joint(fn, key):
            a = s.get(key)
            if a is None or a.shape[0] == 0:
                return [None] * self.n
            return [float(v) for v in fn(a)]

        out = {
            "scenario": self.scenario,
            "status": self.status,
            "message": self.message,
            "t_end": float(self.t[-1]) if T else 0.0,
            "t_final": self.stats.get("t_final"),
            "points": int(T),
            **self.margins(),
            "min_margin_e1": self.extreme("m1"),
            "min_margin_e2": self.extreme("m2"),
            "max_abs_e1": per_joint(lambda a: np.max(np.abs(a), axis=0), "e1"),
            "max_abs_tau": self.extreme("tau"),
            "max_abs_tau_applied": self.extreme("tau_applied"),
            "rms_esn_error": per_joint(lambda a: np.sqrt(np.mean(a ** 2, axis=0)), "esn_error"),
            "rms_f_true": per_joint(lambda a: np.sqrt(np.mean(a ** 2, axis=0)), "f_true"),
            "max_abs_w_hat": float(np.max(np.abs(s["w_hat"]))) if T and "w_hat" in s else None,
            "max_abs_x_esn": float(np.max(np.abs(s["x_esn"]))) if T and "x_esn" in s else None,
            "breach": self.breach,
            "wall_time": self.stats.get("wall_time"),
            "realtime_factor": self.stats.get("realtime_factor"),
            "compile_time": self.stats.get("compile_time"),
            "code": self.stats.get("code"),
            "integrator": self.stats.get("integrator"),
            "cvodes_backend": self.stats.get("cvodes_backend"),
            "smoothing_width": self.stats.get("smoothing_width"),
            "non_smooth_treatment": self.stats.get("non_smooth_treatment"),
            "steps": self.stats.get("steps"),
            "rhs_evaluations": self.stats.get("rhs_evaluations"),
            "jacobian_evaluations": self.stats.get("jacobian_evaluations"),
            "error_test_failures": self.stats.get("error_test_failures"),
            "events": self.stats.get("events"),
            "event_counts": self.stats.get("event_counts"),
            "between_points": self.between or None,
        }
        out["metrics"] = self.metrics()
        if self.convergence is not None:
            out["convergence"] = self.convergence
        return json_safe(out)

    def metrics(self) -> dict:
        """Per joint, the metrics an engineer reads (`simulation.metrics`) on the output grid, with their units."""
        from .metrics import metrics_block
        n = max(self.n, 1)
        e1 = self.signals.get("e1", np.zeros((0, n)))
        tau = self.signals.get("tau", np.zeros((0, n)))
        return metrics_block(self.t, e1, tau, float(self.stats.get("settle_time", 0.0)), self.joint_types or [],
                             n=n)

    def margins(self) -> dict:
        """Whole-run and post-transient margin minima per joint, with their times and the settle time used
        (`simulation.margins`)."""
        from .margins import margin_summary
        s = self.signals
        n = max(self.n, 1)
        m1 = s.get("m1", np.zeros((0, n)))
        m2 = s.get("m2", np.zeros((0, n)))
        return margin_summary(self.t, m1, m2, float(self.stats.get("settle_time", 0.0)),
                              self.stats.get("settle_source", ""))

    def to_json(self) -> dict:
        """The JSON summary (as `simulate --json`)."""
        return self.summary()

    def _repr_html_(self) -> str:
        """A notebook line: status and message."""
        import html
        return f"<p>simulation <b>{html.escape(self.status)}</b>: {html.escape(self.message)}</p>"

    def save(self, path, arrays: dict | None = None) -> Path:
        """Write the trajectory (time first; `arrays` adds e.g. V and W* of the Lyapunov stage) and the run's
        metadata, atomically, by the file's suffix: .npz, .csv (units in its header) or .mat (`simulation.export`)."""
        from .export import write_trajectory
        data = {"t": self.t}
        for k, v in self.signals.items():
            data[k] = np.asarray(v)
        for k, v in (arrays or {}).items():
            data[k] = np.asarray(v)
        meta = {"scenario": self.scenario, "status": self.status, "message": self.message,
                "smoothing_width": self.stats.get("smoothing_width", float("nan")),
                "integrator": self.stats.get("integrator", "")}
        if Path(path).suffix.lower() == ".npz":
            meta.pop("scenario")            # the npz's keys as before
        return write_trajectory(path, data, joint_types=self.joint_types or [], n=self.n, meta=meta)

    def save_npz(self, path, arrays: dict | None = None) -> Path:
        """`save` (kept under its first name: any of the suffixes works)."""
        return self.save(path, arrays)



def count_events(sc: Scenario, o: dict, dq: np.ndarray) -> dict:
    """Switches of the non-smooth terms seen on the output grid (friction sign, dead-zone regions, e = 0)."""
    def crossings(a):
        s = np.sign(a)
        return int(np.sum((s[1:] * s[:-1]) < 0)) if a.shape[0] > 1 else 0
    ev = {"friction_sign_changes": crossings(dq) if len(dq) else 0,
          "e1_zero_crossings": crossings(o["e1"]) if len(o["e1"]) else 0,
          "e2_zero_crossings": crossings(o["e2"]) if len(o["e2"]) else 0}
    dz = sc.plant.dead_zone
    if dz is not None and len(o["tau"]) > 1:
        tau = o["tau"]
        region = (tau >= np.asarray(dz.b_r)).astype(int) - (tau <= np.asarray(dz.b_l)).astype(int)
        ev["dead_zone_transitions"] = int(np.sum(region[1:] != region[:-1]))
    else:
        ev["dead_zone_transitions"] = 0
    return ev


def finish(sc: Scenario, cl: ClosedLoop, comp: Compiled, t_list: list, X_list: list, status: str, message: str,
           breach: dict | None, stats: dict, runner: Runner | None, start: float, O_list: list | None = None) -> SimResult:
    """The SimResult of a run from its segments (times, states, and the outputs already computed or None)."""
    O_list = list(O_list or [])
    if status == "failed" and runner is not None and not message.startswith("the initial state"):
        from .hints import failure_hint
        message += failure_hint(runner.method, stats["smoothing_width"], sc.simulation, stats["dt"],
                                getattr(runner, "last_error", None))
    segs = []
    for i, (ta, Xa) in enumerate(zip(t_list, X_list)):
        ta = np.atleast_1d(np.asarray(ta, dtype=float))
        if ta.size == 0:
            continue
        Xa = np.asarray(Xa, dtype=float).reshape(ta.size, cl.nx)
        oa = O_list[i] if i < len(O_list) and O_list[i] is not None else evaluate_outputs(comp, cl.n, ta, Xa)
        segs.append((ta, Xa, oa))
    if segs:
        t = np.concatenate([a for a, _, _ in segs])
        X = np.concatenate([b for _, b, _ in segs], axis=0)
        o = {k: np.concatenate([c[k] for _, _, c in segs], axis=0) for k in OUTPUT_NAMES}
    else:
        t, X = np.zeros(0), np.zeros((0, cl.nx))
        o = evaluate_outputs(comp, cl.n, t, X)
    parts = cl.unpack(X)
    signals = dict(parts)
    signals.update(o)
    signals["esn_error"] = o["w_phi"] - o["f_true"]
    gamma = float(sc.gamma)
    wall = time.perf_counter() - start
    stats.update(runner.stats)
    ev = count_events(sc, o, parts["dq"])
    stats["event_counts"] = ev
    stats["events"] = int(sum(ev.values())) + (1 if status == "breach" else 0)
    stats["wall_time"] = wall
    if "settle_time" not in stats:
        from .margins import settle_time
        stats["settle_time"], stats["settle_source"] = settle_time(
            cl.design, stats.get("t_final") or sc.simulation.t_final, sc.simulation.settle_time)
    sw = stats.get("sim_wall_time")
    t_end = float(t[-1]) if t.size else 0.0
    stats["realtime_factor"] = t_end / sw if sw else None
    if status == "initial_outside" and breach is not None:
        from .hints import initial_hint
        hint = initial_hint(cl.design, funnel=breach["funnel"], joint=int(breach["joint"]),
                            abs_error=float(breach["abs_error"]), scenario_arg=scenario_arg(sc))
        breach = {**breach, "hint": hint}
        message += f"; what to do: {hint}"
    elif status == "breach" and breach is not None and t.size:
        from .hints import breach_hint
        p = parts
        k = -2 if t.size >= 2 else -1      # the last point inside: the design's torque is not defined outside
        hint = breach_hint(cl.design, t=float(t[k]), q=p["q"][k], dq=p["dq"][k],
                           x_esn=p["x_esn"][k] if "x_esn" in p else None,
                           w_hat=p["w_hat"][k] if "w_hat" in p else None, funnel=breach["funnel"],
                           joint=int(breach["joint"]), tau_max=sc.tune.tau_max if sc.tune is not None else None,
                           scenario_arg=scenario_arg(sc))
        breach = {**breach, "hint": hint}
        message += f"; what to do: {hint}"
    res = SimResult(scenario=sc.name, t=t, x=X, signals=signals, status=status, message=message, breach=breach,
                    stats=stats, n=cl.n, gamma=gamma, joint_types=list(sc.model.joint_types or []))
    if status == "ok":
        res.message = ok_message(res)
    return res


def ok_message(res: SimResult) -> str:
    """The message of a run that reached its final time inside both funnels (margins also between output points)."""
    m1 = min(v for v in res.extreme("m1") if v is not None)
    m2 = min(v for v in res.extreme("m2") if v is not None)
    return (f"reached t = {float(res.t[-1]):g} s inside both funnels (min margin e1 {m1:.3g}, e2 {m2:.3g})")


def scenario_arg(sc) -> str:
    """How a command line names the scenario: its built-in name or its file."""
    from ..scenario import is_builtin
    return sc.name if is_builtin(sc.path) else str(sc.file)

"""Sampled-data simulation of the deployed controller: the generated C step function in a zero-order-hold loop.

At each sample t_k = k h (h = 1/rate_hz) the measurements q + noise, dq + noise (q quantised to the encoder
resolution) go to the compiled `symfunnel_step` of the files `codegen --lang c` writes (loaded with ctypes), so
the code verified is the code shipped. Its torque is held over the period (one period later with
delay_samples = 1; zero torque before the first one arrives) and the true plant (dead zone, friction,
disturbance, the plant's M, C, G: `plant.equations.plant_acceleration`) is integrated over the period by CasADi's
fixed-step `rk` integrator, expanded to SX and compiled to C. Funnel margins 1 - |e|/F are those of the true
state, at the samples and, between them, at every RK4 step of the plant (`between_margins`: per period the smallest
over its steps; the controller only sees the samples, the plant's state leaves a funnel wherever it does).

API::

    res = simulate_sampled(scenario, design, rate_hz=2000.0)   # SampledResult: t, q, dq, tau, margins, breach
    res.ok, res.min_margin, res.saturated_fraction

The checks on such a run (`implementation.containment`, `implementation.saturation`) are
`symfunnel.checks.implementation.implementation_checks`.
"""

from __future__ import annotations

import ctypes
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..core.text import reached
from .cfun import _CFun, _compiled
from .step_lib import MARK, StepLibrary, step_library
from ..simulation.between import margin_function

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design
    from ..scenario import Scenario

__all__ = ["SampledResult", "StepLibrary", "simulate_sampled", "plant_step_function", "step_library",
           "plant_substeps"]



@dataclass
class SampledResult:
    """One sampled-data run: states at the samples, the held torques, the true margins, and its status."""

    scenario: str
    rate_hz: float
    t: np.ndarray                  # (K+1,) sample times
    q: np.ndarray                  # (K+1, n) true joint positions at the samples
    dq: np.ndarray                 # (K+1, n)
    tau: np.ndarray                # (K, n) torque applied over [t_k, t_k+1) (after delay; saturated by the step)
    margins: np.ndarray            # (K+1, 2n) true 1 - |e|/F at the samples: e1 columns, then e2
    status: str                    # "ok" | "breach" | "failed"
    message: str
    breach: dict | None
    tau_max: tuple | None
    wall_time: float
    stats: dict = field(default_factory=dict)
    between_margins: np.ndarray | None = None     # (K, 2n) per period the smallest true margins over its RK4 steps
    e1: np.ndarray | None = None                  # (K+1, n) tracking error at the samples
    joint_types: list | None = None               # the model's joint types: the metrics' units

    def __repr__(self) -> str:
        """Short: rate, status and samples (not the arrays; `summary()` has every figure)."""
        return (f"SampledResult(scenario={self.scenario!r}, rate_hz={self.rate_hz:.6g}, status={self.status!r}, "
                f"{max(self.t.size - 1, 0)} samples)")

    @property
    def ok(self) -> bool:
        """True when the run reached its final time inside both funnels."""
        return self.status == "ok"

    @property
    def min_margin(self) -> float:
        """The smallest true funnel margin over samples, the plant's steps between them, joints and both funnels
        (-inf when it failed)."""
        m = self._all_margins()
        m = m[np.all(np.isfinite(m), axis=1)]
        return float(m.min()) if m.size and self.status != "failed" else -math.inf

    def _all_margins(self) -> np.ndarray:
        if self.between_margins is None or self.between_margins.size == 0:
            return self.margins
        return np.concatenate([self.margins, self.between_margins])

    @property
    def min_margin_after_transient(self) -> float:
        """The smallest true margin over the samples at t >= the settle time (`simulation.margins`), joints and both
        funnels; at a breach the breach's margin wherever it happened; -inf when the run failed or ended before."""
        if self.status == "failed":
            return -math.inf
        from ..simulation.margins import after_transient
        mins, _ = after_transient(self.t, self.margins, float(self.stats.get("settle_time", 0.0)))
        vals = [v for v in mins if v is not None]
        m = min(vals) if vals else -math.inf
        if self.breach is not None:
            m = min(m, float(self.breach["margin"]))
        return float(m)

    @property
    def saturated_fraction(self) -> list[float] | None:
        """Per joint, the fraction of the run's time its torque sat at tau_max (None without a limit)."""
        if self.tau_max is None or self.tau.shape[0] == 0:
            return None
        tm = np.asarray(self.tau_max)
        return (np.abs(self.tau) >= tm * (1 - 1e-12)).mean(axis=0).tolist()

    def summary(self) -> dict:
        """Plain data for JSON output."""
        n = self.q.shape[1]
        m = self._all_margins()
        return {"scenario": self.scenario, "rate_hz": self.rate_hz, "status": self.status, "message": self.message,
                "t_end": float(self.t[-1]), "samples": int(self.tau.shape[0]),
                "min_margin_e1": np.nanmin(m[:, :n], axis=0).tolist() if m.size else None,
                "min_margin_e2": np.nanmin(m[:, n:], axis=0).tolist() if m.size else None,
                **({} if not m.size else self._post_transient(n)),
                "max_abs_tau": np.max(np.abs(self.tau), axis=0).tolist() if self.tau.size else None,
                "tau_max": None if self.tau_max is None else list(self.tau_max),
                "saturated_fraction": self.saturated_fraction, "breach": self.breach,
                "wall_time": self.wall_time,
                "realtime_factor": float(self.t[-1] / self.wall_time) if self.wall_time > 0 else None,
                **self.stats, "metrics": self.metrics()}

    def save(self, path) -> Path:
        """Write t, q, dq, tau (held: one row less), the true margins and e1 at the samples by the file's suffix
        (.npz, .csv, .mat; `simulation.export`), atomically."""
        from ..simulation.export import write_trajectory
        arrays = {"t": self.t, "q": self.q, "dq": self.dq, "tau": self.tau, "margins": self.margins, "e1": self.e1}
        return write_trajectory(path, arrays, joint_types=self.joint_types or [], n=self.q.shape[1],
                                meta={} if str(path).lower().endswith(".npz") else
                                {"scenario": self.scenario, "rate_hz": self.rate_hz, "status": self.status,
                                 "message": self.message})

    def metrics(self) -> dict:
        """Per joint, the metrics an engineer reads (`simulation.metrics`): the error at the samples, the held
        torque (after delay and saturation) over its periods."""
        from ..simulation.metrics import metrics_block
        n = self.q.shape[1]
        e1 = self.e1 if self.e1 is not None else np.full(self.q.shape, np.nan)
        return metrics_block(self.t, e1, self.tau, float(self.stats.get("settle_time", 0.0)),
                             self.joint_types or [], n=n, held=True)


    def _post_transient(self, n: int) -> dict:
        from ..simulation.margins import after_transient
        ts = float(self.stats.get("settle_time", 0.0))
        m1, t1 = after_transient(self.t, self.margins[:, :n], ts)
        m2, t2 = after_transient(self.t, self.margins[:, n:], ts)
        return {"min_margin_e1_after_transient": m1, "min_margin_e2_after_transient": m2,
                "t_min_margin_e1_after_transient": t1, "t_min_margin_e2_after_transient": t2}


def plant_substeps(scenario, h: float) -> int:
    """RK4 steps per period (a power of 2): h / substeps inside RK4's stability interval for the stiffest term.

    That term is the smoothed Coulomb friction (slope coulomb / smoothing_width) plus viscous friction, over the
    smallest eigenvalue of M(q0): rate lambda; 1.5 / lambda keeps h*lambda well under RK4's 2.78; at most 1e-3 s.
    Powers of 2 let a rate search reuse a few compiled plant steps.
    """
    sc = scenario
    pl = sc.plant
    w = sc.simulation.smoothing_width
    slope = max(v + (c / w if w > 0 else 0.0) for v, c in zip(pl.viscous, pl.coulomb)) if sc.n else 0.0
    M = np.array(ca.Function("M", [sc.model.q], [sc.model.numeric(sc.model.M)])(sc.q0)) * pl.mass_scale
    lam = slope / max(float(np.linalg.eigvalsh(0.5 * (M + M.T)).min()), 1e-12)
    h_max = min(1e-3, 1.5 / lam if lam > 0 else 1e-3)
    need = h / h_max
    if not need <= MAX_PLANT_SUBSTEPS:
        raise InputError(f"is {1.0 / h:.6g} Hz: one period of {h:.6g} s needs {need:.3g} RK4 plant steps of at most "
                         f"{h_max:.3g} s (at most {MAX_PLANT_SUBSTEPS}; the plant step's code grows with them)",
                         file=sc.file, key="implementation.rate_hz",
                         expected=f"a rate of at least {min_rate_hz(sc):.6g} Hz for this plant")
    need = max(1, int(math.ceil(need - 1e-9)))
    return 1 << (need - 1).bit_length()


#: the most RK4 steps of the plant per sample period (their code is unrolled into the compiled plant step)
MAX_PLANT_SUBSTEPS = 1024


def min_rate_hz(scenario) -> float:
    """The lowest sample rate whose period the plant step integrates within MAX_PLANT_SUBSTEPS RK4 steps."""
    sc = scenario
    pl = sc.plant
    w = sc.simulation.smoothing_width
    slope = max(v + (c / w if w > 0 else 0.0) for v, c in zip(pl.viscous, pl.coulomb)) if sc.n else 0.0
    M = np.array(ca.Function("M", [sc.model.q], [sc.model.numeric(sc.model.M)])(sc.q0)) * pl.mass_scale
    lam = slope / max(float(np.linalg.eigvalsh(0.5 * (M + M.T)).min()), 1e-12)
    h_max = min(1e-3, 1.5 / lam if lam > 0 else 1e-3)
    return 1.0 / (MAX_PLANT_SUBSTEPS * h_max)


def plant_step_function(scenario, substeps: int, name: str = "sfs_plant", design=None) -> ca.Function:
    """([t0, h], x = [q; dq], tau) -> x at t0 + h with tau held: CasADi's rk integrator (RK4, `substeps` steps);
    with `design` also the smallest true margins [e1; e2] over the states after each step (the second output).

    The ODE is integrated in s = (t - t0)/h over [0, 1], so one compiled function serves every period h.
    """
    from ..plant.equations import plant_acceleration
    n = scenario.n
    q, dq = ca.SX.sym("q", n), ca.SX.sym("dq", n)
    s, th, tau, s0 = ca.SX.sym("s"), ca.SX.sym("th", 2), ca.SX.sym("tau", n), ca.SX.sym("s0")
    x = ca.vertcat(q, dq)
    X, TH, U = ca.MX.sym("x", 2 * n), ca.MX.sym("th", 2), ca.MX.sym("tau", n)
    # simplify: the fixed-step scheme as a plain MX graph (a loop over the substeps' SX step), which generates
    # compact C; expanding it to SX would unroll every substep and make large models slow to compile
    if design is None:
        ddq = plant_acceleration(scenario, q, dq, th[0] + th[1] * s, tau, scenario.simulation.smoothing_width)["ddq"]
        F = ca.integrator("plant", "rk", {"x": x, "p": ca.vertcat(th, tau), "t": s,
                                          "ode": th[1] * ca.vertcat(dq, ddq)}, 0.0, 1.0,
                          {"number_of_finite_elements": substeps, "simplify": True})
        xf = F(x0=X, p=ca.vertcat(TH, U))["xf"]
        return ca.Function(name, [TH, X, U], [xf], ["th", "x", "tau"], ["xf"])
    # the same RK4 steps one at a time (s = s0 + s' over [0, 1/substeps]), keeping every step's state: the last
    # one is bit for bit the plain step's
    ddq = plant_acceleration(scenario, q, dq, th[0] + th[1] * (s0 + s), tau,
                             scenario.simulation.smoothing_width)["ddq"]
    G = ca.integrator("plant", "rk", {"x": x, "p": ca.vertcat(th, tau, s0), "t": s,
                                      "ode": th[1] * ca.vertcat(dq, ddq)}, 0.0, 1.0 / substeps,
                      {"number_of_finite_elements": 1, "simplify": True})
    XX, PP = ca.MX.sym("x", 2 * n), ca.MX.sym("p", 3 + n)
    step = ca.Function("plant_step", [XX, PP], [G(x0=XX, p=PP)["xf"]])
    starts = ca.DM([j / substeps for j in range(substeps)]).T
    xs = step.mapaccum("plant_steps", substeps)(X, ca.vertcat(ca.repmat(ca.vertcat(TH, U), 1, substeps), starts))
    ts = TH[0] + TH[1] * ca.DM([(j + 1) / substeps for j in range(substeps)]).T
    m = margin_function(design).map(substeps)(ts, xs[:n, :], xs[n:, :])
    mmin = ca.vertcat(*[ca.mmin(m[i, :]) for i in range(2 * n)])
    return ca.Function(name, [TH, X, U], [xs[:, -1], mmin], ["th", "x", "tau"], ["xf", "between"])




def simulate_sampled(scenario: Scenario, design: Design, *, rate_hz: float | None = None,
                     t_final: float | None = None, progress: Callable[[str], None] | None = None,
                     stop_on_breach: bool = True, controller=None, engine: str | None = None,
                     plant=None, search_build: bool = False) -> SampledResult:
    """Run the sampled-data loop (see the module doc) to t_final; stops at the first sample outside a funnel.

    `controller` replaces the compiled C step by any object with `init()`, buffers `q`, `dq`, `tau` and
    `raw()` like StepLibrary's (the bench's CasADi-VM baseline; symfunnel's plant only). `engine` chooses the plant
    ("symfunnel" or "mujoco", default the scenario's `[plant] engine`; `deployed.engine` for MuJoCo), `plant` (an
    `engine.EngineRunPlant`) overrides an engine run's plant quantities and initial state (a sweep's run).
    `search_build` runs the rate searches' build of the same C (`deployed.rate_step`: compiled once for every rate).
    """
    from ..emit.files import generate
    from ..scenario.implementation import implementation_of
    say = progress or (lambda s: None)
    sc = scenario
    impl = implementation_of(sc, rate_hz) or implementation_of(sc, 1000.0)
    n = sc.n
    h = 1.0 / impl.rate_hz
    T = float(t_final if t_final is not None else sc.simulation.t_final)
    engine = engine or getattr(sc.plant, "engine", "symfunnel")
    if engine == "symfunnel":
        subs = plant_substeps(sc, h)          # first: a rate too low for the plant is refused before any work
    from ..core.validate import check_horizon
    check_horizon(T, h, key="--t-final" if t_final is not None else "simulation.t_final",
                  file=None if t_final is not None else sc.file, step_name="sample period 1/rate_hz")
    from ..core.validate import check_run_memory    # q, dq, tau, margins, noise and what the summary copies
    check_run_memory(T * impl.rate_hz, 10 * n + 2,
                     key=("--t-final" if t_final is not None else "simulation.t_final")
                     + f" at {impl.rate_hz:g} Hz", file=None if t_final is not None else sc.file)
    K = int(math.floor(T * impl.rate_hz + 1e-9))
    if controller is None and search_build:
        from .rate_step import search_step
        controller = search_step(design, impl.rate_hz, impl.tau_max, on_build=say)
    elif controller is None:
        files = generate(design, "c", rate_hz=impl.rate_hz, tau_max=impl.tau_max)
        controller = step_library(design, files, on_build=say)
    controller.init()
    if engine != "symfunnel":
        return _engine_sampled(sc, design, impl, controller, K, h, stop_on_breach, plant, say, T)
    plant = _compiled(plant_step_function(sc, subs, name=f"sfs_plant_{subs}_m", design=design), on_build=say)
    p_t, p_x, p_u = plant.inputs
    xf, mb = plant.outputs
    rng = np.random.default_rng(impl.seed)
    nq = rng.standard_normal((K, n)) * impl.noise_q if impl.noise_q > 0 else None
    ndq = rng.standard_normal((K, n)) * impl.noise_dq if impl.noise_dq > 0 else None
    res = impl.encoder_resolution
    X = np.full((K + 1, 2 * n), np.nan)
    TAU = np.zeros((K, n))
    MB = np.full((K, 2 * n), np.nan)
    p_x[:n], p_x[n:] = sc.q0, sc.dq0
    X[0] = p_x
    xq, xdq = p_x[:n], p_x[n:]
    qbuf, dqbuf, taubuf = controller.q, controller.dq, controller.tau
    stepf, sp, ptrs = controller.raw()
    pending = np.zeros(n)
    p_t[1] = h
    status, message, k_end = "ok", f"{reached(K * h, T, h)} inside both funnels", K
    outside = None
    start = time.perf_counter()
    if isinstance(controller, StepLibrary):
        rc, k_end, outside = _c_loop(controller, plant, n, K, h, nq, ndq, res, impl.delay_samples, stop_on_breach,
                                     X, TAU, MB, say)
        if rc < 0 and outside is None:
            status, message = "failed", (f"the step function returned {rc} at t = {k_end * h:g} s" if rc > -100
                                         else "the plant function failed")
    for k in range(K if not isinstance(controller, StepLibrary) else 0):
        t = k * h
        # measurements into the step's input buffers: noise, then the encoder's quantisation of q
        if nq is None:
            qbuf[:] = xq
        else:
            np.add(xq, nq[k], out=qbuf)
        if res > 0:
            np.round(qbuf / res, out=qbuf)
            qbuf *= res
        if ndq is None:
            dqbuf[:] = xdq
        else:
            np.add(xdq, ndq[k], out=dqbuf)
        rc = stepf(sp, t, *ptrs)
        if rc < 0:
            k_end = k
            if outside is None:        # e.g. a non-finite plant state after leaving a funnel: found below
                status, message = "failed", f"the step function returned {rc} at t = {t:g} s"
            break
        if rc == 1 and outside is None:
            outside = k
        if impl.delay_samples:
            p_u[:] = pending
            pending[:] = taubuf
        else:
            p_u[:] = taubuf
        TAU[k] = p_u
        p_t[0] = t
        plant()
        p_x[:] = xf
        X[k + 1] = p_x
        MB[k] = mb
        if stop_on_breach and outside is not None and k - outside >= 1:
            k_end = k + 1
            break
    wall = time.perf_counter() - start
    return _result(sc, design, impl, h, k_end, X, TAU, status, message, wall,
                   {"engine": "symfunnel", "plant_substeps": subs, "delay_samples": impl.delay_samples,
                    "noise_q": impl.noise_q, "noise_dq": impl.noise_dq,
                    "encoder_resolution": impl.encoder_resolution,
                    "between_checked": "the true margins at every RK4 step of the plant between samples"},
                   MB=MB, subs=subs, stop_on_breach=stop_on_breach, controller=controller, horizon=T)


def _result(sc, design, impl, h, k_end, X, TAU, status, message, wall, stats, MB=None, subs=None,
            stop_on_breach: bool = True, controller=None, horizon: float | None = None) -> SampledResult:
    """The SampledResult of a loop that ended at sample k_end: true margins at the samples (and at the plant's steps
    between them, MB, where the loop has them), breach with its hint, status, the settle time of the horizon."""
    n = sc.n
    if MB is None:
        MB = np.full((k_end, 2 * n), np.nan)
    tt = np.arange(k_end + 1) * h
    Q, DQ, TAU = X[:k_end + 1, :n], X[:k_end + 1, n:], TAU[:k_end]
    mf = margin_function(design).map(k_end + 1)
    good = np.all(np.isfinite(Q), axis=1) & np.all(np.isfinite(DQ), axis=1)
    M = np.full((k_end + 1, 2 * n), np.nan)
    if good.any():
        M[good] = np.array(mf(tt[None, :], np.nan_to_num(Q.T), np.nan_to_num(DQ.T))).T[good]
    MB = MB[:k_end]
    breach = None
    bad = np.where(~(M > 0).all(axis=1) & good)[0]
    # a period whose plant steps leave a funnel before the next sample shows it (the state may come back by then)
    finite_mb = np.all(np.isfinite(MB), axis=1)
    bad_mb = np.where(~(MB > 0).all(axis=1) & finite_mb & good[1:])[0]
    if status == "ok" and not good.all() and not bad.size:
        status, message = "failed", f"the plant state is not finite at t = {tt[-1]:g} s"
    if bad_mb.size and status != "failed" and (not bad.size or bad_mb[0] + 1 <= bad[0]):
        kb = int(bad_mb[0])
        tb, j, mj = _between_breach(sc, subs, design, tt[kb], h, X[kb], TAU[kb])
        breach = {"time": tb, "funnel": "e1" if j < n else "e2", "joint": j % n + 1, "margin": mj,
                  "between_samples": [float(tt[kb]), float(tt[kb + 1])]}
        status = "breach"
        message = (f"left funnel {breach['funnel']} (joint {breach['joint']}) at t = {tb:.6g} s, between the samples "
                   f"at {tt[kb]:g} and {tt[kb + 1]:g} s (the plant's state; the controller sees the samples only)")
        if stop_on_breach:                 # as the loop stops after a sample outside: at the period's end
            k_end = kb + 1
            tt, Q, DQ, TAU, M, MB = (tt[:k_end + 1], Q[:k_end + 1], DQ[:k_end + 1], TAU[:k_end], M[:k_end + 1],
                                     MB[:k_end])
    elif bad.size and status != "failed":
        i = int(bad[0])
        j = int(np.nanargmin(M[i]))
        breach = {"time": float(tt[i]), "funnel": "e1" if j < n else "e2", "joint": j % n + 1,
                  "margin": float(M[i, j])}
        status = "breach"
        message = f"left funnel {breach['funnel']} (joint {breach['joint']}) at t = {tt[i]:g} s"
    if breach is not None:
        # the last sample inside: before a sample outside, or the period's start for a breach between samples
        last = int(kb) if "between_samples" in breach else max(int(i) - 1, 0)
        breach["hint"] = _breach_hint(sc, design, impl, controller, breach, tt, Q, DQ, TAU, last)
        message += f"; what to do: {breach['hint']}"
    from ..simulation.margins import settle_time
    ts, how = settle_time(design, float(horizon if horizon is not None else k_end * h), sc.simulation.settle_time)
    stats = {**stats, "settle_time": ts, "settle_source": how}
    E1 = np.full(Q.shape, np.nan)
    if good.any():
        from ..simulation.between import error_function
        E1[good[:Q.shape[0]]] = np.array(error_function(design).map(Q.shape[0])(
            tt[None, :], np.nan_to_num(Q.T))).T[good[:Q.shape[0]]]
    return SampledResult(sc.name, impl.rate_hz, tt, Q, DQ, TAU, M, status, message, breach, impl.tau_max, wall,
                         stats, between_margins=MB, e1=E1, joint_types=list(sc.model.joint_types or []))


def _breach_hint(sc, design, impl, controller, breach, tt, Q, DQ, TAU, k: int) -> str:
    """What to do about a breach, from the last sample k inside the funnel (or from the first saturated sample when
    the torque saturated before it: what it asked for there is the cause)."""
    from ..simulation.hints import breach_hint
    from ..simulation.result import scenario_arg
    st = {}
    if isinstance(controller, StepLibrary):
        st = {k: np.array(getattr(controller, k)) for k in ("x_esn", "w_hat") if k in design.sym}
    what = breach["funnel"]
    if impl.tau_max is not None and TAU.shape[0]:
        sat = np.nonzero(np.any(np.abs(TAU[:k + 1]) >= np.asarray(impl.tau_max) * (1 - 1e-12), axis=1))[0]
        if sat.size:
            k = int(sat[0])
            what = f"{what} (after the torque saturated from t = {tt[k]:g} s)"
            st = {}
    return breach_hint(design, t=float(tt[k]), q=Q[k], dq=DQ[k], funnel=what, joint=breach["joint"],
                       tau_max=impl.tau_max, sampled_rate=impl.rate_hz, scenario_arg=scenario_arg(sc), **st)


#: what the engine loop's negative return codes mean
_ENGINE_RC = {-100: "a plant force function failed", -101: "too many joints for the loop (at most 64)"}


def _engine_sampled(sc, design, impl, controller, K, h, stop_on_breach, plant, say, T=None) -> SampledResult:
    """simulate_sampled on a physics engine (deployed.engine): the same measurements, step and hold."""
    from .engine import EngineRunPlant, engine_setup, run_engine_loop
    if not isinstance(controller, StepLibrary):
        raise TypeError("a physics-engine plant is driven by the compiled C step (StepLibrary) only")
    n = sc.n
    setup = engine_setup(sc, on_build=say)
    run = plant or EngineRunPlant(setup.p0.copy(), sc.plant.mujoco, np.asarray(sc.q0, dtype=float),
                                  np.asarray(sc.dq0, dtype=float))
    rng = np.random.default_rng(impl.seed)
    nq = rng.standard_normal((K, n)) * impl.noise_q if impl.noise_q > 0 else None
    ndq = rng.standard_normal((K, n)) * impl.noise_dq if impl.noise_dq > 0 else None
    X = np.full((K + 1, 2 * n), np.nan)
    TAU = np.zeros((K, n))
    # the stability rule's configurations: the reference over the scenario's horizon (a shorter run keeps its steps)
    T = max(K * h, float(sc.simulation.t_final))
    rf = design.reference
    ref = [np.asarray(rf(t)[0], dtype=float).ravel() for t in np.linspace(0.0, T, 65)]
    start = time.perf_counter()
    out = run_engine_loop(setup, run, controller, n=n, K=K, h=h, nq=nq, ndq=ndq,
                          resolution=impl.encoder_resolution, delay=impl.delay_samples, stop=stop_on_breach, X=X,
                          TAU=TAU, width=float(sc.simulation.smoothing_width), reference=ref, file=sc.file)
    wall = time.perf_counter() - start
    rc, k_end = out["rc"], out["k_end"]
    status, message = "ok", f"{reached(K * h, K * h if T is None else T, h)} inside both funnels"
    if rc < 0 and rc != -102 and out["outside"] is None:
        status = "failed"
        message = (f"the step function returned {rc} at t = {k_end * h:g} s" if rc > -100
                   else f"{_ENGINE_RC.get(rc, f'error {rc}')} at t = {k_end * h:g} s")
    eng = setup.engine
    stats = {"engine": "mujoco", "plant_substeps": out["substeps"], "engine_timestep": h / out["substeps"],
             "engine_substeps_rule": out["substeps_rule"], "engine_integrator": out["integrator"],
             "engine_only": out["engine_only"], "engine_mass_scale": _engine_mass_scale(setup, run),
             "engine_notes": eng.notes.lines(), "engine_warnings": out["warnings"],
             "engine_last_warning": out["last_warning"] or None, "engine_force_callback": out["force_callback"],
             "delay_samples": impl.delay_samples, "noise_q": impl.noise_q, "noise_dq": impl.noise_dq,
             "encoder_resolution": impl.encoder_resolution,
             "between_checked": "none: the engine's margins are checked at the samples only"}
    return _result(sc, design, impl, h, k_end, X, TAU, status, message, wall, stats,
                   stop_on_breach=stop_on_breach, controller=controller, horizon=K * h)


def _engine_mass_scale(setup, run) -> list[float]:
    s = float(run.p[setup.p_names.index("plant.mass_scale")])
    ms = run.mujoco.mass_scale
    return [s * (1.0 if ms is None else float(v)) for v in (ms or [1.0] * setup.engine.n)]


def _between_breach(sc, subs: int, design, t0: float, h: float, x0: np.ndarray, tau: np.ndarray):
    """The first plant step of the period from (t0, x0) under tau whose state is outside a funnel: (t, index of the
    margin [e1 columns, then e2], margin)."""
    n = sc.n
    from ..plant.equations import plant_acceleration
    q, dq = ca.SX.sym("q", n), ca.SX.sym("dq", n)
    s, th, u = ca.SX.sym("s"), ca.SX.sym("th", 2), ca.SX.sym("tau", n)
    ddq = plant_acceleration(sc, q, dq, th[0] + th[1] * s, u, sc.simulation.smoothing_width)["ddq"]
    grid = [(j + 1) / subs for j in range(subs)]
    F = ca.integrator("plant", "rk", {"x": ca.vertcat(q, dq), "p": ca.vertcat(th, u), "t": s,
                                      "ode": th[1] * ca.vertcat(dq, ddq)}, 0.0, grid,
                      {"number_of_finite_elements": subs})
    xs = np.array(F(x0=x0, p=np.concatenate([[t0, h], tau]))["xf"])
    ts = t0 + h * np.array(grid)
    m = np.array(margin_function(design).map(subs)(ts[None, :], xs[:n], xs[n:]))
    j_step = int(np.argmax(~(m > 0).all(axis=0)))
    j = int(np.argmin(m[:, j_step]))
    return float(ts[j_step]), j, float(m[j, j_step])


def _c_loop(controller: StepLibrary, plant: _CFun, n, K, h, nq, ndq, res, delay, stop, X, TAU, MB, say):
    """Run the loop in C (templates/sampled_loop.c) with the compiled step and plant: (rc, k_end, outside)."""
    from ..core.ccompile import SHARED_FLAGS, compile_cached
    from ..emit.c import template
    built = compile_cached({"sampled_loop.c": template("sampled_loop.c")}, ["sampled_loop.c"],
                           "libsfs_loop.so", SHARED_FLAGS, on_build=say)
    lib = ctypes.CDLL(str(built.path))
    f = lib.sfs_loop
    f.restype = ctypes.c_int
    vp = ctypes.c_void_p
    f.argtypes = [vp, vp, vp, vp, vp, vp, vp, ctypes.c_int, ctypes.c_long, ctypes.c_double, vp, vp,
                  ctypes.c_double, ctypes.c_int, ctypes.c_int, vp, vp, vp, vp, vp]
    k_end, outside = ctypes.c_long(), ctypes.c_long()
    step_ptr = ctypes.cast(controller._step, vp)
    plant_ptr = ctypes.cast(plant._f, vp)
    nqa = None if nq is None else np.ascontiguousarray(nq)
    ndqa = None if ndq is None else np.ascontiguousarray(ndq)
    rc = f(step_ptr, controller._state_p, plant_ptr, ctypes.addressof(plant._arg), ctypes.addressof(plant._res),
           ctypes.addressof(plant._iw), ctypes.addressof(plant._w), n, K, h,
           None if nqa is None else nqa.ctypes.data, None if ndqa is None else ndqa.ctypes.data, res, int(delay),
           int(bool(stop)), X.ctypes.data, TAU.ctypes.data, MB.ctypes.data, ctypes.byref(k_end),
           ctypes.byref(outside))
    return rc, int(k_end.value), (None if outside.value < 0 else int(outside.value))

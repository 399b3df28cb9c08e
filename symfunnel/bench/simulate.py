"""Bench area `simulate`: the paper's closed loop with symfunnel (CVODES on compiled C) against scipy's solve_ivp
on a plain numpy right-hand side generated from the same graph (what a user would otherwise write), same run.

Ids: `simulate.realtime_factor` (simulated s per wall s of `simulate`, after the one-time, cached compilation;
baseline: solve_ivp's real-time factor) and `simulate.speedup_vs_scipy` (ratio = scipy wall time / symfunnel wall
time, same horizon, same tolerances).
"""

from __future__ import annotations

import os
import time
import types

import numpy as np

from ._result import result


def scipy_rhs(cl):
    """A numpy right-hand side f(t, x) -> xdot generated from the closed loop's SX graph by emit_python.

    It accepts x of shape (n_x,) or (n_x, k) (solve_ivp's `vectorized=True`, so the finite-difference Jacobian
    costs one batched call instead of n_x calls): the fair, fast version of what a user would write.
    """
    from ..emit.python import emit_python
    src = emit_python([cl.f.expand() if not cl.f.is_a("SXFunction") else cl.f], module_doc="closed loop RHS")
    mod = types.ModuleType("symfunnel_bench_rhs")
    exec(compile(src, "<symfunnel_bench_rhs>", "exec"), mod.__dict__)   # noqa: S102 - our own generated code
    fn = getattr(mod, cl.f.name())

    def rhs(t, x):
        x = np.asarray(x, dtype=float)
        out = np.asarray(fn(np.array([t]), x)[0], dtype=float)
        return out.reshape(x.shape)
    return rhs


def run_scipy(cl, t_final: float, method: str = "BDF"):
    """Integrate the closed loop with scipy.integrate.solve_ivp on the scenario's grid and tolerances."""
    from scipy.integrate import solve_ivp
    sim = cl.scenario.simulation
    rhs = scipy_rhs(cl)
    M = max(1, int(np.ceil(t_final / sim.dt - 1e-9)))
    grid = np.linspace(0.0, t_final, M + 1)
    t0 = time.perf_counter()
    sol = solve_ivp(rhs, (0.0, t_final), cl.x0, method=method, t_eval=grid, rtol=sim.rtol, atol=sim.atol,
                    vectorized=True)
    return time.perf_counter() - t0, sol


def run(progress=None, *, t_final: float | None = None, repeats: int = 3) -> list[dict]:
    """Measure both sides on the paper scenario (override the horizon with $SYMFUNNEL_BENCH_T_FINAL)."""
    from ..pipeline import Run
    from ..simulation import simulate
    say = progress or (lambda s: None)
    pr = Run.load("paper")
    sc, d = pr.scenario, pr.design
    tf = float(t_final or os.environ.get("SYMFUNNEL_BENCH_T_FINAL", sc.simulation.t_final))
    cl = pr.closed_loop
    say("simulate: first run (compiles the closed loop once, or loads it from the cache)")
    t0 = time.perf_counter()
    first = simulate(sc, d, t_final=tf, closed_loop=cl, progress=say)
    first_wall = time.perf_counter() - t0
    walls, sims, integ = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = simulate(sc, d, t_final=tf, closed_loop=cl)
        walls.append(time.perf_counter() - t0)
        sims.append(r.stats["sim_wall_time"])
        integ.append(r.stats["integrate_time"])
    wall = float(np.median(walls))
    say(f"simulate: symfunnel {wall:.3f} s for {tf:g} s; now scipy solve_ivp (BDF) on the numpy RHS")
    base_wall, sol = run_scipy(cl, tf)
    q_diff = None
    if sol.success and sol.y.shape[1] == r.t.size:
        q_diff = float(np.max(np.abs(sol.y[:cl.n].T - r.signals["q"])))
    info = {"t_final": tf, "status": r.status, "first_run_wall": first_wall,
            "compile_time": first.stats.get("compile_time"), "cache_hit_first_run": first.stats.get("cache_hit"),
            "code": r.stats.get("code"), "integration_wall": float(np.median(sims)),
            "scipy_success": bool(sol.success), "scipy_nfev": int(sol.nfev), "scipy_njev": int(sol.njev),
            "max_abs_q_diff_vs_scipy": q_diff, "steps": r.stats.get("steps")}
    return [
        result("simulate.realtime_factor", tf / wall, "s/s", "scipy solve_ivp BDF, numpy RHS", tf / base_wall,
               None, **info),
        result("simulate.speedup_vs_scipy", wall, "s", "scipy solve_ivp BDF, numpy RHS", base_wall,
               base_wall / wall, **info),
        result("simulate.overhead_ratio", wall / float(np.median(integ)), "x", "time inside the integrator calls",
               float(np.median(integ)), None, target=1.3, meets_target=bool(wall / float(np.median(integ)) <= 1.3),
               note="simulate() wall time with a built closed loop over the time spent in CVODES itself"),
    ]

"""Bench area `simulate`: the paper's closed loop with symfunnel (CVODES on compiled C) against scipy's solve_ivp
on a plain numpy right-hand side generated from the same graph (what a user would otherwise write), same run.

Ids: `simulate.realtime_factor` (simulated s per wall s of `simulate`, after the one-time, cached compilation;
baseline: solve_ivp's real-time factor; the CPU-time factor beside), `simulate.speedup_vs_scipy` (ratio = scipy
wall time / symfunnel wall time, same horizon, same tolerances), `simulate.cpu_per_run` (CPU seconds of one 20 s
paper run through the direct CVODES backend, `simulation.sundials`; baseline: the same runs through
casadi.integrator with CSparse, interleaved in the same process; the median over runs whose plant mass differs by
<= 1e-10 relative, because the number of CVODES steps of this loop moves by +-30 % with rounding-level changes, so
one run is one draw) and `simulate.cli_wall_s` (wall time of `symfunnel simulate paper` in a fresh process with a
warm compile cache and bytecode cache, CPU time beside; baseline: a process that only imports numpy and casadi).
`simulate.cpu_per_run_vs_previous` (the same perturbed 20 s paper runs in a fresh process, against the previous
path -- the chunks run by the Python loop, `simulation.crun` off -- in another, the two alternated) and
`simulate.arm7_cpu_per_sim_s` (CPU seconds per simulated second of arm7's 20 s run, the same two paths alternated).
`simulate.driver_kernels` (CPU per 20 s paper run with the CVODES driver's Newton LU along its update schedule and
its vector operations four doubles at a time, against the same runs with the column LU and SUNDIALS' own vector
operations, interleaved in one process: the same trajectories, so a paired ratio; each kernel's own ratio beside).
`simulate.cpu_per_run` and `simulate.realtime_factor` carry the previous path (the Python loop over the same C
driver, interleaved with the C loop in the same process) beside them: its CPU per run and the paired ratio.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
import types

import numpy as np

from ._result import result
from ._timing import env_set

#: Targets of issue 43 (issue 24's CPU per run was 0.07).
TARGET_CPU_PER_RUN = 0.045
TARGET_REALTIME = 400.0
TARGET_CLI_S = 1.0
#: relative changes of the plant's mass the CPU-per-run median runs over (rounding level: the same run)
PERTURBATIONS = (0.0, 1e-12, -1e-12, 2e-12, 1e-11, -1e-11, 3e-11, 1e-10, -1e-10)


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


def cpu_per_run(sc, d, cl, t_final: float, backend: str) -> dict:
    """CPU and wall seconds of each perturbed run with one CVODES backend (`PERTURBATIONS`), and their steps."""
    from ..simulation import simulate
    with env_set("SYMFUNNEL_CVODES", backend):
        simulate(sc, d, t_final=min(t_final, 0.5), closed_loop=cl)          # the backend's one-time set-up
        cpu, wall, steps = [], [], []
        for eps in PERTURBATIONS:
            c0, t0 = time.process_time(), time.perf_counter()
            r = simulate(sc, d, t_final=t_final, closed_loop=cl,
                         params={"plant.mass_scale": float(sc.plant.mass_scale) * (1 + eps)})
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - t0)
            steps.append(int(r.stats.get("steps") or 0))
            if r.stats.get("cvodes_backend") != backend:
                raise RuntimeError(f"the {backend} CVODES backend did not run: {r.stats.get('cvodes_backend')}")
    return {"cpu": cpu, "wall": wall, "steps": steps}


def alternated(sc, d, cl, t_final: float, module, flag: str, rounds: int = 2) -> dict:
    """CPU and wall seconds and CVODES steps per run with the module switch `module.<flag>` on (True) and off
    (False), the two interleaved over the perturbed runs in this process (the switch as it was afterwards), and
    their paired ratio (off / on)."""
    from ..simulation import simulate
    old = getattr(module, flag)
    cpu, wall, steps = ({True: [], False: []} for _ in range(3))
    try:
        for k in range(rounds):
            for eps in PERTURBATIONS:
                for on in ((True, False) if k % 2 else (False, True)):
                    setattr(module, flag, on)
                    c0, t0 = time.process_time(), time.perf_counter()
                    r = simulate(sc, d, t_final=t_final, closed_loop=cl,
                                 params={"plant.mass_scale": float(sc.plant.mass_scale) * (1 + eps)})
                    cpu[on].append(time.process_time() - c0)
                    wall[on].append(time.perf_counter() - t0)
                    steps[on].append(int(r.stats.get("steps") or 0))
    finally:
        setattr(module, flag, old)
    ratio = np.array(cpu[False]) / np.array(cpu[True])
    return {"cpu": cpu, "wall": wall, "steps": steps, "paired_ratio": float(np.median(ratio))}


def c_loop_vs_python(sc, d, cl, t_final: float, rounds: int = 2) -> dict:
    """CPU and wall seconds per run with the chunks in C (`simulation.crun`) and with the Python loop (the previous
    path), interleaved over the perturbed runs in this process; their paired ratio (Python / C)."""
    from ..simulation import crun
    r = alternated(sc, d, cl, t_final, crun, "RUN_IN_C", rounds)
    cpu, wall, steps = r["cpu"], r["wall"], r["steps"]
    return {"c": cpu[True], "python": cpu[False], "wall_c": wall[True], "wall_python": wall[False],
            "steps_c": steps[True], "steps_python": steps[False], "median_c": float(np.median(cpu[True])),
            "median_python": float(np.median(cpu[False])), "paired_ratio": r["paired_ratio"]}


class _Kernels:
    """The CVODES driver's two kernels (`sundials.SCHEDULED_LU`, `sundials.WIDE_VECTORS`) as one switch `on`."""

    @property
    def on(self) -> bool:
        from ..simulation import sundials
        return bool(sundials.SCHEDULED_LU and sundials.WIDE_VECTORS)

    @on.setter
    def on(self, value: bool) -> None:
        from ..simulation import sundials
        sundials.SCHEDULED_LU = sundials.WIDE_VECTORS = bool(value)


def driver_kernels(sc, d, cl, t_final: float, rounds: int = 2) -> dict:
    """CPU per run with both driver kernels and with neither (the previous path), interleaved over the perturbed
    runs; then each kernel alone against its previous form. Paired ratios (previous / this); the steps of both
    sides (the same: the kernels compute the same doubles)."""
    from ..simulation import sundials
    both = alternated(sc, d, cl, t_final, _Kernels(), "on", rounds)
    lu = alternated(sc, d, cl, t_final, sundials, "SCHEDULED_LU", rounds)
    vec = alternated(sc, d, cl, t_final, sundials, "WIDE_VECTORS", rounds)
    return {"this": both["cpu"][True], "previous": both["cpu"][False], "steps_this": both["steps"][True],
            "steps_previous": both["steps"][False], "median_this": float(np.median(both["cpu"][True])),
            "median_previous": float(np.median(both["cpu"][False])), "paired_ratio": both["paired_ratio"],
            "lu_paired_ratio": lu["paired_ratio"], "vectors_paired_ratio": vec["paired_ratio"]}


def samples_from_steps(sc, d, cl, t_final: float, rounds: int = 2) -> dict:
    """CPU seconds per run with the samples between output points taken from the kept steps and with a chunk
    integrated again instead (`runner.SAMPLE_FROM_STEPS`; the C loop runs only with it on), interleaved over the
    perturbed runs; their paired ratio."""
    from ..simulation import runner as runner_mod
    r = alternated(sc, d, cl, t_final, runner_mod, "SAMPLE_FROM_STEPS", rounds)
    return {"with": r["cpu"][True], "without": r["cpu"][False], "paired_ratio": r["paired_ratio"]}


def switch_pair(sc, d, cl, t_final: float, module, flag: str, on: str, off: str, rounds: int = 2) -> dict:
    """CPU seconds and CVODES steps per run with `module.<flag>` on (named `on`) and off (`off`, the previous path),
    interleaved over the perturbed runs (`alternated`); their paired ratio off / on."""
    r = alternated(sc, d, cl, t_final, module, flag, rounds)
    return {on: r["cpu"][True], off: r["cpu"][False], "steps_" + on: r["steps"][True],
            "steps_" + off: r["steps"][False], "paired_ratio": r["paired_ratio"]}


def samples_in_place(sc, d, cl, t_final: float, rounds: int = 2) -> dict:
    """The samples between output points written straight into their rows, and copied into time order after
    (`crun.SAMPLES_IN_PLACE`, the previous path): `switch_pair`'s "in_place" and "copied"."""
    from ..simulation import crun
    return switch_pair(sc, d, cl, t_final, crun, "SAMPLES_IN_PLACE", "in_place", "copied", rounds)


def fused_interpolation(sc, d, cl, t_final: float, rounds: int = 2) -> dict:
    """The samples from the kept steps interpolated in one pass into their rows, and through CVodeGetDky then
    permuted (`sundials.FUSED_DKY`, the previous path): `switch_pair`'s "fused" and "previous"."""
    from ..simulation import sundials
    return switch_pair(sc, d, cl, t_final, sundials, "FUSED_DKY", "fused", "previous", rounds)


def _switch_result(rid: str, r: dict, on: str, off: str, baseline: str, t_final: float) -> dict:
    """A `switch_pair` measurement as a bench result: medians, every run's CPU and steps, the paired ratio."""
    return result(rid, float(np.median(r[on])), "CPU s", baseline, float(np.median(r[off])), r["paired_ratio"],
                  **{"cpu_" + on: r[on], "cpu_" + off: r[off], "steps_" + on: r["steps_" + on],
                     "steps_" + off: r["steps_" + off]}, t_final=t_final, target=TARGET_CPU_PER_RUN,
                  note=f"median CPU per run; ratio: median of the paired ratios {off} / {on} (interleaved, same "
                       "variants)")


def _process_seconds(cmd: list[str], env: dict, repeats: int = 3) -> dict:
    """Median wall and CPU (the child's rusage) seconds of running `cmd`, after one warm-up run."""
    subprocess.run(cmd, env=env, capture_output=True, timeout=600)
    wall, cpu = [], []
    for _ in range(repeats):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        wall.append(time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append((r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime))
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr.strip()[-500:]}")
    return {"wall_s": float(np.median(wall)), "cpu_s": float(np.median(cpu)), "walls": wall, "cpus": cpu}


def cli_seconds() -> dict:
    """`symfunnel simulate paper` and a numpy + casadi import in fresh processes, each with a warm bytecode cache
    of its own (a temporary PYTHONPYCACHEPREFIX: also where $PYTHONDONTWRITEBYTECODE forbids writing one)."""
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-pyc-") as tmp:
        env = dict(os.environ, PYTHONPYCACHEPREFIX=tmp)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        cli = _process_seconds([sys.executable, "-m", "symfunnel", "simulate", "paper", "-q"], env)
        floor = _process_seconds([sys.executable, "-c", "import numpy, casadi"], env)
    return {"cli": cli, "floor": floor}


#: a fresh process's CPU per run: argv scenario, t_final, perturbations (JSON); the previous path with argv[4] == "1"
_CHILD = """
import json, sys, time
if sys.argv[4] == "1":
    import symfunnel.simulation.crun as crun
    crun.RUN_IN_C = False
from symfunnel.pipeline import Run
from symfunnel.simulation import simulate
pr = Run.load(sys.argv[1])
sc, d, cl, tf = pr.scenario, pr.design, pr.closed_loop, float(sys.argv[2])
simulate(sc, d, t_final=min(tf, 0.5), closed_loop=cl)
cpu, steps = [], []
for eps in json.loads(sys.argv[3]):
    c0 = time.process_time()
    r = simulate(sc, d, t_final=tf, closed_loop=cl, params={"plant.mass_scale": float(sc.plant.mass_scale) * (1 + eps)})
    cpu.append(time.process_time() - c0)
    steps.append(int(r.stats.get("steps") or 0))
print(json.dumps({"cpu": cpu, "steps": steps, "status": r.status}))
"""


def against_previous(scenario: str, t_final: float, perturbations=PERTURBATIONS, rounds: int = 2) -> dict:
    """CPU per run of this path and of the previous one (`_CHILD`: the chunks in the Python loop, crun.RUN_IN_C
    off), each in fresh processes alternated over `rounds`; their medians and paired ratios (previous / this)."""
    import json
    out = {"this": [], "previous": [], "steps_this": [], "steps_previous": []}
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    for k in range(rounds):
        for prev in ((False, True) if k % 2 == 0 else (True, False)):
            e = dict(env, SYMFUNNEL_KEEP_HEAP="1")
            proc = subprocess.run([sys.executable, "-c", _CHILD, scenario, repr(t_final),
                                   json.dumps(list(perturbations)), "1" if prev else "0"], env=e,
                                  capture_output=True, text=True, timeout=1200)
            if proc.returncode != 0:
                raise RuntimeError(f"the {scenario} runs failed: {proc.stderr.strip()[-500:]}")
            got = json.loads(proc.stdout.strip().splitlines()[-1])
            side = "previous" if prev else "this"
            out[side].extend(got["cpu"])
            out["steps_" + side].extend(got["steps"])
    ratio = np.array(out["previous"]) / np.array(out["this"])
    return dict(out, median_this=float(np.median(out["this"])), median_previous=float(np.median(out["previous"])),
                paired_ratio=float(np.median(ratio)))


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
    say("simulate: CPU per run, the chunks in C and in the Python loop, interleaved")
    with env_set("SYMFUNNEL_CVODES", "direct"):
        loops = c_loop_vs_python(sc, d, cl, tf)
    say("simulate: CPU per run, direct CVODES backend and casadi.integrator")
    direct, casadi_ = cpu_per_run(sc, d, cl, tf, "direct"), cpu_per_run(sc, d, cl, tf, "casadi")
    cpu_d, cpu_c = loops["median_c"], float(np.median(casadi_["cpu"]))
    say("simulate: samples between output points from the kept steps, and from a chunk integrated again")
    with env_set("SYMFUNNEL_CVODES", "direct"):
        sfs = samples_from_steps(sc, d, cl, tf)
    say("simulate: the samples between output points written in place, and copied into time order, interleaved")
    with env_set("SYMFUNNEL_CVODES", "direct"):
        sip = samples_in_place(sc, d, cl, tf)
    say("simulate: the samples interpolated in one pass, and through CVodeGetDky, interleaved")
    with env_set("SYMFUNNEL_CVODES", "direct"):
        fdk = fused_interpolation(sc, d, cl, tf)
    say("simulate: the driver's LU schedule and wide vector operations, and their previous forms, interleaved")
    with env_set("SYMFUNNEL_CVODES", "direct"):
        kern = driver_kernels(sc, d, cl, tf)
    say("simulate: this path and the previous one in fresh processes, alternated (paper, then arm7 20 s)")
    prev = against_previous("paper", tf)
    arm7_tf = float(os.environ.get("SYMFUNNEL_BENCH_ARM7_T_FINAL", 20.0))
    arm7 = against_previous("arm7", arm7_tf, perturbations=(0.0, 1e-11, -1e-11))
    say("simulate: `symfunnel simulate paper` in a fresh process (warm caches)")
    cli = cli_seconds()
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
    cpu_info = {"t_final": tf, "runs": len(PERTURBATIONS), "mass_scale_perturbations": list(PERTURBATIONS),
                "cpu_direct": direct["cpu"], "cpu_casadi": casadi_["cpu"], "wall_direct": direct["wall"],
                "wall_casadi": casadi_["wall"], "steps_direct": direct["steps"], "steps_casadi": casadi_["steps"],
                "median_steps_direct": float(np.median(direct["steps"])),
                "median_steps_casadi": float(np.median(casadi_["steps"])), "clock": "process CPU time"}
    return [
        result("simulate.realtime_factor", tf / wall, "s/s", "scipy solve_ivp BDF, numpy RHS", tf / base_wall,
               None, realtime_factor_cpu=tf / cpu_d, target=TARGET_REALTIME,
               previous_path="the chunks in the Python loop (same process, interleaved)",
               previous_realtime_factor_cpu=tf / loops["median_python"], paired_ratio_vs_previous=loops["paired_ratio"],
               meets_target=bool(tf / wall >= TARGET_REALTIME), meets_target_cpu=bool(tf / cpu_d >= TARGET_REALTIME),
               note="wall clock (a loaded machine stretches it); realtime_factor_cpu: simulated s per CPU s", **info),
        result("simulate.cpu_per_run", cpu_d, "CPU s",
               "the previous path: the chunks in the Python loop, same runs interleaved", loops["median_python"],
               loops["paired_ratio"], target=TARGET_CPU_PER_RUN, meets_target=bool(cpu_d <= TARGET_CPU_PER_RUN),
               cpu_c_loop=loops["c"], cpu_python_loop=loops["python"], steps_c_loop=loops["steps_c"],
               steps_python_loop=loops["steps_python"], casadi_integrator_cpu=cpu_c,
               ratio_vs_casadi_integrator=cpu_c / cpu_d,
               note="ratio: median of the paired ratios, Python loop / C loop (same perturbation, same round)",
               **cpu_info),
        result("simulate.cpu_per_run_vs_previous", prev["median_this"], "CPU s",
               "the previous path (the chunks in the Python loop), fresh processes alternated",
               prev["median_previous"], prev["paired_ratio"], t_final=tf, cpu_this=prev["this"],
               cpu_previous=prev["previous"], steps_this=prev["steps_this"], steps_previous=prev["steps_previous"],
               realtime_factor_cpu=tf / prev["median_this"], target=TARGET_CPU_PER_RUN,
               note="ratio: median of the paired ratios (same variant, same round)"),
        result("simulate.driver_kernels", kern["median_this"], "CPU s",
               "the column LU and SUNDIALS' own vector operations, same runs interleaved", kern["median_previous"],
               kern["paired_ratio"], t_final=tf, cpu_this=kern["this"], cpu_previous=kern["previous"],
               steps_this=kern["steps_this"], steps_previous=kern["steps_previous"],
               lu_paired_ratio=kern["lu_paired_ratio"], vectors_paired_ratio=kern["vectors_paired_ratio"],
               realtime_factor_cpu=tf / kern["median_this"], target=TARGET_CPU_PER_RUN,
               meets_target=bool(kern["median_this"] <= TARGET_CPU_PER_RUN),
               note="ratio: median of the paired ratios (same perturbation, same round); lu_ and vectors_: each "
                    "kernel alone against its previous form"),
        result("simulate.arm7_cpu_per_sim_s", arm7["median_this"] / arm7_tf, "CPU s per simulated s",
               "the previous path, fresh processes alternated", arm7["median_previous"] / arm7_tf,
               arm7["paired_ratio"], t_final=arm7_tf, cpu_this=arm7["this"], cpu_previous=arm7["previous"],
               steps_this=arm7["steps_this"], steps_previous=arm7["steps_previous"],
               paper_cpu_per_sim_s=prev["median_this"] / tf),
        result("simulate.cli_wall_s", cli["cli"]["wall_s"], "s", "a process importing numpy and casadi only",
               cli["floor"]["wall_s"], cli["floor"]["wall_s"] / cli["cli"]["wall_s"], cpu_s=cli["cli"]["cpu_s"],
               baseline_cpu_s=cli["floor"]["cpu_s"], target=TARGET_CLI_S,
               meets_target=bool(cli["cli"]["wall_s"] <= TARGET_CLI_S),
               meets_target_cpu=bool(cli["cli"]["cpu_s"] <= TARGET_CLI_S), walls=cli["cli"]["walls"],
               cpus=cli["cli"]["cpus"], command="symfunnel simulate paper -q"),
        result("simulate.speedup_vs_scipy", wall, "s", "scipy solve_ivp BDF, numpy RHS", base_wall,
               base_wall / wall, **info),
        result("simulate.samples_from_steps", float(np.median(sfs["with"])), "CPU s",
               "the same runs integrating a chunk again for its samples", float(np.median(sfs["without"])),
               sfs["paired_ratio"], cpu_with=sfs["with"], cpu_without=sfs["without"], t_final=tf,
               note="median CPU per run; ratio: median of the paired ratios (interleaved, same variants)"),
        _switch_result("simulate.samples_in_place", sip, "in_place", "copied", "the same runs with the samples "
                       "copied into time order after sampling (crun.SAMPLES_IN_PLACE off)", tf),
        _switch_result("simulate.fused_interpolation", fdk, "fused", "previous", "the same runs interpolating each "
                       "sample through CVodeGetDky, then permuted (sundials.FUSED_DKY off)", tf),
        result("simulate.overhead_ratio", wall / float(np.median(integ)), "x", "time inside the integrator calls",
               float(np.median(integ)), None, target=1.3, meets_target=bool(wall / float(np.median(integ)) <= 1.3),
               note="simulate() wall time with a built closed loop over the time spent in CVODES itself"),
    ]

"""Bench area `implementation`: the deployed controller (generated C step) in the sampled-data loop, same run.

Ids: `implementation.sampled_realtime_factor` (the 20 s paper run at 10 kHz around the compiled C step, simulated
s per wall s; baseline: the same loop with the step evaluated by CasADi's VM from Python, over the first second),
`codegen.c_step_ns` (one `Pstep` call timed in C by bench.c on the thread's CPU clock, the generated pair built
with `_timing.bench_cflags`; baseline: the same step with the controller and step core unrolled as one SX function
each, built and timed the same way in the same run; the strict -O2 build of both and the step on CasADi's VM from
Python beside, and the previous path -- the same pair with the reservoir's W x as loops over arrays instead of
straight-line code -- built and timed the same way in the same run, `w_loops_ns`; and the previous tanh, three
divisions per lane (templates/sf_tanh3div.h) in place of the one-division one, `tanh3div_ns`; and the previous
W x, the scalar straight-line rows instead of blocks of 4 rows in fused multiply-adds, `wx_scalar_ns`) and
`implementation.rate_search_s` (wall time of `symfunnel rate` on the paper; baseline: one 20 s sampled run at the
rate it finds).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ._result import result

#: Targets of the issues (one Pstep: 250 ns CPU time since issue 43, 400 before; the goal the upper end of that
#: issue's compute floor, ~120-230 ns).
TARGET_REALTIME = 20.0
TARGET_STEP_NS = 250.0
GOAL_STEP_NS = 230.0
TARGET_RATE_S = 60.0


def _generated_with(design, rate: float, **switches) -> dict:
    """The generated C pair with `family.esn.ESN`'s class switches set as given, and set back afterwards."""
    from ..emit import step
    from ..emit.files import generate
    from ..family.esn import ESN
    old = {k: getattr(ESN, k) for k in switches}
    step._RATE_FREE.clear()
    try:
        for k, v in switches.items():
            setattr(ESN, k, v)
        return generate(design, "c", rate_hz=rate)
    finally:
        for k, v in old.items():
            setattr(ESN, k, v)
        step._RATE_FREE.clear()


def w_as_loops(design, rate: float) -> dict:
    """The generated C pair with the reservoir's W x as loops over arrays (the previous path), whatever its size."""
    return _generated_with(design, rate, UNROLL_W_MAX=0)


def wx_scalar(design, rate: float) -> dict:
    """The generated C pair with the reservoir's W x as the scalar straight-line rows only (the previous path), without
    the fused blocks of 4 rows (`family.esn._wx_blocks`)."""
    return _generated_with(design, rate, VECTOR_WX=False)


def tanh_as_3div(files: dict) -> dict:
    """The generated C pair with the previous vectorised tanh (three divisions per lane) in place of the current one."""
    import re
    from ..emit.c import template
    pattern = re.compile(re.escape(template("sf_tanh.h")).replace(re.escape("@P@"), r"(\w*)"))
    old = template("sf_tanh3div.h")
    out, hits = dict(files), 0
    for name, text in files.items():
        if name.endswith(".c"):
            out[name], n = pattern.subn(lambda m: old.replace("@P@", m.group(1)), text)
            hits += n
    if hits != 1:
        raise RuntimeError(f"the vectorised tanh was found {hits} times in the generated C, expected once")
    return out


class VMStep:
    """The step function on CasADi's VM, with the compiled step's interface (buffers and raw())."""

    def __init__(self, design, rate_hz: float, tau_max=None):
        from ..emit.step import step_function, step_initial
        self.f = step_function(design, rate_hz, tau_max)
        self.x0, self.w0 = step_initial(design)
        n = design.n
        self.q, self.dq, self.tau = np.zeros(n), np.zeros(n), np.zeros(n)
        self.init()

    def init(self) -> int:
        self.x, self.w = self.x0.copy(), self.w0.copy()
        return 0

    def raw(self):
        def step(_state, t, *_):
            tau, x, w, m, _qd = self.f(t, self.q, self.dq, self.x, self.w)
            self.tau[:] = np.asarray(tau).ravel()
            self.x, self.w = x, w
            return 0 if np.all(np.asarray(m) > 0) else 1
        return step, None, ()


def run(progress) -> list[dict]:
    """The three results above, for the paper scenario."""
    from ..emit.files import generate
    from ..emit.step import step_function
    from ..design import derive
    from ..deployed.rate import min_rate
    from ..deployed.loop import simulate_sampled
    from ..scenario import load_scenario
    sc = load_scenario("paper")
    design = derive(sc)
    rate = 10000.0
    progress("implementation: 20 s sampled run at 10 kHz (compiled C step)")
    simulate_sampled(sc, rate_hz=rate, t_final=0.01, design=design)          # compile (cached), load
    res = simulate_sampled(sc, rate_hz=rate, design=design)
    rtf = float(res.t[-1] / res.wall_time)
    progress("implementation: the same loop with the step on CasADi's VM (first second)")
    vm = simulate_sampled(sc, rate_hz=rate, t_final=1.0, design=design, controller=VMStep(design, rate))
    rtf_vm = float(vm.t[-1] / vm.wall_time)
    common = {"scenario": sc.name, "rate_hz": rate, "status": res.status}
    out = [result("implementation.sampled_realtime_factor", rtf, "x real time",
                  "same loop, step on CasADi's VM from Python (1 s)", rtf_vm, rtf / rtf_vm,
                  target=TARGET_REALTIME, meets_target=bool(rtf >= TARGET_REALTIME), samples=int(res.tau.shape[0]),
                  **common)]

    progress("codegen: one Pstep call, timed in C (loops and unrolled, fast and strict flags)")
    from ._timing import bench_cflags, best, run_c_bench
    from ..emit.c import STRICT_CFLAGS
    files = generate(design, "c", rate_hz=rate)
    unrolled = generate(design, "c", rate_hz=rate, structured=False)
    w_loops = w_as_loops(design, rate)
    fast, strict = bench_cflags(), tuple(STRICT_CFLAGS)
    t = {(k, fl): run_c_bench(f, fl, 100000, on_build=progress)["step_ns"]
         for k, f in (("loops", files), ("unrolled", unrolled)) for fl in (fast, strict)}
    tanh3 = tanh_as_3div(files)
    wx_rows = wx_scalar(design, rate)
    w_ns, tanh_ns, wx_ns = [], [], []          # the previous paths and this one, interleaved
    for _ in range(3):
        w_ns.append((run_c_bench(w_loops, fast, 100000)["step_ns"], run_c_bench(files, fast, 100000)["step_ns"]))
        tanh_ns.append((run_c_bench(tanh3, fast, 100000)["step_ns"], run_c_bench(files, fast, 100000)["step_ns"]))
        wx_ns.append((run_c_bench(wx_rows, fast, 100000)["step_ns"], run_c_bench(files, fast, 100000)["step_ns"]))
    step_ns, base_ns = t[("loops", fast)], t[("unrolled", fast)]
    f = step_function(design, rate)
    vm_step = VMStep(design, rate)
    x0, w0 = vm_step.x0, vm_step.w0
    args = (0.1, np.asarray(sc.q0, float), np.asarray(sc.dq0, float), x0, w0)
    vm = best(lambda: f(*args), 0.2, 3)
    out.append(result("codegen.c_step_ns", step_ns, "ns", "the same step unrolled (one SX function), same flags",
                      base_ns, base_ns / step_ns, target_ns=TARGET_STEP_NS, goal_ns=GOAL_STEP_NS,
                      meets_target=bool(step_ns <= TARGET_STEP_NS), clock="CPU time of the thread (bench.c)",
                      flags=" ".join(fast), strict_flags=" ".join(strict), strict_ns=t[("loops", strict)],
                      strict_unrolled_ns=t[("unrolled", strict)], casadi_vm_ns=vm["cpu_ns"],
                      casadi_vm_wall_ns=vm["wall_ns"], lines=files["symfunnel_controller.c"].count("\n"),
                      unrolled_lines=unrolled["symfunnel_controller.c"].count("\n"), scenario=sc.name,
                      w_loops_ns=min(a for a, _ in w_ns), w_straight_ns=min(b for _, b in w_ns),
                      w_paired_ratio=float(np.median([a / b for a, b in w_ns])),
                      w_note="the previous path: W x as loops over arrays (ESN.UNROLL_W_MAX = 0), interleaved",
                      tanh3div_ns=min(a for a, _ in tanh_ns), tanh1div_ns=min(b for _, b in tanh_ns),
                      tanh_paired_ratio=float(np.median([a / b for a, b in tanh_ns])),
                      tanh_note="the previous tanh: three divisions per lane (templates/sf_tanh3div.h), interleaved",
                      wx_scalar_ns=min(a for a, _ in wx_ns), wx_blocks_ns=min(b for _, b in wx_ns),
                      wx_paired_ratio=float(np.median([a / b for a, b in wx_ns])),
                      wx_note="the previous W x: the scalar straight-line rows (ESN.VECTOR_WX = False) instead of "
                              "blocks of 4 rows in fused multiply-adds, interleaved",
                      load_average_1min=os.getloadavg()[0]))

    progress("implementation: symfunnel rate on the paper")
    t0 = time.perf_counter()
    r = min_rate(sc, design=design)
    rate_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    simulate_sampled(sc, rate_hz=r["min_rate_hz"], design=design)
    one = time.perf_counter() - t0
    out.append(result("implementation.rate_search_s", rate_s, "s", "one 20 s sampled run at the minimum rate", one,
                      one / rate_s, target_s=TARGET_RATE_S, meets_target=bool(rate_s <= TARGET_RATE_S),
                      min_rate_hz=r["min_rate_hz"], runs=len(r["tried"]), scenario=sc.name))
    return out

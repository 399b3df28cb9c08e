"""Bench area `implementation`: the deployed controller (generated C step) in the sampled-data loop, same run.

Ids: `implementation.sampled_realtime_factor` (the 20 s paper run at 10 kHz around the compiled C step, simulated
s per wall s; baseline: the same loop with the step evaluated by CasADi's VM from Python, over the first second),
`codegen.c_step_ns` (one `Pstep` call timed in C by bench.c; baseline: the same step function on CasADi's VM from
Python) and `implementation.rate_search_s` (wall time of `symfunnel rate` on the paper; baseline: one 20 s
sampled run at the rate it finds).
"""

from __future__ import annotations

import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from ._result import result

#: Targets of the issue.
TARGET_REALTIME = 20.0
TARGET_STEP_NS = 2000.0
TARGET_RATE_S = 60.0


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
    from ..core.ccompile import compile_cached
    from ..emit.c import STRICT_CFLAGS
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

    progress("codegen: one Pstep call, timed in C")
    files = generate(design, "c", rate_hz=rate)
    base = "symfunnel_controller"
    src = {k: files[k] for k in (base + ".c", base + ".h", "bench.c")}
    exe = compile_cached(src, ["bench.c", base + ".c"], "symfunnel_bench", STRICT_CFLAGS, on_build=progress).path
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-") as tmp:
        p = Path(tmp) / "trajectory.txt"
        p.write_text(files["trajectory.txt"], encoding="utf-8")
        proc = subprocess.run([str(exe), str(p), "100000"], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"bench program failed: {proc.stderr.strip()}")
    words = proc.stdout.split()
    step_ns = float(words[words.index("step_ns_per_call") + 1])
    f = step_function(design, rate)
    vm_step = VMStep(design, rate)
    x0, w0 = vm_step.x0, vm_step.w0
    args = (0.1, np.asarray(sc.q0, float), np.asarray(sc.dq0, float), x0, w0)
    f(*args)
    reps = 2000
    t0 = time.perf_counter()
    for _ in range(reps):
        f(*args)
    vm_ns = (time.perf_counter() - t0) / reps * 1e9
    out.append(result("codegen.c_step_ns", step_ns, "ns", "step function on CasADi's VM from Python", vm_ns,
                      vm_ns / step_ns, target_ns=TARGET_STEP_NS, meets_target=bool(step_ns <= TARGET_STEP_NS),
                      scenario=sc.name))

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

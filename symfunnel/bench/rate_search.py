"""Bench area `rate_search`: what the minimum-rate search (`symfunnel rate`) spends compiling the deployed step.

Id: `rate_search.cpu_s` -- CPU seconds (this process plus the compilers it ran) of `deployed.rate.min_rate` on the
paper scenario from an empty compile cache, with the search build of the step (`deployed.rate_step`: compiled once,
the period's weights set per rate); baseline: the same search building the shipped step at every rate tried (the
previous path), from its own empty cache. The two alternate ROUNDS times in one process; value and baseline are the
medians, ratio the median of the paired ratios; the compiler runs of each and whether their results agree beside.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np

from ._result import result

ROUNDS = 3


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def cold_search(scenario, design, *, search_build: bool, t_final: float | None = None) -> tuple[float, list, dict]:
    """(CPU seconds, the compiler's command lines, result) of one min_rate from an empty compile cache (and no
    search build of this process reused)."""
    from ..core import ccompile
    from ..deployed import rate_step
    from ..deployed.rate import min_rate
    runs = []
    real = ccompile.run_compiler

    def counted(cmd, **kw):
        runs.append(cmd)
        return real(cmd, **kw)
    old_env, old_built = os.environ.get("SYMFUNNEL_CACHE"), list(rate_step._BUILT)
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-rate-") as tmp:
        os.environ["SYMFUNNEL_CACHE"] = tmp
        rate_step._BUILT.clear()
        ccompile.run_compiler = counted
        try:
            t0 = _cpu()
            r = min_rate(scenario, design, t_final=t_final, search_build=search_build)
            cpu = _cpu() - t0
        finally:
            ccompile.run_compiler = real
            rate_step._BUILT[:] = old_built
            if old_env is None:
                os.environ.pop("SYMFUNNEL_CACHE", None)
            else:
                os.environ["SYMFUNNEL_CACHE"] = old_env
    return cpu, runs, r


def run(progress) -> list[dict]:
    """The result above."""
    from ..design import derive
    from ..scenario import load_scenario
    sc = load_scenario("paper")
    design = derive(sc)
    progress("rate_search: min_rate from an empty cache, search build and per-rate build interleaved")
    new, old = [], []
    for _ in range(ROUNDS):
        old.append(cold_search(sc, design, search_build=False))
        new.append(cold_search(sc, design, search_build=True))
    same = all(a[2] == b[2] for a, b in zip(old, new))
    cpu_new, cpu_old = float(np.median([c for c, _, _ in new])), float(np.median([c for c, _, _ in old]))
    return [result("rate_search.cpu_s", cpu_new, "s CPU",
                   "the same search building the shipped step at every rate (the previous path), interleaved",
                   cpu_old, float(np.median([o[0] / n[0] for o, n in zip(old, new)])),
                   compiler_runs=len(new[0][1]), baseline_compiler_runs=len(old[0][1]),
                   rates_tried=len(new[0][2]["tried"]),
                   min_rate_hz=new[0][2]["min_rate_hz"], same_result=bool(same), rounds=ROUNDS, scenario=sc.name,
                   clock="CPU time of the process and its compilers (os.times)")]

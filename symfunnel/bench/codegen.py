"""Bench area `codegen`: one controller call in compiled C (timed in C, thread CPU time), via CasADi's VM from Python,
and in the generated numpy-only Python, side by side in one run, for the paper's controller (N = 50 reservoir units);
and the compile time of the generated C for an N = 500 reservoir beside the unrolled file's.

Ids: `codegen.c_controller_ns` (baseline: CasADi's VM from Python; the unrolled SX controller compiled with the
same flags in `unrolled_c_ns`), `codegen.python_controller_ns`, `codegen.python_batch_ns`, `codegen.controller_ops`,
`codegen.c_compile_n500_s` (CPU seconds of the compiler for the N = 500 paper's generated pair, strict flags;
baseline: the same file with the controller and step unrolled, stopped at the target's 60 s, so a lower bound;
$SYMFUNNEL_BENCH_LARGE_N sets another N), `codegen.rate_search_generate_s` (CPU seconds of generating the C pair at
a rate search's seven rates, its rate-free part reused; baseline: each rate generated afresh).
"""

from __future__ import annotations

import copy
import os

from ._result import result

#: Target of the issue: at most this many ns per compiled-C controller call for the paper's controller.
TARGET_NS = 5000.0
#: Target of issue 24: the N = 500 reservoir's generated C compiles in at most this many seconds.
TARGET_COMPILE_S = 60.0


def large_reservoir(size: int = 500):
    """The paper scenario with an N = `size` reservoir."""
    from pathlib import Path

    from ..scenario import from_dict, load_scenario
    sc = load_scenario("paper")
    raw = copy.deepcopy(sc.raw)
    raw["esn"]["size"] = size
    return from_dict(raw, file=sc.file, base_dir=Path(sc.file).parent, default_name=f"paper_n{size}")


#: rates a rate search visits (bisection between 125 Hz and 1 kHz), each generated once per round
RATE_SEARCH_RATES = (1000.0, 500.0, 250.0, 125.0, 750.0, 375.0, 625.0)


def rate_search_generation(design, rounds: int = 3) -> tuple[float, float]:
    """(reused, fresh): median CPU seconds of generating the C pair at every rate of RATE_SEARCH_RATES, with the
    rate-free part reused across the rates (as a rate search does) and with it generated afresh at each rate;
    the two interleaved in every round."""
    import statistics
    import time

    from ..emit import step
    from ..emit.files import generate
    reused, fresh = [], []
    for _ in range(rounds):
        step._RATE_FREE.clear()
        t0 = time.process_time()
        for r in RATE_SEARCH_RATES:
            generate(design, "c", rate_hz=r)
        reused.append(time.process_time() - t0)
        t0 = time.process_time()
        for r in RATE_SEARCH_RATES:
            step._RATE_FREE.clear()
            generate(design, "c", rate_hz=r)
        fresh.append(time.process_time() - t0)
    return statistics.median(reused), statistics.median(fresh)


def run(progress) -> list[dict]:
    """Results codegen.c_controller_ns, .python_controller_ns, .python_batch_ns, .controller_ops,
    .rate_search_generate_s and .c_compile_n500_s."""
    from ._timing import bench_cflags, compile_seconds, run_c_bench, time_controller
    from ..design import derive
    from ..emit.c import STRICT_CFLAGS
    from ..emit.files import generate
    from ..pipeline import Run
    run = Run.load("paper")
    sc, design = run.scenario, run.design
    progress("codegen: generating C and Python")
    c_files, py_files = run.code("c"), run.code("python")
    progress("codegen: timing the controller (C in C, CasADi VM, generated Python)")
    tm = time_controller(design, c_files, py_files)
    unrolled = generate(design, "c", trajectory=run.code_trajectory, structured=False)
    un = run_c_bench(unrolled, bench_cflags(), 200000)
    c, vm, py = tm["c_ns"], tm["casadi_vm_ns"], tm["python_ns"]
    n_esn = design.sym["x_esn"].numel()
    common = {"scenario": sc.name, "esn_units": n_esn, "operations": tm["operations"],
              "casadi_vm_numpy_ns": tm["casadi_vm_numpy_ns"], "clock": "CPU time (thread in C, process in Python)"}
    out = [
        result("codegen.c_controller_ns", c, "ns", "casadi VM from Python (DM arguments)", vm, vm / c,
               target_ns=TARGET_NS, meets_target=bool(c <= TARGET_NS), python_ns=py, flags=tm["c_flags"],
               unrolled_c_ns=un["controller_ns"], ratio_vs_unrolled_c=un["controller_ns"] / c,
               casadi_vm_wall_ns=tm["casadi_vm_wall_ns"], ns_per_operation=c / tm["operations"], **common),
        result("codegen.python_controller_ns", py, "ns", "casadi VM from Python (DM arguments)", vm, vm / py,
               python_wall_ns=tm["python_wall_ns"], **common),
        result("codegen.python_batch_ns", tm["python_batch_ns"], "ns/point", "casadi map from Python (per point)",
               tm["casadi_map_ns"], tm["casadi_map_ns"] / tm["python_batch_ns"], batch=1000, **common),
        result("codegen.controller_ops", tm["operations"], "ops", None, None, None,
               note="tape operations of the controller after CSE (count_ops)", **common),
    ]
    progress("codegen: generating the C pair at the rates of a rate search, the rate-free part reused and fresh")
    reused, fresh = rate_search_generation(design)
    out.append(result("codegen.rate_search_generate_s", reused, "CPU s",
                      "the same rates, each generated afresh (the rate-free part not reused)", fresh,
                      fresh / max(reused, 1e-9), rates=list(RATE_SEARCH_RATES), **common))
    N = int(os.environ.get("SYMFUNNEL_BENCH_LARGE_N", 500))
    progress(f"codegen: generating C for an N = {N} reservoir (loops, and unrolled as the baseline)")
    big = derive(large_reservoir(N))
    name, hdr = "symfunnel_controller.c", "symfunnel_controller.h"
    fast_files, slow_files = generate(big, "c"), generate(big, "c", structured=False)
    fast, slow = fast_files[name], slow_files[name]
    progress("codegen: compiling both (the unrolled one is stopped at 60 s)")
    a = compile_seconds({name: fast, hdr: fast_files[hdr]}, name, tuple(STRICT_CFLAGS), timeout=TARGET_COMPILE_S * 5)
    b = compile_seconds({name: slow, hdr: slow_files[hdr]}, name, tuple(STRICT_CFLAGS), timeout=TARGET_COMPILE_S)
    # a compile stopped at the limit is killed with its cc1, whose CPU time then never reaches our rusage: its wall
    # time (at least the limit) is the baseline's lower bound
    base = b["cpu_s"] if b["finished"] else max(b["wall_s"], TARGET_COMPILE_S)
    out.append(result("codegen.c_compile_n500_s", a["cpu_s"], "CPU s",
                      "the same file unrolled (stopped at 60 s wall: a lower bound)" if not b["finished"] else
                      "the same file unrolled", base, base / max(a["cpu_s"], 1e-9),
                      target_s=TARGET_COMPILE_S, meets_target=bool(a["finished"] and a["cpu_s"] <= TARGET_COMPILE_S),
                      wall_s=a["wall_s"], lines=fast.count("\n"), baseline_lines=slow.count("\n"),
                      baseline_finished=b["finished"], baseline_wall_s=b["wall_s"], esn_units=N,
                      flags=" ".join(STRICT_CFLAGS)))
    return out

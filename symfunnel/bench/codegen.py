"""Bench area `codegen`: one controller call in compiled C (timed in C), via CasADi's VM from Python, and in the
generated numpy-only Python, side by side in one run, for the paper's controller (N = 50 reservoir units)."""

from __future__ import annotations

from ._result import result

#: Target of the issue: at most this many ns per compiled-C controller call for the paper's controller.
TARGET_NS = 5000.0


def run(progress) -> list[dict]:
    """Results codegen.c_controller_ns, .python_controller_ns, .python_batch_ns and .controller_ops."""
    from ._timing import time_controller
    from ..pipeline import Run
    run = Run.load("paper")
    sc, design = run.scenario, run.design
    progress("codegen: generating C and Python")
    c_files, py_files = run.code("c"), run.code("python")
    progress("codegen: timing the controller (C in C, CasADi VM, generated Python)")
    tm = time_controller(design, c_files, py_files)
    c, vm, py = tm["c_ns"], tm["casadi_vm_ns"], tm["python_ns"]
    n_esn = design.sym["x_esn"].numel()
    common = {"scenario": sc.name, "esn_units": n_esn, "operations": tm["operations"],
              "casadi_vm_numpy_ns": tm["casadi_vm_numpy_ns"]}
    return [
        result("codegen.c_controller_ns", c, "ns", "casadi VM from Python (DM arguments)", vm, vm / c,
               target_ns=TARGET_NS, meets_target=bool(c <= TARGET_NS), python_ns=py,
               ns_per_operation=c / tm["operations"], **common),
        result("codegen.python_controller_ns", py, "ns", "casadi VM from Python (DM arguments)", vm, vm / py, **common),
        result("codegen.python_batch_ns", tm["python_batch_ns"], "ns/point", "casadi map from Python (per point)",
               tm["casadi_map_ns"], tm["casadi_map_ns"] / tm["python_batch_ns"], batch=1000, **common),
        result("codegen.controller_ops", tm["operations"], "ops", None, None, None,
               note="tape operations of the controller after CSE (count_ops)", **common),
    ]

"""Bench timing of the generated controller: compiled C (timed in C by bench.c), CasADi's VM from Python and the
generated numpy-only Python, side by side (code generation itself never times anything)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design


def best_ns(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 5) -> float:
    """Best-of-`repeats` wall time per call of fn() in ns, each repeat running at least min_time / repeats."""
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time / repeats or n >= 1 << 22:
            break
        n *= 2
    best = dt / n
    for _ in range(repeats - 1):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e9


def time_controller(design: Design, c_files: dict[str, str], py_files: dict[str, str],
                    *, min_time: float = 0.2, c_iterations: int = 200000, batch: int = 1000) -> dict:
    """ns per controller call: compiled C (timed in C by bench.c), CasADi's VM from Python, generated Python.

    Returns {"c_ns", "casadi_vm_ns" (Function call with DM arguments), "casadi_vm_numpy_ns" (numpy arguments,
    conversion included), "python_ns", "python_batch_ns" (per point, one call over `batch` points),
    "casadi_map_ns" (per point, casadi map over the same batch), "operations"}.
    """
    import subprocess

    from ..emit import check
    from ..core.ccompile import compile_cached
    from ..emit.c import BASENAME, STRICT_CFLAGS
    from ..emit.contract import trajectory_inputs
    from ..sx.tape import count_ops
    ctl = design.controller()
    out = {"operations": count_ops(ctl)["operations"]}

    src = {k: c_files[k] for k in (BASENAME + ".c", BASENAME + ".h", "bench.c")}
    exe = compile_cached(src, ["bench.c", BASENAME + ".c"], "symfunnel_bench", STRICT_CFLAGS).path
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-") as tmp:
        p = Path(tmp) / "trajectory.txt"
        p.write_text(c_files["trajectory.txt"], encoding="utf-8")
        proc = subprocess.run([str(exe), str(p), str(c_iterations)], capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"bench program failed: {proc.stderr.strip()}")
    out["c_ns"] = float(proc.stdout.split()[1])

    inp = trajectory_inputs(design, c_files["trajectory.txt"])
    names = [ctl.name_in(i) for i in range(ctl.n_in())]
    one = [inp[n][:, :, 1] for n in names]
    import casadi as ca
    one_dm = [ca.DM(a) for a in one]
    out["casadi_vm_ns"] = best_ns(lambda: ctl(*one_dm), min_time)          # arguments already DM
    out["casadi_vm_numpy_ns"] = best_ns(lambda: ctl(*one), min_time)       # incl. numpy -> DM conversion

    with tempfile.TemporaryDirectory(prefix="symfunnel-py-") as tmp:
        path = Path(tmp) / (BASENAME + ".py")
        path.write_text(py_files[BASENAME + ".py"], encoding="utf-8")
        mod = check.load_python_module(path)
    out["python_ns"] = best_ns(lambda: mod.controller(*one), min_time)

    pts = check.sample_points(design, batch, seed=1)
    bargs = [pts[n] for n in names]
    out["python_batch_ns"] = best_ns(lambda: mod.controller(*bargs), min_time, 3) / batch
    fmap = ctl.map(batch)
    margs = [pts[n].transpose(0, 2, 1).reshape(pts[n].shape[0], -1) for n in names]
    out["casadi_map_ns"] = best_ns(lambda: fmap(*margs), min_time, 3) / batch
    return out


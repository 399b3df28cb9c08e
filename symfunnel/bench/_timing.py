"""Bench timing: the generated controller in compiled C (timed in C by bench.c on the thread's CPU clock), CasADi's
VM from Python and the generated numpy-only Python, side by side; CPU time (`time.process_time`) beside wall time
for everything timed in Python (code generation itself never times anything).

CPU time is the figure to compare on a shared machine: a loaded machine stretches the wall clock of the same work
(the shipped bench once gave 4.6-6.7 us for a 1.4 us step), not its CPU time.
"""

from __future__ import annotations

import contextlib
import functools
import os
import resource
import subprocess
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

    from ..design import Design


def best(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 5) -> dict:
    """Best-of-`repeats` time per call of fn() in ns, wall and CPU (each repeat at least min_time / repeats)."""
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= min_time / repeats or n >= 1 << 22:
            break
        n *= 2
    wall, cpu = dt / n, float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(n):
            fn()
        c1, t1 = time.process_time(), time.perf_counter()
        wall, cpu = min(wall, (t1 - t0) / n), min(cpu, (c1 - c0) / n)
    return {"wall_ns": wall * 1e9, "cpu_ns": cpu * 1e9}


def best_ns(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 5) -> float:
    """Best-of-`repeats` CPU time per call of fn() in ns (`best`)."""
    return best(fn, min_time, repeats)["cpu_ns"]


@functools.lru_cache(maxsize=None)
def bench_cflags() -> tuple[str, ...]:
    """The strict flags (docs/exports.md, "Controller code") with -O3 -march=native where the compiler takes them, which
    lets it vectorise the reservoir's loops; otherwise the strict flags alone."""
    from ..core.ccompile import find_compiler
    from ..emit.c import STRICT_CFLAGS
    fast = tuple(f for f in STRICT_CFLAGS if not f.startswith("-O")) + ("-O3", "-march=native")
    try:
        probe = subprocess.run([find_compiler(), *fast, "-E", "-x", "c", "-", "-o", "/dev/null"], input="",
                               capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return tuple(STRICT_CFLAGS)
    return fast if probe.returncode == 0 else tuple(STRICT_CFLAGS)


def run_c_bench(files: dict[str, str], flags: tuple[str, ...], iterations: int = 100000, repeats: int = 3,
                on_build=None) -> dict:
    """bench.c over trajectory.txt with the generated pair built with `flags`: ns per controller call and per
    Pstep call, CPU time of the thread (bench.c), the best of `repeats` runs of the program."""
    from ..core.ccompile import compile_cached
    from ..emit.files import c_names
    base = c_names(files)[0]
    src = {k: files[k] for k in (base + ".c", base + ".h", "bench.c")}
    exe = compile_cached(src, ["bench.c", base + ".c"], "symfunnel_bench", flags, on_build=on_build).path
    out = {"controller_ns": float("inf"), "step_ns": float("inf"), "flags": " ".join(flags)}
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-") as tmp:
        p = Path(tmp) / "trajectory.txt"
        p.write_text(files["trajectory.txt"], encoding="utf-8")
        for _ in range(repeats):
            proc = subprocess.run([str(exe), str(p), str(iterations)], capture_output=True, text=True, timeout=600)
            if proc.returncode != 0:
                raise RuntimeError(f"bench program failed: {proc.stderr.strip()}")
            words = proc.stdout.split()
            out["controller_ns"] = min(out["controller_ns"], float(words[words.index("ns_per_call") + 1]))
            out["step_ns"] = min(out["step_ns"], float(words[words.index("step_ns_per_call") + 1]))
    return out


def compile_seconds(sources: dict[str, str], name: str, flags: tuple[str, ...], timeout: float) -> dict:
    """CPU seconds (the compiler's, from the children's rusage) and wall seconds of compiling the C file `name` of
    `sources` (its headers beside it) to an object, uncached; "finished" False when it passed `timeout` (then
    killed, and the times are those so far)."""
    from ..core.ccompile import find_compiler
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-cc-") as tmp:
        for k, v in sources.items():
            (Path(tmp) / k).write_text(v, encoding="utf-8")
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.Popen([find_compiler(), *flags, "-c", name, "-o", "out.o"], cwd=tmp,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        try:
            _, err = proc.communicate(timeout=timeout)
            finished = True
        except subprocess.TimeoutExpired:
            import os
            import signal
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            finished, err = False, b""
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        if finished and proc.returncode != 0:
            raise RuntimeError(f"compiling {name} failed: {err.decode(errors='replace').strip()[:2000]}")
    return {"cpu_s": (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime), "wall_s": wall,
            "finished": finished}


def time_controller(design: Design, c_files: dict[str, str], py_files: dict[str, str],
                    *, min_time: float = 0.2, c_iterations: int = 200000, batch: int = 1000) -> dict:
    """ns per controller call: compiled C (timed in C by bench.c, thread CPU time, `bench_cflags`), CasADi's VM
    from Python, generated Python (CPU time; `*_wall_ns` beside).

    Returns {"c_ns", "c_flags", "casadi_vm_ns" (Function call with DM arguments), "casadi_vm_numpy_ns" (numpy
    arguments, conversion included), "python_ns", "python_batch_ns" (per point, one call over `batch` points),
    "casadi_map_ns" (per point, casadi map over the same batch), the same with _wall_ns, "operations"}.
    """
    from ..emit import check
    from ..emit.contract import trajectory_inputs
    from ..emit.c import BASENAME
    from ..sx.tape import count_ops
    ctl = design.controller()
    out = {"operations": count_ops(ctl)["operations"]}
    cb = run_c_bench(c_files, bench_cflags(), c_iterations)
    out["c_ns"], out["c_flags"] = cb["controller_ns"], cb["flags"]

    inp = trajectory_inputs(design, c_files["trajectory.txt"])
    names = [ctl.name_in(i) for i in range(ctl.n_in())]
    one = [inp[n][:, :, 1] for n in names]
    import casadi as ca
    one_dm = [ca.DM(a) for a in one]

    def put(key: str, b: dict, per: int = 1) -> None:
        out[key] = b["cpu_ns"] / per
        out[key.replace("_ns", "_wall_ns")] = b["wall_ns"] / per
    put("casadi_vm_ns", best(lambda: ctl(*one_dm), min_time))          # arguments already DM
    put("casadi_vm_numpy_ns", best(lambda: ctl(*one), min_time))       # incl. numpy -> DM conversion

    with tempfile.TemporaryDirectory(prefix="symfunnel-py-") as tmp:
        path = Path(tmp) / (BASENAME + ".py")
        path.write_text(py_files[BASENAME + ".py"], encoding="utf-8")
        mod = check.load_python_module(path)
    put("python_ns", best(lambda: mod.controller(*one), min_time))

    pts = check.sample_points(design, batch, seed=1)
    bargs = [pts[n] for n in names]
    put("python_batch_ns", best(lambda: mod.controller(*bargs), min_time, 3), batch)
    fmap = ctl.map(batch)
    margs = [pts[n].transpose(0, 2, 1).reshape(pts[n].shape[0], -1) for n in names]
    put("casadi_map_ns", best(lambda: fmap(*margs), min_time, 3), batch)
    return out


@contextlib.contextmanager
def env_set(name: str, value: str):
    """$name set to `value` for the block, and as it was afterwards (a variant of the code under test chosen by its
    environment variable, e.g. $SYMFUNNEL_CVODES or $SYMFUNNEL_INTERVAL)."""
    old = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old

"""Generated code for the controller: C (CasADi's CodeGenerator) and numpy-only Python (from the SX tape).

Both languages get the same functions, in the same order, all built with `Design.function` from the one SX graph
(CSE on), and described in `manifest.json` (README, "Generated code"):

==============  ======================================  ===========================================
function        inputs                                  outputs
==============  ======================================  ===========================================
funnels         t                                       F1, dF1, F2, dF2
errors          t, q, dq, qd, dqd                       e1, z1, e2, z2
alpha2          t, q, qd, dqd                           alpha2
alpha2_dot      t, q, dq, qd, dqd, ddqd                 alpha2_dot
controller      t, q, dq, qd, dqd, ddqd, x_esn, w_hat   tau, x_esn_dot, w_hat_dot
==============  ======================================  ===========================================

API::

    files = generate(design, "c", trajectory=traj)   # {file name: text}, manifest.json included; deterministic
    write_output(files, "ctl")               # atomic: a failure never leaves half-written files
    report = check_output(design, "c", files, points=1000)   # compile (cached) / import, compare with CasADi
    summary = codegen_summary(design, traj)   # both languages: files, sizes, op counts, checks

Notes
-----
The recorded trajectory shipped with the code (`trajectory.txt`, 50 samples over the first 2 s) comes from the
pipeline's one simulation of the scenario (`trajectory_from_run`; `symfunnel.pipeline.Run.code` passes it).
Timing the generated code is `symfunnel bench`'s job, not the report's.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["CONTRACT", "BASENAME", "contract_functions", "trajectory_from_run", "generate", "write_output",
           "check_output", "time_controller", "codegen_summary"]

BASENAME = "symfunnel_controller"

#: (name, inputs, outputs) of every generated function, in manifest order.
CONTRACT: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("funnels", ("t",), ("F1", "dF1", "F2", "dF2")),
    ("errors", ("t", "q", "dq", "qd", "dqd"), ("e1", "z1", "e2", "z2")),
    ("alpha2", ("t", "q", "qd", "dqd"), ("alpha2",)),
    ("alpha2_dot", ("t", "q", "dq", "qd", "dqd", "ddqd"), ("alpha2_dot",)),
    ("controller", ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"), ("tau", "x_esn_dot", "w_hat_dot")),
)

LANGS = ("c", "python")


def contract_functions(design) -> list:
    """The casadi.Functions of the contract, in manifest order, from the design's one graph."""
    out = []
    for name, inputs, outputs in CONTRACT:
        f = design.controller() if name == "controller" else design.function(name, list(inputs), list(outputs))
        out.append(f)
    return out


def initial_trajectory(design) -> dict[str, np.ndarray]:
    """The controller inputs at t = 0 from the scenario's initial state: one sample, no simulation."""
    sc = design.scenario
    init = design.variant.initial_states()
    qd, dqd, ddqd = (np.array(v).reshape(-1, 1, 1) for v in design.reference(0.0))
    col = lambda a: np.asarray(a, dtype=float).reshape(-1, 1, 1)  # noqa: E731
    out = {"t": np.zeros((1, 1, 1)), "q": col(sc.q0), "dq": col(sc.dq0), "qd": qd, "dqd": dqd, "ddqd": ddqd}
    for name, (r, c) in design.states:
        out[name] = np.asarray(init[name], dtype=float).reshape(r, c, 1, order="F")
    out["source"] = f"the initial state of scenario '{sc.name}' (t = 0; no recorded run)"
    return out


def trajectory_from_run(design, closed_loop, result, samples: int = 50, span: float = 2.0) -> dict[str, np.ndarray]:
    """Controller inputs at `samples` times of a simulated run's first `span` seconds, as (r, c, k) arrays.

    Also holds "source", a one-line description. The samples are interpolated linearly from the simulation's
    output grid (the simulation stage of the pipeline: no second simulator here); a run that stopped at t = 0
    gives its initial state alone.
    """
    t_sim = np.asarray(result.t, dtype=float)
    if t_sim.size >= 2:
        t = np.linspace(t_sim[0], min(t_sim[-1], t_sim[0] + span), samples)
        X = np.stack([np.interp(t, t_sim, result.x[:, j]) for j in range(closed_loop.nx)], axis=1)
    else:
        t = np.zeros(1)
        X = (result.x[:1] if t_sim.size else closed_loop.x0[None, :]).astype(float)
    k = t.size
    parts = closed_loop.unpack(X)
    qd, dqd, ddqd = (np.array(v) for v in design.reference.map(k)(t[None, :]))
    col = lambda a: np.asarray(a, dtype=float)[:, None, :]  # noqa: E731
    out = {"t": t[None, None, :], "q": col(parts["q"].T), "dq": col(parts["dq"].T), "qd": col(qd),
           "dqd": col(dqd), "ddqd": col(ddqd)}
    for name, (r, c) in design.states:
        v = parts[name]                                    # (k, r) or (k, r, c)
        out[name] = np.moveaxis(v.reshape(k, r, c), 0, -1)
    out["source"] = (f"the simulated closed loop of scenario '{design.scenario.name}' (plant with its unknowns), "
                     f"{k} samples over t = {t[0]:g}..{t[-1]:g} s")
    return out


def _manifest(design, functions, lang: str, files: dict[str, str]) -> str:
    import casadi

    from .. import __version__
    from .python import manifest_entry
    from ..sx.tape import count_ops
    entries = []
    for f in functions:
        e = manifest_entry(f)
        e["operations"] = count_ops(f)["operations"]
        entries.append(e)
    info = {
        "generator": f"symfunnel {__version__}",
        "casadi_version": casadi.__version__,
        "scenario": design.scenario.name,
        "language": lang,
        "files": [{"name": k, "bytes": len(v.encode("utf-8")),
                   "sha256": hashlib.sha256(v.encode("utf-8")).hexdigest()} for k, v in files.items()],
        "functions": entries,
    }
    if lang == "c":
        info["c_api"] = {"source": BASENAME + ".c", "header": BASENAME + ".h", "casadi_real": "double",
                         "casadi_int": "int", "memory": "static (no malloc; work in locals)"}
    info["trajectory"] = {"file": "trajectory.txt",
                          "row": "controller inputs in manifest order, matrices column-major"}
    return json.dumps(info, indent=2) + "\n"


def generate(design, lang: str, *, trajectory: dict[str, np.ndarray] | None = None, prefix: str | None = None,
             rate_hz: float | None = None, tau_max=None) -> dict[str, str]:
    """Every output file of one language as {name: text}, manifest.json last; byte-identical for the same design.

    `trajectory` (controller inputs over time, see `trajectory_from_run`) is what `trajectory.txt` ships; without
    one (a library build, e.g. the sampled-data loop) it holds the initial state alone. C only: `prefix` starts
    every exported symbol (None: the historical names, see codegen.step), `rate_hz` is the period of the generated
    step (default: [implementation].rate_hz, else step.DEFAULT_RATE_HZ) and `tau_max` its saturation (default:
    [implementation].tau_max).
    """
    from .c import support_files, trajectory_text
    from .python import emit_python
    if lang not in LANGS:
        raise ValueError(f"unknown language {lang!r}; expected one of {LANGS}")
    functions = contract_functions(design)
    sc = design.scenario
    traj = trajectory if trajectory is not None else initial_trajectory(design)
    traj_txt = trajectory_text(design.controller(), traj, header=(
        f"symfunnel recorded trajectory for scenario '{sc.name}': one sample per line\n"
        + str(traj.get("source", "supplied by the caller"))))
    if lang == "c":
        from .step import emit_controller_c, step_settings
        rate_hz, tau_max = step_settings(design, rate_hz, tau_max)
        base = c_basename(prefix)
        files = emit_controller_c(design, functions, prefix=prefix, basename=base, rate_hz=rate_hz, tau_max=tau_max)
        sp = prefix if prefix is not None else "symfunnel_"
        files.update(support_files(traj_txt, {"@BASENAME@": base, "@F@": prefix or "", "@P@": sp,
                                              "@UP@": sp.upper()}))
    else:
        doc = (f"Funnel controller of scenario '{sc.name}' ({sc.title}).\n\n"
               "See manifest.json for the functions, their inputs and outputs.")
        from .c import template
        files = {BASENAME + ".py": emit_python(functions, module_doc=doc),
                 "run_trajectory.py": template("run_trajectory.py"),
                 "trajectory.txt": traj_txt}
    files["manifest.json"] = _manifest(design, functions, lang, files)
    if lang == "c":
        m = json.loads(files["manifest.json"])
        m["c_api"].update({"source": base + ".c", "header": base + ".h", "function_prefix": prefix or "",
                           "step": {"prefix": sp, "rate_hz": rate_hz,
                                    "tau_max": None if tau_max is None else np.broadcast_to(
                                        np.asarray(tau_max, float), (design.n,)).tolist(),
                                    "functions": [sp + "state_size", sp + "init", sp + "step"],
                                    "casadi_functions": [(prefix or "") + "reference",
                                                         (prefix or "") + "step_core"]}})
        files["manifest.json"] = json.dumps(m, indent=2) + "\n"
    return files


def c_basename(prefix: str | None) -> str:
    """Base name of the generated C pair: symfunnel_controller without a prefix, else <prefix>controller."""
    return BASENAME if prefix is None else prefix + "controller"


def c_names(files: dict[str, str]) -> tuple[str, str]:
    """(basename, function prefix) of a generated C file set, from its manifest."""
    api = json.loads(files["manifest.json"]).get("c_api", {})
    return api.get("source", BASENAME + ".c")[:-2], api.get("function_prefix", "")


def write_output(files: dict[str, str], out_dir: str | os.PathLike) -> list[Path]:
    """Write the files into out_dir atomically: all go to a temporary directory first, then are renamed in.

    Raises InputError when out_dir exists and is not a directory. Other files in out_dir are left alone.
    """
    from ..errors import InputError
    from ..io import umask_mode
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a directory", file=str(out), key="--out",
                         expected="a directory (created when missing)")
    # The temporary directory lives inside an existing out_dir (it may be a mount point: renames never cross
    # file systems), else beside it so that the whole directory can be renamed into place.
    parent = out.absolute() if out.is_dir() else out.absolute().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))
        os.chmod(tmp, umask_mode(directory=True))
    except OSError as exc:
        raise InputError(f"cannot be created ({exc.strerror})", file=str(out), key="--out",
                         expected="a writable directory") from None
    try:
        for name, text in files.items():
            with open(tmp / name, "w", encoding="utf-8", newline="\n") as fh:
                fh.write(text)
        if not out.exists():
            try:
                os.rename(tmp, out)
                return [out / n for n in files]
            except OSError:
                out.mkdir(parents=True, exist_ok=True)
        for name in files:
            os.replace(tmp / name, out / name)
    except OSError as exc:
        raise InputError(f"cannot be written ({exc.strerror or exc})", file=str(out), key="--out",
                         expected="a writable directory") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out / n for n in files]


def check_output(design, lang: str, files: dict[str, str], *, points: int = 1000, seed: int = 0,
                 fill: float | None = None, pts: dict | None = None):
    """Compile (C, cached) or import (Python) generated files and compare every function with CasADi.

    For C also compiles main.c with the strict flags and runs it over trajectory.txt, comparing its torques with
    CasADi (extra entry 'main.c trajectory'). Returns a check.CheckReport.
    """
    from . import check
    functions = contract_functions(design)
    if pts is None:
        pts = check.sample_points(design, points, seed, check.FILL if fill is None else fill)
    if lang == "c":
        base, fprefix = c_names(files)
        lib = check.c_library(files[base + ".c"], files[base + ".h"], base)
        report = check.check_c(functions, lib.path, pts, prefix=fprefix)
        report.extra["main.c trajectory"] = _check_main(design, files)
        return report
    with tempfile.TemporaryDirectory(prefix="symfunnel-py-") as tmp:
        path = Path(tmp) / (BASENAME + ".py")
        path.write_text(files[BASENAME + ".py"], encoding="utf-8")
        mod = check.load_python_module(path)
    return check.check_python(functions, mod, pts)


def _trajectory_inputs(design, text: str) -> dict[str, np.ndarray]:
    """Parse trajectory.txt back into (r, c, k) arrays of the controller's inputs."""
    data = np.loadtxt(text.splitlines(), comments="#", ndmin=2).T
    ctl = design.controller()
    out, row = {}, 0
    for i in range(ctl.n_in()):
        r, c = ctl.size1_in(i), ctl.size2_in(i)
        out[ctl.name_in(i)] = data[row:row + r * c].reshape(r, c, -1, order="F")
        row += r * c
    return out


def main_program(files: dict[str, str], flags=None):
    """Build main.c + the generated pair with the strict flags (cached); returns build.Built."""
    from .build import compile_cached
    from .c import STRICT_CFLAGS
    base = c_names(files)[0]
    src = {k: files[k] for k in (base + ".c", base + ".h", "main.c")}
    return compile_cached(src, ["main.c", base + ".c"], "symfunnel_main", tuple(flags or STRICT_CFLAGS))


def _check_main(design, files: dict[str, str]) -> float:
    """Worst relative error of main.c's torques over trajectory.txt against CasADi."""
    from .check import casadi_values, relative_error, run_main
    exe = main_program(files).path
    with tempfile.TemporaryDirectory(prefix="symfunnel-traj-") as tmp:
        p = Path(tmp) / "trajectory.txt"
        p.write_text(files["trajectory.txt"], encoding="utf-8")
        rows = run_main(exe, p)
    inp = _trajectory_inputs(design, files["trajectory.txt"])
    tau = casadi_values(design.controller(), inp)[0]                  # (n, 1, k)
    tau_max = json.loads(files["manifest.json"])["c_api"]["step"]["tau_max"]
    if tau_max is not None:                                           # main.c's Pstep saturates
        tm = np.asarray(tau_max, dtype=float)[:, None, None]
        tau = np.clip(tau, -tm, tm)
    if rows.shape != (tau.shape[2], 1 + tau.shape[0]):
        return float("inf")
    return float(relative_error(rows[:, 1:].T[:, None, :], tau).max())


# --- timing -----------------------------------------------------------------------------------------

def _best_ns(fn, min_time: float = 0.2, repeats: int = 5) -> float:
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


def time_controller(design, c_files: dict[str, str], py_files: dict[str, str],
                    *, min_time: float = 0.2, c_iterations: int = 200000, batch: int = 1000) -> dict:
    """ns per controller call: compiled C (timed in C by bench.c), CasADi's VM from Python, generated Python.

    Returns {"c_ns", "casadi_vm_ns" (Function call with DM arguments), "casadi_vm_numpy_ns" (numpy arguments,
    conversion included), "python_ns", "python_batch_ns" (per point, one call over `batch` points),
    "casadi_map_ns" (per point, casadi map over the same batch), "operations"}.
    """
    import subprocess

    from . import check
    from .build import compile_cached
    from .c import STRICT_CFLAGS
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

    inp = _trajectory_inputs(design, c_files["trajectory.txt"])
    names = [ctl.name_in(i) for i in range(ctl.n_in())]
    one = [inp[n][:, :, 1] for n in names]
    import casadi as ca
    one_dm = [ca.DM(a) for a in one]
    out["casadi_vm_ns"] = _best_ns(lambda: ctl(*one_dm), min_time)          # arguments already DM
    out["casadi_vm_numpy_ns"] = _best_ns(lambda: ctl(*one), min_time)       # incl. numpy -> DM conversion

    with tempfile.TemporaryDirectory(prefix="symfunnel-py-") as tmp:
        path = Path(tmp) / (BASENAME + ".py")
        path.write_text(py_files[BASENAME + ".py"], encoding="utf-8")
        mod = check.load_python_module(path)
    out["python_ns"] = _best_ns(lambda: mod.controller(*one), min_time)

    pts = check.sample_points(design, batch, seed=1)
    bargs = [pts[n] for n in names]
    out["python_batch_ns"] = _best_ns(lambda: mod.controller(*bargs), min_time, 3) / batch
    fmap = ctl.map(batch)
    margs = [pts[n].transpose(0, 2, 1).reshape(pts[n].shape[0], -1) for n in names]
    out["casadi_map_ns"] = _best_ns(lambda: fmap(*margs), min_time, 3) / batch
    return out


# --- report -----------------------------------------------------------------------------------------

def codegen_summary(design, trajectory: dict, *, points: int = 1000, timings: bool = False) -> dict:
    """Generate both languages into a temp dir, check them against CasADi, time them; plain data for the report.

    Returns {"scenario", "functions": [{"name", "inputs", "outputs", "operations"}],
    "languages": {"c"|"python": {"files": [{"name", "bytes", "lines"}], "check": CheckReport.to_json()}},
    "controller_operations", "timings": time_controller(...) or None, "points"}.
    """
    from . import check
    from .build import find_compiler
    from ..sx.tape import count_ops
    functions = contract_functions(design)
    pts = check.sample_points(design, points, 0)
    out = {"scenario": design.scenario.name, "points": points, "languages": {},
           "functions": [], "controller_operations": count_ops(design.controller())["operations"]}
    from .python import manifest_entry
    for f in functions:
        e = manifest_entry(f)
        e["operations"] = count_ops(f)["operations"]
        out["functions"].append(e)
    files = {}
    with tempfile.TemporaryDirectory(prefix="symfunnel-codegen-") as tmp:
        for lang in LANGS:
            files[lang] = generate(design, lang, trajectory=trajectory)
            write_output(files[lang], Path(tmp) / lang)
            entry = {"files": [{"name": k, "bytes": len(v.encode("utf-8")), "lines": v.count("\n")}
                               for k, v in files[lang].items()]}
            try:
                if lang == "c":
                    find_compiler()
                entry["check"] = check_output(design, lang, files[lang], pts=pts).to_json()
            except Exception as exc:  # noqa: BLE001 - the report shows why a language could not be checked
                entry["check"] = None
                entry["error"] = f"{type(exc).__name__}: {exc}"
            out["languages"][lang] = entry
    out["timings"] = None
    if timings:
        try:
            out["timings"] = time_controller(design, files["c"], files["python"])
        except Exception as exc:  # noqa: BLE001
            out["timings_error"] = f"{type(exc).__name__}: {exc}"
    return out


from .._callable import make_callable  # noqa: E402 - after the module body: calling this module is the API function

make_callable(__name__, "codegen")

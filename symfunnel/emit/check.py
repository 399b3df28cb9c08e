"""Cross-check generated code against CasADi's evaluation of the same SX graph, at random points inside the funnels;
`check_output` checks a generated file set (and runs its main.c), `codegen_summary` both languages for the report.

Error measure, per output and point (normwise): max|generated - casadi| / max(1, max|casadi|) over the entries of
that output (relative, with a unit floor so that outputs near zero are compared absolutely). The check reports the
worst value per function and overall.
"""

from __future__ import annotations

import ctypes
import importlib.util
import itertools
import json
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import casadi
import numpy as np

from .c import BASENAME
from .contract import LANGS, contract_functions, trajectory_inputs
from .files import c_names, generate, write_output

if TYPE_CHECKING:
    from ..design import Design
    from ..core.ccompile import Built

__all__ = ["THRESHOLDS", "FILL", "CheckReport", "sample_points", "casadi_values", "c_library", "CLibrary",
           "check_c", "check_python", "load_python_module", "relative_error", "check_output", "main_program",
           "codegen_summary"]

#: Worst relative error allowed by `codegen --check` per language.
THRESHOLDS = {"c": 1e-12, "python": 1e-10}


@dataclass
class CheckReport:
    """Worst relative error per function (and the point where it occurred) for one language."""

    lang: str
    points: int
    errors: dict[str, float] = field(default_factory=dict)
    where: dict[str, dict] = field(default_factory=dict)
    extra: dict[str, float] = field(default_factory=dict)   # e.g. the trajectory run of main.c

    @property
    def threshold(self) -> float:
        return THRESHOLDS[self.lang]

    @property
    def worst(self) -> float:
        vals = list(self.errors.values()) + list(self.extra.values())
        return max(vals) if vals else 0.0

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.worst)) and self.worst <= self.threshold

    def to_json(self) -> dict:
        """Plain data; a non-finite error (NaN/inf mismatch) becomes null."""
        fin = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {"lang": self.lang, "points": self.points, "threshold": self.threshold, "worst": fin(self.worst),
                "passed": self.passed, "errors": {k: fin(v) for k, v in self.errors.items()},
                "extra": {k: fin(v) for k, v in self.extra.items()}, "where": dict(self.where)}


def relative_error(got: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Normwise relative error per point of (r, c, k) arrays: max|got - ref| / max(1, max|ref|) over (r, c).

    Entries that agree exactly (NaN with NaN included) contribute 0; any other non-finite difference gives inf.
    """
    got = np.asarray(got, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if got.shape != ref.shape:
        raise ValueError(f"shape mismatch {got.shape} vs {ref.shape}")
    if got.ndim == 2:
        got, ref = got[:, :, None], ref[:, :, None]
    same = (got == ref) | (np.isnan(got) & np.isnan(ref))
    with np.errstate(invalid="ignore"):
        diff = np.where(same, 0.0, np.abs(got - ref))
    diff = np.where(np.isfinite(diff), diff, np.inf)
    scale = np.maximum(1.0, np.max(np.where(np.isfinite(ref), np.abs(ref), 0.0), axis=(0, 1)))
    if diff.size == 0:
        return np.zeros(got.shape[2])
    return np.max(diff, axis=(0, 1)) / scale


# --- points and reference values ----------------------------------------------------------------------

#: Default depth of the check points: |e_i| <= FILL * F_i, as the audit samples. Near the boundary the controller
#: is ill-conditioned (1/(F - |e|), and e2 = dq - alpha2 cancels when |alpha2| >> F2), so the generated Python
#: evaluates exp through libm like CasADi and the C code (numpy's SIMD exp differs in the last bit).
FILL = 0.98


def sample_points(design, k: int = 1000, seed: int = 0, fill: float = FILL) -> dict[str, np.ndarray]:
    """k points inside both funnels (|e_i| <= fill * F_i), every base input as an (r, c, k) array, sample last."""
    from ..design.sampling import funnel_states
    pts = funnel_states(design, k, np.random.default_rng(seed), fill=fill)
    out = {}
    for name in design.inputs:
        a = pts[name]
        r, c = design.sym[name].shape
        a = np.asarray(a, dtype=float)
        # casadi map layout: (r, k*c) with sample j's matrix in columns j*c .. j*c+c-1
        out[name] = a.reshape(r, k, c).transpose(0, 2, 1).copy()
    return out


def casadi_values(f: casadi.Function, pts: dict[str, np.ndarray]) -> list[np.ndarray]:
    """f at every point through CasADi's virtual machine (map), outputs as (r, c, k) arrays."""
    names = [f.name_in(i) for i in range(f.n_in())]
    k = next(iter(pts.values())).shape[2]
    args = [pts[n].transpose(0, 2, 1).reshape(pts[n].shape[0], -1) for n in names]
    res = f.map(k)(*args)
    res = [res] if f.n_out() == 1 else list(res)
    return [np.array(v).reshape(f.size1_out(j), k, f.size2_out(j)).transpose(0, 2, 1)
            for j, v in enumerate(res)]


def _point(pts: dict[str, np.ndarray], j: int) -> dict:
    return {"t": float(pts["t"][0, 0, j]), "q": pts["q"][:, 0, j].tolist(), "dq": pts["dq"][:, 0, j].tolist()}


def _compare(report: CheckReport, f: casadi.Function, got: list[np.ndarray], ref: list[np.ndarray],
             pts: dict[str, np.ndarray]) -> None:
    worst, where = 0.0, None
    for g, r in zip(got, ref):
        e = relative_error(g, r)
        if e.size and e.max() > worst:
            worst = float(e.max())
            where = int(np.argmax(e))
    report.errors[f.name()] = worst
    if where is not None:
        report.where[f.name()] = _point(pts, where)


# --- C through ctypes ---------------------------------------------------------------------------------

_real_p = ctypes.POINTER(ctypes.c_double)


class CLibrary:
    """The generated functions of a compiled shared library, called through CasADi's C API with ctypes."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.lib = ctypes.CDLL(str(self.path))

    def function(self, name: str) -> "CFunction":
        return CFunction(self.lib, name)


class CFunction:
    """One generated function: NAME_incref/checkout, NAME_work for the buffer sizes, NAME(arg, res, iw, w, mem)."""

    def __init__(self, lib: ctypes.CDLL, name: str):
        self.name = name
        get = lambda suffix: getattr(lib, name + suffix)  # noqa: E731
        for suffix, restype in (("_n_in", ctypes.c_int), ("_n_out", ctypes.c_int), ("_checkout", ctypes.c_int)):
            get(suffix).restype = restype
        get("_sparsity_in").restype = ctypes.POINTER(ctypes.c_int)
        get("_sparsity_out").restype = ctypes.POINTER(ctypes.c_int)
        self.n_in, self.n_out = get("_n_in")(), get("_n_out")()
        self.in_shapes = [self._dense(get("_sparsity_in")(i)) for i in range(self.n_in)]
        self.out_shapes = [self._dense(get("_sparsity_out")(i)) for i in range(self.n_out)]
        sz = [ctypes.c_int() for _ in range(4)]
        if get("_work")(*[ctypes.byref(s) for s in sz]):
            raise RuntimeError(f"{name}_work failed")
        sz_arg, sz_res, sz_iw, sz_w = (max(1, s.value) for s in sz)
        get("_incref")()
        self.mem = get("_checkout")()
        self._f = getattr(lib, name)
        self._f.restype = ctypes.c_int
        self.inputs = [np.zeros(r * c) for r, c in self.in_shapes]
        self.outputs = [np.zeros(r * c) for r, c in self.out_shapes]
        self.arg = (_real_p * sz_arg)(*[a.ctypes.data_as(_real_p) for a in self.inputs])
        self.res = (_real_p * sz_res)(*[a.ctypes.data_as(_real_p) for a in self.outputs])
        self.iw = (ctypes.c_int * sz_iw)()
        self.w = (ctypes.c_double * sz_w)()

    @staticmethod
    def _dense(sp) -> tuple[int, int]:
        r, c = sp[0], sp[1]
        if c > 0 and sp[2] != 1 and sp[2 + c] != r * c:
            raise ValueError("generated function has a sparse input/output; the contract is dense")
        return r, c

    def __call__(self, *args) -> list[np.ndarray]:
        """Evaluate at one point; arguments of the input shapes, outputs as (r, c) arrays."""
        for buf, a, (r, c) in zip(self.inputs, args, self.in_shapes):
            buf[:] = np.asarray(a, dtype=float).reshape(r * c, order="F") if r * c else 0.0
        if self._f(self.arg, self.res, self.iw, self.w, self.mem):
            raise RuntimeError(f"{self.name} returned an error")
        return [o.reshape(r, c, order="F").copy() for o, (r, c) in zip(self.outputs, self.out_shapes)]


def c_library(c_source: str, h_source: str, basename: str):
    """Compile the generated pair into a cached shared library; returns build.Built."""
    from ..core.ccompile import SHARED_FLAGS, compile_cached
    return compile_cached({basename + ".c": c_source, basename + ".h": h_source}, [basename + ".c"],
                          f"lib{basename}.so", SHARED_FLAGS)


def check_c(functions, lib_path: str | Path, pts: dict[str, np.ndarray], prefix: str = "") -> CheckReport:
    """Compare every function of the compiled library with CasADi at the points."""
    lib = CLibrary(lib_path)
    k = next(iter(pts.values())).shape[2]
    report = CheckReport("c", k)
    for f in functions:
        cf = lib.function(prefix + f.name())
        names = [f.name_in(i) for i in range(f.n_in())]
        got = [np.zeros((f.size1_out(j), f.size2_out(j), k)) for j in range(f.n_out())]
        for j in range(k):
            outs = cf(*[pts[n][:, :, j] for n in names])
            for g, o in zip(got, outs):
                g[:, :, j] = o
        _compare(report, f, got, casadi_values(f, pts), pts)
    return report


# --- Python -------------------------------------------------------------------------------------------

_counter = itertools.count()


def load_python_module(path: str | Path):
    """Import a generated module from its file under a unique name (not added to sys.modules)."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(f"_symfunnel_generated_{next(_counter)}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def check_python(functions, module, pts: dict[str, np.ndarray]) -> CheckReport:
    """Compare every function of the generated module (one batched call each) with CasADi at the points."""
    k = next(iter(pts.values())).shape[2]
    report = CheckReport("python", k)
    for f in functions:
        names = [f.name_in(i) for i in range(f.n_in())]
        got = getattr(module, f.name())(*[pts[n] for n in names])
        _compare(report, f, list(got), casadi_values(f, pts), pts)
    return report


def run_main(exe: str | Path, trajectory: str | Path, cwd: str | Path | None = None) -> np.ndarray:
    """Run the example program over a trajectory file; its rows (t, tau...) as an array."""
    from .c import parse_trajectory_output
    proc = subprocess.run([str(exe), str(trajectory)], capture_output=True, text=True, cwd=cwd, timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(f"{exe} failed with exit code {proc.returncode}: {proc.stderr.strip()}")
    return parse_trajectory_output(proc.stdout)



# --- the generated files, checked --------------------------------------------------------------------

def check_output(design: Design, lang: str, files: dict[str, str], *, points: int = 1000, seed: int = 0,
                 fill: float | None = None, pts: dict | None = None) -> CheckReport:
    """Compile (C, cached) or import (Python) generated files and compare every function with CasADi.

    For C also compiles main.c with the strict flags and runs it over trajectory.txt, comparing its torques with
    CasADi (extra entry 'main.c trajectory').
    """
    functions = contract_functions(design)
    if pts is None:
        pts = sample_points(design, points, seed, FILL if fill is None else fill)
    if lang == "c":
        base, fprefix = c_names(files)
        lib = c_library(files[base + ".c"], files[base + ".h"], base)
        report = check_c(functions, lib.path, pts, prefix=fprefix)
        _check_step_core(design, files, lib.path, pts, fprefix, report)
        report.extra["main.c trajectory"] = _check_main(design, files)
        return report
    with tempfile.TemporaryDirectory(prefix="symfunnel-py-") as tmp:
        path = Path(tmp) / (BASENAME + ".py")
        path.write_text(files[BASENAME + ".py"], encoding="utf-8")
        mod = load_python_module(path)
    return check_python(functions, mod, pts)



def _check_step_core(design: Design, files: dict[str, str], lib_path, pts: dict[str, np.ndarray], fprefix: str,
                     report: CheckReport) -> None:
    """The generated Pstep_core (loops over the reservoir where emit.kernel applies) against the SX step core,
    at the same points and the manifest's rate and saturation; its entry is the step core's name."""
    from .step import etd_factors, step_core
    api = json.loads(files["manifest.json"])["c_api"]["step"]
    core = step_core(design, api["tau_max"], fprefix + "step_core")
    k = next(iter(pts.values())).shape[2]
    etd = np.broadcast_to(np.asarray(etd_factors(design.scenario, api["rate_hz"]), float)[:, None, None], (2, 1, k))
    full = {"etd": np.ascontiguousarray(etd)}
    for i in range(core.n_in()):
        name = core.name_in(i)
        if name != "etd":
            full[name] = pts[name] if name in pts else np.zeros((core.size1_in(i), core.size2_in(i), k))
    sub = check_c([core], lib_path, full)
    report.errors.update(sub.errors)
    report.where.update(sub.where)


def main_program(files: dict[str, str], flags=None) -> Built:
    """Build main.c + the generated pair with the strict flags (cached)."""
    from ..core.ccompile import compile_cached
    from .c import STRICT_CFLAGS
    base = c_names(files)[0]
    src = {k: files[k] for k in (base + ".c", base + ".h", "main.c")}
    return compile_cached(src, ["main.c", base + ".c"], "symfunnel_main", tuple(flags or STRICT_CFLAGS))


def _check_main(design: Design, files: dict[str, str]) -> float:
    """Worst relative error of main.c's torques over trajectory.txt against CasADi."""
    exe = main_program(files).path
    from .c import STRICT_CFLAGS              # and under the compiler's default standard (gnu17: POSIX names visible)
    main_program(files, tuple(f for f in STRICT_CFLAGS if not f.startswith("-std=")))
    with tempfile.TemporaryDirectory(prefix="symfunnel-traj-") as tmp:
        p = Path(tmp) / "trajectory.txt"
        p.write_text(files["trajectory.txt"], encoding="utf-8")
        rows = run_main(exe, p)
    inp = trajectory_inputs(design, files["trajectory.txt"])
    tau = casadi_values(design.controller(), inp)[0]                  # (n, 1, k)
    tau_max = json.loads(files["manifest.json"])["c_api"]["step"]["tau_max"]
    if tau_max is not None:                                           # main.c's Pstep saturates
        tm = np.asarray(tau_max, dtype=float)[:, None, None]
        tau = np.clip(tau, -tm, tm)
    if rows.shape != (tau.shape[2], 1 + tau.shape[0]):
        return float("inf")
    return float(relative_error(rows[:, 1:].T[:, None, :], tau).max())



def codegen_summary(design: Design, trajectory: dict, *, points: int = 1000) -> dict:
    """Generate both languages into a temp dir and check them against CasADi; plain data for the report.

    Returns {"scenario", "functions": [{"name", "inputs", "outputs", "operations"}],
    "languages": {"c"|"python": {"files": [{"name", "bytes", "lines"}], "check": CheckReport.to_json()}},
    "controller_operations", "timings": None (timing is `symfunnel bench --only codegen`'s job), "points"}.
    """
    from ..sx.tape import count_ops
    from ..core.ccompile import find_compiler
    from .python import manifest_entry
    functions = contract_functions(design)
    pts = sample_points(design, points, 0)
    out = {"scenario": design.scenario.name, "points": points, "languages": {},
           "functions": [], "controller_operations": count_ops(design.controller())["operations"]}
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
                from ..core.lifecycle import reraise_interrupt
                reraise_interrupt(exc)        # a signal or the limit a C call turned into an error: stop, not show
                entry["check"] = None
                entry["error"] = f"{type(exc).__name__}: {exc}"
            out["languages"][lang] = entry
    out["timings"] = None
    return out


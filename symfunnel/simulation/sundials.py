"""CVODES on the compiled closed loop without CasADi's integrator object: the SUNDIALS inside CasADi's wheel,
driven from C (`csrc/cvodes_driver.c`), with the Newton matrix I - gamma J factorised on its fixed pattern.

Same algorithm and options as `casadi.integrator(..., "cvodes", ...)` with linear_solver "csparse" (the runner's
other backend, kept as the reference and as the fallback): what changes is the cost of each call. The generated
right-hand side and Jacobian are called directly (CasADi wraps them in an MX function on its virtual machine and
times every call with two process-clock reads), and the LU keeps its symbolic analysis (CSparse redoes its depth-
first searches and allocations at every refactorisation). The trajectories agree with CasADi's to rounding in the
LU's pivot order, far inside the integrator's tolerance (tests/test_sundials.py).

The driver attaches its linear solver through CVODES' memory block, as CasADi's interface does; the block's layout
is checked against the public setters before it is used (sf_check_layout), so a CasADi whose CVODES differs makes
`available()` false and the runner uses casadi.integrator. `$SYMFUNNEL_CVODES=casadi` selects that backend.
"""

from __future__ import annotations

import ctypes
import os
import threading
import weakref
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = ["BACKENDS", "DirectCvodes", "available", "backend", "driver_library", "unavailable_reason"]

BACKENDS = ("direct", "casadi")
#: the most memory one chunk's step history may take (the paper's 500-point chunks: ~12 MB)
HISTORY_BYTES = 256e6
#: the Newton matrix factorised along the LU's precomputed update schedule (`csrc/sf_lu.h`: the same factors bit for
#: bit, less time); False: through a dense work column, the previous path (the bench's baseline)
SCHEDULED_LU = True
#: CVODES' vector operations four doubles at a time where the processor has AVX2 (`csrc/sf_nvec.h`: the same
#: doubles); False: SUNDIALS' own (the previous path, the bench's baseline)
WIDE_VECTORS = True
#: the samples between output points interpolated from the kept steps straight into their rows in the output order
#: (`csrc/cvodes_driver.c`, sf_dky_put: CVodeGetDky's operations, the same doubles); False: CVodeGetDky into a scratch
#: vector, then permuted (the previous path, the bench's baseline)
FUSED_DKY = True
DRIVER_FLAGS = ("-std=c99", "-O2", "-fPIC", "-shared")
_SOURCES = ("cvodes_driver.c", "cvodes_loop.c", "cvodes_mem.h", "sf_lu.h", "sf_nvec.h")
_REASON: list[str] = []
_CREATE_LOCK = threading.Lock()


def backend() -> str:
    """The CVODES backend runs use: $SYMFUNNEL_CVODES ("direct", the default, or "casadi")."""
    b = os.environ.get("SYMFUNNEL_CVODES", "direct").strip().lower() or "direct"
    return b if b in BACKENDS else "direct"


def _casadi_dir() -> Path:
    import casadi
    return Path(casadi.__file__).resolve().parent


@lru_cache(maxsize=None)
def driver_library() -> ctypes.CDLL | None:
    """The driver compiled against this CasADi's CVODES (once per machine, cached), or None (reason recorded)."""
    import casadi
    from ..core.ccompile import compile_cached
    d = _casadi_dir()
    if not (d / "libcasadi_integrator_cvodes.so").exists() or not (d / "libcasadi_sundials_common.so").exists():
        _REASON.append(f"CasADi's CVODES libraries are not in {d}")
        return None
    src = {name: resources.files("symfunnel.simulation").joinpath("csrc", name).read_text(encoding="utf-8")
           for name in _SOURCES}
    src["casadi.txt"] = f"casadi {casadi.__version__} at {d}\n"      # part of the cache key
    libs = (f"-L{d}", "-l:libcasadi_integrator_cvodes.so", "-l:libcasadi_sundials_common.so", f"-Wl,-rpath,{d}",
            "-lm")
    try:
        built = compile_cached(src, ["cvodes_driver.c", "cvodes_loop.c"], "symfunnel_cvodes.so", DRIVER_FLAGS,
                               libs=libs)
        lib = ctypes.CDLL(str(built.path))
    except (OSError, RuntimeError) as exc:
        from .hints import error_line
        _REASON.append(f"building the CVODES driver failed ({error_line(str(exc))})")
        return None
    vp, ip, dp = ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double)
    lib.sf_create.restype = vp
    lib.sf_create.argtypes = [ctypes.c_int, ctypes.c_int, vp, vp, ctypes.POINTER(ctypes.c_longlong), ip, ip,
                              ctypes.c_double, ctypes.c_double, ctypes.c_long, ctypes.c_double, ctypes.c_int,
                              ctypes.c_char_p, ctypes.c_int]
    lib.sf_run.restype = ctypes.c_int
    lib.sf_run.argtypes = [vp, dp, dp, ctypes.c_int, dp, dp, ctypes.POINTER(ctypes.c_long), ctypes.c_char_p,
                           ctypes.c_int]
    lib.sf_run_hist.restype = ctypes.c_int
    lib.sf_run_hist.argtypes = [vp, dp, dp, ctypes.c_int, dp, dp, ctypes.POINTER(ctypes.c_long), ctypes.c_char_p,
                                ctypes.c_int, ctypes.c_double]
    lib.sf_sample.restype = ctypes.c_int
    lib.sf_sample.argtypes = [vp, ctypes.c_int, dp, dp]
    lib.sf_set_order.restype = ctypes.c_int
    lib.sf_set_order.argtypes = [vp, ip]
    lib.sf_free.restype = None
    lib.sf_free.argtypes = [vp]
    lib.sf_set_fused_dky.restype = None
    lib.sf_set_fused_dky.argtypes = [ctypes.c_int]
    lib.sf_set_wide_vectors.restype = None
    lib.sf_set_wide_vectors.argtypes = [ctypes.c_int]
    lib.sf_nv_apply.restype = ctypes.c_int
    lib.sf_nv_apply.argtypes = [ctypes.c_int, ctypes.c_double, ctypes.c_double, ctypes.c_long, dp, dp, dp,
                                ctypes.c_int, ctypes.c_int, dp]
    lib.sf_has_wide_vectors.restype = ctypes.c_int
    lib.sf_has_wide_vectors.argtypes = [vp]
    lib.sf_set_lu_columns.restype = None
    lib.sf_set_lu_columns.argtypes = [vp, ctypes.c_int]
    lib.sf_max_growth.restype = ctypes.c_double
    lib.sf_max_growth.argtypes = [vp]
    lib.sf_factor_solve.restype = ctypes.c_int
    lib.sf_factor_solve.argtypes = [vp, dp, ctypes.c_double, dp]
    lp = ctypes.POINTER(ctypes.c_long)
    lib.sf_loop_run.restype = ctypes.c_int
    lib.sf_loop_run.argtypes = [vp, vp, vp, ip, dp, ip, ip, ip, dp, dp, lp, dp, dp, lp, dp, dp, dp, ctypes.c_long]
    return lib


def available() -> bool:
    """Whether the direct backend can run here (the driver builds and loads)."""
    return driver_library() is not None


def unavailable_reason() -> str | None:
    """Why the direct backend is not available (None when it is, or before it was tried)."""
    return _REASON[-1] if _REASON else None


def _ptr(a: np.ndarray, kind=ctypes.c_double):
    return a.ctypes.data_as(ctypes.POINTER(kind))


class DirectCvodes:
    """One CVODES instance on a compiled closed-loop library (its `symfunnel_ode` and `jac_symfunnel_ode`), reused
    for every call; `run` integrates one chunk (calls from several threads take turns)."""

    #: the options of `family.integrators.cvodes_options` this driver implements (anything else: casadi.integrator)
    OPTIONS = frozenset({"abstol", "reltol", "max_num_steps", "max_step_size", "max_order", "linear_solver",
                         "disable_internal_warnings", "show_eval_warnings"})

    def __init__(self, library: str, nx: int, n_p: int, options: dict, order: np.ndarray | None = None):
        """`order`: the states are returned as x[order] (the caller's public order: the driver writes them so,
        instead of a permuted copy of every output array afterwards); None: CVODES' order."""
        import casadi as ca
        unknown = set(options) - self.OPTIONS
        if unknown or options.get("linear_solver", "csparse") != "csparse":
            raise RuntimeError(f"options the CVODES driver does not implement: {sorted(unknown)}")
        lib = driver_library()
        if lib is None:
            raise RuntimeError(unavailable_reason() or "the CVODES driver is not available")
        self._lib = lib
        self._cl = ctypes.CDLL(library)          # the closed loop's library (CasADi has it loaded already)
        ode = ca.external("symfunnel_ode", library)
        jac = ca.external("jac_symfunnel_ode", library)
        for i, name in ((0, "t"), (1, "x"), (3, "p")):
            if ode.name_in(i) != name or jac.name_in(i) != name:
                raise RuntimeError(f"unexpected inputs of the closed loop's functions: {ode.name_in()}")
        if ode.name_out(0) != "ode" or ode.nnz_out(0) != nx or ode.nnz_in(1) != nx or ode.nnz_in(3) != n_p:
            raise RuntimeError("unexpected outputs of the closed loop's DAE function")
        jx = jac.index_out("jac_ode_x")
        sp = jac.sparsity_out(jx)
        if sp.size() != (nx, nx):
            raise RuntimeError("unexpected Jacobian shape")
        self.nx, self.n_p = nx, n_p
        self.nnz = sp.nnz()
        sizes = np.array([ode.sz_arg(), ode.sz_res(), ode.sz_iw(), ode.sz_w(), jac.sz_arg(), jac.sz_res(),
                          jac.sz_iw(), jac.sz_w(), jac.n_in(), jac.n_out(), jx], dtype=np.longlong)
        Jp = np.array(sp.colind(), dtype=np.intc)
        Ji = np.array(sp.row(), dtype=np.intc)
        err = ctypes.create_string_buffer(400)
        fptr = (ctypes.cast(self._cl.symfunnel_ode, ctypes.c_void_p).value,
                ctypes.cast(self._cl.jac_symfunnel_ode, ctypes.c_void_p).value)
        with _CREATE_LOCK:             # the driver reads the vector switch when it creates the solver
            lib.sf_set_wide_vectors(1 if WIDE_VECTORS else 0)
            h = lib.sf_create(nx, n_p, fptr[0], fptr[1], _ptr(sizes, ctypes.c_longlong), _ptr(Jp, ctypes.c_int),
                              _ptr(Ji, ctypes.c_int), float(options["reltol"]), float(options["abstol"]),
                              int(options["max_num_steps"]), float(options.get("max_step_size", 0.0)),
                              int(options.get("max_order", 0)), err, len(err))
        if not h:
            raise RuntimeError(f"the CVODES driver refused the closed loop: {err.value.decode(errors='replace')}")
        self._h = h
        self._finalizer = weakref.finalize(self, lib.sf_free, h)
        self.scheduled_lu = bool(SCHEDULED_LU)
        #: whether this solver's vectors run the four-wide operations (AVX2 here and the table as expected)
        self.wide_vectors = bool(lib.sf_has_wide_vectors(h))
        lib.sf_set_lu_columns(h, 0 if self.scheduled_lu else 1)
        self.order = None if order is None else np.ascontiguousarray(order, dtype=np.intc)
        if self.order is not None and (self.order.shape != (nx,)
                                       or lib.sf_set_order(h, _ptr(self.order, ctypes.c_int))):
            raise RuntimeError("the output order is not a permutation of the states")
        self._stats = np.zeros(8, dtype=np.int_ if ctypes.sizeof(ctypes.c_long) == 8 else np.int32)
        self._msg = ctypes.create_string_buffer(200)
        self._lock = threading.Lock()

    def run(self, p: np.ndarray, x0: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, dict]:
        """States (K, nx) at the relative times `grid` from x0 at 0 (x0 in integrator order, the states in the
        output order), and CVODES' statistics;
        RuntimeError('CVode returned "..."') when CVODES fails."""
        K = int(grid.size)
        X = np.empty((K, self.nx))
        p = np.ascontiguousarray(p, dtype=float)
        x0 = np.ascontiguousarray(x0, dtype=float)
        grid = np.ascontiguousarray(grid, dtype=float)
        with self._lock:
            rc = self._lib.sf_run(self._h, _ptr(p), _ptr(x0), K, _ptr(grid), _ptr(X),
                                  self._stats.ctypes.data_as(ctypes.POINTER(ctypes.c_long)), self._msg,
                                  len(self._msg))
        stats = self._read_stats()
        if rc < 0:
            raise RuntimeError(self._msg.value.decode(errors="replace"))
        return X, stats

    def _read_stats(self) -> dict:
        """The last integration's CVODES statistics, by name (the driver's stats array)."""
        s = [int(v) for v in self._stats]
        return {"nsteps": s[0], "nfevals": s[1], "nlinsetups": s[2], "netfails": s[3], "nniters": s[4],
                "nncfails": s[5], "n_call_jacF": s[6], "pivot_failures": s[7]}

    def run_sampled(self, p: np.ndarray, x0: np.ndarray, grid: np.ndarray, times_for,
                    max_bytes: float | None = None) -> tuple[np.ndarray, dict, np.ndarray | None] | None:
        """`run`'s integration (the same steps, output points and statistics, bit for bit) keeping every step, then
        the states at `times_for(stats)` (relative times inside the chunk, ascending) as CVODES interpolates an
        output point there -- what `run` on a grid holding those times too returns at them, without integrating
        again. None where the driver leaves the integration to `run` (a CVODES failure, the step limit per output
        point); the samples None when the kept steps would pass `max_bytes` (the caller integrates again for them)."""
        K = int(grid.size)
        X = np.empty((K, self.nx))
        p = np.ascontiguousarray(p, dtype=float)
        x0 = np.ascontiguousarray(x0, dtype=float)
        grid = np.ascontiguousarray(grid, dtype=float)
        with self._lock:                # the history is this solver's until the next run
            rc = self._lib.sf_run_hist(self._h, _ptr(p), _ptr(x0), K, _ptr(grid), _ptr(X),
                                       self._stats.ctypes.data_as(ctypes.POINTER(ctypes.c_long)), self._msg,
                                       len(self._msg), float(HISTORY_BYTES if max_bytes is None else max_bytes))
            if rc != 0:
                return None
            stats = self._read_stats()
            times = np.ascontiguousarray(times_for(stats), dtype=float)
            Y = np.empty((times.size, self.nx))
            self._lib.sf_set_fused_dky(1 if FUSED_DKY else 0)
            if times.size and self._lib.sf_sample(self._h, int(times.size), _ptr(times), _ptr(Y)):
                Y = None
        return X, stats, Y

    def max_growth(self) -> float:
        """The largest growth factor (largest entry during the elimination / largest entry of I - gamma J) of the
        factorisations so far: how far from a refused one (`csrc/cvodes_driver.c`, SF_GROWTH_MAX)."""
        return float(self._lib.sf_max_growth(self._h))

    def factor_solve(self, Jx: np.ndarray, gamma: float, b: np.ndarray) -> np.ndarray | None:
        """(I - gamma J)^-1 b with this solver's LU, J given by its nonzeros (None on a pivot failure): for tests."""
        Jx = np.ascontiguousarray(Jx, dtype=float)
        x = np.array(b, dtype=float)
        if self._lib.sf_factor_solve(self._h, _ptr(Jx), float(gamma), _ptr(x)):
            return None
        return x

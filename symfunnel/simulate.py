"""Closed-loop simulation with CasADi integrators, funnel-breach detection, a wall-clock limit and compiled code.

How a run works (docs/simulation.md has the long version):

* The closed loop (`symfunnel.closedloop`) is one SX graph x' = f(t, x). For the integrator its states are permuted
  to [vec(W_hat); x_esn; q; dq], which lets the sparse LU of CVODES' Newton matrix stay sparse (the rows of ddq are
  dense, so they go last); the public state order stays [q; dq; x_esn; vec(W_hat)].
* The right-hand side, its sparse Jacobian and the logged signals are generated as C (`casadi.CodeGenerator`),
  compiled once with the system C compiler and cached in $SYMFUNNEL_CACHE (default ~/.cache/symfunnel) under the
  sha256 of the generated source, then loaded with `casadi.external`; without a compiler the CasADi VM is used.
* Time is integrated in chunks of the output grid (growing 1, 5, 25, 100, 500 points: reproducible), with
  a parameter for the chunk's start time, so one integrator object serves every chunk. After each chunk the funnel
  margins m_i = (F_i - |e_i|)/F_i and finiteness are checked on the grid; a breach (or an integrator failure) is
  then located on a 100x finer grid within the output step, and the trajectory up to it is kept.
* Non-smooth plant terms (Coulomb friction's sign, the dead zone's kinks) are smoothed with the scenario's
  `simulation.smoothing_width` w (plant.py: sign_w(x) = x/sqrt(x^2 + w^2), ramp_w); w = 0 keeps them exact and
  warns. `convergence_study` measures the effect of w. The controller's own |e| terms are the design, not smoothed:
  z = e/(F - |e|) is C^1 and the resulting right-hand side is Lipschitz, which BDF handles.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import subprocess
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .closedloop import OUTPUT_NAMES, ClosedLoop, build_closed_loop
from .errors import InputError
from .integrators import INTEGRATORS
from .io import json_safe

CHUNK_SIZES = (1, 5, 25, 100, 500)
LOCATE_SUBSTEPS = 100
COMPILE_FLAGS = ["-O1", "-shared", "-fPIC"]
APPROX_ESN_JACOBIAN = True
_LOADED: dict = {}           # source hash -> (ode, outputs) externals loaded in this process


# --- compiled functions ----------------------------------------------------------------------------------

@dataclass
class Compiled:
    """The integrator's DAE function and the logged-signals function, compiled or on the VM."""

    dae: ca.Function                 # dyn_in -> dyn_out, states permuted, p = [chunk start time; plant p]
    outputs: ca.Function             # (t, x, p) -> OUTPUT_NAMES, public state order
    perm: np.ndarray                 # integrator state i = public state perm[i]
    mode: str                        # "compiled" or "vm"
    compile_time: float = 0.0
    cached: bool = False
    library: str | None = None
    source_hash: str | None = None
    maps: dict = field(default_factory=dict, repr=False)
    pvals: np.ndarray | None = None  # the plant parameters of the run this copy is bound to (see `bind`)
    integrators: dict = field(default_factory=dict, repr=False)

    def bind(self, pvals) -> "Compiled":
        """This compiled loop bound to one run's plant parameters (shares the code and the output maps)."""
        return dataclasses.replace(self, pvals=np.asarray(pvals, dtype=float).reshape(-1))


def _permutation(cl: ClosedLoop) -> np.ndarray:
    """Controller states last first, joints last: keeps the Newton matrix's LU fill-in low."""
    s = cl.slices
    idx = np.arange(cl.nx)
    states = [name for name, _ in reversed(cl.design.states)]
    return np.concatenate([idx[s[k]] for k in states] + [idx[s["q"]], idx[s["dq"]]])


def _dae_function(cl: ClosedLoop, perm: np.ndarray) -> ca.Function:
    t0 = ca.SX.sym("t0")
    p = ca.vertcat(t0, cl.p)
    xi = cl.x[list(perm)]
    ode = ca.substitute(cl.xdot_p, cl.t, cl.t + t0)[list(perm)]
    empty = ca.SX(0, 1)
    return ca.Function("symfunnel_ode", [cl.t, xi, ca.SX.sym("z", 0, 1), p, ca.SX.sym("u", 0, 1)],
                       [ode, empty, empty, empty], ca.dyn_in(), ca.dyn_out(), {"cse": True})


def _newton_jacobian(cl: ClosedLoop, dae: ca.Function, perm: np.ndarray) -> ca.Function:
    """The Jacobian CVODES' Newton iteration uses: exact, except the reservoir's internal coupling.

    The block d(x_esn_dot)/d(x_esn) = (1/time_constant)(-leak I + diag(tanh') W) is replaced by its diagonal: the
    dropped part has norm <= spectral-radius-ish 0.9/time_constant, so h*||dropped|| << 1 at the step sizes the
    stiff funnel/friction modes impose, and Newton still converges (a modified Newton iteration; CVODES' error
    control, hence the accuracy, is unchanged). Without it, the random sparse W makes the LU of the Newton matrix
    fill in to a dense 50 x 50 block, which costs more than everything else in the run.
    """
    jac = dae.jacobian()
    ins = [ca.SX.sym(jac.name_in(i), jac.sparsity_in(i)) for i in range(jac.n_in())]
    outs = jac.call(ins)
    ix = jac.name_out().index("jac_ode_x")
    J = outs[ix]
    pos = np.empty(cl.nx, dtype=int)
    pos[perm] = np.arange(cl.nx)
    esn = set(int(v) for v in pos[cl.slices["x_esn"]]) if "x_esn" in cl.slices else set()
    rows, cols = J.sparsity().get_triplet()
    keep_r, keep_c, vals = [], [], []
    for r, c in zip(rows, cols):
        if r in esn and c in esn and r != c:
            continue
        keep_r.append(r)
        keep_c.append(c)
        vals.append(J[r, c])
    sp = ca.Sparsity.triplet(J.size1(), J.size2(), keep_r, keep_c)
    Jn = ca.SX(sp, ca.vertcat(*vals) if vals else ca.SX(0, 1))
    outs[ix] = Jn
    return ca.Function(jac.name(), ins, outs, jac.name_in(), jac.name_out(), {"cse": True})


def compile_closed_loop(cl: ClosedLoop, *, progress=None, jit: bool = True,
                        approx_jacobian: bool = APPROX_ESN_JACOBIAN) -> Compiled:
    """Generate C for the closed loop's RHS, Jacobian and outputs, compile it once (cached) and load it.

    `approx_jacobian` selects the modified-Newton Jacobian of `_newton_jacobian` (right for CVODES, whose error
    control does not depend on it); collocation solves its stage equations with that Jacobian too, and needs the
    exact one to converge.
    """
    say = progress or (lambda s: None)
    perm = _permutation(cl)
    dae = _dae_function(cl, perm)
    outputs = ca.Function("symfunnel_outputs", [cl.t, cl.x, cl.p], [cl.signals_p[k] for k in OUTPUT_NAMES],
                          ["t", "x", "p"], list(OUTPUT_NAMES), {"cse": True})
    vm = Compiled(dae=dae, outputs=outputs, perm=perm, mode="vm")
    if not jit or os.environ.get("SYMFUNNEL_NO_JIT"):
        return vm
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="symfunnel-cg-") as tmp:
        cg = ca.CodeGenerator("symfunnel_cl.c", {"with_header": False})
        cg.add(dae)
        cg.add(_newton_jacobian(cl, dae, perm) if approx_jacobian else dae.jacobian())
        cg.add(outputs)
        cg.generate(tmp + os.sep)
        src = Path(tmp, "symfunnel_cl.c").read_bytes()
    digest = hashlib.sha256(src + " ".join(COMPILE_FLAGS).encode() + ca.__version__.encode()).hexdigest()[:24]
    if digest in _LOADED:
        ext_dae, ext_out, lib = _LOADED[digest]
        return Compiled(ext_dae, ext_out, perm, "compiled", time.perf_counter() - t0, True, lib, digest)
    from .codegen.build import compile_cached, find_compiler
    try:
        find_compiler()
    except InputError:
        warnings.warn("no C compiler found (gcc/cc/$CC): simulating on the CasADi virtual machine (slower)",
                      RuntimeWarning, stacklevel=2)
        return vm
    try:
        built = compile_cached({"symfunnel_cl.c": src}, ["symfunnel_cl.c"], "symfunnel_cl.so", COMPILE_FLAGS,
                               on_build=say)
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        warnings.warn(f"compiling the closed loop failed ({exc}); simulating on the CasADi virtual machine",
                      RuntimeWarning, stacklevel=2)
        return vm
    lib, cached = built.path, built.cached
    try:
        ext_dae = ca.external("symfunnel_ode", str(lib))
        ext_out = ca.external("symfunnel_outputs", str(lib))
    except RuntimeError as exc:
        from .sim_hints import error_line
        warnings.warn(f"loading {lib} failed ({error_line(str(exc))}); simulating on the CasADi virtual machine",
                      RuntimeWarning, stacklevel=2)
        return vm
    _LOADED[digest] = (ext_dae, ext_out, str(lib))
    return Compiled(ext_dae, ext_out, perm, "compiled", time.perf_counter() - t0, cached, str(lib), digest)


# --- results ---------------------------------------------------------------------------------------------

@dataclass
class SimResult:
    """A simulated trajectory (arrays with time as the first axis), its status and statistics."""

    scenario: str
    t: np.ndarray
    x: np.ndarray                              # (T, n_x), public state order
    signals: dict                              # logged signals (T, ...) plus q, dq, x_esn, w_hat
    status: str                                # 'ok' | 'breach' | 'initial_outside' | 'timeout' | 'failed'
    message: str
    breach: dict | None
    stats: dict
    n: int = 0
    gamma: float = 1.0
    convergence: dict | None = None

    @property
    def ok(self) -> bool:
        """True when the run reached its final time inside both funnels."""
        return self.status == "ok"

    def __getattr__(self, name):
        sig = self.__dict__.get("signals", {})
        if name in sig:
            return sig[name]
        raise AttributeError(name)

    def summary(self) -> dict:
        """The JSON summary: margins, torque, ESN estimation error, wall time, integrator statistics."""
        s = self.signals
        T = self.t.size

        def per_joint(fn, key):
            a = s.get(key)
            if a is None or a.shape[0] == 0:
                return [None] * self.n
            return [float(v) for v in fn(a)]

        out = {
            "scenario": self.scenario,
            "status": self.status,
            "message": self.message,
            "t_end": float(self.t[-1]) if T else 0.0,
            "t_final": self.stats.get("t_final"),
            "points": int(T),
            "min_margin_e1": per_joint(lambda a: np.min(a, axis=0), "m1"),
            "min_margin_e2": per_joint(lambda a: np.min(a, axis=0), "m2"),
            "max_abs_e1": per_joint(lambda a: np.max(np.abs(a), axis=0), "e1"),
            "max_abs_tau": per_joint(lambda a: np.max(np.abs(a), axis=0), "tau"),
            "max_abs_tau_applied": per_joint(lambda a: np.max(np.abs(a), axis=0), "tau_applied"),
            "rms_esn_error": per_joint(lambda a: np.sqrt(np.mean(a ** 2, axis=0)), "esn_error"),
            "rms_f_true": per_joint(lambda a: np.sqrt(np.mean(a ** 2, axis=0)), "f_true"),
            "max_abs_w_hat": float(np.max(np.abs(s["w_hat"]))) if T and "w_hat" in s else None,
            "max_abs_x_esn": float(np.max(np.abs(s["x_esn"]))) if T and "x_esn" in s else None,
            "breach": self.breach,
            "wall_time": self.stats.get("wall_time"),
            "realtime_factor": self.stats.get("realtime_factor"),
            "compile_time": self.stats.get("compile_time"),
            "code": self.stats.get("code"),
            "integrator": self.stats.get("integrator"),
            "smoothing_width": self.stats.get("smoothing_width"),
            "non_smooth_treatment": self.stats.get("non_smooth_treatment"),
            "steps": self.stats.get("steps"),
            "rhs_evaluations": self.stats.get("rhs_evaluations"),
            "jacobian_evaluations": self.stats.get("jacobian_evaluations"),
            "error_test_failures": self.stats.get("error_test_failures"),
            "events": self.stats.get("events"),
            "event_counts": self.stats.get("event_counts"),
        }
        if self.convergence is not None:
            out["convergence"] = self.convergence
        return json_safe(out)

    def to_json(self) -> dict:
        """The JSON summary (as `simulate --json`)."""
        return self.summary()

    def _repr_html_(self) -> str:
        """A notebook line: status and message."""
        import html
        return f"<p>simulation <b>{html.escape(self.status)}</b>: {html.escape(self.message)}</p>"

    def save_npz(self, path, arrays: dict | None = None) -> Path:
        """Write the trajectory (time first; `arrays` adds e.g. V and W* of the Lyapunov stage) and the run's
        metadata to an .npz file, atomically."""
        from .io import atomic_path
        data = {"t": self.t}
        for k, v in self.signals.items():
            data[k] = np.asarray(v)
        for k, v in (arrays or {}).items():
            data[k] = np.asarray(v)
        data["status"] = np.array(self.status)
        data["message"] = np.array(self.message)
        data["smoothing_width"] = np.array(self.stats.get("smoothing_width", float("nan")))
        data["integrator"] = np.array(self.stats.get("integrator", ""))
        path = Path(path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **data)
        return path


# --- the run ---------------------------------------------------------------------------------------------

class _Timeout(Exception):
    pass


class _Runner:
    """Chunked integration on the output grid with breach location; one per run."""

    def __init__(self, cl: ClosedLoop, comp: Compiled, method: str, h: float, sim):
        self.cl, self.comp, self.method, self.h, self.sim = cl, comp, method, h, sim
        self.perm = comp.perm
        self.inv = np.argsort(comp.perm)
        # integrators are shared by every run on this compiled loop (a campaign builds them once)
        self._integrators: dict = comp.integrators
        self.stats = {"steps": 0, "rhs_evaluations": 0, "jacobian_evaluations": 0, "error_test_failures": 0,
                      "integrate_time": 0.0}

    def integrator(self, K: int, h: float | None = None):
        """An integrator over the relative output grid h, 2h, ..., K h (p = the chunk's start time)."""
        h = self.h if h is None else h
        key = (self.method, K, h, self.h, self.sim.atol, self.sim.rtol, self.sim.rk_substeps,
               getattr(self.sim, "max_step", 0.0))
        if key not in self._integrators:
            sim = self.sim
            grid = [h * (k + 1) for k in range(K)]
            opts = INTEGRATORS.get(self.method)(sim, h, self.h, K)
            opts["show_eval_warnings"] = False
            self._integrators[key] = ca.integrator(f"sim_{K}", self.method, self.comp.dae, 0.0, grid, opts)
        return self._integrators[key]

    def run(self, t0: float, x0: np.ndarray, K: int, h: float | None = None) -> np.ndarray:
        """States (K, n_x), public order, at t0 + h, ..., t0 + K h; RuntimeError when the integrator fails."""
        F = self.integrator(K, h)
        c0 = time.perf_counter()
        try:
            st = {}
            xf = _evaluate(F, {"x0": x0[self.perm], "p": np.concatenate([[t0], self.comp.pvals])}, "xf", st)
        except RuntimeError as exc:
            from .lifecycle import reraise_interrupt
            reraise_interrupt(exc)                 # a signal during the integration is not an integrator failure
            from .sim_hints import error_line
            self.last_error = error_line(str(exc))
            raise
        self.stats["integrate_time"] += time.perf_counter() - c0
        if self.method == "cvodes":
            self.stats["steps"] += int(st.get("nsteps", 0))
            self.stats["rhs_evaluations"] += int(st.get("nfevals", 0))
            self.stats["jacobian_evaluations"] += int(st.get("n_call_jacF", 0))
            self.stats["error_test_failures"] += int(st.get("netfails", 0))
        else:
            self.stats["steps"] += int(st.get("n_call_step", 0)) * 1
            self.stats["rhs_evaluations"] += int(st.get("n_call_daeF", 0))
        return xf[:, self.inv]


def _outputs(comp: Compiled, n: int, t: np.ndarray, X: np.ndarray) -> dict:
    T = t.size
    if T == 0:
        return {k: np.zeros((0, n)) for k in OUTPUT_NAMES}
    fm = comp.maps.get(T)
    if fm is None:
        # every logged signal stacked into one matrix: one DM -> numpy conversion per chunk instead of one per signal
        f = comp.outputs.map(T)
        ins = [ca.MX.sym(f.name_in(i), f.sparsity_in(i)) for i in range(f.n_in())]
        fm = comp.maps[T] = ca.Function("outputs_stacked", ins, [ca.vertcat(*f.call(ins))])
    P = np.broadcast_to(comp.pvals, (T, comp.pvals.size))             # the map takes p once per point
    # rows in C order, each signal a transposed view of them: the memory layout numpy's reductions (and so the
    # summary's last digits) have always seen
    rows = np.ascontiguousarray(_evaluate(fm, {fm.name_in(0): t, fm.name_in(1): X, fm.name_in(2): P},
                                          fm.name_out(0)).T)
    out, i = {}, 0
    for k in OUTPUT_NAMES:
        r = comp.outputs.size1_out(k)
        out[k] = rows[i:i + r].T
        i += r
    return out


def _evaluate(F: ca.Function, args: dict, out: str, stats: dict | None = None) -> np.ndarray:
    """F's output `out` (transposed: columns first) computed straight into a numpy array from numpy inputs.

    CasADi's buffer interface skips the DM round trip of a plain call (a list of Python floats per matrix, about a
    tenth of a campaign run's CPU time); inputs not given are zero, as in a call. Matrices are column-major in
    CasADi, so a C-ordered (columns, rows) array is the (rows, columns) matrix without a copy. `stats` receives
    this call's statistics (the buffer evaluates in a memory of its own, so `F.stats()` would not see them).
    """
    buf, trigger = F.buffer()
    before = {}
    if stats is not None:
        try:
            before = buf.stats()          # the buffer's memory may have served earlier calls: count from here
        except RuntimeError:
            before = {}
    keep = []                             # CasADi holds raw pointers: the arrays must outlive the call
    for name, a in args.items():
        a = np.ascontiguousarray(a, dtype=float)
        if a.size != F.numel_in(name):
            raise ValueError(f"{F.name()}: input {name} has {a.size} values, expected {F.numel_in(name)}")
        keep.append(a)
        buf.set_arg(F.index_in(name), memoryview(a.reshape(-1)))
    res = np.empty((F.size2_out(out), F.size1_out(out)))
    buf.set_res(F.index_out(out), memoryview(res.reshape(-1)))
    trigger()
    if stats is not None:
        # CasADi's own call counters and timers (n_call_*, t_*) add up in a memory; the solver's counters restart
        stats.update({k: v - before.get(k, 0) if k.startswith(("n_call_", "t_proc_", "t_wall_")) else v
                      for k, v in buf.stats().items()})
    return res


def _bad_index(o: dict, X: np.ndarray) -> tuple[int | None, str]:
    """First grid index where a margin is <= 0 or a value is not finite, with what happened."""
    T = X.shape[0]
    finite = np.isfinite(X).all(axis=1)
    for k in ("m1", "m2", "tau"):
        finite &= np.isfinite(o[k]).reshape(T, -1).all(axis=1)
    inside = (o["m1"] > 0).all(axis=1) & (o["m2"] > 0).all(axis=1)
    bad = ~(finite & inside)
    if not bad.any():
        return None, ""
    i = int(np.argmax(bad))
    return i, ("nonfinite" if not finite[i] else "breach")


def _describe_breach(t: float, o: dict, i: int, n: int) -> dict:
    m1, m2 = o["m1"][i], o["m2"][i]
    for key, m, e, F in (("e1", m1, o["e1"][i], o["F1"][i]), ("e2", m2, o["e2"][i], o["F2"][i])):
        if np.any(~(m > 0)):
            j = int(np.argmax(~(m > 0)))
            return {"time": float(t), "funnel": key, "joint": j + 1, "margin": float(m[j]),
                    "abs_error": float(abs(e[j])), "boundary": float(F[j])}
    j1 = int(np.argmin(m1))
    j2 = int(np.argmin(m2))
    if m1[j1] <= m2[j2]:
        return {"time": float(t), "funnel": "e1", "joint": j1 + 1, "margin": float(m1[j1]),
                "abs_error": float(abs(o["e1"][i][j1])), "boundary": float(o["F1"][i][j1])}
    return {"time": float(t), "funnel": "e2", "joint": j2 + 1, "margin": float(m2[j2]),
            "abs_error": float(abs(o["e2"][i][j2])), "boundary": float(o["F2"][i][j2])}


def _grid(t_final: float, dt: float) -> tuple[int, float]:
    M = max(1, int(math.ceil(t_final / dt - 1e-9)))
    return M, t_final / M


def simulate(scenario, design, *, t_final=None, integrator=None, width=None, progress=None,
             wall_limit=None, closed_loop=None, jit: bool = True, params=None, x0=None,
             fixed_chunks: bool = False) -> SimResult:
    """Simulate a scenario's closed loop; never raises for a breach, a timeout or an integrator failure.

    Returns a SimResult whose status is 'ok', 'breach', 'initial_outside', 'timeout' or 'failed', with the
    trajectory up to where the run stopped. Bad settings raise InputError. `params` (name -> value, names of
    `closedloop.plant_parameters`) and `x0` (public state order) override the closed loop's plant quantities and
    initial state without recompiling: a campaign runs every variant on one compiled loop. `fixed_chunks`
    integrates in the chunks a fast machine chooses (25 points, then 500) whatever the wall time, so that the
    result does not depend on the machine's speed (CVODES restarts at every chunk).
    """
    say = progress or (lambda s: None)
    sc = scenario
    sim = sc.simulation
    tf = sim.t_final if t_final is None else t_final
    if not (isinstance(tf, (int, float)) and not isinstance(tf, bool) and math.isfinite(tf) and tf > 0):
        raise InputError(f"is {tf!r}", key="--t-final", expected="a number > 0")
    if tf / sim.dt > 1e6:
        raise InputError(f"gives {tf / sim.dt:.3g} output points", key="--t-final",
                         expected="at most 1e6 output points (t_final/dt)")
    method = integrator or sim.integrator
    INTEGRATORS.get(method, key="--integrator")
    limit = sim.wall_limit if wall_limit is None else float(wall_limit)
    w = sim.smoothing_width if width is None else width
    if not (isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
        raise InputError(f"is {w!r}", key="--width", expected="a number >= 0")
    w = float(w)

    start = time.perf_counter()
    if closed_loop is None:
        say("building the closed loop")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            cl = build_closed_loop(sc, design, width=w)
    else:
        cl = closed_loop
    if w == 0.0:
        warnings.warn("smoothing_width = 0: exact sign friction and dead-zone kinks; CVODES may take many tiny "
                      "steps at every switch (the wall-clock limit still applies)", RuntimeWarning, stacklevel=2)
    approx = method == "cvodes" and APPROX_ESN_JACOBIAN
    comp = getattr(cl, "_compiled", {}).get((jit, approx))
    if comp is None:
        comp = compile_closed_loop(cl, progress=say, jit=jit, approx_jacobian=approx)
        cl.__dict__.setdefault("_compiled", {})[(jit, approx)] = comp
    compile_time = time.perf_counter() - start
    pv = cl.p0.copy()
    if params:
        index = {k: i for i, k in enumerate(cl.p_names)}
        for k, v in params.items():
            if k not in index:
                raise InputError("is not a plant parameter of this closed loop", key=k,
                                 expected="one of " + ", ".join(cl.p_names))
            pv[index[k]] = float(v)
    comp = comp.bind(pv)

    M, h = _grid(float(tf), sim.dt)
    n = cl.n
    treatment = (f"smoothing of width {w:g} (sign_w(x) = x/sqrt(x^2+w^2) for Coulomb friction, "
                 f"ramp_w(x) = (x+sqrt(x^2+w^2))/2 at the dead-zone breakpoints)") if w > 0 else \
        "exact non-smooth terms (no smoothing)"
    stats = {"integrator": method, "smoothing_width": w, "non_smooth_treatment": treatment,
             "t_final": float(tf), "dt": h, "code": comp.mode, "compiled_library": comp.library,
             "cache_hit": comp.cached, "compile_time": compile_time, "rtol": sim.rtol, "atol": sim.atol,
             "wall_limit": limit}
    runner = _Runner(cl, comp, method, h, sim)

    # initial point
    x0 = cl.x0.copy() if x0 is None else np.asarray(x0, dtype=float).reshape(cl.nx).copy()
    t_list = [np.array([0.0])]
    X_list = [x0[None, :]]
    o0 = _outputs(comp, n, np.array([0.0]), x0[None, :])
    O_list = [o0]              # logged signals of the segments of t_list computed on the way (None: not yet)
    bi, kind = _bad_index(o0, x0[None, :])
    status, message, breach = "ok", "", None
    if bi is not None:
        if kind == "nonfinite":
            status = "failed"
            message = "the initial state gives non-finite signals (check the scenario's initial values)"
        else:
            b = _describe_breach(0.0, o0, 0, n)
            status = "initial_outside"
            breach = b
            message = (f"initial error outside funnel {b['funnel']} at joint {b['joint']}: "
                       f"|{b['funnel']}(0)| = {b['abs_error']:.6g} >= F{b['funnel'][1]}(0) = {b['boundary']:.6g}")
        return _finish(sc, cl, comp, t_list, X_list, status, message, breach, stats, runner, start, O_list)

    sim_start = time.perf_counter()
    k = 0                      # grid index reached
    x = x0
    K = 25
    last_report = sim_start
    try:
        while k < M:
            Kc = min(K, M - k)
            t0 = k * h
            elapsed = time.perf_counter() - start
            if elapsed > limit:
                raise _Timeout()
            c0 = time.perf_counter()
            try:
                X = runner.run(t0, x, Kc)
                failed = False
            except RuntimeError:
                X, failed = None, True
            if failed:
                # redo point by point to find the last good grid point, then locate within the step
                res = _locate_failure(runner, comp, n, k, x, Kc, h, start, limit)
                t_list.extend(res["t"])
                X_list.extend(res["X"])
                status, message, breach = res["status"], res["message"], res["breach"]
                break
            tc = t0 + h * np.arange(1, Kc + 1)
            tc[-1] = min(tc[-1], float(tf)) if k + Kc == M else tc[-1]
            o = _outputs(comp, n, tc, X)
            bi, kind = _bad_index(o, X)
            if bi is not None:
                t_list.append(tc[:bi])
                X_list.append(X[:bi])
                xs = X[bi - 1] if bi > 0 else x
                ts = tc[bi - 1] if bi > 0 else t0
                res = _locate_within(runner, comp, n, ts, xs, h)
                t_list.extend(res["t"])
                X_list.extend(res["X"])
                status, message, breach = res["status"], res["message"], res["breach"]
                break
            t_list.append(tc)
            X_list.append(X)
            O_list.append(o)
            k += Kc
            x = X[-1]
            spent = time.perf_counter() - c0
            # Chunks grow along CHUNK_SIZES whatever the wall time, so a run is reproducible bit for bit (CVODES
            # restarts at chunk boundaries); only a chunk that would overrun the wall-clock limit is shrunk.
            per_point = spent / Kc
            remaining = max(limit - (time.perf_counter() - start), 1e-3)
            if fixed_chunks:
                K = CHUNK_SIZES[-1]
            else:
                K = CHUNK_SIZES[min(CHUNK_SIZES.index(K) + 1, len(CHUNK_SIZES) - 1)] if K in CHUNK_SIZES else 1
            if per_point * K > remaining / 4:
                K = max([c for c in CHUNK_SIZES if per_point * c <= remaining / 4] or [1])
            now = time.perf_counter()
            if now - last_report > 2.0:
                say(f"t = {k * h:.3g} / {tf:g} s")
                last_report = now
    except _Timeout:
        tr = float(np.concatenate(t_list)[-1])
        status = "timeout"
        message = (f"wall-clock limit of {limit:g} s reached at t = {tr:.6g} s of {tf:g} s; the trajectory so "
                   f"far is kept (raise simulation.wall_limit, or check the scenario for stiffness)")
    stats["sim_wall_time"] = time.perf_counter() - sim_start
    return _finish(sc, cl, comp, t_list, X_list, status, message, breach, stats, runner, start, O_list)


def _locate_within(runner: _Runner, comp: Compiled, n: int, ts: float, xs: np.ndarray, h: float) -> dict:
    """From the last good grid point (ts, xs), find the breach/failure within one output step on a fine grid."""
    hf = h / LOCATE_SUBSTEPS
    try:
        X = runner.run(ts, xs, LOCATE_SUBSTEPS, hf)
        failed = False
    except RuntimeError:
        failed = True
    if failed:
        # step through the fine grid one substep at a time
        good_t, good_X = [], []
        x, t = xs, ts
        for j in range(LOCATE_SUBSTEPS):
            try:
                Xj = runner.run(t, x, 1, hf)
            except RuntimeError:
                break
            oj = _outputs(comp, n, np.array([t + hf]), Xj)
            bi, _ = _bad_index(oj, Xj)
            if bi is not None:
                return _breach_result(comp, n, good_t, good_X, t + hf, Xj, oj, ts, xs)
            good_t.append(t + hf)
            good_X.append(Xj[0])
            t, x = t + hf, Xj[0]
        # integrator failure at t: report as a breach when close to a boundary
        oc = _outputs(comp, n, np.array([t]), x[None, :])
        b = _describe_breach(t, oc, 0, n)
        tt = [np.array(good_t)] if good_t else []
        XX = [np.array(good_X)] if good_X else []
        if np.isfinite(b["margin"]) and b["margin"] < 0.05:
            b["integrator_failed"] = True
            msg = (f"funnel breach at t = {t:.6g} s: {b['funnel']} of joint {b['joint']} reached its boundary "
                   f"(margin {b['margin']:.3g}, |{b['funnel']}| = {b['abs_error']:.6g}, "
                   f"F = {b['boundary']:.6g}); the integrator could not continue (z -> infinity)")
            return {"t": tt, "X": XX, "status": "breach", "message": msg, "breach": b}
        msg = (f"the integrator failed at t = {t:.6g} s with every margin > 0.05 (smallest {b['margin']:.3g} "
               f"on {b['funnel']} joint {b['joint']}); the trajectory so far is kept")
        return {"t": tt, "X": XX, "status": "failed", "message": msg, "breach": None}
    tf = ts + hf * np.arange(1, LOCATE_SUBSTEPS + 1)
    o = _outputs(comp, n, tf, X)
    bi, kind = _bad_index(o, X)
    if bi is None:       # not reproduced on the fine grid: keep it, and say the run could not go on
        tt = [tf]
        msg = (f"the integrator failed after t = {tf[-1]:.6g} s although every margin was positive there "
               f"(smallest {min(float(np.min(o['m1'][-1])), float(np.min(o['m2'][-1]))):.3g}); "
               f"the trajectory so far is kept")
        return {"t": tt, "X": [X], "status": "failed", "message": msg, "breach": None}
    good_t = list(tf[:bi])
    good_X = list(X[:bi])
    ob = {k: v[bi:bi + 1] for k, v in o.items()}
    return _breach_result(comp, n, good_t, good_X, tf[bi], X[bi:bi + 1], ob, ts, xs)


def _breach_result(comp, n, good_t, good_X, tb, Xb, ob, ts, xs) -> dict:
    tt = [np.array(good_t)] if good_t else []
    XX = [np.array(good_X)] if good_X else []
    finite = bool(np.isfinite(Xb).all() and all(np.isfinite(ob[k]).all() for k in ("m1", "m2", "tau")))
    if not finite:
        bad = [k for k in ("m1", "m2", "tau") if not np.isfinite(ob[k]).all()]
        msg = (f"non-finite value (NaN/inf) in {'the state' if not np.isfinite(Xb).all() else bad[0]} at "
               f"t = {tb:.6g} s; the run stopped there and the trajectory so far is kept")
        return {"t": tt, "X": XX, "status": "failed", "message": msg, "breach": None}
    b = _describe_breach(tb, ob, 0, n)
    msg = (f"funnel breach at t = {tb:.6g} s: |{b['funnel']}| of joint {b['joint']} = {b['abs_error']:.6g} "
           f"reached F{b['funnel'][1]} = {b['boundary']:.6g} (margin {b['margin']:.3g}); "
           f"the trajectory up to the breach is kept")
    return {"t": tt, "X": XX, "status": "breach", "message": msg, "breach": b}


def _locate_failure(runner, comp, n, k, x, Kc, h, start, limit) -> dict:
    """The chunk from grid index k failed: advance point by point, then locate within the failing step."""
    t_acc, X_acc = [], []
    t = k * h
    for j in range(Kc):
        if time.perf_counter() - start > limit:
            break
        try:
            Xj = runner.run(t, x, 1)
        except RuntimeError:
            res = _locate_within(runner, comp, n, t, x, h)
            return {"t": ([np.array(t_acc)] if t_acc else []) + res["t"],
                    "X": ([np.array(X_acc)] if X_acc else []) + res["X"],
                    "status": res["status"], "message": res["message"], "breach": res["breach"]}
        oj = _outputs(comp, n, np.array([t + h]), Xj)
        bi, _ = _bad_index(oj, Xj)
        if bi is not None:
            res = _locate_within(runner, comp, n, t, x, h)
            return {"t": ([np.array(t_acc)] if t_acc else []) + res["t"],
                    "X": ([np.array(X_acc)] if X_acc else []) + res["X"],
                    "status": res["status"], "message": res["message"], "breach": res["breach"]}
        t_acc.append(t + h)
        X_acc.append(Xj[0])
        t, x = t + h, Xj[0]
    msg = (f"the integrator failed within t = {k * h:.6g} .. {t:.6g} s but not when stepping point by point; "
           f"stopped at t = {t:.6g} s")
    return {"t": [np.array(t_acc)] if t_acc else [], "X": [np.array(X_acc)] if X_acc else [],
            "status": "failed", "message": msg, "breach": None}


def _count_events(sc, o: dict, dq: np.ndarray) -> dict:
    """Switches of the non-smooth terms seen on the output grid (friction sign, dead-zone regions, e = 0)."""
    def crossings(a):
        s = np.sign(a)
        return int(np.sum((s[1:] * s[:-1]) < 0)) if a.shape[0] > 1 else 0
    ev = {"friction_sign_changes": crossings(dq) if len(dq) else 0,
          "e1_zero_crossings": crossings(o["e1"]) if len(o["e1"]) else 0,
          "e2_zero_crossings": crossings(o["e2"]) if len(o["e2"]) else 0}
    dz = sc.plant.dead_zone
    if dz is not None and len(o["tau"]) > 1:
        tau = o["tau"]
        region = (tau >= np.asarray(dz.b_r)).astype(int) - (tau <= np.asarray(dz.b_l)).astype(int)
        ev["dead_zone_transitions"] = int(np.sum(region[1:] != region[:-1]))
    else:
        ev["dead_zone_transitions"] = 0
    return ev


def _finish(sc, cl, comp, t_list, X_list, status, message, breach, stats, runner, start,
            O_list=None) -> SimResult:
    O_list = list(O_list or [])
    if status == "failed" and runner is not None and not message.startswith("the initial state"):
        from .sim_hints import failure_hint
        message += failure_hint(runner.method, stats["smoothing_width"], sc.simulation, stats["dt"],
                                getattr(runner, "last_error", None))
    segs = []
    for i, (ta, Xa) in enumerate(zip(t_list, X_list)):
        ta = np.atleast_1d(np.asarray(ta, dtype=float))
        if ta.size == 0:
            continue
        Xa = np.asarray(Xa, dtype=float).reshape(ta.size, cl.nx)
        oa = O_list[i] if i < len(O_list) and O_list[i] is not None else _outputs(comp, cl.n, ta, Xa)
        segs.append((ta, Xa, oa))
    if segs:
        t = np.concatenate([a for a, _, _ in segs])
        X = np.concatenate([b for _, b, _ in segs], axis=0)
        o = {k: np.concatenate([c[k] for _, _, c in segs], axis=0) for k in OUTPUT_NAMES}
    else:
        t, X = np.zeros(0), np.zeros((0, cl.nx))
        o = _outputs(comp, cl.n, t, X)
    parts = cl.unpack(X)
    signals = dict(parts)
    signals.update(o)
    signals["esn_error"] = o["w_phi"] - o["f_true"]
    gamma = float(sc.gamma)
    wall = time.perf_counter() - start
    stats.update(runner.stats)
    ev = _count_events(sc, o, parts["dq"])
    stats["event_counts"] = ev
    stats["events"] = int(sum(ev.values())) + (1 if status == "breach" else 0)
    stats["wall_time"] = wall
    sw = stats.get("sim_wall_time")
    t_end = float(t[-1]) if t.size else 0.0
    stats["realtime_factor"] = t_end / sw if sw else None
    if status == "ok":
        message = (f"reached t = {t_end:g} s inside both funnels (min margin e1 "
                   f"{np.min(o['m1']):.3g}, e2 {np.min(o['m2']):.3g})")
    return SimResult(scenario=sc.name, t=t, x=X, signals=signals, status=status, message=message, breach=breach,
                     stats=stats, n=cl.n, gamma=gamma)


# --- smoothing convergence ------------------------------------------------------------------------------

def convergence_study(scenario, design, widths=None, *, t_final=None, integrator=None, progress=None) -> dict:
    """Max |q difference| against a reference run at a tenth of the smallest width, with the observed rate.

    Every studied width (the scenario's convergence_widths and its smoothing_width) is compared with the finer
    reference, never with itself; the rate between consecutive widths is log(d_a/d_b)/log(w_a/w_b) (1 for O(w)).
    """
    say = progress or (lambda s: None)
    ws = list(widths if widths is not None else scenario.simulation.convergence_widths)
    ws.append(scenario.simulation.smoothing_width)
    ws = sorted({float(w) for w in ws if w > 0}, reverse=True)
    if len(ws) < 2:
        raise InputError("needs at least two positive widths", key="simulation.convergence_widths",
                         expected="widths > 0 different from the run's smoothing_width")
    ref_w = ws[-1] / 10
    runs = {}
    for w in ws + [ref_w]:
        say(f"convergence study: width {w:g}" + (" (reference)" if w == ref_w else ""))
        runs[w] = simulate(scenario, design, t_final=t_final, integrator=integrator, width=w)
    ref = runs[ref_w]
    rows = []
    for w in ws:
        r = runs[w]
        T = min(r.t.size, ref.t.size)
        diff = float(np.max(np.abs(r.signals["q"][:T] - ref.signals["q"][:T])))
        rows.append({"width": w, "status": r.status, "max_abs_q_diff_vs_smallest": diff,
                     "steps": r.stats.get("steps"), "wall_time": r.stats.get("wall_time"),
                     "min_margin_e1": [float(v) for v in np.min(r.signals["m1"], axis=0)]})
    rates = []
    for a, b in zip(rows[:-1], rows[1:]):
        if a["max_abs_q_diff_vs_smallest"] > 0 and b["max_abs_q_diff_vs_smallest"] > 0:
            rates.append(math.log(a["max_abs_q_diff_vs_smallest"] / b["max_abs_q_diff_vs_smallest"])
                         / math.log(a["width"] / b["width"]))
    return json_safe({"reference_width": ref_w, "runs": rows, "observed_rates": rates,
                         "note": "q difference against a reference run at a tenth of the smallest width; "
                                 "the smoothing error is O(w), so the rate should be near 1"})


from ._callable import make_callable  # noqa: E402 - after the module body: calling this module is the API function

make_callable(__name__, "simulate")

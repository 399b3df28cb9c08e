"""The closed loop compiled for the integrator: its DAE function (states permuted), the Newton Jacobian, the
logged-signals function and the margins the scan between samples evaluates, generated as C with entry points that
evaluate the last two at a whole chunk's points in one call (`many_source`), compiled once (cached by
`core.ccompile`) and loaded, or on the CasADi VM.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import subprocess
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..core import deadline
from ..sx.buffered import Buffered
from .closedloop import OUTPUT_NAMES, ClosedLoop
from ..core.errors import InputError

#: gcc's -Og: measured on this project's loops, the run time of -O1 (paper's 20 s run 0.11 CPU-s, arm7's 10 s run
#: 0.48 s, bit-identical trajectories) at about half its compile time (arm7's closed loop 6 s against 12 s)
COMPILE_FLAGS = ["-Og", "-shared", "-fPIC"]
APPROX_ESN_JACOBIAN = True
#: a closed loop with more SX nodes than this builds its functions in a killable worker (core.worker.run_killable)
FORK_ABOVE_NODES = 100000
#: graph digest (see compile_closed_loop) -> (ode, outputs, margins, library, output maps per thread, (outputs_many,
#: margins_many)) loaded in this process; the maps (evaluate_outputs on the VM) are per thread because their numpy
#: buffers are not for concurrent calls
_LOADED: dict = {}
#: output maps kept per loaded loop and thread (one per chunk length T), the oldest dropped first
MAX_MAPS = 64


@dataclass
class Compiled:
    """The integrator's DAE function and the logged-signals function, compiled or on the VM."""

    dae: ca.Function                 # dyn_in -> dyn_out, states permuted, p = [chunk start time; plant p; z]
    outputs: ca.Function             # (t, x, [plant p; z]) -> OUTPUT_NAMES, public state order
    perm: np.ndarray                 # integrator state i = public state perm[i]
    mode: str                        # "compiled" or "vm"
    compile_time: float = 0.0
    cached: bool = False
    library: str | None = None
    source_hash: str | None = None
    maps: dict = field(default_factory=dict, repr=False)
    pvals: np.ndarray | None = None  # [plant p; z] of the run this copy is bound to (see `bind`)
    integrators: dict = field(default_factory=dict, repr=False)
    #: (t, q, dq, [plant p; z]) -> the margins [1 - |e1|/F1; 1 - |e2|/F2] (`scan_function`), compiled beside the
    #: loop; None where they depend on more of the state than q and dq
    margins: ca.Function | None = None
    #: outputs and margins at many points in one call into the compiled library (`Many`); None on the VM
    outputs_many: Many | None = None
    margins_many: Many | None = None
    #: the design's numbers z (closedloop.design_parameters) this loop runs with; empty where they are folded in
    design_values: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def bind(self, pvals) -> Compiled:
        """This compiled loop bound to one run's plant parameters (shares the code and the output maps); its
        parameter vector is those followed by the design's numbers."""
        return dataclasses.replace(self, pvals=np.concatenate([np.asarray(pvals, dtype=float).reshape(-1),
                                                               self.design_values]))


def state_permutation(n: int, states: list) -> tuple[np.ndarray, dict]:
    """For the state [q; dq; controller states in the design's order] (`states`: (name, (rows, cols)) pairs): the
    integrator's order, controller states last first and the joints last, which keeps the Newton matrix's LU
    fill-in low (the rows of ddq are dense), and where each state lands in it (name -> slice)."""
    sl, i = {"q": slice(0, n), "dq": slice(n, 2 * n)}, 2 * n
    for name, (r, c) in states:
        sl[name] = slice(i, i + r * c)
        i += r * c
    idx = np.arange(i)
    order = [name for name, _ in reversed(states)] + ["q", "dq"]
    perm = np.concatenate([idx[sl[k]] for k in order]) if i else idx
    where, j = {}, 0
    for k in order:
        m = sl[k].stop - sl[k].start
        where[k] = slice(j, j + m)
        j += m
    return perm, where


def _permutation(cl: ClosedLoop) -> np.ndarray:
    """Controller states last first, joints last: keeps the Newton matrix's LU fill-in low."""
    return state_permutation(cl.n, cl.design.states)[0]


def _parameters(cl: ClosedLoop) -> tuple[ca.SX, ca.SX, dict, np.ndarray]:
    """What the compiled loop takes as its parameters beyond time: [plant p; z] with the right-hand side and signals
    in them and this design's z, or the plant's p alone where the design's numbers are folded in."""
    if cl.xdot_pz is None:
        return cl.p, cl.xdot_p, cl.signals_p, np.zeros(0)
    return ca.vertcat(cl.p, cl.z), cl.xdot_pz, cl.signals_pz, np.asarray(cl.z0, dtype=float)


def shared_inputs(f: ca.Function) -> list[int]:
    """The inputs every point of a chunk shares: the parameter vector "p" ([plant p; z]) of the outputs and the
    margins."""
    return [f.name_in().index("p")]


def many_source(f: ca.Function) -> str:
    """C of `<name>_many(T, in, out)`: the generated function f at T points in one call -- the evaluation CasADi's
    serial map makes, without its dispatch at every point (a tenth of the paper run's time). in[i] holds the T
    points of input i one after another (the `shared_inputs`: one value for all), out[i] receives output i
    column-major (T x nnz), the layout the logged signals keep."""
    name = f.name()
    shared = shared_inputs(f)
    nnz_in = [f.nnz_in(i) for i in range(f.n_in())]
    nnz_out = [f.nnz_out(i) for i in range(f.n_out())]
    flags = [1 if i in shared else 0 for i in range(f.n_in())]

    def arr(v):
        return ", ".join(str(int(x)) for x in v)
    return f"""
#include <stdlib.h>
CASADI_SYMBOL_EXPORT int {name}_many(casadi_int T, const casadi_real** in, casadi_real** out) {{
  static const casadi_int nnz_in[{len(nnz_in)}] = {{{arr(nnz_in)}}}, shared[{len(nnz_in)}] = {{{arr(flags)}}};
  static const casadi_int nnz_out[{len(nnz_out)}] = {{{arr(nnz_out)}}};
  const casadi_real* arg[{f.sz_arg() + 1}];
  casadi_real* res[{f.sz_res() + 1}];
  casadi_int iw[{f.sz_iw() + 1}];
  casadi_real *w = (casadi_real*) malloc(sizeof(casadi_real) * ({f.sz_w()} + {sum(nnz_out)} + 1)), *scratch;
  casadi_int i, j, k, off;
  int rc = 0;
  if (!w) return 2;
  scratch = w + {f.sz_w()};
  for (k = 0; k < T && !rc; ++k) {{
    for (i = 0; i < {len(nnz_in)}; ++i) arg[i] = in[i] + (shared[i] ? 0 : k * nnz_in[i]);
    for (i = 0, off = 0; i < {len(nnz_out)}; off += nnz_out[i], ++i) res[i] = scratch + off;
    rc = {name}(arg, res, iw, w, 0);
    for (i = 0, off = 0; i < {len(nnz_out)}; off += nnz_out[i], ++i)
      for (j = 0; j < nnz_out[i]; ++j) out[i][j * T + k] = scratch[off + j];
  }}
  free(w);
  return rc;
}}
"""


class Many:
    """`<name>_many` of a loaded library (`many_source`) through ctypes: the function at T points in one call,
    bit for bit what its serial map gives."""

    def __init__(self, library: str, f: ca.Function):
        import ctypes
        if not Buffered.supports(f):
            raise ValueError(f"{f.name()}_many takes and gives dense values only")
        self._ct = ctypes
        self._c = getattr(ctypes.CDLL(library), f.name() + "_many")
        self._c.restype = ctypes.c_int
        self._c.argtypes = [ctypes.c_longlong, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_void_p)]
        self.name = f.name()
        self.nnz_in = [f.nnz_in(i) for i in range(f.n_in())]
        self.nnz_out = [f.nnz_out(i) for i in range(f.n_out())]
        self.shared = shared_inputs(f)

    def __call__(self, T: int, *inputs) -> list[np.ndarray]:
        """The outputs (each (T, nnz), column-major) at T points: input i given as T rows of its nnz values, or,
        for a shared input, its values once."""
        ct = self._ct
        ins = [np.ascontiguousarray(a, dtype=float) for a in inputs]
        for i, a in enumerate(ins):
            want = self.nnz_in[i] * (1 if i in self.shared else T)
            if a.size != want:
                raise ValueError(f"{self.name}_many: input {i} has {a.size} values, not {want}")
        outs = [np.empty((T, m), order="F") for m in self.nnz_out]
        if T == 0:
            return outs
        pin = (ct.c_void_p * len(ins))(*[a.ctypes.data for a in ins])
        pout = (ct.c_void_p * len(outs))(*[o.ctypes.data for o in outs])
        rc = self._c(int(T), pin, pout)
        if rc:
            raise RuntimeError(f"{self.name}_many failed ({rc})")
        return outs


def scan_function(cl: ClosedLoop) -> ca.Function | None:
    """(t, q, dq, [plant p; z]) -> the margins [1 - |e1|/F1; 1 - |e2|/F2] of the closed loop's signals, which the
    margin scan between samples evaluates (`between.MarginScan`) -- from the loop's own graph, so that it is compiled
    with it and shared by every design on the same library; None when they depend on other states (never, for a
    funnel of the tracking errors)."""
    P, _, S, _ = _parameters(cl)
    sl = cl.slices
    m = ca.vertcat(1 - ca.fabs(S["e1"]) / S["F1"], 1 - ca.fabs(S["e2"]) / S["F2"])
    q, dq = ca.SX.sym("q", cl.n), ca.SX.sym("dq", cl.n)
    m = ca.substitute([m], [cl.x[sl["q"]], cl.x[sl["dq"]]], [q, dq])[0]
    if ca.depends_on(m, cl.x):
        return None
    return ca.Function("symfunnel_margins", [cl.t, q, dq, P], [m], ["t", "q", "dq", "p"], ["m"], {"cse": True})


def _dae_function(cl: ClosedLoop, perm: np.ndarray) -> ca.Function:
    t0 = ca.SX.sym("t0")
    P, xdot, _, _ = _parameters(cl)
    p = ca.vertcat(t0, P)
    xi = cl.x[list(perm)]
    ode = ca.substitute(xdot, cl.t, cl.t + t0)[list(perm)]
    empty = ca.SX(0, 1)
    return ca.Function("symfunnel_ode", [cl.t, xi, ca.SX.sym("z", 0, 1), p, ca.SX.sym("u", 0, 1)],
                       [ode, empty, empty, empty], ca.dyn_in(), ca.dyn_out(), {"cse": True})


def _newton_jacobian(cl: ClosedLoop, dae: ca.Function, perm: np.ndarray, approx: bool = True) -> ca.Function:
    """The Jacobian CVODES' Newton iteration uses: exact, except (`approx`) the reservoir's internal coupling.

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
    esn = set(int(v) for v in pos[cl.slices["x_esn"]]) if "x_esn" in cl.slices and approx else set()
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
    # the blocks in t and p are left structurally zero: the Newton matrix needs d/dx alone, and d/dp (the plant's
    # quantities and the design's numbers) had cost more than d/dx at every Jacobian update
    for k in ("jac_ode_t", "jac_ode_p"):
        if k in jac.name_out():
            i = jac.name_out().index(k)
            outs[i] = ca.SX(*outs[i].shape)
    return ca.Function(jac.name(), ins, outs, jac.name_in(), jac.name_out(), {"cse": True})


def compile_closed_loop(cl: ClosedLoop, *, progress=None, jit: bool = True,
                        approx_jacobian: bool = APPROX_ESN_JACOBIAN) -> Compiled:
    """Generate C for the closed loop's RHS, Jacobian and outputs, compile it once (cached) and load it.

    `approx_jacobian` selects the modified-Newton Jacobian of `_newton_jacobian` (right for CVODES, whose error
    control does not depend on it); collocation solves its stage equations with that Jacobian too, and needs the
    exact one to converge. A limit reached anywhere inside names the step (never the bare "working").
    """
    with deadline.step("compiling the closed loop"):
        return _compile_closed_loop(cl, progress, jit, approx_jacobian)


def _compile_closed_loop(cl: ClosedLoop, progress, jit: bool, approx_jacobian: bool) -> Compiled:
    say = progress or (lambda s: None)
    perm = _permutation(cl)
    jit = jit and not os.environ.get("SYMFUNNEL_NO_JIT")

    P, _, signals, zvals = _parameters(cl)

    def functions():
        dae = _dae_function(cl, perm)
        outputs = ca.Function("symfunnel_outputs", [cl.t, cl.x, P], [signals[k] for k in OUTPUT_NAMES],
                              ["t", "x", "p"], list(OUTPUT_NAMES), {"cse": True})
        margins = scan_function(cl)
        if not jit:
            return dae, outputs, margins, b""
        # The library is keyed by the graphs it is generated from (and this module, which generates it), so a
        # cached entry skips generating the Newton Jacobian and the C: for a large reservoir most of the cost.
        identity = hashlib.sha256(b"\0".join([
            dae.serialize().encode(), outputs.serialize().encode(),
            margins.serialize().encode() if margins is not None else b"", b"approx" if approx_jacobian else b"exact",
            " ".join(COMPILE_FLAGS).encode(), ca.__version__.encode(), Path(__file__).read_bytes()])).digest()
        return dae, outputs, margins, identity

    from ..core.worker import run_killable
    # building and hashing the functions of a large graph are long CasADi calls no signal interrupts: in a worker
    # process the limit can kill, when the graph is large enough for it to matter
    big = int(ca.n_nodes(cl.xdot_p)) > FORK_ABOVE_NODES
    dae, outputs, margins, identity = (run_killable(functions, what="building the closed loop's functions") if big
                                       else functions())
    vm = Compiled(dae=dae, outputs=outputs, perm=perm, mode="vm", design_values=zvals, margins=margins)
    if not jit:
        return vm
    t0 = time.perf_counter()
    digest = identity.hex()[:24]
    if digest in _LOADED:
        ext_dae, ext_out, ext_m, lib, maps, many = _LOADED[digest]
        return Compiled(ext_dae, ext_out, perm, "compiled", time.perf_counter() - t0, True, lib, digest,
                        maps=_thread_maps(maps), design_values=zvals, margins=ext_m, outputs_many=many[0],
                        margins_many=many[1])

    def sources() -> dict[str, bytes]:
        # in a forked worker: the Jacobian and the C of a large graph are long CasADi calls no signal interrupts
        return run_killable(generate, what="generating the closed loop's C")

    def generate() -> dict[str, bytes]:
        with tempfile.TemporaryDirectory(prefix="symfunnel-cg-") as tmp:
            cg = ca.CodeGenerator("symfunnel_cl.c", {"with_header": False})
            cg.add(dae)
            cg.add(_newton_jacobian(cl, dae, perm, approx_jacobian))
            cg.add(outputs)
            if margins is not None:
                cg.add(margins)
            cg.generate(tmp + os.sep)
            src = Path(tmp, "symfunnel_cl.c").read_bytes() + many_source(outputs).encode()
            if margins is not None:
                src += many_source(margins).encode()
        deadline.check()                       # generating the Jacobian is one CasADi call no signal interrupts
        return {"symfunnel_cl.c": src}

    from ..core.ccompile import compile_cached, find_compiler
    try:
        find_compiler()
    except InputError:
        warnings.warn("no C compiler found (gcc/cc/$CC): simulating on the CasADi virtual machine (slower)",
                      RuntimeWarning, stacklevel=2)
        return vm
    try:
        built = compile_cached(sources, ["symfunnel_cl.c"], "symfunnel_cl.so", COMPILE_FLAGS, on_build=say,
                               identity=identity)
    except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
        warnings.warn(f"compiling the closed loop failed ({exc}); simulating on the CasADi virtual machine",
                      RuntimeWarning, stacklevel=2)
        return vm
    lib, cached = built.path, built.cached
    try:
        ext_dae = ca.external("symfunnel_ode", str(lib))
        ext_out = ca.external("symfunnel_outputs", str(lib))
        ext_m = ca.external("symfunnel_margins", str(lib)) if margins is not None else None
        # (a sparse output keeps CasADi's map: its signals are densified there)
        many = (Many(str(lib), outputs) if Buffered.supports(outputs) else None,
                Many(str(lib), margins) if margins is not None and Buffered.supports(margins) else None)
    except (AttributeError, OSError) as exc:          # a library without the _many entry points: an old cache
        warnings.warn(f"loading {lib} failed ({exc}); simulating on the CasADi virtual machine", RuntimeWarning,
                      stacklevel=2)
        return vm
    except RuntimeError as exc:
        from .hints import error_line
        warnings.warn(f"loading {lib} failed ({error_line(str(exc))}); simulating on the CasADi virtual machine",
                      RuntimeWarning, stacklevel=2)
        return vm
    maps: dict = {}
    _LOADED[digest] = (ext_dae, ext_out, ext_m, str(lib), maps, many)
    return Compiled(ext_dae, ext_out, perm, "compiled", time.perf_counter() - t0, cached, str(lib), digest,
                    maps=_thread_maps(maps), design_values=zvals, margins=ext_m, outputs_many=many[0],
                    margins_many=many[1])


def _thread_maps(maps: dict) -> dict:
    """This thread's output maps of a loaded loop: a later simulation of the same loop in the thread reuses them
    (building the maps of one simulation cost about a fifth of a 20 s paper run)."""
    return maps.setdefault(threading.get_ident(), {})


def sundials_functions(dae: ca.Function, jac_x: ca.SX, ins: list, *, forward: bool) -> list[ca.Function]:
    """The functions CasADi's SUNDIALS interface asks its DAE for by name (`OracleFunction::create_function`, which
    takes a library's own function of that name and I/O names instead of an MX wrapper evaluated on CasADi's
    virtual machine): daeF, jacF (d ode/dx only, its diagonal structurally present) and, for forward sensitivities,
    fwd1_daeF (one direction: CasADi's integrators evaluate it once per parameter)."""
    ode = dae.call(ins)[0]
    nx = int(ode.numel())
    io = ["t", "x", "z", "p", "u"]
    daeF = ca.Function("daeF", ins, [ode, ca.SX(0, 1)], io, ["ode", "alg"], {"cse": True})
    J = jac_x + ca.SX(ca.Sparsity.diag(nx), 0)
    jacF = ca.Function("jacF", ins, [J, ca.SX(0, nx), ca.SX(nx, 0), ca.SX(0, 0)], io,
                       ["jac_ode_x", "jac_alg_x", "jac_ode_z", "jac_alg_z"], {"cse": True})
    out = [daeF, jacF]
    if forward:
        out.append(daeF.forward(1))
    return out


def compiled_dae(name: str, t: ca.SX, x: ca.SX, p: ca.SX, ode: ca.SX, *, forward: bool = True,
                 drop: list[tuple[int, int]] | None = None, progress=None) -> ca.Function | None:
    """The ODE x' = ode(t, x, p) as a DAE Function for casadi.integrator, compiled (cached) with the functions
    `sundials_functions` names, so that CVODES (and its forward sensitivities) run generated C instead of CasADi's
    virtual machine; None without a compiler or when building fails (the caller then uses the SX DAE).

    `drop` lists (first, stop) index ranges of x whose coupling among themselves the Newton Jacobian leaves out
    (a modified Newton iteration, as `_newton_jacobian` explains); the DAE itself is exact.
    """
    say = progress or (lambda s: None)
    empty = ca.SX(0, 1)
    ins = [t, x, ca.SX.sym("z", 0, 1), p, ca.SX.sym("u", 0, 1)]
    dae = ca.Function(name, ins, [ode, empty, empty, empty], ca.dyn_in(), ca.dyn_out(), {"cse": True})
    if os.environ.get("SYMFUNNEL_NO_JIT"):
        return None
    J = ca.jacobian(ode, x)
    if drop:
        rows, cols = J.sparsity().get_triplet()
        keep = [(r, c) for r, c in zip(rows, cols)
                if not any(a <= r < b and a <= c < b and r != c for a, b in drop)]
        sp = ca.Sparsity.triplet(J.size1(), J.size2(), [r for r, _ in keep], [c for _, c in keep])
        J = ca.SX(sp, ca.vertcat(*[J[r, c] for r, c in keep]) if keep else ca.SX(0, 1))
    identity = hashlib.sha256(b"\0".join([
        dae.serialize().encode(), ca.Function("j", [x], [ca.DM.ones(J.sparsity())]).serialize().encode(),
        repr(drop).encode(), b"fwd" if forward else b"", " ".join(COMPILE_FLAGS).encode(), ca.__version__.encode(),
        Path(__file__).read_bytes()])).digest()
    lib_name = name + ".so"

    def sources() -> dict[str, bytes]:
        with tempfile.TemporaryDirectory(prefix="symfunnel-cg-") as tmp:
            cg = ca.CodeGenerator(name + ".c", {"with_header": False})
            funcs = sundials_functions(dae, J, ins, forward=forward)
            for f in funcs:
                cg.add(f)
            # CVODES calls daeF, jacF and fwd1_daeF only; <name> (the Function casadi.external loads) and fwd1_<name>
            # (what CasADi derives jtimesF, J times a vector, from) must be in the library too, and are generated as
            # calls of daeF's and fwd1_daeF's code instead of second copies of the same expressions (a third of the
            # source: compiling arm7's tune DAE took ~12 CPU-s, ~8 without them)
            insm = [ca.MX.sym(k, v.sparsity()) for k, v in zip(ca.dyn_in(), ins)]
            none = ca.MX(0, 1)
            oracle = ca.Function(name, insm, [funcs[0].call(insm)[0], none, none, none], ca.dyn_in(),
                                 ca.dyn_out())
            cg.add(oracle)
            cg.add(oracle.forward(1))
            cg.generate(tmp + os.sep)
            src = Path(tmp, name + ".c").read_bytes()
        deadline.check()
        return {name + ".c": src}

    from ..core.ccompile import compile_cached, find_compiler
    try:
        find_compiler()
        built = compile_cached(sources, [name + ".c"], lib_name, COMPILE_FLAGS, on_build=say, identity=identity)
        return ca.external(name, str(built.path))
    except (InputError, OSError, RuntimeError, subprocess.SubprocessError) as exc:
        warnings.warn(f"compiling {name} failed ({exc}); using CasADi's virtual machine", RuntimeWarning,
                      stacklevel=2)
        return None


def evaluate_outputs(comp: Compiled, n: int, t: np.ndarray, X: np.ndarray) -> dict:
    """The logged signals (OUTPUT_NAMES, each (T, size)) at times t and states X (T, n_x), public order."""
    T = t.size
    if T == 0:
        return {k: np.zeros((0, n)) for k in OUTPUT_NAMES}
    if comp.outputs_many is not None:
        return dict(zip(OUTPUT_NAMES, comp.outputs_many(T, t, X, comp.pvals)))
    fm = comp.maps.get(T)
    if fm is None:
        # one serial map over the chunk, the plant parameters shared (reduce_in), evaluated on numpy buffers
        f = comp.outputs.map("outputs_map", "serial", T, shared_inputs(comp.outputs), [])
        while len(comp.maps) >= MAX_MAPS:
            comp.maps.pop(next(iter(comp.maps)))
        fm = comp.maps[T] = Buffered(f) if Buffered.supports(f) else f
    if isinstance(fm, Buffered):
        fm(t, X.T, comp.pvals)
        # copied into Fortran order, the layout a DM's transpose had: reductions over time sum in the same order
        return {k: np.array(r.reshape(T, -1), order="F") for k, r in zip(OUTPUT_NAMES, fm.res)}
    res = fm(t.reshape(1, -1), X.T, comp.pvals)
    return {k: np.asarray(ca.densify(r)).T for k, r in zip(OUTPUT_NAMES, res)}

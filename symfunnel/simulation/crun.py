"""The run loop's chunks in C (`csrc/cvodes_loop.c`): CVODES, the samples between output points, the logged
signals, the margin scan, the refined steps and the extremes between output points of every chunk that ends without
a stop, in one call per run -- Python only before (settings) and after (the arrays wrapped into the run's segments).

The C loop transcribes run.py's chunk operation for operation, so a run is the Python loop's bit for bit
(tests/test_crun.py). A chunk where that loop would stop or take another path (a breach, a non-finite value, a
CVODES failure, a history too large to keep) is handed back: `simulate` runs that chunk in Python, then calls again.
`$SYMFUNNEL_RUN_LOOP=python` (or `RUN_IN_C = False`) keeps every chunk in Python: the bench's baseline.
"""

from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass

import numpy as np

from . import sundials
from .between import BETWEEN_MAX, MAX_REFINED_PER_CHUNK, REFINE_POINTS, SCAN_DIP, SCAN_POINTS
from .closedloop import OUTPUT_NAMES

#: run the chunks in C where the run allows it; the bench switches it off for its baseline
RUN_IN_C = True
#: the samples between output points written straight into their rows in time order (`csrc/cvodes_loop.c`,
#: `sf_sample_rows`) instead of sampled into a buffer and copied after (~12,800 rows x 156 states per paper run):
#: the same arrays bit for bit (tests/test_crun.py). False is the previous path, the bench's baseline
#: (`simulate.samples_in_place`, `sweep.cpu_per_run_vs_previous`)
SAMPLES_IN_PLACE = True
#: the longest a C call runs before it returns for the progress line (seconds)
SLICE_S = 2.0
DONE, HANDOVER, SLICE, TIMEOUT = 0, 1, 2, 3


def enabled() -> bool:
    """Whether runs use the C loop: `RUN_IN_C` and $SYMFUNNEL_RUN_LOOP ("c", the default, or "python")."""
    return RUN_IN_C and os.environ.get("SYMFUNNEL_RUN_LOOP", "c").strip().lower() != "python"


@dataclass
class Advance:
    """What one C call did: its return code, the output points it kept (t, X, logged signals) and the loop's state
    after them."""

    rc: int
    t: np.ndarray
    X: np.ndarray
    O: dict
    k: int
    K: int
    sub: int
    x: np.ndarray
    lowest: float


def _fptr(f) -> int:
    return ctypes.cast(f, ctypes.c_void_p).value


def _long(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int_ if ctypes.sizeof(ctypes.c_long) == 8 else np.int32)


class CLoop:
    """The C loop on one run's compiled closed loop and CVODES driver."""

    def __init__(self, runner, D: sundials.DirectCvodes, comp, cl, chunk_sizes):
        self.runner, self.D, self.comp = runner, D, comp
        self.n, self.nx = cl.n, cl.nx
        om, mm = comp.outputs_many, comp.margins_many
        self.nnz = [int(v) for v in om.nnz_out]
        self._fns = (_fptr(om._c), _fptr(mm._c))
        q, dq = cl.slices["q"], cl.slices["dq"]
        self._q0, self._dq0 = int(q.start), int(dq.start)
        self._perm = np.ascontiguousarray(runner.perm, dtype=np.intc)
        self._nnz = np.ascontiguousarray(self.nnz, dtype=np.intc)
        self._chunks = np.ascontiguousarray(chunk_sizes, dtype=np.intc)
        self._pvals = np.ascontiguousarray(comp.pvals, dtype=float)

    @classmethod
    def for_run(cls, runner, comp, cl, chunk_sizes) -> CLoop | None:
        """The C loop for this run, or None where the run takes the Python loop (not CVODES on compiled C with the
        direct backend writing the public order and sampling from the kept steps, no `_many` functions, or
        switched off)."""
        from . import runner as runner_mod
        if not enabled() or runner.method != "cvodes" or comp.outputs_many is None or comp.margins_many is None \
                or not runner_mod.SAMPLE_FROM_STEPS:
            return None
        D = runner.direct()
        if D is None or D.order is None or len(OUTPUT_NAMES) > 64 or 2 * cl.n > 256:
            return None
        q, dq = cl.slices["q"], cl.slices["dq"]
        if q.step not in (None, 1) or dq.step not in (None, 1):
            return None
        return cls(runner, D, comp, cl, chunk_sizes)

    def advance(self, *, k: int, K: int, sub: int, x: np.ndarray, lowest: float, between, M: int, h: float,
                tf: float, limit: float, elapsed: float, fixed: bool) -> Advance:
        """The chunks from output point k (state x, next chunk length K, density sub) until the run's end, a chunk
        handed back, SLICE_S or the wall-clock limit; `between` (a `between.Between`) and the runner's statistics
        are updated in place."""
        n, nx = self.n, self.nx
        idx = {name: i for i, name in enumerate(OUTPUT_NAMES)}
        ints = np.array([M, nx, n, 1 + self._pvals.size, len(OUTPUT_NAMES), idx["m1"], idx["m2"], idx["tau"],
                         idx["tau_applied"], self._q0, self._dq0, BETWEEN_MAX, SCAN_POINTS, MAX_REFINED_PER_CHUNK,
                         REFINE_POINTS, int(bool(fixed)), self._chunks.size, int(bool(SAMPLES_IN_PLACE))],
                        dtype=np.intc)
        reals = np.array([h, tf, limit, elapsed, SLICE_S, SCAN_DIP, sundials.HISTORY_BYTES], dtype=float)
        runner = self.runner
        state = _long([k, K, sub, between.points, between.density, between.refined, runner.unchecked, 0])
        fstate = np.array([lowest, 0.0])
        bw = np.concatenate([between.m1, between.m2, between.t_m1, between.t_m2, between.tau, between.t_tau,
                             between.tau_applied]).astype(float)
        stats = _long([0, 0, 0, 0])
        rows = M - k
        t_out = np.empty(rows)
        X_out = np.empty((rows, nx))
        O_out = np.empty(rows * sum(self.nnz))
        xs = np.ascontiguousarray(x, dtype=float).copy()
        lib, D = self.D._lib, self.D
        dp, ip = ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int)
        lp = ctypes.POINTER(ctypes.c_long)

        def P(a, kind=dp):
            return a.ctypes.data_as(kind)
        with D._lock:
            lib.sf_set_fused_dky(1 if sundials.FUSED_DKY else 0)
            rc = lib.sf_loop_run(D._h, self._fns[0], self._fns[1], P(ints, ip), P(reals), P(self._perm, ip),
                                 P(self._nnz, ip), P(self._chunks, ip), P(self._pvals), P(xs), P(state, lp),
                                 P(fstate), P(bw), P(stats, lp), P(t_out), P(X_out), P(O_out), rows)
        if rc < 0:
            raise MemoryError("the C run loop ran out of memory")
        for i, a in enumerate((between.m1, between.m2, between.t_m1, between.t_m2, between.tau, between.t_tau,
                               between.tau_applied)):
            a[:] = bw[i * n:(i + 1) * n]
        between.points, between.density, between.refined = int(state[3]), int(state[4]), int(state[5])
        runner.unchecked = int(state[6])
        st = runner.stats
        st["steps"] += int(stats[0])
        st["rhs_evaluations"] += int(stats[1])
        st["jacobian_evaluations"] += int(stats[2])
        st["error_test_failures"] += int(stats[3])
        st["integrate_time"] += float(fstate[1])
        st["cvodes_backend"] = "direct"
        done = int(state[7])
        O, off = {}, 0
        for name, m in zip(OUTPUT_NAMES, self.nnz):
            O[name] = np.array(O_out[off:off + rows * m].reshape(m, rows).T[:done], order="F")
            off += rows * m
        if done < rows:              # a call that stopped early: copies, so that the rows not written are freed
            t_out, X_out = t_out[:done].copy(), X_out[:done].copy()
        return Advance(rc=int(rc), t=t_out, X=X_out, O=O, k=int(state[0]), K=int(state[1]),
                       sub=int(state[2]), x=xs, lowest=float(fstate[0]))

"""What happens between output points: the run's trajectory sampled as densely as the integrator's own steps, and
the smallest funnel margins and largest torques found there (they enter the run's summary and verify's checks).

How the samples are taken (`simulation.runner.Runner.run_dense`):

- CVODES: CasADi's CVODES interface sets no stop time at output points (the closed loop has no piecewise-constant
  inputs, so the stop time is the chunk's end) and returns each output by CVODES' own interpolation, so more output
  points do not change the steps -- except through CVODES' estimate of its first step, which looks at the first
  output time. A chunk is therefore integrated on its output grid with `sub - 1` extra points inside every output
  step after the first: its stored points are bit for bit those of the plain grid, and the extra points are CVODES'
  interpolant of the very same steps. The first output step of a chunk is sampled by a separate integration of that
  step on a grid of `sub` points. `sub` is the integrator's own density: the power of two at or above the steps per
  output point CVODES took in the previous chunk (BETWEEN_MAX for the first; a chunk that took more is sampled
  again, at its own density), at most BETWEEN_MAX. On the direct backend the chunk is integrated once, on its
  output grid, keeping every step's Nordsieck array; the extra points are then interpolated from the step that
  reaches each (CVodeGetDky, as CVODES does for an output point) once the chunk's own step count is known: the
  same samples, bit for bit, without integrating a chunk again.
- rk and collocation (fixed steps, `rk_substeps` per output step): the chunk is integrated again on a grid of
  `sub` points per output step (`sub` = the power of two at or above the fixed steps per output step, at most
  BETWEEN_MAX).

At every sample the funnel margins (a margin <= 0 or a non-finite value is where the run stops, located further on
a finer grid) and the torque are evaluated, as at the output points. The integrator steps more densely where the
trajectory moves fast than on average, so the extremes are refined: in every chunk the output step holding its
smallest margin, and after the run the output step holding each joint's largest |tau|, are integrated again from
their start on REFINE_POINTS points (a fresh integration of that one step: it agrees with the run to the
integrator's tolerance).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

#: the most samples per output step between two output points (a power of two)
BETWEEN_MAX = 64
#: samples of an output step integrated again around an extreme
REFINE_POINTS = 256
#: margin evaluations per gap between two consecutive samples (on the linearly interpolated joint state)
SCAN_POINTS = 4
#: output steps refined per chunk because the scan saw a dip (the most pronounced first)
MAX_REFINED_PER_CHUNK = 4
#: how far below both of its samples the scan of a gap must go to count as a dip
SCAN_DIP = 0.01
#: refine_peaks integrates an output step once however many joints peak in it; False: once per joint (the same
#: samples again: the bench's baseline)
SHARE_REFINED_STEPS = True


def margin_function(design) -> ca.Function:
    """(t, q, dq) -> the true margins [1 - |e1|/F1; 1 - |e2|/F2] (2n) with the scenario's reference."""
    s, S = design.sym, design.signals
    ref_syms = [s["qd"], s["dqd"], s["ddqd"]]
    ref_t = [design.reference_t[k] for k in ("qd", "dqd", "ddqd")]
    m = ca.vertcat(1 - ca.fabs(S["e1"]) / S["F1"], 1 - ca.fabs(S["e2"]) / S["F2"])
    m = ca.substitute([m], ref_syms, ref_t)[0]
    return ca.Function("margins", [s["t"], s["q"], s["dq"]], [m])


def error_function(design) -> ca.Function:
    """(t, q) -> the tracking error e1 (n) with the scenario's reference (built once per design)."""
    known = design.__dict__
    if "_error_function" not in known:
        s, S = design.sym, design.signals
        e1 = ca.substitute([S["e1"]], [s["qd"], s["dqd"], s["ddqd"]],
                           [design.reference_t[k] for k in ("qd", "dqd", "ddqd")])[0]
        known["_error_function"] = ca.Function("tracking_error", [s["t"], s["q"]], [e1])
    return known["_error_function"]


class MarginScan:
    """The margins between consecutive samples at SCAN_POINTS - 1 times each, on the linearly interpolated q, dq:
    the funnels, the reference and alpha2 are exact functions of t there, so a dip they make between two samples
    shows even where the integrator's steps do not resolve it (the state moves smoothly at that scale).

    It evaluates the compiled loop's own margin function (`compiled.scan_function`: generated C where the loop is
    compiled, all points in one call; a fifth of the paper run's time on CasADi's virtual machine before) with the
    run's parameters, or, where the loop has none, the design's (`margin_function`) on the VM in blocks."""

    #: the mapped evaluation's sizes: a call takes the largest block that fits what is left, the smallest at the
    #: end (one 4096-point block for every call wasted 61 % of the paper run's evaluations: calls of 1 and 768)
    BLOCKS = (4096, 1024, 256, 64, 16)

    def __init__(self, comp, slices: dict, design=None):
        self._many = comp.margins_many        # all points in one call into the library (compiled.Many)
        if comp.margins is not None and comp.pvals is None:
            raise ValueError("the compiled loop is not bound to a run's parameters (Compiled.bind)")
        self._p = None if comp.margins is None else np.asarray(comp.pvals, dtype=float)
        if self._p is None:
            if design is None:
                raise ValueError("a loop without its margin function needs the design's")
            self._margin, self._f = margin_function(design), {}
        else:
            # the mapped blocks are kept with the loaded loop's output maps (per thread): every run on it reuses them
            self._margin, self._f = comp.margins, comp.maps
        self.q, self.dq = slices["q"], slices["dq"]
        self.width = 2 * (slices["q"].stop - slices["q"].start)

    def _block(self, size: int):
        """The margin function mapped over `size` points on numpy buffers, built on first use."""
        key = ("scan", size)
        f = self._f.get(key)
        if f is None:
            from .compiled import Buffered
            from .compiled import shared_inputs
            mapped = (self._margin.map(size) if self._p is None
                      else self._margin.map("scan_map", "serial", size, shared_inputs(self._margin), []))
            f = self._f[key] = Buffered(mapped)
        return f

    def margins(self, t: np.ndarray, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Margins (B, 2n) at times t (B,) and joint states q, dq (B, n)."""
        B = t.size
        if self._many is not None:
            return self._many(B, t, q, dq, self._p)[0]
        out = np.empty((B, self.width))
        a = 0
        while a < B:
            left = B - a
            size = next((k for k in self.BLOCKS if k <= left), self.BLOCKS[-1])
            b = min(B, a + size)
            f = self._block(size)
            tt = np.zeros(size)
            qq = np.zeros((q.shape[1], size))
            dd = np.zeros((dq.shape[1], size))
            tt[:b - a], qq[:, :b - a], dd[:, :b - a] = t[a:b], q[a:b].T, dq[a:b].T
            if self._p is None:
                f(tt, qq, dd)
            else:
                f(tt, qq, dd, self._p)
            out[a:b] = f.res[0].reshape(size, self.width)[:b - a]
            a = b
        return out

    def __call__(self, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Samples (t (T,), X (T, n_x)) in time order, the first one the start: (scan times (T-1, S-1), margins
        (T-1, S-1, 2n)) on the linearly interpolated joint state (`state` gives the whole one)."""
        T = t.size
        w = np.arange(1, SCAN_POINTS) / SCAN_POINTS
        ts = t[:-1, None] + (t[1:] - t[:-1])[:, None] * w[None, :]
        Q, DQ = X[:, self.q], X[:, self.dq]
        Qs = (Q[:-1, None, :] + (Q[1:] - Q[:-1])[:, None, :] * w[None, :, None]).reshape(-1, Q.shape[1])
        DQs = (DQ[:-1, None, :] + (DQ[1:] - DQ[:-1])[:, None, :] * w[None, :, None]).reshape(-1, DQ.shape[1])
        with np.errstate(all="ignore"):
            m = self.margins(ts.reshape(-1), Qs, DQs)
        return ts, m.reshape(max(T - 1, 0), SCAN_POINTS - 1, self.width)

    @staticmethod
    def state(X: np.ndarray, g: int, j: int) -> np.ndarray:
        """The interpolated state of scan point j of gap g (between samples g and g + 1 of X)."""
        w = (j + 1) / SCAN_POINTS
        return X[g] + (X[g + 1] - X[g]) * w


def scan_dips(scan_m: np.ndarray, sample_m: np.ndarray) -> np.ndarray:
    """Gaps (indices) whose scan goes to 0 or dips SCAN_DIP below both of its samples, the deepest first.
    sample_m: the smallest margin at each sample, the start first (T,)."""
    if scan_m.size == 0:
        return np.zeros(0, int)
    mn = np.min(np.where(np.isfinite(scan_m), scan_m, -np.inf), axis=(1, 2))
    ends = np.fmin(sample_m[:-1], sample_m[1:])
    dips = np.flatnonzero((mn <= 0) | (mn < ends - SCAN_DIP))
    return dips[np.argsort(mn[dips], kind="stable")]


def density(steps: float, points: int) -> int:
    """Samples per output step as dense as `steps` integrator steps over `points` output points: a power of two,
    1..BETWEEN_MAX."""
    ratio = steps / max(points, 1)
    if not ratio > 1:
        return 1
    return min(BETWEEN_MAX, 1 << max(0, math.ceil(math.log2(ratio) - 1e-12)))


class Between:
    """The extremes seen between output points over a run (per joint), and how many samples showed them."""

    #: the logged signals `update` reads
    KEYS = ("m1", "m2", "tau", "tau_applied")

    def __init__(self, n: int):
        self.n = n
        self.points = 0
        self.density = 1
        self.unchecked = 0                    # chunks whose extra integration failed (their inside is not sampled)
        self.refined = 0                      # output steps integrated again around an extreme
        self.m1 = np.full(n, np.inf)
        self.m2 = np.full(n, np.inf)
        self.t_m1 = np.full(n, np.nan)
        self.t_m2 = np.full(n, np.nan)
        self.tau = np.full(n, -np.inf)
        self.t_tau = np.full(n, np.nan)
        self.tau_applied = np.full(n, -np.inf)

    def update(self, t: np.ndarray, o: dict, sub: int) -> None:
        """Take the samples at times t (B,) with outputs o (each (B, n)), taken `sub` per output step (0: the
        samples of a refined output step)."""
        if t.size == 0:
            return
        self.points += int(t.size)
        if sub:
            self.density = max(self.density, int(sub))
        else:
            self.refined += 1
        for key, best, when in (("m1", self.m1, self.t_m1), ("m2", self.m2, self.t_m2)):
            m = np.where(np.isfinite(o[key]), o[key], np.inf)
            i = np.argmin(m, axis=0)
            v = m[i, np.arange(self.n)]
            better = v < best
            best[better] = v[better]
            when[better] = t[i][better]
        for key, best, when in (("tau", self.tau, self.t_tau), ("tau_applied", self.tau_applied, None)):
            a = np.abs(o[key])
            a = np.where(np.isfinite(a), a, -np.inf)
            i = np.argmax(a, axis=0)
            v = a[i, np.arange(self.n)]
            better = v > best
            best[better] = v[better]
            if when is not None:
                when[better] = t[i][better]

    def to_json(self) -> dict:
        """Plain data: samples taken, the density, and the extremes between output points (None: no sample)."""
        def vals(a):
            return [float(v) if np.isfinite(v) else None for v in a]
        return {"points": self.points, "per_output_step": self.density, "refined_steps": self.refined,
                "refine_points": REFINE_POINTS, "unchecked_chunks": self.unchecked,
                "min_margin_e1": vals(self.m1), "t_min_margin_e1": vals(self.t_m1),
                "min_margin_e2": vals(self.m2), "t_min_margin_e2": vals(self.t_m2),
                "max_abs_tau": vals(self.tau), "t_max_abs_tau": vals(self.t_tau),
                "max_abs_tau_applied": vals(self.tau_applied)}


def refine(runner, comp, n: int, t_a: float, x_a: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The output step from (t_a, x_a) integrated again on REFINE_POINTS points: (t, X, outputs), None when that
    integration fails."""
    from .compiled import evaluate_outputs
    try:
        X = runner.run(t_a, x_a, REFINE_POINTS, h / REFINE_POINTS, count=False)
    except RuntimeError:
        return None
    t = t_a + (h / REFINE_POINTS) * np.arange(1, REFINE_POINTS + 1)
    return t, X, evaluate_outputs(comp, n, t, X)


def refine_peaks(result, runner, comp, between: Between) -> None:
    """After a run: each joint's largest |tau| (output points or samples between them) refined on its output step,
    each step integrated once however many joints peak in it (the paper's two joints both peak in the first)."""
    t, X = result.t, result.x
    if t.size < 2:
        return
    h = runner.h
    tau = np.abs(result.signals["tau"])
    done: dict[int, tuple | None] = {}     # output step -> its refinement: joints peaking in one step share it
    for j in range(between.n):
        i = int(np.nanargmax(np.where(np.isfinite(tau[:, j]), tau[:, j], -np.inf)))
        best, tb = float(tau[i, j]), float(t[i])
        if np.isfinite(between.tau[j]) and between.tau[j] > best:
            best, tb = float(between.tau[j]), float(between.t_tau[j])
        k = int(np.searchsorted(t, tb, side="left"))          # the output step (t[k-1], t[k]] holds tb
        for a in sorted({max(k - 1, 0), min(k, t.size - 2)}):
            if t[a + 1] - t[a] < 0.5 * h or t[a + 1] - t[a] > 1.5 * h:
                continue                                     # not a whole output step (the located end of a run)
            if a not in done or not SHARE_REFINED_STEPS:   # a fresh integration from the same state: the same
                # samples, bit for bit
                done[a] = refine(runner, comp, between.n, float(t[a]), X[a], float(t[a + 1] - t[a]))
            r = done[a]
            if r is not None:           # taken once per joint as before (the same counts in `between`)
                between.update(r[0], r[2], 0)

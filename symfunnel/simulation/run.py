"""The run loop: `simulate` integrates the compiled closed loop in chunks of the output grid (a fixed schedule:
reproducible), checks the funnel margins after each chunk, stops at a breach, a failure or the wall-clock limit."""

from __future__ import annotations

import math
import time
import warnings
from typing import TYPE_CHECKING

import numpy as np

from ..core import deadline
from .closedloop import ClosedLoop, build_closed_loop
from ..core.errors import InputError
from ..core.validate import check_horizon
from ..family.integrators import INTEGRATORS
from ..plant.nonlinearities import check_smoothing_width
from .between import (BETWEEN_MAX, MAX_REFINED_PER_CHUNK, SCAN_DIP, Between, MarginScan, density, refine,
                      refine_peaks, scan_dips)
from .breach import bad_index, describe_breach, locate_failure, locate_within
from .compiled import APPROX_ESN_JACOBIAN, compile_closed_loop, evaluate_outputs
from .crun import SLICE, TIMEOUT, CLoop
from .heap import keep_heap
from .result import SimResult, finish, ok_message
from .runner import Runner, Timeout

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from ..design import Design
    from ..scenario import Scenario

CHUNK_SIZES = (1, 5, 25, 100, 500)


def _grid(t_final: float, dt: float) -> tuple[int, float]:
    """Number of output steps and the step that divides t_final evenly (at most dt)."""
    M = max(1, int(math.ceil(t_final / dt - 1e-9)))
    return M, t_final / M


def _density(method: str, sim, sub: int) -> int:
    """Samples per output step between output points: CVODES' own density (`sub`), or the fixed-step methods'."""
    if method == "cvodes":
        return sub
    return density(sim.rk_substeps if method == "rk" else max(1, sim.rk_substeps // 2), 1)


def _in_time_order(x: np.ndarray, X: np.ndarray, Xb: np.ndarray, order: np.ndarray) -> np.ndarray:
    """[x; (X stacked on Xb)[order]] written in one pass (no stacked copy to index): the chunk's start, then its
    output points and the samples between them in time order (`order`: argsort of their times, X's first)."""
    K = X.shape[0]
    rank = np.empty_like(order)
    rank[order] = np.arange(1, order.size + 1)
    Xg = np.empty((order.size + 1, x.size))
    Xg[0] = x
    Xg[rank[:K]] = X
    Xg[rank[K:]] = Xb
    return Xg


def _refine_chunk(runner, comp, n, mscan, t0, x, tc, X, ta, Xa, oa, is_out, between, used, lowest, Xg=None):
    """The output steps of a chunk where its margins come closest to 0 -- the one holding its smallest sampled margin,
    and those where the margin scan between samples dips -- integrated again on REFINE_POINTS points. Returns the
    run's stop (as the chunk loop takes it) when such a step leaves a funnel, else None (its samples counted).
    Xg: [x; Xa] when the caller has it."""
    samp = np.fmin(oa["m1"].min(axis=1), oa["m2"].min(axis=1))
    start_m = mscan.margins(np.array([t0]), x[None, mscan.q], x[None, mscan.dq])[0].min()
    _, scan_m = mscan(np.concatenate([[t0], ta]), np.concatenate([x[None, :], Xa]) if Xg is None else Xg)
    gaps = scan_dips(scan_m, np.concatenate([[start_m], samp]))[:MAX_REFINED_PER_CHUNK]
    iw = int(np.argmin(np.where(np.isfinite(samp), samp, np.inf)))
    steps = set()
    if samp[iw] < lowest + SCAN_DIP:     # it may be the run's smallest margin (or a breach): refine it
        k_w = int(np.searchsorted(tc, ta[iw], side="left"))     # output step (tc[k-1], tc[k]] holds the sample
        steps = {k_w, k_w + 1} if is_out[iw] else {k_w}           # at an output point: the step after it too
    for g in gaps:                       # gap g lies between sample g - 1 (the start for g = 0) and sample g
        steps.add(int(np.searchsorted(tc, ta[g], side="left")))
    for q_ in sorted(k for k in steps if k < tc.size):
        t_a, x_a = (t0, x) if q_ == 0 else (float(tc[q_ - 1]), X[q_ - 1])
        r = refine(runner, comp, n, t_a, x_a, float(tc[q_]) - t_a)
        if r is None:
            continue
        tr, Xr, orr = r
        br, _ = bad_index(orr, Xr)
        if br is None:                   # the scan inside the refined step: a dip narrower than its samples
            Xg = np.concatenate([x_a[None, :], Xr])
            st, sm = mscan(np.concatenate([[t_a], tr]), Xg)
            flat = sm.min(axis=2).reshape(-1)
            if flat.size and np.nanmin(flat) <= 0:
                i = int(np.argmax(flat <= 0))
                g, j = divmod(i, sm.shape[1])
                t_s, x_s = float(st[g, j]), mscan.state(Xg, g, j)
                o_s = evaluate_outputs(comp, n, np.array([t_s]), x_s[None, :])
                tr, Xr = np.concatenate([tr[:g], [t_s]]), np.concatenate([Xr[:g], x_s[None, :]])
                orr = {key: np.concatenate([v[:g], o_s[key]]) for key, v in orr.items()}
                br = g
        if br is not None:               # the run ends in this output step
            before = ta <= t_a
            return (np.concatenate([ta[before], tr]), np.concatenate([Xa[before], Xr]),
                    {key: np.concatenate([v[before], orr[key]]) for key, v in oa.items()},
                    np.concatenate([is_out[before], np.zeros(tr.size, bool)]), int(before.sum()) + br, used)
        between.update(tr, orr, 0)
    return None


def simulate(scenario: Scenario, design: Design, *, t_final: float | None = None, integrator: str | None = None,
             width: float | None = None, progress: Callable[[str], None] | None = None,
             wall_limit: float | None = None, closed_loop: ClosedLoop | None = None, jit: bool = True,
             params: Mapping[str, float] | None = None, x0=None, fixed_chunks: bool = False) -> SimResult:
    """Simulate a scenario's closed loop; never raises for a breach, a timeout or an integrator failure.

    Returns a SimResult whose status is 'ok', 'breach', 'initial_outside', 'timeout' or 'failed', with the
    trajectory up to where the run stopped. Bad settings raise InputError. `params` (name -> value, names of
    `plant.equations.plant_parameters`) and `x0` (public state order) override the closed loop's plant quantities and
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
    check_horizon(float(tf), sim.dt, key="--t-final" if t_final is not None else "simulation.t_final",
                  file=None if t_final is not None else sc.file)
    method = integrator or sim.integrator
    INTEGRATORS.get(method, key="--integrator")
    limit = sim.wall_limit if wall_limit is None else float(wall_limit)
    w = sim.smoothing_width if width is None else width
    if not (isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
        raise InputError(f"is {w!r}", key="--width", expected="a number >= 0")
    w = check_smoothing_width(float(w), sc.plant, file=None if width is not None else sc.file,
                              key="--width" if width is not None else "simulation.smoothing_width")

    keep_heap()                                   # a run frees and reallocates MB per chunk (heap module)
    start = time.perf_counter()
    limit = min(limit, deadline.remaining())      # a command's (or Run's) wall-clock limit bounds this run too
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
        with deadline.step("compiling the closed loop"):
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
    runner = Runner(cl, comp, method, h, sim)

    # initial point
    x0 = cl.x0.copy() if x0 is None else np.asarray(x0, dtype=float).reshape(cl.nx).copy()
    t_list = [np.array([0.0])]
    X_list = [x0[None, :]]
    o0 = evaluate_outputs(comp, n, np.array([0.0]), x0[None, :])
    O_list = [o0]              # logged signals of the segments of t_list computed on the way (None: not yet)
    bi, kind = bad_index(o0, x0[None, :])
    status, message, breach = "ok", "", None
    if bi is not None:
        if kind == "nonfinite":
            status = "failed"
            message = "the initial state gives non-finite signals (check the scenario's initial values)"
        else:
            b = describe_breach(0.0, o0, 0, n)
            status = "initial_outside"
            breach = b
            message = (f"initial error outside funnel {b['funnel']} at joint {b['joint']}: "
                       f"|{b['funnel']}(0)| = {b['abs_error']:.6g} >= F{b['funnel'][1]}(0) = {b['boundary']:.6g}")
        return finish(sc, cl, comp, t_list, X_list, status, message, breach, stats, runner, start, O_list)

    sim_start = time.perf_counter()
    k = 0                      # grid index reached
    x = x0
    K = 25
    sub = BETWEEN_MAX          # samples per output step between the output points (the first chunk: the most)
    between = Between(n)
    lowest = float(np.min(np.fmin(o0["m1"], o0["m2"])))      # the smallest margin sampled so far
    mscan = MarginScan(comp, cl.slices, cl.design)
    cloop = CLoop.for_run(runner, comp, cl, CHUNK_SIZES)
    last_report = sim_start
    with deadline.paused():                    # the loop stops at `limit` itself, keeping the trajectory
        try:
            while k < M:
                if cloop is not None:          # the chunks that end without a stop, in C (`crun`)
                    adv = cloop.advance(k=k, K=K, sub=sub, x=x, lowest=lowest, between=between, M=M, h=h,
                                        tf=float(tf), limit=limit, elapsed=time.perf_counter() - start,
                                        fixed=fixed_chunks)
                    if adv.t.size:
                        t_list.append(adv.t)
                        X_list.append(adv.X)
                        O_list.append(adv.O)
                        k, x = adv.k, adv.x
                    K, sub, lowest = adv.K, adv.sub, adv.lowest
                    if adv.rc == TIMEOUT:
                        raise Timeout()
                    if adv.rc == SLICE:
                        say(f"t = {k * h:.3g} / {tf:g} s")
                        continue
                    if k >= M:
                        break
                Kc = min(K, M - k)
                t0 = k * h
                elapsed = time.perf_counter() - start
                if elapsed > limit:
                    raise Timeout()
                c0 = time.perf_counter()
                steps0 = runner.stats["steps"]
                try:
                    X, tb, Xb = runner.run_dense(t0, x, Kc, _density(method, sim, sub), adapt=method == "cvodes")
                    failed = False
                except RuntimeError:
                    X, failed = None, True
                if failed:
                    # redo point by point to find the last good grid point, then locate within the step
                    res = locate_failure(runner, comp, n, k, x, Kc, h, start, limit, _density(method, sim, sub),
                                         between)
                    t_list.extend(res["t"])
                    X_list.extend(res["X"])
                    status, message, breach = res["status"], res["message"], res["breach"]
                    break
                used = runner.last_density     # at least as dense as this chunk's own steps (CVODES)
                if method == "cvodes":
                    sub = density(runner.stats["steps"] - steps0, Kc)    # the integrator's own density
                tc = t0 + h * np.arange(1, Kc + 1)
                tc[-1] = min(tc[-1], float(tf)) if k + Kc == M else tc[-1]
                # every sample in time order: the output points and the samples between them
                ta = np.concatenate([tc, tb])
                order = np.argsort(ta, kind="stable")
                Xg = _in_time_order(x, X, Xb, order)          # [the start; the samples in time order]
                ta, Xa = ta[order], Xg[1:]
                is_out = order < Kc
                oa = evaluate_outputs(comp, n, ta, Xa)
                bi, kind = bad_index(oa, Xa)
                stop = None            # (samples in time order, their outputs, which are output points, first bad)
                if bi is not None:
                    stop = (ta, Xa, oa, is_out, bi, used)
                else:
                    stop = _refine_chunk(runner, comp, n, mscan, t0, x, tc, X, ta, Xa, oa, is_out, between, used,
                                         lowest, Xg)
                    samp_min = float(np.nanmin(np.fmin(oa["m1"].min(axis=1), oa["m2"].min(axis=1))))
                    lowest = min(lowest, samp_min, float(np.nanmin(np.fmin(between.m1, between.m2))))
                if stop is not None:
                    sa, sX, so, sout, bi, used_ = stop
                    inb = ~sout[:bi]
                    between.update(sa[:bi][inb], {key: v[:bi][inb] for key, v in so.items()}, used_)
                    last_out = int(np.flatnonzero(sout[:bi])[-1]) if sout[:bi].any() else -1
                    t_list.append(sa[:bi][sout[:bi]])
                    X_list.append(sX[:bi][sout[:bi]])
                    if bi - last_out > 1:              # samples after the last good output point, up to the breach
                        t_list.append(sa[last_out + 1:bi])
                        X_list.append(sX[last_out + 1:bi])
                    ts, xs = (float(sa[bi - 1]), sX[bi - 1]) if bi > 0 else (t0, x)
                    res = locate_within(runner, comp, n, ts, xs, float(sa[bi]) - ts)
                    t_list.extend(res["t"])
                    X_list.extend(res["X"])
                    status, message, breach = res["status"], res["message"], res["breach"]
                    break
                inside = ~is_out
                between.update(ta[inside], {key: oa[key][inside] for key in Between.KEYS}, used)
                t_list.append(tc)
                X_list.append(X)
                O_list.append({key: np.array(v[is_out], order="F") for key, v in oa.items()})
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
        except Timeout:
            tr = float(np.concatenate(t_list)[-1])
            status = "timeout"
            message = (f"wall-clock limit of {limit:g} s reached at t = {tr:.6g} s of {tf:g} s; the trajectory so "
                       f"far is kept (raise simulation.wall_limit, or check the scenario for stiffness)")
    between.unchecked = runner.unchecked
    stats["between"] = between.to_json()
    stats["sim_wall_time"] = time.perf_counter() - sim_start
    result = finish(sc, cl, comp, t_list, X_list, status, message, breach, stats, runner, start, O_list)
    refine_peaks(result, runner, comp, between)
    result.stats["between"] = between.to_json()
    if result.status == "ok":
        result.message = ok_message(result)
    return result


"""Where a run stopped: the first bad grid point of a chunk (margin <= 0 or not finite), the breach or
integrator failure located on a finer grid within the output step, and the run's message for it."""

from __future__ import annotations

import time

import numpy as np

from .compiled import Compiled, evaluate_outputs
from .runner import Runner

LOCATE_SUBSTEPS = 100


def bad_index(o: dict, X: np.ndarray) -> tuple[int | None, str]:
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


def describe_breach(t: float, o: dict, i: int, n: int) -> dict:
    """The breached funnel at grid index i of outputs o (else the one with the smallest margin), as JSON data."""
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



def locate_within(runner: Runner, comp: Compiled, n: int, ts: float, xs: np.ndarray, h: float) -> dict:
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
            oj = evaluate_outputs(comp, n, np.array([t + hf]), Xj)
            bi, _ = bad_index(oj, Xj)
            if bi is not None:
                return breach_result(comp, n, good_t, good_X, t + hf, Xj, oj, ts, xs)
            good_t.append(t + hf)
            good_X.append(Xj[0])
            t, x = t + hf, Xj[0]
        # integrator failure at t: report as a breach when close to a boundary
        oc = evaluate_outputs(comp, n, np.array([t]), x[None, :])
        b = describe_breach(t, oc, 0, n)
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
    o = evaluate_outputs(comp, n, tf, X)
    bi, kind = bad_index(o, X)
    if bi is None:       # not reproduced on the fine grid: keep it, and say the run could not go on
        tt = [tf]
        msg = (f"the integrator failed after t = {tf[-1]:.6g} s although every margin was positive there "
               f"(smallest {min(float(np.min(o['m1'][-1])), float(np.min(o['m2'][-1]))):.3g}); "
               f"the trajectory so far is kept")
        return {"t": tt, "X": [X], "status": "failed", "message": msg, "breach": None}
    good_t = list(tf[:bi])
    good_X = list(X[:bi])
    ob = {k: v[bi:bi + 1] for k, v in o.items()}
    return breach_result(comp, n, good_t, good_X, tf[bi], X[bi:bi + 1], ob, ts, xs)


def breach_result(comp: Compiled, n: int, good_t: list, good_X: list, tb: float, Xb: np.ndarray, ob: dict,
                  ts: float, xs: np.ndarray) -> dict:
    """The run's end at a located bad point (tb, Xb, outputs ob): a breach, or a non-finite value."""
    tt = [np.array(good_t)] if good_t else []
    XX = [np.array(good_X)] if good_X else []
    finite = bool(np.isfinite(Xb).all() and all(np.isfinite(ob[k]).all() for k in ("m1", "m2", "tau")))
    if not finite:
        bad = [k for k in ("m1", "m2", "tau") if not np.isfinite(ob[k]).all()]
        msg = (f"non-finite value (NaN/inf) in {'the state' if not np.isfinite(Xb).all() else bad[0]} at "
               f"t = {tb:.6g} s; the run stopped there and the trajectory so far is kept")
        return {"t": tt, "X": XX, "status": "failed", "message": msg, "breach": None}
    b = describe_breach(tb, ob, 0, n)
    msg = (f"funnel breach at t = {tb:.6g} s: |{b['funnel']}| of joint {b['joint']} = {b['abs_error']:.6g} "
           f"reached F{b['funnel'][1]} = {b['boundary']:.6g} (margin {b['margin']:.3g}); "
           f"the trajectory up to the breach is kept")
    return {"t": tt, "X": XX, "status": "breach", "message": msg, "breach": b}


def locate_failure(runner: Runner, comp: Compiled, n: int, k: int, x: np.ndarray, Kc: int, h: float, start: float,
                   limit: float, sub: int = 1, between=None) -> dict:
    """The chunk from grid index k failed: advance point by point (sampling `sub` points per step between them into
    `between`, a `simulation.between.Between`), then locate within the failing step."""
    t_acc, X_acc = [], []
    t = k * h
    for j in range(Kc):
        if time.perf_counter() - start > limit:
            break
        try:
            Xj, tb, Xb = runner.run_dense(t, x, 1, sub)
        except RuntimeError:
            res = locate_within(runner, comp, n, t, x, h)
            return {"t": ([np.array(t_acc)] if t_acc else []) + res["t"],
                    "X": ([np.array(X_acc)] if X_acc else []) + res["X"],
                    "status": res["status"], "message": res["message"], "breach": res["breach"]}
        ta = np.concatenate([tb, [t + h]])
        Xa = np.concatenate([Xb, Xj])
        oa = evaluate_outputs(comp, n, ta, Xa)
        bi, _ = bad_index(oa, Xa)
        if between is not None:
            upto = ta.size - 1 if bi is None else bi
            between.update(ta[:upto], {key: v[:upto] for key, v in oa.items()}, sub)
        if bi is not None:
            ts, xs = (float(ta[bi - 1]), Xa[bi - 1]) if bi > 0 else (t, x)
            res = locate_within(runner, comp, n, ts, xs, float(ta[bi]) - ts)
            inner = [ta[:bi]] if bi > 0 else []
            inner_X = [Xa[:bi]] if bi > 0 else []
            return {"t": ([np.array(t_acc)] if t_acc else []) + inner + res["t"],
                    "X": ([np.array(X_acc)] if X_acc else []) + inner_X + res["X"],
                    "status": res["status"], "message": res["message"], "breach": res["breach"]}
        t_acc.append(t + h)
        X_acc.append(Xj[0])
        t, x = t + h, Xj[0]
    msg = (f"the integrator failed within t = {k * h:.6g} .. {t:.6g} s but not when stepping point by point; "
           f"stopped at t = {t:.6g} s")
    return {"t": [np.array(t_acc)] if t_acc else [], "X": [np.array(X_acc)] if X_acc else [],
            "status": "failed", "message": msg, "breach": None}

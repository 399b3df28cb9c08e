"""Funnel margins that tell designs apart: beside the minimum over the whole run, the minimum after the transient.

At t = 0 the margin 1 - |e(0)|/F(0) is fixed by the initial state and the funnels' start, so the minimum over the run
is often that value whatever the design does afterwards. The post-transient margin is the minimum over t >= t_s, where
t_s is the time from which every funnel stays within SETTLE_BAND of its width at the horizon (or the scenario's
declared `simulation.settle_time`); its time says where the design is tightest.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SETTLE_BAND", "settle_time", "margin_summary", "after_transient"]

#: the funnels have settled once each stays within this fraction above its width at the horizon
SETTLE_BAND = 0.05
#: points of the grid on which the settle time is found
SETTLE_GRID = 4001


def settle_time(design, t_final: float, declared: float | None = None) -> tuple[float, str]:
    """(t_s, how it was set): the declared `simulation.settle_time`, else the first time from which F1 and F2 of
    every joint stay within SETTLE_BAND of their width at t_final."""
    if declared is not None:
        return float(declared), "simulation.settle_time"
    T = float(t_final)
    if not T > 0:
        return 0.0, "no horizon"
    # a design's funnels do not change: every run of a campaign on it has the same horizon (a tenth of a short run)
    known = design.__dict__.setdefault("_settle_times", {})
    if T not in known:
        if len(known) >= 16:
            known.clear()
        known[T] = _settle(design, T)
    return known[T]


def _settle(design, T: float) -> tuple[float, str]:
    """settle_time's search on SETTLE_GRID points of [0, T]."""
    import casadi as ca
    t = np.linspace(0.0, T, SETTLE_GRID)
    f = ca.Function("settle_funnels", [design.sym["t"]], [design.signals["F1"], design.signals["F2"]])
    F1, F2 = (np.asarray(a, float).reshape(-1, t.size) for a in f.map(t.size)(t.reshape(1, -1)))
    F = np.vstack([F1, F2])
    wide = np.any(F > (1.0 + SETTLE_BAND) * F[:, -1:], axis=0)
    idx = np.nonzero(wide)[0]
    # the grid's value as T k / (N - 1), correctly rounded (5.975, not linspace's 5.9750000000000005)
    ts = 0.0 if idx.size == 0 else T * min(int(idx[-1]) + 1, t.size - 1) / (t.size - 1)
    return ts, f"funnels within {100 * SETTLE_BAND:g} % of their width at t = {T:g} s"


def after_transient(t: np.ndarray, m: np.ndarray, ts: float) -> tuple[list, list]:
    """Per joint (columns of m), the minimum of the margins m over t >= ts and the time of that minimum; None where
    the run ended before ts."""
    t = np.asarray(t, float)
    m = np.asarray(m, float).reshape(t.size, -1) if t.size else np.zeros((0, 1))
    keep = t >= ts - 1e-12
    if not keep.any():
        return [None] * m.shape[1], [None] * m.shape[1]
    mm, tt = m[keep], t[keep]
    mins, times = [], []
    for j in range(m.shape[1]):
        col = mm[:, j]
        ok = np.isfinite(col)
        if not ok.any():
            mins.append(None)
            times.append(None)
            continue
        i = int(np.argmin(np.where(ok, col, np.inf)))
        mins.append(float(col[i]))
        times.append(float(tt[i]))
    return mins, times


def margin_summary(t: np.ndarray, m1: np.ndarray, m2: np.ndarray, ts: float, source: str = "") -> dict:
    """The margin fields of every summary: whole-run minima, post-transient minima and their times, t_s."""
    t = np.asarray(t, float)
    out = {}
    for key, m in (("e1", m1), ("e2", m2)):
        m = np.asarray(m, float).reshape(t.size, -1) if t.size else np.zeros((0, 1))
        out[f"min_margin_{key}"] = [float(np.nanmin(m[:, j])) if t.size and np.isfinite(m[:, j]).any() else None
                                    for j in range(m.shape[1])]
        out[f"t_min_margin_{key}"] = [float(t[int(np.nanargmin(m[:, j]))]) if t.size and np.isfinite(m[:, j]).any()
                                      else None for j in range(m.shape[1])]
        mins, times = after_transient(t, m, ts)
        out[f"min_margin_{key}_after_transient"] = mins
        out[f"t_min_margin_{key}_after_transient"] = times
    out["settle_time"] = float(ts)
    out["settle_source"] = source
    return out


def scalar(values) -> float:
    """The smallest of per-joint values (None counts as -inf: a run that never got past t_s has no margin there)."""
    vals = [(-np.inf if v is None else float(v)) for v in (values or [None])]
    return float(min(vals))

"""Per-joint performance metrics a control engineer reads, from a trajectory: tracking after the transient,
overshoot, settling time, torque peaks, control energy and a chattering index, with their units.

One definition serves the continuous-time loop (signals on the output grid) and the sampled loop (errors at the
samples, torque held over each period); docs/metrics.md states each definition.

- ``e1_rms_after_transient``: sqrt( integral over [t_s, t_end] of e1^2 dt / (t_end - t_s) ), trapezoidal on the
  points at t >= t_s (t_s: the run's settle time, `simulation.margins`); |e1| of the one point when only one is left.
- ``e1_max_after_transient``: max |e1| over the points at t >= t_s.
- ``overshoot``: how far e1 swings past zero to the side opposite its first excursion: with t_a the first time
  |e1| exceeds the settling band below and s = sign(e1(t_a)), max(0, max over t >= t_a of -s e1(t)) (for a run
  starting off the reference, s is the sign of the initial error); 0 when e1 is zero throughout.
- ``settling_time``: the first point's time from which |e1| stays within the band SETTLING_BAND * max_t |e1(t)|
  (reported as ``settling_band``) up to the run's end; None when the last point is outside the band (not settled
  within the run); 0 when e1 is zero throughout.
- ``peak_tau``: max |tau| over the run. ``peak_tau_after_t0``: max |tau| once the initial decay from t = 0 has
  ended, i.e. over the points from the first at which |tau| stops decreasing (the whole run when it does not
  decrease at first): the whole-run peak of a funnel design is usually the torque at t = 0, fixed by the initial
  error whatever the design, and the points just after it only show its decay (on any grid).
- ``control_energy``: integral of tau^2 dt (trapezoidal on the output grid; exact for the held torque).
- ``chattering``: total variation of tau per second once the initial decay has ended (the cut of
  ``peak_tau_after_t0``, at t_c): sum over k >= c of |tau_{k+1} - tau_k| / (t_end - t_c) (on the output grid a lower
  bound of the continuous signal's; exact for the held torque: the sum of its jumps). Counted from t = 0, the
  decay of the initial spike alone would dominate it on a short run.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SETTLING_BAND", "METRIC_KEYS", "joint_metrics", "metric_units", "metrics_block"]

#: the settling band, as a fraction of the run's largest |e1| of that joint
SETTLING_BAND = 0.02
#: the per-joint keys of `simulate --json`'s "metrics" (in this order)
METRIC_KEYS = ("e1_rms_after_transient", "e1_max_after_transient", "overshoot", "settling_time", "settling_band",
               "peak_tau", "peak_tau_after_t0", "control_energy", "chattering")


def metric_units(joint_types, n: int) -> dict:
    """Per metric key, the unit of each joint's value: rad or m for the errors, N m or N for the torques, s, ..."""
    from ..core.names import joint_units
    units = joint_units(joint_types, n)
    out = {}
    for k in METRIC_KEYS:
        row = []
        for u in units:
            tau = u["tau"]
            sq = "N^2 m^2 s" if tau == "N m" else "N^2 s"
            row.append({"settling_time": "s", "peak_tau": tau, "peak_tau_after_t0": tau, "control_energy": sq,
                        "chattering": f"{tau}/s"}.get(k, u["e1"]))
        out[k] = row
    return out


def _trapz(y, x) -> float:
    """The trapezoidal integral of samples y at x (numpy's own is named differently across the versions we take)."""
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


def _decay_end(a: np.ndarray) -> int:
    """The index of the first point at which the sequence a stops strictly decreasing (0 when it does not decrease
    at first; the last index when it decreases throughout)."""
    up = np.nonzero(np.diff(a) >= 0)[0]
    return int(up[0]) if up.size else a.size - 1


def _f(v) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def joint_metrics(t, e1, tau, ts: float, *, held: bool = False) -> list[dict]:
    """Per joint (columns), the metrics of METRIC_KEYS. `t`: the times of the e1 rows; `tau`: rows on the same
    times, or with `held`, one row per period [t_k, t_k+1) (the sampled loop's zero-order hold)."""
    t = np.asarray(t, float).reshape(-1)
    e1 = np.asarray(e1, float).reshape(t.size, -1)
    n = e1.shape[1]
    tau = np.asarray(tau, float).reshape(-1, n) if np.size(tau) else np.zeros((0, n))
    tt = t[:tau.shape[0] + 1] if held else t[:tau.shape[0]]
    keep = t >= ts - 1e-12
    out = []
    for j in range(n):
        e = e1[:, j]
        m = {}
        ek, tk = e[keep], t[keep]
        if ek.size >= 2 and tk[-1] > tk[0]:
            m["e1_rms_after_transient"] = _f(np.sqrt(_trapz(ek ** 2, tk) / (tk[-1] - tk[0])))
        else:
            m["e1_rms_after_transient"] = _f(abs(ek[0])) if ek.size else None
        m["e1_max_after_transient"] = _f(np.max(np.abs(ek))) if ek.size else None
        peak = float(np.max(np.abs(e))) if e.size else 0.0
        band = SETTLING_BAND * peak
        m["settling_band"] = _f(band)
        above = np.nonzero(np.abs(e) > band)[0]
        if not e.size:
            m["overshoot"] = None
        elif peak == 0.0 or not above.size:
            m["overshoot"] = 0.0
        else:
            a0 = int(above[0])
            m["overshoot"] = _f(max(0.0, float(np.max(-np.sign(e[a0]) * e[a0:]))))
        if not e.size:
            m["settling_time"] = None
        elif peak == 0.0:
            m["settling_time"] = 0.0
        else:
            out_ = np.nonzero(np.abs(e) > band)[0]
            if out_.size and out_[-1] == e.size - 1:
                m["settling_time"] = None
            else:
                # rounded to 12 digits: a time of the grid, without the float noise of its construction
                m["settling_time"] = float(f"{t[out_[-1] + 1] - t[0]:.12g}") if out_.size else 0.0
        a = tau[:, j]
        m["peak_tau"] = _f(np.max(np.abs(a))) if a.size else None
        c = _decay_end(np.abs(a)) if a.size >= 2 else 0
        m["peak_tau_after_t0"] = _f(np.max(np.abs(a[c:]))) if a.size >= 2 else None
        if held:
            m["control_energy"] = _f(np.sum(a ** 2 * np.diff(tt))) if a.size else None
        else:
            m["control_energy"] = _f(_trapz(a ** 2, tt)) if a.size >= 2 else None
        # over [t_c, t_end]: on a grid, between its points; held, the jumps at t_c+1 .. t_K-1 of the periods'
        span = float(tt[-1] - tt[c])
        m["chattering"] = (_f(np.sum(np.abs(np.diff(a[c:]))) / span)
                           if a.size - c >= 2 and span > 0 else None)
        out.append({k: m[k] for k in METRIC_KEYS})
    return out


def metrics_block(t, e1, tau, ts: float, joint_types, *, n: int, held: bool = False) -> dict:
    """`{"per_joint": [...], "units": {...}, "settle_time": t_s}`: the "metrics" of a JSON summary."""
    per = joint_metrics(t, e1, tau, ts, held=held) if np.size(t) else []
    return {"per_joint": per, "units": metric_units(joint_types, n), "settle_time": float(ts),
            "settling_band_fraction": SETTLING_BAND}


#: the metrics a campaign keeps per run (results.parquet): each the largest over the joints
CAMPAIGN_METRICS = ("e1_rms_after_transient", "peak_tau_after_t0", "control_energy", "chattering")


def campaign_row(block: dict) -> dict:
    """A run's CAMPAIGN_METRICS, each the largest over its joints (NaN where no joint has a value)."""
    out = {}
    for k in CAMPAIGN_METRICS:
        vals = [m[k] for m in block.get("per_joint") or [] if m.get(k) is not None]
        out[k] = float(max(vals)) if vals else float("nan")
    return out

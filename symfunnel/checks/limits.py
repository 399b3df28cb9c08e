"""The URDF's joint position and velocity limits against the run and against the design's e1 funnel.

- `limits.position`, `limits.velocity`: q and dq of the simulated run (its output points) inside [lower, upper] and
  |dq| <= velocity; fail when the run leaves them (the real robot would hit its stops or its drives' limits).
- `limits.funnel`: the set the design lets q take, the reference plus or minus the e1 funnel, qd(t) +- F1(t) over
  [0, T], inside [lower, upper]; warn when it is not (a finding: the funnel allows leaving the joint range, even if
  this run did not), on a grid of FUNNEL_GRID points of [0, T] (not a proof between them).

Each skips when the model is not a URDF or its joints declare no such limit (a continuous joint has no position
limit; a `velocity` of 0 is taken as absent).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from .result import CheckResult

__all__ = ["urdf_joint_limits", "check_limits", "FUNNEL_GRID"]

#: points of [0, T] on which the funnel region is compared with the position limits
FUNNEL_GRID = 4001


def urdf_joint_limits(model) -> list[dict] | None:
    """Per joint of a URDF model (its coordinate order), {"name", "lower", "upper", "velocity"} (None where the
    URDF declares none); None for a model that is not a URDF."""
    if getattr(model, "kind", None) != "urdf" or getattr(model, "tree", None) is None:
        return None
    import pathlib

    from ..model.tree import bodies_from_tree
    from ..model.urdf import limit_attributes
    bodies = bodies_from_tree(model.tree)
    velocity: dict[str, float] = {}
    try:
        for name, v in limit_attributes(pathlib.Path(model.tree.file), "velocity").items():
            try:
                fv = float(v) if v is not None else math.nan
            except ValueError:
                fv = math.nan
            if math.isfinite(fv) and fv > 0:
                velocity[name] = fv
    except (ET.ParseError, OSError):
        pass
    return [{"name": b.joint.name, "lower": b.joint.lower, "upper": b.joint.upper,
             "velocity": velocity.get(b.joint.name)} for b in bodies]


def _skip(cid: str, why: str) -> CheckResult:
    return CheckResult(cid, "skip", why, method="URDF <limit>")


def check_limits(scenario, design, result, t_final: float) -> list[CheckResult]:
    """limits.position, limits.velocity (along the run) and limits.funnel (the e1 funnel around the reference)."""
    from ..core.names import joint_units
    ids = ("limits.position", "limits.velocity", "limits.funnel")
    lim = urdf_joint_limits(scenario.model)
    if lim is None:
        return [_skip(c, "the model is not a URDF: no joint limits declared") for c in ids]
    n = len(lim)
    units = joint_units(scenario.model.joint_types, n)
    lo = np.array([-np.inf if x["lower"] is None else x["lower"] for x in lim])
    hi = np.array([np.inf if x["upper"] is None else x["upper"] for x in lim])
    vel = np.array([np.inf if x["velocity"] is None else x["velocity"] for x in lim])
    has_pos = bool(np.isfinite(lo).any() or np.isfinite(hi).any())
    out = []
    t = np.asarray(result.t, float)
    q = np.asarray(result.signals.get("q", np.zeros((0, n))), float).reshape(t.size, -1)
    dq = np.asarray(result.signals.get("dq", np.zeros((0, n))), float).reshape(t.size, -1)
    method = f"the run's {t.size} output points against the URDF's <limit>"
    if not has_pos:
        out.append(_skip(ids[0], "the URDF declares no position limit on any joint"))
    elif t.size == 0:
        out.append(_skip(ids[0], "no trajectory"))
    else:
        out.append(_along(ids[0], t, np.minimum(q - lo, hi - q), q, lo, hi, units, "e1", lim, method))
    if not np.isfinite(vel).any():
        out.append(_skip(ids[1], "the URDF declares no velocity limit (velocity > 0) on any joint"))
    elif t.size == 0:
        out.append(_skip(ids[1], "no trajectory"))
    else:
        out.append(_along(ids[1], t, vel - np.abs(dq), dq, -vel, vel, units, "e2", lim, method))
    if not has_pos:
        out.append(_skip(ids[2], "the URDF declares no position limit on any joint"))
    else:
        out.append(_funnel(design, float(t_final), lo, hi, units, lim))
    return out


def _along(cid, t, margin, x, lo, hi, units, ukey, lim, method) -> CheckResult:
    """A check of a signal x (T, n) against [lo, hi] per joint by its margin (T, n): fail where negative."""
    m = np.where(np.isfinite(margin), margin, np.inf)
    i, j = np.unravel_index(int(np.argmin(m)), m.shape)
    worst = float(m[i, j])
    what = "q" if ukey == "e1" else "dq"
    u = units[j][ukey]
    where = {"t": float(t[i]), "joint": int(j + 1)}
    ev = {"value": float(x[i, j]), "lower": float(lo[j]), "upper": float(hi[j])}
    rng = f"[{lo[j]:.4g}, {hi[j]:.4g}] {u}"
    if worst < 0:
        k = int(np.argmax(np.any(m < 0, axis=1)))
        return CheckResult(cid, "fail", f"joint {j + 1} ({lim[j]['name']}) leaves its range {rng}: {what} = "
                           f"{x[i, j]:.4g} {u} at t = {t[i]:.4g} s (first outside at t = {t[k]:.4g} s)",
                           method=method, margin=worst, where=where, evidence=ev)
    return CheckResult(cid, "pass", f"inside every joint's range; closest: joint {j + 1} ({lim[j]['name']}), "
                       f"{what} = {x[i, j]:.4g} {u} at t = {t[i]:.4g} s, {worst:.4g} {u} inside {rng}",
                       method=method, margin=worst, where=where, evidence=ev)


def _funnel(design, T: float, lo, hi, units, lim) -> CheckResult:
    """limits.funnel: qd(t) - F1(t) >= lower and qd(t) + F1(t) <= upper on FUNNEL_GRID points of [0, T]."""
    import casadi as ca
    cid = "limits.funnel"
    if not T > 0:
        return _skip(cid, "no horizon")
    tg = np.linspace(0.0, T, FUNNEL_GRID)
    f = ca.Function("limits_funnel", [design.sym["t"]], [design.reference_t["qd"], design.signals["F1"]])
    qd, F1 = (np.asarray(a, float).reshape(-1, tg.size).T for a in f.map(tg.size)(tg.reshape(1, -1)))
    margin = np.minimum(qd - F1 - lo, hi - (qd + F1))
    m = np.where(np.isfinite(margin), margin, np.inf)
    i, j = np.unravel_index(int(np.argmin(m)), m.shape)
    worst = float(m[i, j])
    u = units[j]["e1"]
    method = (f"qd(t) +- F1(t) on {FUNNEL_GRID} points of [0, {T:g}] s against the URDF's <limit lower upper> "
              "(a grid, not a proof between its points)")
    where = {"t": float(tg[i]), "joint": int(j + 1)}
    ev = {"qd": float(qd[i, j]), "F1": float(F1[i, j]), "lower": float(lo[j]), "upper": float(hi[j])}
    rng = f"[{lo[j]:.4g}, {hi[j]:.4g}] {u}"
    if worst < 0:
        bad = np.any(m < 0, axis=1)
        return CheckResult(cid, "warn", f"the e1 funnel lets joint {j + 1} ({lim[j]['name']}) leave its range {rng}: "
                           f"qd +- F1 = {qd[i, j]:.4g} +- {F1[i, j]:.4g} {u} at t = {tg[i]:.4g} s, "
                           f"{-worst:.4g} {u} beyond (outside over {bad.mean():.1%} of [0, {T:g}] s); narrow the "
                           "funnel or move the reference away from the limit", method=method, margin=worst,
                           where=where, evidence=ev)
    return CheckResult(cid, "pass", f"the reference +- the e1 funnel stays inside every joint's range; closest: joint "
                       f"{j + 1} ({lim[j]['name']}), {worst:.4g} {u} inside {rng} at t = {tg[i]:.4g} s",
                       method=method, margin=worst, where=where, evidence=ev)

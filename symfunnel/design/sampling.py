"""Random states for numeric checks: over the joint range, or inside both funnels of the design."""

from __future__ import annotations

import numpy as np

from . import Design


def unit_samples(k: int, dim: int, rng: np.random.Generator, method: str = "random") -> np.ndarray:
    """k points in [0, 1]^dim (rows), plain random or scrambled Sobol ('sobol')."""
    if method == "sobol":
        from ..core.sobol import sobol           # scipy's points without importing scipy.stats
        m = int(np.ceil(np.log2(max(k, 2))))
        return sobol(dim, 2 ** m, rng)[:k]
    return rng.random((k, dim))


def joint_states(design: Design, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """k states (q, dq) as (n, k) arrays: q uniform over the audit's joint range, dq over +-velocity_range."""
    a = design.scenario.audit
    n = design.n
    u = rng.random((2 * n, k))
    lo, hi = np.array(a.joint_lower)[:, None], np.array(a.joint_upper)[:, None]
    q = lo + (hi - lo) * u[:n]
    vr = np.array(a.velocity_range)[:, None]
    dq = vr * (2 * u[n:] - 1)
    return q, dq


def funnel_states(design: Design, k: int, rng: np.random.Generator, *, method: str = "random",
                  fill: float = 0.98, t_range: tuple[float, float] | None = None,
                  w_scale: float = 1.0, edge: bool = False) -> dict[str, np.ndarray]:
    """k points strictly inside both funnels, as design-input arrays with the sample index last.

    t is drawn over [0, t_final], e1 = u1 * fill * F1(t), q = qd(t) + e1, e2 = u2 * fill * F2(t),
    dq = alpha2 + e2; each approximator state within its invariant box and w_hat within +-w_scale. With `edge`
    the errors crowd the funnels' boundaries instead (|e|/F = 1 - 10^(-6 v), v uniform).
    Matrix states come side by side (casadi's map layout: block j holds sample j); `vec_<name>` holds them
    column-major vectorised, one column per sample (the closed loop's state layout).
    """
    sc = design.scenario
    n = design.n
    box = design.approximator.box()
    sizes = [(name, r * c) for name, (r, c) in design.states]
    t0, t1 = t_range if t_range is not None else (0.0, sc.simulation.t_final)
    dim = 1 + 2 * n + sum(m for _, m in sizes)
    u = unit_samples(k, dim, rng, method).T               # (dim, k)
    t = t0 + (t1 - t0) * u[0:1]
    ref = design.reference.map(k)
    qd, dqd, ddqd = (np.array(v) for v in ref(t))
    F = design.function("funnel_bounds", ["t"], ["F1", "F2"]).map(k)
    F1, F2 = (np.array(v) for v in F(t))
    if edge:     # |e|/F = 1 - 10^(-6 v): half the points within 0.1 % of the funnel's boundary, none on it
        for rows in (slice(1, 1 + n), slice(1 + n, 1 + 2 * n)):
            v = u[rows]
            side = np.where(v < 0.5, -1.0, 1.0)
            u[rows] = 0.5 + 0.5 * side * (1.0 - 10.0 ** (-6.0 * np.abs(2 * v - 1))) / fill
    e1 = (2 * u[1:1 + n] - 1) * fill * F1
    q = qd + e1
    a2 = design.function("alpha2", ["t", "q", "qd", "dqd"]).map(k)
    alpha2 = np.array(a2(t, q, qd, dqd))
    e2 = (2 * u[1 + n:1 + 2 * n] - 1) * fill * F2
    dq = alpha2 + e2
    out = dict(t=t, q=q, dq=dq, qd=qd, dqd=dqd, ddqd=ddqd)
    i = 1 + 2 * n
    for (name, (r, c)), (_, m) in zip(design.states, sizes):
        half = box.get(name, w_scale)
        v = (2 * u[i:i + m] - 1) * half
        i += m
        out["vec_" + name] = v
        # casadi's map takes matrix inputs side by side: block j holds sample j's (r x c) matrix.
        out[name] = v.reshape(r, c, k, order="F").transpose(0, 2, 1).reshape(r, k * c) if c > 1 else v
    return out


def eval_mapped(f, pts: dict[str, np.ndarray], k: int) -> list[np.ndarray]:
    """Evaluate a design Function (inputs named after base inputs) at k points; outputs side by side per sample."""
    out = f.map(k)(*[pts[f.name_in(i)] for i in range(f.n_in())])
    if f.n_out() == 1:
        out = [out]
    return [np.array(o) for o in out]


def point_of(pts: dict[str, np.ndarray], j: int) -> dict:
    """The j-th sampled point as a plain dict (for 'where' in check results)."""
    return {"t": float(pts["t"][0, j]), "q": pts["q"][:, j].tolist(), "dq": pts["dq"][:, j].tolist()}


__all__ = ["unit_samples", "joint_states", "funnel_states", "eval_mapped", "point_of"]

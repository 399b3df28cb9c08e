"""The design's twins against what the scenario declares: the funnels and the reference the controller is fed.

- ``funnel.consistency``: the F1, dF1, F2, dF2 the design uses (its SX: what the controller, the simulation's
  containment checks and the generated code see) against the declared funnel, evaluated independently from the
  scenario's numbers or expressions on sympy (dF by sympy's diff), on the horizon grid; and each shape's numeric
  `value()` against its SX. A funnel that is widened anywhere between the declaration and the checks fails here,
  although every containment check against the widened funnel passes.
- ``reference.derivatives``: the reference as fed to the controller (`Design.reference_t`, the one the closed loop,
  the C step and the exported `reference` function take) is a derivative chain: dq_d = d/dt q_d and
  ddq_d = d/dt dq_d by AD of the SX, q_d and its derivatives equal the declared expressions on sympy, and
  fourth-order central differences of the generated (numpy-only) `reference` code agree. The design identity
  holds for any reference signal, so no other check notices a controller fed a wrong derivative.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .result import CheckResult

#: relative disagreement above which an SX twin differs from the declaration (round-off is ~1e-15)
TWIN_TOL = 1e-9
#: relative disagreement above which a finite difference of the generated reference code differs from its
#: derivative output (a fourth-order stencil at the step below is accurate to ~1e-10 relative)
FD_TOL = 1e-6
#: points of the horizon where the twins are compared
GRID_POINTS = 401
#: sample times where a shape's numeric value() is compared with its SX (value() builds a Function per call)
VALUE_POINTS = 11


def _grid(t_final: float, k: int = GRID_POINTS) -> np.ndarray:
    return np.linspace(0.0, float(t_final), k)


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| relative to b's peak magnitude over the grid, per row (joint): (rows, T)."""
    scale = np.maximum(np.max(np.abs(b), axis=-1, keepdims=True), 1e-12)
    out = np.abs(a - b) / scale
    return np.where(np.isfinite(out), out, np.inf)


def _sympy_rows(exprs, t_sym, grid: np.ndarray, order: int) -> list[np.ndarray]:
    """Values of sympy expressions in t and of their first `order` derivatives on a grid: [(rows, T), ...]."""
    import sympy
    out = []
    cur = list(exprs)
    for k in range(order + 1):
        f = sympy.lambdify(t_sym, cur, modules="numpy")
        vals = np.array([np.broadcast_to(np.asarray(v, dtype=float), grid.shape) for v in f(grid)])
        out.append(vals)
        if k < order:
            # a kink (abs, sign, max, min) differentiates to DiracDelta, which numpy cannot evaluate: it is zero
            # wherever the derivative exists, as CasADi's AD takes it; the kink's instants are the scenario's matter
            cur = [sympy.diff(e, t_sym).replace(sympy.DiracDelta, lambda *a: sympy.S.Zero) for e in cur]
    return out


def _worst(rel: np.ndarray, grid: np.ndarray) -> tuple[float, int, float]:
    """(largest relative error, its joint (1-based), its time)."""
    i, j = np.unravel_index(int(np.argmax(rel)), rel.shape)
    return float(rel[i, j]), int(i) + 1, float(grid[j])


def check_funnel_consistency(design, t_final: float) -> CheckResult:
    """funnel.consistency: the design's F, dF (SX) equal the declared funnels, and value() equals the SX."""
    import sympy

    from ..family.funnels import sx_function
    sc = design.scenario
    grid = _grid(t_final)
    t_sym = sympy.Symbol("t", real=True)
    f = design.function("funnel_twins", ["t"], ["F1", "dF1", "F2", "dF2"]).map(grid.size)
    F1, dF1, F2, dF2 = (np.asarray(v) for v in f(grid[None, :]))
    used = {"e1": (F1, dF1), "e2": (F2, dF2)}
    rows, worst = [], (0.0, "", 0, 0.0)
    for key in ("e1", "e2"):
        shape = sc.funnels[key]
        decl_F, decl_dF = _sympy_rows(shape.declared(t_sym), t_sym, grid, 1)
        for what, mine, ref in ((f"F{key[1]}", used[key][0], decl_F), (f"dF{key[1]}", used[key][1], decl_dF)):
            e, j, t = _worst(_rel(mine, ref), grid)
            rows.append({"signal": what, "against": "declared", "max_relative": e, "joint": j, "t": t})
            if e > worst[0]:
                worst = (e, f"the design's {what} against the declared funnel {key}", j, t)
        ts = grid[np.linspace(0, grid.size - 1, VALUE_POINTS).astype(int)]
        val = np.array([shape.value(float(t)) for t in ts]).T
        sx = np.asarray(sx_function(shape).map(ts.size)(ts[None, :])[0])
        e, j, t = _worst(_rel(val, sx), ts)
        rows.append({"signal": f"F{key[1]}", "against": "value() vs SX", "max_relative": e, "joint": j, "t": t})
        if e > worst[0]:
            worst = (e, f"funnel {key}'s numeric value() against its SX", j, t)
    ev = {"comparisons": rows, "tolerance": TWIN_TOL, "grid_points": int(grid.size)}
    method = (f"the design's F, dF (SX, dF by AD) against the declaration evaluated on sympy (dF by sympy.diff) at "
              f"{grid.size} times on [0, {t_final:g}] s, and each shape's value() against its SX")
    e, what, j, t = worst
    where = {"t": t, "joint": j} if what else None
    if e <= TWIN_TOL:
        return CheckResult("funnel.consistency", "pass", f"the funnels the design uses are the declared ones: "
                           f"largest relative difference {e:.2g} (tolerance {TWIN_TOL:g})", method=method,
                           margin=TWIN_TOL - e, where=where, evidence=ev)
    return CheckResult("funnel.consistency", "fail", f"{what} differ: relative difference {e:.3g} at t = {t:.4g} s, "
                       f"joint {j} (tolerance {TWIN_TOL:g}): the funnel that is checked is not the one declared",
                       method=method, margin=TWIN_TOL - e, where=where, evidence=ev)


def reference_code(design):
    """The generated numpy-only code of the design's `reference` function (t -> qd, dqd, ddqd), loaded."""
    from ..emit.python import emit_python
    text = emit_python([design.reference])
    ns: dict = {}
    exec(compile(text, "<generated reference>", "exec"), ns)      # noqa: S102 - our own generated module
    return ns["reference"]


def _fd(f, grid: np.ndarray, h: float) -> np.ndarray:
    """Fourth-order central difference of a batched function of t: (rows, T)."""
    return (8 * (f(grid + h) - f(grid - h)) - (f(grid + 2 * h) - f(grid - 2 * h))) / (12 * h)


def check_reference_derivatives(design, t_final: float) -> CheckResult:
    """reference.derivatives: the reference fed to the controller is the declared one with its true derivatives."""
    import sympy
    sc = design.scenario
    n = design.n
    grid = _grid(t_final)
    rt = design.reference_t
    t = design.sym["t"]
    chain = ca.Function("chain", [t], [rt["qd"], rt["dqd"], rt["ddqd"], ca.jtimes(rt["qd"], t, ca.SX(1)),
                                       ca.jtimes(rt["dqd"], t, ca.SX(1))]).map(grid.size)
    qd, dqd, ddqd, d_qd, d_dqd = (np.asarray(v).reshape(n, -1) for v in chain(grid[None, :]))
    t_sym = sympy.Symbol("t", real=True)
    decl = _sympy_rows([e.to_sympy({"t": t_sym}) for e in sc.reference], t_sym, grid, 2)
    code = reference_code(design)

    def gen(k):
        return lambda s: np.asarray(code(s[None, :])[k]).reshape(n, -1)
    h = 1e-3
    comparisons = [
        ("dq_d = d/dt q_d (AD)", dqd, d_qd, TWIN_TOL), ("ddq_d = d/dt dq_d (AD)", ddqd, d_dqd, TWIN_TOL),
        ("q_d = declared", qd, decl[0], TWIN_TOL), ("dq_d = d/dt declared", dqd, decl[1], TWIN_TOL),
        ("ddq_d = d2/dt2 declared", ddqd, decl[2], TWIN_TOL),
        ("generated dq_d = FD of generated q_d", gen(1)(grid), _fd(gen(0), grid, h), FD_TOL),
        ("generated ddq_d = FD of generated dq_d", gen(2)(grid), _fd(gen(1), grid, h), FD_TOL),
    ]
    rows, bad, worst = [], [], None
    for what, mine, ref, tol in comparisons:
        e, j, tt = _worst(_rel(mine, ref), grid)
        rows.append({"comparison": what, "max_relative": e, "joint": j, "t": tt, "tolerance": tol})
        if e > tol:
            bad.append(rows[-1])
        if worst is None or e / tol > worst["max_relative"] / worst["tolerance"]:
            worst = rows[-1]
    ev = {"comparisons": rows, "grid_points": int(grid.size), "fd_step": h}
    method = (f"AD of the SX reference, sympy derivatives of the declared expressions and fourth-order central "
              f"differences (h = {h:g} s) of the generated reference code at {grid.size} times on [0, {t_final:g}] s")
    where = {"t": worst["t"], "joint": worst["joint"]}
    margin = float(1.0 - worst["max_relative"] / worst["tolerance"])
    if not bad:
        return CheckResult("reference.derivatives", "pass", "the controller's q_d, dq_d, ddq_d are the declared "
                           f"reference and its derivatives (worst: {worst['comparison']}, relative "
                           f"{worst['max_relative']:.2g})", method=method, margin=margin, where=where, evidence=ev)
    b = bad[0]
    return CheckResult("reference.derivatives", "fail", f"{b['comparison']} fails: relative difference "
                       f"{b['max_relative']:.3g} at t = {b['t']:.4g} s, joint {b['joint']} (tolerance "
                       f"{b['tolerance']:g}); the controller is not fed the reference's derivative chain"
                       + (f" ({len(bad)} of {len(rows)} comparisons fail)" if len(bad) > 1 else ""),
                       method=method, margin=margin, where=where, evidence=ev)

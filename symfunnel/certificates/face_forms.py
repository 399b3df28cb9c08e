"""Exact rewrites of the face expressions of `certify.containment` that keep interval arithmetic from subtracting
two wide enclosures of one quantity (dependency), each checked on the SX graph before it is used.

alpha2_dot by forward AD is dalpha2/dq dq + dalpha2/dqd dqd + ...: two large terms in dq and dq_d that are, in
truth, one term in de1 = dq - dq_d. Where alpha2 = dq_d + g(t, e1) on the graph (e1 = q - q_d the only way q and
q_d enter, dq_d entering with coefficient 1), the same function is

    alpha2_dot = ddq_d + dg/dt + dg/de1 (g + e2),     since de1 = dq - dq_d = alpha2 + e2 - dq_d = g + e2,

in which t enters only through the funnels (and ddq_d): over a box of t its enclosure is the width of what
actually changes, not of dq and dq_d separately.

Also the graph-identity test these rewrites rest on (`_drop_cancelled`: a node provably not entering), the form of
M_p^-1 whose enclosure is tightest (`solver_form`), and the normal components n1, n2 in all these forms
(`normal_components`), which `certify.containment`'s faces and `certify.sampled`'s one-period map share.
"""

from __future__ import annotations

import casadi as ca

from ..sx.rewrite import replace_nodes
from .region import structurally_zero


def _drop_cancelled(expr: ca.SX, nodes: ca.SX, restore: tuple[ca.SX, ca.SX] | None = None) -> tuple[ca.SX, bool]:
    """`expr` with the nodes set to 0 when it provably does not depend on them: the nodes are replaced by fresh
    symbols A and the Jacobian of expr in A must be structurally zero (a graph identity, no numbers). `restore`
    (symbol, node): a placeholder symbol of `expr` replaced by its node afterwards (e.g. e2, kept opaque so that
    alpha2 + (dq - alpha2) is not simplified to dq before the cancellation is seen)."""
    A = ca.SX.sym("A", nodes.numel())
    e = replace_nodes([expr], ca.vec(nodes), A)[0]
    # CasADi differentiates sign, floor, comparisons as 0: the Jacobian shows independence only where A enters
    # through none of them
    ok = _enters_smoothly(e, A) and structurally_zero(ca.jacobian(e, A))
    e = ca.substitute(e, A, ca.DM.zeros(A.numel())) if ok else expr
    if restore is not None:
        e = ca.substitute(e, restore[0], restore[1])
    return e, ok


#: operations CasADi differentiates as 0 (or as a step) although they are not constant: jumps and kinks
_IRREGULAR = {getattr(ca, k): k[3:].lower() for k in ("OP_SIGN", "OP_FABS", "OP_FMIN", "OP_FMAX", "OP_FLOOR",
                                                    "OP_CEIL", "OP_IF_ELSE_ZERO", "OP_LT", "OP_LE", "OP_EQ",
                                                    "OP_NE", "OP_NOT", "OP_AND", "OP_OR", "OP_FMOD",
                                                    "OP_REMAINDER", "OP_COPYSIGN")}


def _enters_smoothly(e: ca.SX, A: ca.SX) -> bool:
    """Whether no operation CasADi differentiates as 0 although it is not constant (sign, floor, a comparison,
    min/max, abs...) takes an argument that depends on the symbols A, in the graph of e (a pass over its tape)."""
    rest = [v for v in ca.symvar(e) if not ca.depends_on(v, A)]
    f = ca.Function("dependency", [A, ca.vertcat(*rest) if rest else ca.SX(0, 1)], [e])
    dep: dict[int, bool] = {}
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        ins, outs = f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_INPUT:
            d = ins[0] == 0
        elif op == ca.OP_OUTPUT:
            continue
        else:
            d = any(dep.get(i, False) for i in ins) if op != ca.OP_CONST else False
        if d and op in _IRREGULAR:
            return False
        for o in outs:
            dep[o] = d
    return True


def alpha2_dot_through_e1(design) -> tuple[ca.SX | None, str]:
    """(alpha2_dot written through e1 and e2, in the design's symbols and its e1, e2 nodes, "") or (None, why the
    design's alpha2 does not have the form dq_d + g(t, e1))."""
    S, sym = design.signals, design.sym
    n = design.n
    E1 = ca.SX.sym("E1", n)
    a = replace_nodes([S["alpha2"]], ca.vec(S["e1"]), E1)[0]
    if ca.depends_on(a, ca.vertcat(sym["q"], sym["qd"])):
        return None, "alpha2 depends on q or q_d beyond e1 = q - q_d"
    g, ok = _drop_cancelled(a - sym["dqd"], sym["dqd"])
    if not ok:
        return None, "alpha2 - dq_d depends on dq_d"
    others = [ca.vec(v) for k, v in sym.items() if k != "t"]
    if ca.depends_on(g, ca.vertcat(*others)):
        return None, "alpha2 - dq_d depends on more than t and e1"
    E2 = ca.SX.sym("E2", n)
    adot = ca.jtimes(g, ca.vertcat(sym["t"], E1), ca.vertcat(ca.SX(1), g + E2)) + sym["ddqd"]
    adot = ca.substitute(adot, ca.vertcat(E1, E2), ca.vertcat(ca.vec(S["e1"]), ca.vec(S["e2"])))
    return adot, ""


def with_alpha2_dot_through_e1(design, expr: ca.SX) -> tuple[ca.SX, bool]:
    """`expr` with every alpha2_dot node replaced by `alpha2_dot_through_e1` (unchanged, False, where alpha2 does
    not have that form)."""
    adot, _ = alpha2_dot_through_e1(design)
    if adot is None:
        return expr, False
    return replace_nodes([expr], ca.vec(design.signals["alpha2_dot"]), ca.vec(adot))[0], True


#: widths of the q boxes around the reference's start on which the elimination orders' enclosures are compared
PIVOT_WIDTHS = (0.01, 0.03, 0.1)


def solver_form(design, adjugate: bool, pivots: bool, qc: ca.SX | None = None):
    """(solve(M, b) or None for the default LDL^T, its name): M_p^-1 by the adjugate for two joints (if `adjugate`);
    for three or more (if `pivots`) the form whose interval enclosure of M^-1 1 over boxes of q around the
    reference's start (`PIVOT_WIDTHS`, the design's model M) is finite on most of them, then narrowest, among
    LDL^T base-first, LDL^T tip-first (the articulated-body order of a serial arm) and, given the symbols `qc` (a
    point per box: the box's centre), (C M)^-1 C b with C = M_model(qc)^-1 (`sx.linalg.preconditioned_solve`).
    Each is the same M^-1 b, so the choice, made on numbers, changes how tight an enclosure is, never whether it
    is right."""
    import numpy as np

    from ..sx.batch import BatchIntervalFunction
    from ..sx.interval import IntervalError
    from ..sx.linalg import ldl_solve, preconditioned_solve, solve2
    n, M, q = design.n, design.signals["M"], design.sym["q"]
    if n == 2 and adjugate:
        return solve2, "adjugate"
    others = [ca.vec(v) for k, v in design.sym.items() if k != "q"]
    if n < 3 or not pivots or ca.depends_on(M, ca.vertcat(*others)):
        return None, "LDL^T"
    tip = list(reversed(range(n)))
    forms = {"LDL^T": None, "LDL^T tip-first": lambda A, rhs: ldl_solve(A, rhs, tip)}
    Q = ca.SX.sym("Q", n)
    if qc is not None:
        Mc = ca.substitute(M, q, qc)
        C = ca.horzcat(*[ldl_solve(Mc, ca.DM.eye(n)[:, j]) for j in range(n)])
        forms["preconditioned at the box's centre"] = lambda A, rhs: preconditioned_solve(A, rhs, C)
    q0 = np.asarray(design.reference(0.0)[0], float).ravel()
    w = np.asarray(PIVOT_WIDTHS, float)[:, None]
    best, pick = None, "LDL^T"
    for name, f in forms.items():
        x = (f or ldl_solve)(M, ca.DM.ones(n))
        try:
            F = BatchIntervalFunction(ca.Function("Minv", [q, qc if qc is not None else Q], [x]))
        except (IntervalError, RuntimeError):
            continue
        L, H, _ = F.eval_batch(np.c_[q0 - w / 2, np.repeat(q0[None], w.size, 0)],
                               np.c_[q0 + w / 2, np.repeat(q0[None], w.size, 0)])
        width = np.max(H - L, axis=1)
        fin = np.isfinite(width)
        score = (int(fin.sum()), -float(np.sum(np.log(width[fin]))) if fin.any() else 0.0)
        if best is None or score > best:
            best, pick = score, name
    return forms[pick], pick


def normal_components(design, p: ca.SX, adjugate: bool, u: ca.SX | None = None,
                      through_e1: bool = True, pivots: bool = False, qc: ca.SX | None = None
                      ) -> tuple[ca.SX, ca.SX, dict]:
    """(n1, n2, which rewrites applied): the normal components n1 = de1 - (e1/F1) dF1 and n2 = de2 - (e2/F2) dF2
    along the true plant (parameters p) in their exact rewrites -- de1 = alpha2 + e2 - dq_d with dq_d dropped where
    it cancels, alpha2_dot through e1, and under the design's own torque (`u` None) de2 = nominal de2 + f_true
    (`region.true_unknown`, M_p^-1 by the adjugate for two joints if `adjugate`); under a torque `u` held apart
    (the sampled loop's zero-order hold) de2 = ddq_plant(u) - alpha2_dot. `through_e1` False keeps the design's
    forward-AD alpha2_dot (for measuring what the rewrite buys); `pivots`: M_p^-1 for three or more joints in the
    form of `solver_form` (`qc`: the symbols of its preconditioner's point). Shared by `certify.containment`'s faces
    and `certify.sampled`'s one-period map."""
    from ..plant.equations import plant_acceleration
    from .region import true_unknown
    S, sym = design.signals, design.sym
    E2 = ca.SX.sym("E2", design.n)                 # e2 = dq - alpha2, as a placeholder (see _drop_cancelled)
    n1 = S["alpha2"] + E2 - sym["dqd"] - S["e1"] / S["F1"] * S["dF1"]      # de1 = dq - dqd = alpha2 + e2 - dqd
    n1, c1 = _drop_cancelled(n1, sym["dqd"], restore=(E2, S["e2"]))
    solve, how = solver_form(design, adjugate, pivots, qc)
    if u is None:
        nominal = S["ddq"] - S["alpha2_dot"] - S["e2"] / S["F2"] * S["dF2"]
        nominal, c2 = _drop_cancelled(nominal, S["alpha2_dot"])
        tu = true_unknown(design, p, solve=solve)
        form, n2 = tu["form"], nominal + tu["f_true"]
    else:
        ddq = plant_acceleration(design.scenario, sym["q"], sym["dq"], sym["t"], u, 0.0, p=p, solve=solve)["ddq"]
        form, c2, n2 = "held torque", False, ddq - S["alpha2_dot"] - S["e2"] / S["F2"] * S["dF2"]
    # alpha2_dot (in tau and the nominal ddq inside f_true) through de1 = g + e2, not dq and dq_d apart
    n2, c3 = with_alpha2_dot_through_e1(design, n2) if through_e1 else (n2, False)
    return n1, n2, {"cancelled": {"dqd in de1": c1, "alpha2_dot in de2": c2, "dqd in alpha2_dot": c3},
                    "f_true": form, "solve": how}


__all__ = ["alpha2_dot_through_e1", "normal_components", "with_alpha2_dot_through_e1"]

"""Exact rewrites of the face expressions of `certify.containment` that keep interval arithmetic from subtracting
two wide enclosures of one quantity (dependency), each checked on the SX graph before it is used.

alpha2_dot by forward AD is dalpha2/dq dq + dalpha2/dqd dqd + ...: two large terms in dq and dq_d that are, in
truth, one term in de1 = dq - dq_d. Where alpha2 = dq_d + g(t, e1) on the graph (e1 = q - q_d the only way q and
q_d enter, dq_d entering with coefficient 1), the same function is

    alpha2_dot = ddq_d + dg/dt + dg/de1 (g + e2),     since de1 = dq - dq_d = alpha2 + e2 - dq_d = g + e2,

in which t enters only through the funnels (and ddq_d): over a box of t its enclosure is the width of what
actually changes, not of dq and dq_d separately.

Also the graph-identity test these rewrites rest on (`_drop_cancelled`: a node provably not entering).
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


__all__ = ["alpha2_dot_through_e1", "with_alpha2_dot_through_e1"]

"""What `certify.sampled`'s one-period map needs beyond the design's signals: facts read off the design's graph
(whether sigma' is continuous along a period) and the outward
rounded interval helpers of its enclosures."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..sx.batch_rules import _dn, _up


_SWITCHING = ("OP_SIGN", "OP_IF_ELSE_ZERO", "OP_LT", "OP_LE", "OP_EQ", "OP_NE", "OP_NOT", "OP_AND", "OP_OR",
              "OP_FLOOR", "OP_CEIL")


def _switching_on(inputs: list, wrt: list, outputs: list) -> int:
    """How many discontinuous operations (sign, comparisons, branches, floor) of the graph of `outputs` have an
    argument that depends on the symbols `wrt` (the other inputs are held constant)."""
    f = ca.Function("g", inputs, outputs)
    codes = {getattr(ca, k) for k in _SWITCHING if hasattr(ca, k)}
    op_input, op_output, op_const = ca.OP_INPUT, ca.OP_OUTPUT, ca.OP_CONST
    wrt_ids = set()
    for i, x in enumerate(inputs):
        for k in range(x.nnz()):
            if any(ca.depends_on(x.nz[k], w) for w in wrt):
                wrt_ids.add((i, k))
    dep: dict[int, bool] = {}
    count = 0
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        o = f.instruction_output(k)
        if op == op_input:
            i, nz = f.instruction_input(k)
            dep[o[0]] = (i, nz) in wrt_ids
        elif op == op_output or op == op_const:
            if op == op_const:
                dep[o[0]] = False
        else:
            d = any(dep.get(a, False) for a in f.instruction_input(k) if a >= 0)
            if op in codes and d:
                count += 1
            dep[o[0]] = d
    return count


def coulomb_signs_as(exprs, dq, s) -> list:
    """`exprs` (an SX or a list) with every sign(dq_j) node -- Coulomb friction's, as `plant.equations` writes it
    at width 0 -- replaced by s_j: the plant with the friction's sign held, smooth in the state where only that
    sign jumps."""
    from ..sx.rewrite import replace_nodes
    exprs = exprs if isinstance(exprs, (list, tuple)) else [exprs]
    return replace_nodes(list(exprs), ca.vertcat(*[ca.sign(dq[j]) for j in range(dq.numel())]), s)


def _continuous_rates(design, inputs, state, plant_ddq) -> tuple[bool, str]:
    """Whether sigma' is continuous along a period (so the next sample's second-order form may use the Lipschitz
    mean-value argument where its interval evaluation flags a sign that may switch): the plant's acceleration has no
    discontinuous operation depending on the state (t, q, dq) -- the held torque's dead zone is constant -- and the
    design's alpha2, F and F' have none, and the transformation's z is C^1 at e = 0 (proven by sympy: the
    derivative of each branch of |s| agrees at 0), so alpha2_dot's sign(e1) from the AD of |e1| multiplies a jump 0."""
    S = design.signals
    if _switching_on(inputs, state, [plant_ddq]):
        return False, "the plant's acceleration switches with the state (Coulomb friction, a branch)"
    sym = design.sym
    ins = [sym[k] for k in ("t", "q", "qd", "dqd", "ddqd")]
    if _switching_on(ins, ins, [S["alpha2"], S["F1"], S["F2"], S["dF1"], S["dF2"]]):
        return False, "alpha2 or a funnel has a discontinuous operation"
    if not _transform_c1(design.variant.transform.name):
        return False, "the transformation's z is not shown C^1 at e = 0"
    return True, "sigma' is continuous along a period (checked)"


_C1: dict = {}


def _transform_c1(name: str) -> bool:
    """sympy: z(s) of the registered transformation (F = 1) has equal one-sided derivatives at s = 0."""
    if name in _C1:
        return _C1[name]
    import sympy

    from ..family.transforms import TRANSFORMS
    from ..sx.proof import _Timeout, simplify, time_limit
    from ..sx.tosympy import sx_to_sympy
    T = TRANSFORMS.get(name)()
    s = ca.SX.sym("s")
    z = T.build(s, ca.SX(1))["z"]
    ok = False
    try:
        with time_limit(10.0):
            S = sympy.Symbol("s", real=True)
            e = sx_to_sympy(z, [s], [[S]])[0]
            P = sympy.Symbol("P", positive=True)
            right = sympy.diff(e.subs(S, P), P)
            left = sympy.diff(e.subs(S, -P), P)         # d/ds at -P is -d/dP of z(-P)
            ok = bool(simplify(sympy.limit(right, P, 0, "+") + sympy.limit(left, P, 0, "+")) == 0)
    except (_Timeout, RecursionError, NotImplementedError, TypeError, ValueError):
        ok = False
    _C1[name] = ok
    return ok


def _imul(al, ah, bl, bh):
    """Interval product [al, ah] x [bl, bh], outward rounded (0 x inf as the whole line)."""
    with np.errstate(invalid="ignore"):
        P = np.stack([al * bl, al * bh, ah * bl, ah * bh])
    bad = np.any(np.isnan(P), axis=0)
    lo = np.where(bad, -np.inf, _dn(np.min(P, axis=0)))
    hi = np.where(bad, np.inf, _up(np.max(P, axis=0)))
    return lo, hi


def _sum_dn(X, axis):
    """A lower bound of the sum along `axis` (the summation's rounding error bounded by m u sum |x|)."""
    m = X.shape[axis]
    with np.errstate(invalid="ignore"):
        return _dn(np.sum(X, axis=axis) - _up(np.sum(np.abs(X), axis=axis) * ((m + 1) * 2.0 ** -52)))


def _sum_up(X, axis):
    """An upper bound of the sum along `axis`."""
    m = X.shape[axis]
    with np.errstate(invalid="ignore"):
        return _up(np.sum(X, axis=axis) + _up(np.sum(np.abs(X), axis=axis) * ((m + 1) * 2.0 ** -52)))


def _add_up(a, b):
    """An upper bound of a + b for b >= 0 (b = h D rounded up): exact where b is 0, so a box whose rate points
    inward keeps its face without an ulp of outward rounding."""
    return np.where(b > 0, _up(a + _up(b)), a)


def _add_dn(a, b):
    """A lower bound of a + b for b <= 0, exact where b is 0."""
    return np.where(b < 0, _dn(a + _dn(b)), a)

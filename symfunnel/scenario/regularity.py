"""The regularity the design's argument needs, proven at load over [0, T] by interval arithmetic (not sampled):
each funnel F_i > 0 and in C^1, the reference q_d in C^2.

The design differentiates F once and q_d twice by AD, which drops the Dirac of a jump and the jump of a kink: a
`sign`, `abs`, `min`, `max`, comparison or if-else of t that can switch inside [0, T] makes the controller (and
every certificate) reason about a signal the loop does not follow (a q_d jumping by more than the funnel's width is
a breach no design can avoid). Such an input is refused with the key and why (exit 2) unless the switch is proven
away: abs(2 + sin(t)) is smooth and accepted. A funnel that touches 0 between grid points (a dip narrower than any
sampling) is refused because positivity is proven by branch and bound on [0, T], not checked on a grid.
"""

from __future__ import annotations

import casadi as ca

from ..core.errors import InputError
from ..sx.regularity import nonsmooth_arguments, prove_on_horizon

#: the scenario language's name of a tape operation
_NAME = {"FABS": "abs", "SIGN": "sign", "FMIN": "min", "FMAX": "max", "IF_ELSE_ZERO": "if_else", "ATAN2": "atan2",
         "LT": "a comparison", "LE": "a comparison", "EQ": "a comparison", "NE": "a comparison", "NOT": "not",
         "AND": "and", "OR": "or", "FLOOR": "floor", "CEIL": "ceil", "FMOD": "fmod", "COPYSIGN": "copysign"}
_WHY = {"nonzero": "can cross its switch", "same_floor": "can cross an integer", "same_ceil": "can cross an integer"}


def _prove(rows: list[tuple[ca.SX, str, str]], t: ca.SX, t_final: float):
    """rows (expression, predicate, what) -> the first failure as (what, failure) or None."""
    from ..sx.interval import IntervalError
    try:
        f = ca.Function("regularity", [t], [ca.densify(ca.vertcat(*[r[0] for r in rows]))], ["t"], ["g"])
        fails = prove_on_horizon(f, [r[1] for r in rows], t_final)
    except IntervalError:
        # an operation without an interval rule (certify refuses it by name, exit 2): prove what can be proven --
        # the rows built from operations with rules (a switching argument usually is one)
        keep = []
        for r in rows:
            try:
                prove_on_horizon(ca.Function("row", [t], [ca.densify(r[0])]), ["finite"], 0.0, max_boxes=1)
                keep.append(r)
            except IntervalError:
                continue
        if not keep:
            return None
        return _prove(keep, t, t_final)
    if not fails:
        return None
    rank = {"positive": 0, "nonzero": 1, "same_floor": 1, "same_ceil": 1, "finite": 2}
    # a definite violation first; then positivity, a switch, a non-finite derivative (the clearest cause)
    first = min(fails, key=lambda x: (not x.definite, rank[rows[x.output][1]], x.output))
    return rows[first.output][2], first


def _where(fail) -> str:
    if fail.t_hi - fail.t_lo > 1e-6 * max(1.0, abs(fail.t_hi)):
        return f"t in [{fail.t_lo:.9g}, {fail.t_hi:.9g}] s"
    return f"t = {0.5 * (fail.t_lo + fail.t_hi):.9g} s"


def _switch_rows(exprs: list[ca.SX], t: ca.SX, suffix: str = "") -> list:
    """One row per distinct switching argument, those of the expression itself before its derivatives'."""
    rows, seen = [], set()
    for k, e in enumerate(exprs):
        for s in nonsmooth_arguments(e, t):
            h = s.argument.nz[0].element_hash() if s.argument.nnz() else None
            if (h, s.kind) in seen:
                continue
            seen.add((h, s.kind))
            where = "" if k == 0 else f" (in its {'first' if k == 1 else 'second'} derivative)"
            rows.append((s.argument, s.kind, f"the argument of {_NAME.get(s.op, s.op.lower())}{where}{suffix}, which "
                                             f"{_WHY[s.kind]}"))
    return rows


#: (what, expression text, horizon) already proven regular in this process (a campaign re-loads the same funnels
#: and reference for every run; the proof depends on nothing else)
_PROVEN: set = set()


def check_funnel_regular(shape, t_final: float, *, file: str, key: str) -> None:
    """InputError naming `key` unless F_i > 0, F_i and dF_i/dt finite and no kink or jump of F_i on [0, T]."""
    t = ca.SX.sym("t")
    F = ca.SX(shape.sx(t))
    memo = ("F", str(F), float(t_final))
    if memo in _PROVEN:
        return
    dF = ca.jacobian(F, t)
    n = F.numel()
    rows = []
    for j in range(n):
        joint = f" (joint {j + 1})" if n > 1 else ""
        rows += [(F[j], "positive", f"F{joint}"), (dF[j], "finite", f"dF/dt{joint}")]
        rows += _switch_rows([F[j], dF[j]], t, joint)
    got = _prove(rows, t, t_final)
    if got is None:
        _PROVEN.add(memo)
        return
    what, fail = got
    T = float(t_final)
    if what.startswith("F"):
        msg = (f"{what} = {fail.value:.6g} at t = {0.5 * (fail.t_lo + fail.t_hi):.9g} s" if fail.definite else
               f"{what} is not proven positive near {_where(fail)} (interval branch and bound; smallest enclosure "
               "reaches 0)")
        raise InputError(f"is not positive on [0, {T:g}]: {msg}", file=file, key=key,
                         expected=f"F(t) > 0 on [0, t_final = {T:g}], proven (a dip between grid points counts)")
    raise InputError(f"is not continuously differentiable on [0, {T:g}]: {what} near {_where(fail)}",
                     file=file, key=key,
                     expected="F(t) in C^1 on [0, t_final]: abs/sign/min/max/comparisons only of arguments that "
                              "provably never switch on the horizon")


def check_reference_regular(reference: list, t_final: float, *, file: str) -> None:
    """InputError naming `reference.q[i]` unless q_d, dq_d, ddq_d are finite and no kink or jump of q_d, dq_d or
    ddq_d on [0, T] (q_d in C^2)."""
    t = ca.SX.sym("t")
    T = float(t_final)
    for i, e in enumerate(reference):
        memo = ("q", e.text, T)
        if memo in _PROVEN:
            continue
        q = ca.SX(e.to_casadi({"t": t}))
        dq = ca.jacobian(q, t)
        ddq = ca.jacobian(dq, t)
        rows = [(q, "finite", "q_d"), (dq, "finite", "dq_d/dt"), (ddq, "finite", "d2q_d/dt2")]
        rows += _switch_rows([q, dq, ddq], t)
        got = _prove(rows, t, T)
        if got is None:
            _PROVEN.add(memo)
            continue
        what, fail = got
        raise InputError(f"'{e.text}' is not twice continuously differentiable on [0, {T:g}]: {what} near "
                         f"{_where(fail)}", file=file,
                         key=f"reference.q[{i}]" if len(reference) > 1 else "reference.q",
                         expected="q_d(t) in C^2 on [0, t_final] (the design uses dq_d and ddq_d): "
                                  "abs/sign/min/max only of arguments that provably never switch on the horizon")

"""The plant's nonlinearities that the controller does not know (dead zone eq. 2, friction), with optional smoothing.

Every function is elementwise over the joints and returns CasADi (SX for SX/numeric input, MX for MX input); the
``*_numpy`` forms evaluate that SX on arrays (through a CasADi Function: one source, no second formula). A smoothing width ``w`` selects the form: ``w = 0`` is the
exact, non-smooth nonlinearity (``fmax``/``sign``, which CasADi differentiates as a step and as 0), ``w > 0`` an
algebraic smooth approximation whose error vanishes as w -> 0. Smoothing exists because CVODES stalls on the kinks
of Coulomb friction and of the dead zone; the simulation should use a small w > 0 and report it as a deviation.

Bounds of the approximations (all sharp, all checked by tests/test_plant.py):

* ``ramp``: 0 <= ramp_w(x) - max(x, 0) <= w/2, largest at x = 0; derivative continuous with value 1/2 at 0.
* ``sign``: |sign_w(x) - sign(x)| <= min(1, w^2 / (2 x^2)); the error cannot be uniform in x (a continuous function
  cannot approximate a jump uniformly), only pointwise and in any band |x| >= delta.
* ``dead_zone``: |d_w(u) - d(u)| <= (L_l + L_r) w / 2, with L_l, L_r the branch slopes' bounds on the range used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import casadi as ca
import numpy as np

from ..core.errors import InputError
from ..expr import Expression

Branch = Callable[[ca.SX], ca.SX]


def _width(w) -> float | ca.SX:
    if isinstance(w, ca.SX):       # a symbol (a compiled loop's parameter): the smooth form, for a value > 0
        return w
    if isinstance(w, bool) or not isinstance(w, (int, float, np.integer, np.floating)) or not math.isfinite(w) \
            or w < 0:
        raise ValueError(f"smoothing width w = {w!r}, expected a finite number >= 0")
    return float(w)


def _cas(x):
    if isinstance(x, (ca.SX, ca.MX)):
        return x
    if isinstance(x, ca.DM):
        return ca.SX(x)
    a = np.asarray(x, dtype=float)
    return ca.SX(a.reshape(-1, 1) if a.ndim <= 1 else a)


def _per_joint(v, n: int, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).ravel()
    if a.size == 1:
        a = np.full(n, a[0])
    if a.size != n:
        raise ValueError(f"{name} has {a.size} entries, expected 1 or {n} (one per joint)")
    return a


def ramp(x, w: float = 0.0):
    """max(x, 0), or for w > 0 its smooth algebraic approximation (x + sqrt(x^2 + w^2))/2 (error <= w/2, no exp to overflow)."""
    w = _width(w)
    x = _cas(x)
    if not isinstance(w, ca.SX) and w == 0.0:
        return ca.fmax(x, 0)
    return 0.5 * (x + ca.sqrt(x * x + w * w))


def _elementwise(fn, x) -> np.ndarray:
    """A scalar SX function of one variable, evaluated elementwise on an array of any shape."""
    x = np.asarray(x, dtype=float)
    s = ca.SX.sym("x")
    f = ca.Function("f", [s], [fn(s)])
    if x.size == 0:
        return x.copy()
    return np.asarray(f.map(x.size)(x.reshape(1, -1))).reshape(x.shape)


def ramp_numpy(x, w: float = 0.0) -> np.ndarray:
    """`ramp` evaluated on an array (from its SX)."""
    w = _width(w)
    return _elementwise(lambda s: ramp(s, w), x)


def sign(x, w: float = 0.0):
    """sign(x) (0 at 0), or for w > 0 the smooth x / sqrt(x^2 + w^2), which keeps Coulomb friction integrable by CVODES."""
    w = _width(w)
    x = _cas(x)
    if not isinstance(w, ca.SX) and w == 0.0:
        return ca.sign(x)
    return x / ca.sqrt(x * x + w * w)


def sign_numpy(x, w: float = 0.0) -> np.ndarray:
    """`sign` evaluated on an array (from its SX)."""
    w = _width(w)
    return _elementwise(lambda s: sign(s, w), x)


#: the largest smoothing width accepted at all: sign_w(v) is off sign(v) by more than 29 % only for |v| < w, so a
#: width of 0.1 (rad/s or m/s) already blurs the friction of every slow motion; beyond, the plant loses its friction
MAX_SMOOTHING_WIDTH = 0.1
#: the largest width as a fraction of a dead zone's smallest breakpoint |b|: the smooth ramp's error w/2 stays a quarter of it
WIDTH_PER_BREAKPOINT = 0.5


def check_smoothing_width(w: float, plant, *, file: str | None, key: str) -> float:
    """A smoothing width bounded by the scales it smooths (issue 44): at most MAX_SMOOTHING_WIDTH and at most
    WIDTH_PER_BREAKPOINT of the dead zone's smallest nonzero breakpoint; a width is a numerical device, and an
    unbounded one removes the friction and the dead zone from the plant (InputError naming `key` otherwise)."""
    limit, why = MAX_SMOOTHING_WIDTH, "the friction's velocity band"
    dz = getattr(plant, "dead_zone", None)
    if dz is not None:
        b = [abs(float(v)) for v in (*dz.b_l, *dz.b_r) if float(v) != 0.0]
        if b and WIDTH_PER_BREAKPOINT * min(b) < limit:
            limit, why = WIDTH_PER_BREAKPOINT * min(b), f"{WIDTH_PER_BREAKPOINT:g} x the dead zone's smallest breakpoint"
    if not w <= limit:
        raise InputError(f"is {w:g}, which smooths the friction and dead zone away", file=file, key=key,
                         expected=f"a numerical width of at most {limit:.3g} ({why}; the default is 1e-3)")
    return w


def _check_branches(left: Sequence, right: Sequence) -> int:
    n = len(left)
    if len(right) != n:
        raise ValueError(f"{len(left)} left branches but {len(right)} right branches (expected one per joint each)")
    return n


def dead_zone(u, b_l, b_r, left: Sequence[Branch], right: Sequence[Branch], w: float = 0.0):
    """The dead zone of eq. 2 per joint, as right(b_r + ramp(u - b_r, w)) + left(b_l - ramp(b_l - u, w)).

    Why this form: for w = 0 the first term is right(u) for u >= b_r and right(b_r) = 0 otherwise, the second is
    left(u) for u <= b_l and left(b_l) = 0 otherwise, so the sum is exactly eq. 2 (b_l < 0 < b_r keeps the two
    terms from overlapping). For w > 0 the smooth ramp is strictly positive, so each branch is only ever evaluated
    inside its own domain (right on (b_r, inf), left on (-inf, b_l)), where Assumption 1 makes it smooth; the
    result is then smooth, with error <= (L_l + L_r) w / 2 for branch slopes bounded by L_l, L_r.

    `u` is an n x 1 CasADi column (or numbers), `b_l`, `b_r` per-joint arrays (or one number), `left`, `right` lists
    of n callables mapping a scalar CasADi expression to one.
    """
    w = _width(w)
    u = _cas(u)
    n = _check_branches(left, right)
    if u.shape != (n, 1):
        raise ValueError(f"dead zone input has shape {u.shape}, expected ({n}, 1)")
    b_l = _per_joint(b_l, n, "b_l")
    b_r = _per_joint(b_r, n, "b_r")
    out = []
    for i in range(n):
        ui = u[i]
        out.append(right[i](b_r[i] + ramp(ui - b_r[i], w)) + left[i](b_l[i] - ramp(b_l[i] - ui, w)))
    return ca.vertcat(*out)


def _columns(expr_of, n: int, v) -> np.ndarray:
    """An (n, 1) SX function of one (n, 1) variable evaluated at v of shape (n,) or (n, m)."""
    v = np.asarray(v, dtype=float)
    if v.shape[0] != n:
        raise ValueError(f"input has {v.shape[0]} rows, expected {n}")
    s = ca.SX.sym("v", n)
    f = ca.Function("f", [s], [expr_of(s)])
    cols = v.reshape(n, -1)
    out = np.asarray(f.map(cols.shape[1])(cols))
    return out.reshape(v.shape)


def dead_zone_numpy(u, b_l, b_r, left: Sequence[Callable], right: Sequence[Callable], w: float = 0.0) -> np.ndarray:
    """`dead_zone` evaluated (from its SX) for u of shape (n,) or (n, m); the branches must accept SX."""
    w = _width(w)
    n = _check_branches(left, right)
    return _columns(lambda s: dead_zone(s, b_l, b_r, left, right, w), n, u)


def friction(dq, viscous, coulomb, w: float = 0.0):
    """Joint friction viscous*dq + coulomb*sign(dq, w) per joint (Section 4 uses 15*dq + 6*sign(dq))."""
    dq = _cas(dq)
    n = dq.shape[0]
    fv = ca.DM(_per_joint(viscous, n, "viscous"))
    fc = ca.DM(_per_joint(coulomb, n, "coulomb"))
    return fv * dq + fc * sign(dq, w)


def friction_numpy(dq, viscous, coulomb, w: float = 0.0) -> np.ndarray:
    """`friction` evaluated (from its SX) for dq of shape (n,) or (n, m)."""
    dq = np.asarray(dq, dtype=float)
    return _columns(lambda s: friction(s, viscous, coulomb, w), dq.shape[0], dq)


def _branch_function(f: Callable, label: str) -> ca.Function:
    """A CasADi Function s -> (f(s), f'(s)) for one scalar branch; ValueError if it does not build a scalar."""
    s = ca.SX.sym("u")
    try:
        e = f(s)
    except Exception as exc:  # the branch comes from user input: report, don't crash
        raise ValueError(f"{label} could not be evaluated symbolically: {exc}") from exc
    try:
        e = e if isinstance(e, ca.SX) else ca.SX(e)
    except Exception as exc:
        raise ValueError(f"{label} does not give a CasADi SX expression: {exc}") from exc
    if e.shape != (1, 1):
        raise ValueError(f"{label} returns shape {e.shape}, expected a scalar")
    return ca.Function("branch", [s], [e, ca.jacobian(e, s)])


def _samples(fun: ca.Function, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    vals, slopes = fun.map(points.size)(points.reshape(1, -1))
    return np.asarray(vals).ravel(), np.asarray(slopes).ravel()


def check_dead_zone(left: Sequence[Branch], right: Sequence[Branch], b_l, b_r, *, span: float = 10.0,
                    samples: int = 101, tol: float = 1e-9) -> list[str]:
    """Problems of a dead zone found by computation (empty if none), so a scenario can be rejected with a reason.

    Checks per joint: b_l < 0 < b_r; continuity right(b_r) = 0 and left(b_l) = 0 within `tol`; branch slopes
    (CasADi AD) finite and > 0 at `samples` points of [b_r, b_r + span] and [b_l - span, b_l], breakpoints
    included, so that a passing dead zone has the positive slope bounds that eq. 5's d(t) needs.
    """
    n = _check_branches(left, right)
    b_l = _per_joint(b_l, n, "b_l")
    b_r = _per_joint(b_r, n, "b_r")
    offsets = np.linspace(0.0, float(span), int(samples))
    problems: list[str] = []
    for i in range(n):
        j = f"joint {i + 1}"
        if not b_l[i] < 0:
            problems.append(f"{j}: b_l = {b_l[i]:g} is not < 0 (eq. 2 needs b_l < 0 < b_r)")
        if not b_r[i] > 0:
            problems.append(f"{j}: b_r = {b_r[i]:g} is not > 0 (eq. 2 needs b_l < 0 < b_r)")
        for side, branch, b, points in (("right", right[i], b_r[i], b_r[i] + offsets),
                                        ("left", left[i], b_l[i], b_l[i] - offsets)):
            label = f"{j}: {side} branch"
            try:
                fun = _branch_function(branch, label)
            except ValueError as exc:
                problems.append(str(exc))
                continue
            at_b = float(fun(b)[0])
            if not math.isfinite(at_b) or abs(at_b) > tol:
                problems.append(f"{label} is {at_b:g} at its breakpoint {b:g}, not 0: the dead zone jumps there "
                                f"(eq. 2 is continuous)")
            vals, slopes = _samples(fun, points)
            bad = ~np.isfinite(vals) | ~np.isfinite(slopes)
            if bad.any():
                k = int(np.argmax(bad))
                problems.append(f"{label} is not finite at u = {points[k]:g}")
                continue
            if (slopes <= 0).any():
                k = int(np.argmax(slopes <= 0))
                problems.append(f"{label} has slope {slopes[k]:g} <= 0 at u = {points[k]:g} "
                                f"(branches must be increasing)")
    return problems


def dead_zone_slope_bounds(left: Sequence[Branch], right: Sequence[Branch], b_l, b_r, span: float = 10.0,
                           samples: int = 101) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint (min, max) of the branch slopes sampled on [b_r, b_r + span] and [b_l - span, b_l].

    By the mean value theorem (eqs. 3-4) these bound the paper's d(t) in eq. 5 for torques within span of the
    breakpoints; returns two arrays of length n (take .min() / .max() for one pair of numbers).
    """
    n = _check_branches(left, right)
    b_l = _per_joint(b_l, n, "b_l")
    b_r = _per_joint(b_r, n, "b_r")
    offsets = np.linspace(0.0, float(span), int(samples))
    lo, hi = np.empty(n), np.empty(n)
    for i in range(n):
        _, sr = _samples(_branch_function(right[i], f"joint {i + 1}: right branch"), b_r[i] + offsets)
        _, sl = _samples(_branch_function(left[i], f"joint {i + 1}: left branch"), b_l[i] - offsets)
        both = np.concatenate([sr, sl])
        lo[i], hi[i] = float(np.min(both)), float(np.max(both))
    return lo, hi


@dataclass
class DeadZoneSpec:
    """Asymmetric dead zone of eq. 2: branch expressions in u, b_l and b_r, per joint breakpoints."""

    b_l: list[float]
    b_r: list[float]
    left: Expression
    right: Expression
    left_scale: list[float] | None = None   # per joint factor on the left branch (its slope); None = 1
    right_scale: list[float] | None = None


def check_dead_zone_spec(dz: DeadZoneSpec, n: int, file: str) -> None:
    """Branches must vanish at their breakpoints and increase beyond them (eq. 2-4), decided numerically."""
    u = ca.SX.sym("u")
    for j in range(n):
        env = {"u": u, "b_l": dz.b_l[j], "b_r": dz.b_r[j]}
        for side, expr, b, span in (("right", dz.right, dz.b_r[j], 1.0), ("left", dz.left, dz.b_l[j], -1.0)):
            e = expr.to_casadi(env)
            f = ca.Function("f", [u], [e, ca.jacobian(e, u)])
            at_b = float(f(b)[0])
            if not math.isfinite(at_b) or abs(at_b) > 1e-9 * max(1.0, abs(b)):
                raise InputError(f"gives {at_b:g} at u = {b:g} for joint {j + 1}", file=file,
                                 key=f"plant.dead_zone.{side}",
                                 expected="a branch that is 0 at its breakpoint (continuous dead zone)")
            for s in (0.0, 0.5, 1.0, 5.0, 50.0):
                slope = float(f(b + span * s)[1])
                if not math.isfinite(slope) or slope <= 0:
                    raise InputError(f"has slope {slope:g} at u = {b + span * s:g} for joint {j + 1}",
                                     file=file, key=f"plant.dead_zone.{side}",
                                     expected="an increasing branch (positive slope, eq. 3-4)")

"""Funnel shapes F(t) > 0, one registered class each; the design asks a shape for F as SX and for its bounds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from ..core import validate as V
from ..core.errors import InputError
from ..expr import Expression, parse_expression
from ..core.registry import Registry

FUNNEL_SHAPES = Registry("funnel shape", "funnel.eK")

#: points per second (at least 2001 in all) where a funnel's extremes over a horizon are sampled
_GRID_PER_SECOND = 200


@FUNNEL_SHAPES.register("exponential", "F(t) = phi0 exp(-a t) + phi_inf, per joint (keys `phi0`, `phi_inf`, `a`)")
@dataclass
class FunnelSpec:
    """F(t) = phi0*exp(-a*t) + phi_inf, per joint."""

    phi0: list[float]
    phi_inf: list[float]
    a: list[float]

    KEYS = ("phi0", "phi_inf", "a")

    @classmethod
    def parse(cls, table: dict, n: int, file: str, prefix: str, defaults, parameters=None) -> "FunnelSpec":
        """Validate `[funnel.eK]` with the exponential keys (`parameters`: unused, the keys are numbers)."""
        V.check_keys(table, cls.KEYS, file=file, prefix=prefix)
        if defaults is None:                      # nothing to inherit (e.g. a claim about an expression funnel)
            defaults = (V._MISSING,) * 3
        phi0 = V.per_joint(table, "phi0", n, defaults[0], file=file, prefix=prefix, minimum=0)
        phi_inf = V.per_joint(table, "phi_inf", n, defaults[1], file=file, prefix=prefix, minimum=0,
                              strict_min=True)
        a = V.per_joint(table, "a", n, defaults[2], file=file, prefix=prefix, minimum=0)
        return cls(phi0, phi_inf, a)

    def sx(self, t: ca.SX, **values) -> ca.SX:
        """F as an (n, 1) SX expression in t (`values`: phi0, phi_inf or a as expressions instead of the numbers)."""
        phi0, phi_inf, a = (values.get(k, ca.DM(getattr(self, k))) for k in self.KEYS)
        return phi0 * ca.exp(-a * t) + phi_inf

    def value(self, t: float) -> list[float]:
        """F at time t, per joint, evaluated from `sx` (one source: no numeric re-implementation to drift)."""
        return sx_value(self, t)

    def declared(self, t):
        """The declared F as a sympy expression in the sympy symbol t, from the numbers as written (the independent
        evaluation `funnel.consistency` compares the SX with)."""
        import sympy
        return [sympy.Float(p0) * sympy.exp(-sympy.Float(a) * t) + sympy.Float(pi)
                for p0, pi, a in zip(self.phi0, self.phi_inf, self.a)]

    def text(self, i: int) -> str:
        """Joint i's F as readable text."""
        return f"{self.phi0[i]:g} exp(-{self.a[i]:g} t) + {self.phi_inf[i]:g}"


@FUNNEL_SHAPES.register("expression", "F(t) = any expression in `t` and the model's parameters (key `F`: one "
                         "string, or one per joint); F > 0 and C^1 on [0, t_final] proven at load")
class ExpressionFunnel:
    """F(t) given as expressions of the scenario language, one per joint; no monotonicity assumed anywhere."""

    KEYS = ("F",)

    def __init__(self, exprs: list[Expression], parameters: dict[str, float] | None = None):
        self.exprs = list(exprs)
        self.parameters = dict(parameters or {})

    @classmethod
    def parse(cls, table: dict, n: int, file: str, prefix: str, defaults=None,
              parameters: dict[str, float] | None = None) -> "ExpressionFunnel":
        """Validate `[funnel.eK] F = "..."` (or an array of n strings) in t and the model's parameters."""
        V.check_keys(table, cls.KEYS, file=file, prefix=prefix)
        params = dict(parameters or {})
        names = {"t"} | set(params)
        full = V.join(prefix, "F")
        value = table["F"]
        if isinstance(value, str):
            exprs = [parse_expression(value, names, file=file, key=full)] * n
        elif isinstance(value, list) and len(value) == n and all(isinstance(v, str) for v in value):
            exprs = [parse_expression(v, names, file=file, key=V.join(full, i)) for i, v in enumerate(value)]
        else:
            raise InputError(f"is {V.a_type(value)}" if not isinstance(value, list)
                             else f"is an array of {len(value)}", file=file, key=full,
                             expected=f"an expression string in t, or an array of {n} strings (one per joint)")
        for i, e in enumerate(exprs):
            shape = e.to_casadi({"t": ca.SX.sym("t"), **params}).shape
            if shape != (1, 1):
                raise InputError(f"has shape {shape[0]}x{shape[1]}", file=file,
                                 key=full if isinstance(value, str) else V.join(full, i), expected="a scalar in t")
        return cls(exprs, params)

    def sx(self, t: ca.SX) -> ca.SX:
        """F as an (n, 1) SX expression in t."""
        return ca.vertcat(*[ca.SX(e.to_casadi({"t": t, **self.parameters})) for e in self.exprs])

    def value(self, t: float) -> list[float]:
        """F at time t, per joint, evaluated from `sx`."""
        return sx_value(self, t)

    def declared(self, t):
        """The declared F as sympy expressions in the sympy symbol t (the expression language's sympy backend)."""
        return [e.to_sympy({"t": t, **self.parameters}) for e in self.exprs]

    def text(self, i: int) -> str:
        """Joint i's F as written."""
        return self.exprs[i].text


def sx_function(shape: Any) -> ca.Function:
    """t -> (F, dF/dt) of a shape, from its SX (dF by AD): what the design, value() and the checks evaluate."""
    t = ca.SX.sym("t")
    F = shape.sx(t)
    return ca.Function("F", [t], [F, ca.jtimes(F, t, ca.SX(1))], ["t"], ["F", "dF"])


def sx_value(shape: Any, t: float) -> list[float]:
    """F of a shape at one time, per joint, from its SX."""
    return np.asarray(sx_function(shape)(float(t))[0]).ravel().tolist()


def horizon_grid(t_final: float) -> np.ndarray:
    """The sample times on [0, t_final] where a funnel's extremes are taken."""
    return np.linspace(0.0, float(t_final), max(2001, int(_GRID_PER_SECOND * float(t_final)) + 1))


def _grid_values(shape: Any, t_final: float) -> tuple[np.ndarray, np.ndarray]:
    """(grid, F on it as (n, T))."""
    t = ca.SX.sym("t")
    f = ca.Function("F", [t], [shape.sx(t)])
    grid = horizon_grid(t_final)
    return grid, np.asarray(f.map(grid.size)(grid.reshape(1, -1)))


def extremes(shape: Any, t_final: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inf F, sup F, argmin t) per joint over [0, t_final], on a dense grid (no monotonicity assumed)."""
    grid, vals = _grid_values(shape, t_final)
    return vals.min(axis=1), vals.max(axis=1), grid[np.argmin(vals, axis=1)]


#: the largest funnel value accepted (F = 1e8 around an error of 1e-2 already spends 10 of the 16 digits)
MAX_F = 1e8


def check_positive(shape: Any, t_final: float, *, file: str, key: str) -> None:
    """InputError naming `key` (e.g. funnel.e2.F) and the first time F is not a finite positive number, on the
    dense grid of [0, t_final] (and its derivative is finite there: the design differentiates F)."""
    grid, vals = _grid_values(shape, t_final)
    t = ca.SX.sym("t")
    F = shape.sx(t)
    dvals = np.asarray(ca.Function("dF", [t], [ca.jtimes(F, t, ca.SX(1))]).map(grid.size)(grid.reshape(1, -1)))
    bad = ~(np.isfinite(vals) & (vals > 0) & np.isfinite(dvals))
    if (np.isfinite(vals) & (vals > MAX_F)).any() and not bad.any():
        k = int(np.argmax((vals > MAX_F).any(axis=0)))
        j = int(np.argmax(vals[:, k] > MAX_F))
        raise InputError(f"is {vals[j, k]:.6g} at t = {grid[k]:.6g} s", file=file, key=key,
                         expected=f"F(t) at most {MAX_F:g} (errors bounded by a larger funnel lose their precision "
                                  "in double arithmetic)")
    if bad.any():
        k = int(np.argmax(bad.any(axis=0)))                 # the first bad time, then its first bad joint
        j = int(np.argmax(bad[:, k]))
        what = f"F = {vals[j, k]:.6g}" if not (np.isfinite(vals[j, k]) and vals[j, k] > 0) else \
            f"dF/dt = {dvals[j, k]:.6g}"
        joint = f" joint {j + 1}" if vals.shape[0] > 1 else ""
        raise InputError(f"is not positive at t = {grid[k]:.6g} s{joint} ({what})", file=file, key=key,
                         expected=f"F(t) > 0 (finite, differentiable) on [0, t_final = {float(t_final):g}]")


def parse_funnel(table: Any, n: int, file: str, prefix: str, defaults, parameters: dict | None = None) -> Any:
    """Validate one `[funnel.eK]` table into the shape its keys select (keys of two shapes: an input error)."""
    V.check_keys(table, [k for e in FUNNEL_SHAPES for k in e.obj.KEYS], file=file, prefix=prefix)
    chosen = [e for e in FUNNEL_SHAPES if any(k in table for k in e.obj.KEYS)]
    if len(chosen) > 1:
        a, b = chosen[-1], chosen[0]
        mine = next(k for k in a.obj.KEYS if k in table)
        other = next(k for k in b.obj.KEYS if k in table)
        raise InputError(f"cannot be combined with '{other}'", file=file, key=V.join(prefix, mine),
                         expected=f"either {' or '.join('/'.join(e.obj.KEYS) for e in chosen)}, not both")
    shape = chosen[0].obj if chosen else FunnelSpec            # no keys: the exponential with its defaults
    return shape.parse(table, n, file, prefix, defaults, parameters)

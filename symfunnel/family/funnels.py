"""Funnel shapes F(t) > 0, one registered class each; the design asks a shape for F as SX and for its bounds."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from .. import validate as V
from ..registry import Registry

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
    def parse(cls, table: dict, n: int, file: str, prefix: str, defaults) -> "FunnelSpec":
        """Validate `[funnel.eK]` with the exponential keys."""
        V.check_keys(table, cls.KEYS, file=file, prefix=prefix)
        phi0 = V.per_joint(table, "phi0", n, defaults[0], file=file, prefix=prefix, minimum=0)
        phi_inf = V.per_joint(table, "phi_inf", n, defaults[1], file=file, prefix=prefix, minimum=0,
                              strict_min=True)
        a = V.per_joint(table, "a", n, defaults[2], file=file, prefix=prefix, minimum=0)
        return cls(phi0, phi_inf, a)

    def sx(self, t: ca.SX) -> ca.SX:
        """F as an (n, 1) SX expression in t."""
        return ca.DM(self.phi0) * ca.exp(-ca.DM(self.a) * t) + ca.DM(self.phi_inf)

    def value(self, t: float) -> list[float]:
        """F at time t, per joint."""
        return [p0 * math.exp(-a * t) + pi for p0, pi, a in zip(self.phi0, self.phi_inf, self.a)]

    def text(self, i: int) -> str:
        """Joint i's F as readable text."""
        return f"{self.phi0[i]:g} exp(-{self.a[i]:g} t) + {self.phi_inf[i]:g}"


def horizon_grid(t_final: float) -> np.ndarray:
    """The sample times on [0, t_final] where a funnel's extremes are taken."""
    return np.linspace(0.0, float(t_final), max(2001, int(_GRID_PER_SECOND * float(t_final)) + 1))


def extremes(shape: Any, t_final: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inf F, sup F, argmin t) per joint over [0, t_final], on a dense grid (no monotonicity assumed)."""
    t = ca.SX.sym("t")
    f = ca.Function("F", [t], [shape.sx(t)])
    grid = horizon_grid(t_final)
    vals = np.asarray(f.map(grid.size)(grid.reshape(1, -1)))           # (n, T)
    return vals.min(axis=1), vals.max(axis=1), grid[np.argmin(vals, axis=1)]


def parse_funnel(table: Any, n: int, file: str, prefix: str, defaults) -> Any:
    """Validate one `[funnel.eK]` table into the shape its keys select."""
    V.check_keys(table, [k for e in FUNNEL_SHAPES for k in e.obj.KEYS], file=file, prefix=prefix)
    for entry in FUNNEL_SHAPES:
        if any(k in table for k in entry.obj.KEYS) or not table:
            return entry.obj.parse(table, n, file, prefix, defaults)
    return FunnelSpec.parse(table, n, file, prefix, defaults)

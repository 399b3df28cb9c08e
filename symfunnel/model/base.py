"""The model layer's common form: M(q), C(q, dq), G(q) as CasADi SX in q, dq and named parameters."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np


@dataclass
class RigidBodyModel:
    """A manipulator's rigid-body dynamics M(q) ddq + C(q, dq) dq + G(q) = torque, symbolically.

    `q`, `dq` are n x 1 SX symbols named after `coordinates` (velocities prefixed with ``d``);
    `p` holds the model's named parameters as SX symbols (possibly empty) with numeric `p_values`,
    so that symbolic checks can keep parameters as symbols and numeric work substitutes them once.
    """

    kind: str                      # "matrices", "planar", "dh", "urdf"
    coordinates: list[str]
    q: ca.SX
    dq: ca.SX
    M: ca.SX
    C: ca.SX
    G: ca.SX
    p: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    p_names: list[str] = field(default_factory=list)
    p_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    C_source: str = "christoffel"   # "given" (typed in by the user) or "christoffel" (derived from M)
    joint_types: list[str] = field(default_factory=list)   # "revolute", "prismatic", "continuous"
    joint_lower: np.ndarray | None = None   # sampling range of q for audits (None: scenario default)
    joint_upper: np.ndarray | None = None
    tree: Any = None                        # the rigid-body Tree of a planar, dh or urdf model (None: matrices)
    gravity: np.ndarray | None = None       # gravity acceleration in the base frame (None: matrices)

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.coordinates)

    def numeric(self, expr: ca.SX) -> ca.SX:
        """Replace the parameter symbols in `expr` by their numeric values."""
        if self.p.numel() == 0:
            return expr
        return ca.substitute(expr, self.p, ca.DM(self.p_values))

    def parameter_dict(self) -> dict[str, float]:
        """Parameter names to values."""
        return {k: float(v) for k, v in zip(self.p_names, self.p_values)}


def christoffel_C(M: ca.SX, q: ca.SX, dq: ca.SX) -> ca.SX:
    """C(q, dq) from M(q) by Christoffel symbols of the first kind.

    C_kj = sum_i 1/2 (dM_kj/dq_i + dM_ki/dq_j - dM_ij/dq_k) dq_i, the choice for which
    dM/dt - 2C is skew-symmetric (Property 1) by construction.
    """
    n = q.numel()
    dM = [ca.jacobian(M[:, j], q) for j in range(n)]   # dM[j][k, i] = dM_kj / dq_i
    C = ca.SX.zeros(n, n)
    for k in range(n):
        for j in range(n):
            s = 0
            for i in range(n):
                c_ijk = 0.5 * (dM[j][k, i] + dM[i][k, j] - dM[j][i, k])
                s = s + c_ijk * dq[i]
            C[k, j] = s
    return ca.simplify(C) if n <= 3 else C


def symbols(coordinates: list[str]) -> tuple[ca.SX, ca.SX]:
    """SX vectors q and dq named after the coordinates (velocity names are 'd' + coordinate)."""
    q = ca.vertcat(*[ca.SX.sym(c) for c in coordinates])
    dq = ca.vertcat(*[ca.SX.sym("d" + c) for c in coordinates])
    return q, dq

"""A tree's RigidBodyModel: M and G by the rigid-body algorithms (`dynamics`), C by Christoffel symbols of M
(`base.christoffel_C`), checked regular at sampled configurations, and merged by one CSE pass."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..core.errors import InputError
from .base import RigidBodyModel, christoffel_C, symbols
from .dynamics import mass_and_gravity
from .tree import Body, Tree, bodies_from_tree, fmt_values

_SINGULAR_RTOL = 1e-12


def check_regular(M: ca.SX, q: ca.SX, bodies: list[Body], lower: np.ndarray, upper: np.ndarray,
                  file: str, samples: int = 5) -> None:
    """M must be positive definite at a few random configurations; name the joint where it is not."""
    f = ca.Function("M", [q], [M])
    rng = np.random.default_rng(0)
    n = len(bodies)
    for s in range(samples):
        qv = np.clip(np.zeros(n), lower, upper) if s == 0 else lower + (upper - lower) * rng.random(n)
        Mv = np.array(f(qv))
        lam, vec = np.linalg.eigh(0.5 * (Mv + Mv.T))
        scale = max(float(np.max(np.abs(lam))), 1e-300)
        if lam[0] > _SINGULAR_RTOL * scale:
            continue
        diag = np.diag(Mv)
        k = int(np.argmin(diag)) if np.min(diag) <= _SINGULAR_RTOL * scale else int(np.argmax(np.abs(vec[:, 0])))
        what = ("its row and column of M are zero: it moves no mass or inertia about its axis"
                if diag[k] <= _SINGULAR_RTOL * scale else
                f"M is singular (smallest eigenvalue {lam[0]:.3g}) along this joint")
        raise InputError(f"joint '{bodies[k].joint.name}': {what} at q = {fmt_values(qv)}", file=file,
                         key=bodies[k].joint.where,
                         expected="links with mass/inertia such that M(q) is positive definite")


def sample_box(bodies: list[Body], lower: np.ndarray | None, upper: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Finite sampling bounds per joint: the limits where known, else [-pi, pi] (revolute) or [-1, 1] (prismatic)."""
    lo, hi = [], []
    for k, b in enumerate(bodies):
        d = 1.0 if b.joint.type == "prismatic" else math.pi
        l = lower[k] if lower is not None and np.isfinite(lower[k]) else -d
        u = upper[k] if upper is not None and np.isfinite(upper[k]) else d
        lo.append(l)
        hi.append(u)
    return np.array(lo), np.array(hi)


def build_model(kind: str, tree: Tree, *, coordinates: list[str] | None, gravity: np.ndarray,
                joint_range: list[tuple[float, float]] | None, cse: bool = True) -> RigidBodyModel:
    """The RigidBodyModel of a tree: M, C, G as SX with numbers embedded, joint types and limits."""
    bodies = bodies_from_tree(tree)
    n = len(bodies)
    coordinates = coordinates or [f"q{i + 1}" for i in range(n)]
    q, dq = symbols(coordinates)
    M, G = mass_and_gravity(bodies, q, gravity)
    if joint_range is not None:
        lower = np.array([r[0] for r in joint_range])
        upper = np.array([r[1] for r in joint_range])
    else:
        lower = np.array([np.nan if b.joint.lower is None else b.joint.lower for b in bodies])
        upper = np.array([np.nan if b.joint.upper is None else b.joint.upper for b in bodies])
    check_regular(M, q, bodies, *sample_box(bodies, lower, upper), tree.file)
    C = christoffel_C(M, q, dq)
    if cse:
        M, C, G = _cse(M, C, G)
    if np.all(np.isnan(lower)) and np.all(np.isnan(upper)):
        lower = upper = None
    return RigidBodyModel(kind=kind, coordinates=coordinates, q=q, dq=dq, M=M, C=C, G=G,
                          C_source="christoffel", joint_types=[b.joint.type for b in bodies],
                          joint_lower=lower, joint_upper=upper, tree=tree,
                          gravity=np.asarray(gravity, dtype=float).copy())


def _cse(M: ca.SX, C: ca.SX, G: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
    """Merge equal subexpressions of M, C and G in one pass (casadi.cse), keeping shapes."""
    if not hasattr(ca, "cse"):
        return M, C, G
    n = M.size1()
    v = ca.cse(ca.vertcat(ca.vec(M), ca.vec(C), G))
    return ca.reshape(v[: n * n], n, n), ca.reshape(v[n * n: 2 * n * n], n, n), v[2 * n * n:]

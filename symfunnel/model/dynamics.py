"""Rigid-body algorithms on a tree's bodies: M(q) by composite rigid bodies and G(q) by RNEA at rest, in body frames.

Expressions are built entry by entry from Python floats and SX scalars so that products with the constant zeros and
ones of joint axes and origins never reach the expression graph. C comes from M by the one Christoffel routine,
`base.christoffel_C`.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from .tree import SNAP, Body, skew

# ---------------------------------------------------------------- scalar algebra on floats and SX

def _num(x) -> bool:
    return isinstance(x, float)


def _mul(a, b):
    if _num(a):
        if a == 0.0:
            return 0.0
        if _num(b):
            return a * b
        if a == 1.0:
            return b
        if a == -1.0:
            return -b
    elif _num(b):
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
        if b == -1.0:
            return -a
    return a * b


def _add(a, b):
    if _num(a):
        if a == 0.0:
            return b
        if _num(b):
            return a + b
    elif _num(b) and b == 0.0:
        return a
    return a + b


def _sum(terms) -> Any:
    out = 0.0
    for t in terms:
        out = _add(out, t)
    return out


def _dot(u, v):
    return _sum(_mul(a, b) for a, b in zip(u, v))


def _matvec(A, v):
    return [_dot(A[i], v) for i in range(3)]


def _matTvec(A, v):
    return [_sum(_mul(A[k][i], v[k]) for k in range(3)) for i in range(3)]


def _cross(a, b):
    return [_add(_mul(a[1], b[2]), _neg(_mul(a[2], b[1]))),
            _add(_mul(a[2], b[0]), _neg(_mul(a[0], b[2]))),
            _add(_mul(a[0], b[1]), _neg(_mul(a[1], b[0])))]


def _neg(a):
    return -a if not _num(a) else (0.0 if a == 0.0 else -a)


def _vadd(u, v):
    return [_add(a, b) for a, b in zip(u, v)]


def _floats(a: np.ndarray) -> list:
    """A numpy vector or matrix as nested lists of Python floats."""
    return [float(x) for x in a] if a.ndim == 1 else [[float(x) for x in row] for row in a]


def _joint_rotation(axis: np.ndarray, c, s) -> list:
    """R = a a^T + (E - a a^T) cos + [a] sin, with the constant coefficients folded in."""
    aa = np.outer(axis, axis)
    K = skew(axis)
    R = []
    for i in range(3):
        row = []
        for j in range(3):
            const = float(aa[i, j]) if abs(aa[i, j]) > SNAP else 0.0
            kc = float((1.0 if i == j else 0.0) - aa[i, j])
            kc = kc if abs(kc) > SNAP else 0.0
            ks = float(K[i, j]) if abs(K[i, j]) > SNAP else 0.0
            row.append(_add(_add(const, _mul(kc, c)), _mul(ks, s)))
        R.append(row)
    return R


def _matmul(A, B):
    return [[_sum(_mul(A[i][k], B[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]


# ---------------------------------------------------------------- dynamics

def mass_and_gravity(bodies: list[Body], q: ca.SX, gravity: np.ndarray) -> tuple[ca.SX, ca.SX]:
    """M(q) by the composite-rigid-body algorithm and G(q) by RNEA at rest, in body frames to keep expressions small."""
    # In each joint's own frame M_ij does not depend on q_1..q_min(i,j) even structurally (a
    # world-frame Lagrangian gives 3x the operations for the 7-joint arm).
    n = len(bodies)
    Rs, ps = [], []
    for k, b in enumerate(bodies):
        qk = q[k]
        R0 = _floats(b.R0)
        p0 = _floats(b.p0)
        if b.joint.type == "prismatic":
            Rs.append(R0)
            ps.append(_vadd(p0, [_mul(float(x), qk) for x in b.R0 @ b.joint.axis]))
        else:
            Rj = _joint_rotation(b.joint.axis, ca.cos(qk), ca.sin(qk))
            Rs.append(_matmul(R0, Rj))
            ps.append(p0)

    # composite inertias (mass, first moment h, rotational inertia about the frame origin), leaves first
    mc = [b.mass for b in bodies]
    hc = [_floats(b.h) for b in bodies]
    Ic = [_floats(b.I) for b in bodies]
    for k in range(n - 1, -1, -1):
        par = bodies[k].parent
        if par < 0:
            continue
        m2, h2, I2 = _transform_inertia(mc[k], hc[k], Ic[k], Rs[k], ps[k])
        mc[par] = mc[par] + m2
        hc[par] = _vadd(hc[par], h2)
        Ic[par] = [[_add(Ic[par][i][j], I2[i][j]) for j in range(3)] for i in range(3)]

    M = ca.SX.zeros(n, n)
    for i, b in enumerate(bodies):
        a = _floats(b.joint.axis)
        if b.joint.type == "prismatic":
            nf = _cross(hc[i], a)                       # moment about the origin: h x v
            ff = [_mul(float(mc[i]), x) for x in a]
        else:
            nf = _matvec(Ic[i], a)                      # I w
            ff = _cross(a, hc[i])                       # w x h
        j = i
        while j >= 0:
            bj = bodies[j]
            aj = _floats(bj.joint.axis)
            mij = _dot(aj, ff) if bj.joint.type == "prismatic" else _dot(aj, nf)
            M[i, j] = mij
            if j != i:
                M[j, i] = mij
            if bj.parent < 0:
                break
            fr = _matvec(Rs[j], ff)
            nf = _vadd(_matvec(Rs[j], nf), _cross(ps[j], fr))
            ff = fr
            j = bj.parent

    g_frame: list[list] = []
    G = ca.SX.zeros(n, 1)
    g0 = _floats(np.asarray(gravity, dtype=float))
    for k, b in enumerate(bodies):
        gp = g0 if b.parent < 0 else g_frame[b.parent]
        gk = _matTvec(Rs[k], gp)
        g_frame.append(gk)
        a = _floats(b.joint.axis)
        if b.joint.type == "prismatic":
            G[k] = _neg(_mul(float(mc[k]), _dot(a, gk)))
        else:
            G[k] = _neg(_dot(a, _cross(hc[k], gk)))
    return M, G


def _transform_inertia(m: float, h, I, R, p):
    """Express (m, h, I about the child origin) in the parent frame, where the child frame is at (R, p)."""
    hr = _matvec(R, h)
    RI = [[_sum(_mul(R[i][k], I[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]
    Ir = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            Ir[i][j] = Ir[j][i] = _sum(_mul(RI[i][k], R[j][k]) for k in range(3))
    # I_P = R I R^T + 2 (h.p) E - p h^T - h p^T + m (|p|^2 E - p p^T)
    hp2 = _mul(2.0, _dot(hr, p))
    pp = _dot(p, p)
    out = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            e = Ir[i][j]
            e = _add(e, _neg(_add(_mul(p[i], hr[j]), _mul(hr[i], p[j]))))
            e = _add(e, _neg(_mul(m, _mul(p[i], p[j]))))
            if i == j:
                e = _add(e, _add(hp2, _mul(m, pp)))
            out[i][j] = out[j][i] = e
    return m, _vadd(hr, [_mul(m, x) for x in p]), out


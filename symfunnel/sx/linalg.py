"""Linear algebra written out in SX (no symbolic blow-up, no pivoting), for models and designs alike."""

from __future__ import annotations

import casadi as ca


def ldl_solve(M: ca.SX, b: ca.SX, order=None) -> ca.SX:
    """x = M^{-1} b for a symmetric positive definite SX matrix, by an LDL^T factorisation written out in SX;
    `order` (a permutation of the rows, e.g. reversed: the tip joint's pivot first, as the articulated-body
    factorisation of a serial arm) eliminates in that order -- the same x, other interval enclosures."""
    if order is not None:
        P = [int(i) for i in order]
        y = ldl_solve(M[P, P], b[P])
        x = [None] * len(P)
        for k, i in enumerate(P):
            x[i] = y[k]
        return ca.vertcat(*x)
    n = M.shape[0]
    L = [[None] * n for _ in range(n)]
    D = [None] * n
    for j in range(n):
        d = M[j, j]
        for k in range(j):
            d = d - L[j][k] * L[j][k] * D[k]
        D[j] = d
        for i in range(j + 1, n):
            s = M[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k] * D[k]
            L[i][j] = s / d
    y = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s
    z = [y[i] / D[i] for i in range(n)]
    x = [None] * n
    for i in reversed(range(n)):
        s = z[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = s
    return ca.vertcat(*x)


def solve2(M: ca.SX, b: ca.SX) -> ca.SX:
    """x = M^{-1} b for a 2 x 2 SX matrix by its adjugate, adj(M) b / det(M): every entry of M enters once per term,
    so an interval evaluation over a box is narrower than the LDL^T one (whose pivot and multiplier share M's
    entries); where det's enclosure contains 0 the enclosure is unbounded, never wrong."""
    det = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    return ca.vertcat(M[1, 1] * b[0] - M[0, 1] * b[1], M[0, 0] * b[1] - M[1, 0] * b[0]) / det




def preconditioned_solve(M: ca.SX, b: ca.SX, C: ca.SX) -> ca.SX:
    """x = M^{-1} b as (C M)^{-1} (C b), by Gaussian elimination without pivoting: the same x for every invertible
    C; with C ~ M^{-1} at a point of an interval box (a midpoint preconditioner) C M is near I, so its interval
    elimination stays finite on boxes where the hull of M is too wide for LDL^T (the Hansen-Bliek / Gauss-Seidel
    idea written out in SX)."""
    n = M.shape[0]
    CM, Cb = ca.mtimes(C, M), ca.mtimes(C, b)
    A = [[CM[i, j] for j in range(n)] for i in range(n)]
    r = [Cb[i] for i in range(n)]
    for k in range(n):
        for i in range(k + 1, n):
            f = A[i][k] / A[k][k]
            for j in range(k + 1, n):
                A[i][j] = A[i][j] - f * A[k][j]
            r[i] = r[i] - f * r[k]
    x = [None] * n
    for i in reversed(range(n)):
        s = r[i]
        for j in range(i + 1, n):
            s = s - A[i][j] * x[j]
        x[i] = s / A[i][i]
    return ca.vertcat(*x)

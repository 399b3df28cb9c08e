"""Load-time checks of a typed-in (`type = "matrices"`) inertia matrix: symmetric, and positive definite at the
initial state and on samples of the joint range, as the planar, DH and URDF builders guarantee by construction."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..core.errors import InputError

#: Configurations sampled (besides the initial state) for symmetry and positive definiteness.
SAMPLES = 64
#: Relative size of M - M^T (against max |M|) that counts as an asymmetry rather than round-off.
SYMMETRY_RTOL = 1e-10
SYMPY_SECONDS = 5.0


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.ravel(v)) + "]"


def check_inertia_matrix(model, q0, lower, upper, *, file: str, key: str = "model.matrices.M",
                         seed: int = 0) -> None:
    """InputError naming `key` unless M(q) is symmetric and positive definite at q0 and on SAMPLES configurations.

    Symmetry is decided exactly where it can be: entries that CasADi sees as the same expression pass at once;
    others are compared at the samples (a difference above round-off is a counterexample) and then handed to
    sympy for a proof (time-limited; when sympy is undecided the sampled agreement is accepted).
    """
    n = model.n
    M = model.numeric(model.M)
    f = ca.Function("M", [model.q], [M])
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    qs = [np.asarray(q0, float)] + [lo + (hi - lo) * rng.random(n) for _ in range(SAMPLES)]
    values = [np.array(f(q)) for q in qs]
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if not ca.is_equal(M[i, j], M[j, i], 64)]
    for q, Mv in zip(qs, values):
        scale = max(float(np.max(np.abs(Mv))), 1e-300)
        for i, j in pairs:
            if abs(Mv[i, j] - Mv[j, i]) > SYMMETRY_RTOL * scale:
                raise InputError(f"is not symmetric: M[{i}][{j}] = {Mv[i, j]:.6g} but M[{j}][{i}] = {Mv[j, i]:.6g} "
                                 f"at q = {_fmt(q)}", file=file, key=key,
                                 expected="a symmetric inertia matrix (M[i][j] and M[j][i] the same expression)")
    if pairs and _sympy_differs(M, model.q, pairs):
        raise InputError("is not symmetric: sympy finds M - M^T nonzero (though below round-off at the samples)",
                         file=file, key=key, expected="a symmetric inertia matrix")
    for k, (q, Mv) in enumerate(zip(qs, values)):
        lam = np.linalg.eigvalsh(0.5 * (Mv + Mv.T))
        if not lam[0] > 1e-12 * max(abs(lam[-1]), 1e-300):
            where = "the initial state" if k == 0 else "a sampled configuration"
            raise InputError(f"is not positive definite at {where} q = {_fmt(q)} (eigenvalues {_fmt(lam)})",
                             file=file, key=key,
                             expected="an inertia matrix positive definite over the joint range "
                                      "(narrow it with audit.joint_range if the model holds only there)")


def _sympy_differs(M, q, pairs) -> bool:
    """True only when sympy simplifies some M[i][j] - M[j][i] to a nonzero expression free of doubt (a number)."""
    import sympy

    from ..sx.tosympy import sx_to_sympy
    from ..sx.proof import _Timeout, simplify, time_limit
    diffs = ca.vertcat(*[M[i, j] - M[j, i] for i, j in pairs])
    if ca.Function("d", [q], [diffs]).n_instructions() > 2000:
        return False
    try:
        with time_limit(SYMPY_SECONDS):
            m = sx_to_sympy(diffs, [q])
            simp = [simplify(sympy.expand_trig(e)) for e in m]
    except (_Timeout, RecursionError, MemoryError, NotImplementedError):
        return False
    return any(e.is_number and e != 0 for e in simp)

"""The projection of the adaptive law onto a ball (`[adaptation] projection = R`): W_hat kept in ||W_hat||_F <= R
up to a thin boundary layer, the standard robust-adaptive modification (Lavretsky & Wise's continuous projection
operator, the Pomet-Praly form with a boundary layer).

With Y the unprojected law (Gamma (Phi (mu2 z2)^T - sigma W_hat)), a = <W_hat, Y>_F, b = ||W_hat||_F^2 and the
convex function f(b) = (b - R^2) / (((1 + eps)^2 - 1) R^2) (0 on the ball of radius R, 1 on radius R (1 + eps)):

    W_hat' = Y - c W_hat,   c = max(a, 0) k(b),   k(b) = max(f(b), 0) / max(b, R^2).

Inside the ball (f <= 0) or where Y points inwards (a <= 0) the law is Y unchanged; in the layer the outward radial
part of Y is removed in proportion f. So d/dt ||W_hat||^2 / 2 = a - max(a, 0) k(b) b, which is a <= 0 for a <= 0 and
a (1 - f(b)) <= 0 for b >= (R (1 + eps))^2: the ball of radius R (1 + eps) is invariant. Why this form: it is
continuous and locally Lipschitz (a max of smooth terms, never a switch), so the ODE solvers integrate it without a
discontinuity; and for ||W*|| <= R it keeps the Lyapunov argument, tr(W~^T c W_hat) = c (<W*, W_hat> - b) <= 0.

The deployed step (`emit.step`) integrates it by its exponential-Euler step and then scales W_hat radially back onto
the ball of radius R (1 + eps) when the step left it (`radial_clip`): a discrete step can cross the layer.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

#: the boundary layer's relative width eps when [adaptation] projection_layer is not given
DEFAULT_LAYER = 0.05


def outer_radius(R: float, eps: float) -> float:
    """The radius R (1 + eps) of the ball the projected law keeps W_hat in."""
    return float(R) * (1.0 + float(eps))


def project(W: ca.SX, Y: ca.SX, R: float, eps: float) -> dict[str, ca.SX]:
    """The projected law and its parts as SX: {"w_dot": Y - c W, "raw": Y, "a", "b", "k", "c"} (module doc)."""
    R2 = float(R) ** 2
    layer = ((1.0 + float(eps)) ** 2 - 1.0) * R2
    a = ca.dot(ca.vec(W), ca.vec(Y))
    b = ca.sumsqr(W)
    k = ca.fmax((b - R2) / layer, 0) / ca.fmax(b, R2)
    c = ca.fmax(a, 0) * k
    return {"w_dot": Y - c * W, "raw": Y, "a": a, "b": b, "k": k, "c": c}


def radial_clip(W: ca.SX, radius: float) -> ca.SX:
    """W scaled radially onto the ball ||W||_F <= radius when it lies outside (identity inside): the deployed
    step's projection after its exponential-Euler update."""
    nrm = ca.sqrt(ca.sumsqr(W))
    return W * (float(radius) / ca.fmax(nrm, float(radius)))


__all__ = ["DEFAULT_LAYER", "outer_radius", "project", "radial_clip"]

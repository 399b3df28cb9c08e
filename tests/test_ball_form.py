"""BallForm: enclosures over the ball ||W||_F <= r (certify.sampled's W_hat ball) contain the function's values at
points of the ball drawn here, and are narrower than the bounding box's where W enters as W^T phi."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest


def _function(N=51):
    """f(x, w) = (tanh(x) + 2) w^T phi(x) + max(x, 0) w_0^2 + x^2, phi_i(x) = sin(i x + 1): affine in w but for the
    last term, with a kink in x, and a dependence of phi on x."""
    x, w = ca.SX.sym("x"), ca.SX.sym("w_hat", N)
    phi = ca.vertcat(*[ca.sin(i * x + 1) for i in range(N)])
    f = (ca.tanh(x) + 2) * ca.dot(w, phi) + ca.fmax(x, 0) * w[0] ** 2 + x ** 2
    return ca.Function("f", [x, w], [ca.vertcat(f, ca.dot(w, phi))], ["x", "w_hat"], ["f"])


def _ball_points(rng, N, r, k):
    """k points of the ball of radius r in R^N: directions uniform on the sphere, radii r u^(1/N); plus the poles."""
    d = rng.normal(size=(k, N))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * (r * rng.random(k) ** (1.0 / N))[:, None]
    return np.concatenate([pts, r * d[:8]])


@pytest.mark.parametrize("radius_scale", [1.0, 0.5])
def test_ball_enclosure_contains_values_over_the_ball_and_is_narrower(radius_scale):
    """Values at points of the ball lie in the enclosure; stated with half the radius (a wrong ball) some do not.
    The enclosure of w^T phi is at least 3x narrower than the box's (sqrt(51) ~ 7 in the limit)."""
    from symfunnel.certificates.ball_form import BallForm
    from symfunnel.sx.batch import BatchCenteredForm
    N, r = 51, 2.0
    F = _function(N)
    form = BatchCenteredForm(F, ["x"])
    ball = BallForm(form)
    rng = np.random.default_rng(7)
    K = 40
    xc = rng.uniform(-2, 2, K)
    xw = rng.uniform(0.0, 0.05, K)
    LO = np.concatenate([(xc - xw)[:, None], np.full((K, N), -r)], 1)
    HI = np.concatenate([(xc + xw)[:, None], np.full((K, N), r)], 1)
    L, H, _ = ball.eval_batch(LO, HI, radius_scale * r)
    BL, BH, _ = form.eval_batch(LO, HI)
    assert np.all(L >= BL) and np.all(H <= BH)
    outside = 0
    for k in range(K):
        W = _ball_points(rng, N, r, 200)
        xs = LO[k, 0] + rng.random(W.shape[0]) * (HI[k, 0] - LO[k, 0])
        # and the extremes of w^T phi over the ball (Cauchy-Schwarz): w = +-r phi(x) / ||phi(x)||
        xe = LO[k, 0] + rng.random(10) * (HI[k, 0] - LO[k, 0])
        ph = np.sin(np.arange(N)[None, :] * xe[:, None] + 1)
        We = r * ph / np.linalg.norm(ph, axis=1, keepdims=True)
        W, xs = np.concatenate([W, We, -We]), np.concatenate([xs, xe, xe])
        vals = np.hstack([np.asarray(F(x_, w_), float) for x_, w_ in zip(xs, W)])
        outside += int(np.sum(vals < L[k][:, None] - 1e-12) + np.sum(vals > H[k][:, None] + 1e-12))
    if radius_scale == 1.0:
        assert outside == 0
        ratio = (BH[:, 1] - BL[:, 1]) / (H[:, 1] - L[:, 1])
        assert np.median(ratio) >= 3.0
    else:
        assert outside > 0

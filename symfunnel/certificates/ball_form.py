"""Enclosures over the adaptive weights' ball ||W_hat||_F <= r instead of its bounding box, for `certify.sampled`.

An evaluator over boxes treats W_hat's entries as independent intervals [-r, r]: a term W_hat^T phi is then enclosed
with r sum |phi_i|, up to sqrt(N) times r ||phi||_2, its range over the ball (N = 51 entries per joint on the paper's
ESN: ~7x). By the mean-value theorem along the segment from the ball's centre W_c to W (inside the ball, so inside
its box), f(x, W) = f(x, W_c) + G (W - W_c) with G = df/dW somewhere on the segment, so on a box X of the other inputs

    f_i(X, ball) in f_i(X, W_c) +- r sup ||G_i(X, box)||_2,

G enclosed by interval AD over X and the ball's box (fmax/fmin's kinks in Clarke's form, `BatchCenteredForm`'s
Jacobian); rows where a discontinuous operation may switch keep the box's enclosure. The result is intersected with
the box's own enclosure, so it is never wider.
"""

from __future__ import annotations

import numpy as np

from ..sx.batch import BatchCenteredForm
from ..sx.batch_rules import _dn, _up


class BallForm:
    """`form`'s enclosure (an evaluator with `eval_batch`) tightened over the ball ||W||_F <= r around the centre of
    the input `name`'s box."""

    def __init__(self, form, name: str = "w_hat"):
        F = getattr(form, "natural", form)
        i = F.in_names.index(name)
        self.form, self.lo, self.hi = form, int(F.in_off[i]), int(F.in_off[i + 1])
        self.n_out = F.n_out_nz
        self.jac = BatchCenteredForm(F.function, [name]).jac

    def eval_batch(self, LO, HI, r: float):
        """(L, H, switched) over K boxes whose `name` columns hold the ball's bounding box."""
        L, H, sw = self.form.eval_batch(LO, HI)
        K, nw = LO.shape[0], self.hi - self.lo
        c = 0.5 * LO[:, self.lo:self.hi] + 0.5 * HI[:, self.lo:self.hi]
        CL, CH = LO.copy(), HI.copy()
        CL[:, self.lo:self.hi] = c
        CH[:, self.lo:self.hi] = c
        L0, H0, sw0 = self.form.eval_batch(CL, CH)
        GL, GH, swg = self.jac.eval_batch(LO, HI)
        A = np.maximum(np.abs(GL), np.abs(GH)).reshape(K, nw, self.n_out)      # column-major (outputs fastest)
        with np.errstate(invalid="ignore", over="ignore"):
            sq = _up(np.sum(_up(A * A), axis=1) * (1.0 + 2.0 * nw * 2.0 ** -52))
            rad = _up(float(r) * _up(np.sqrt(sq)))
            BL, BH = _dn(L0 - rad), _up(H0 + rad)
        ok = ~(np.asarray(sw, bool) | np.asarray(sw0, bool) | np.asarray(swg, bool))[:, None] & \
            np.isfinite(BL) & np.isfinite(BH)
        return np.where(ok, np.maximum(L, BL), L), np.where(ok, np.minimum(H, BH), H), sw

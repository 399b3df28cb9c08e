"""Error transformations z = T(e, F), one registered class each.

Both built-ins are functions of the normalised error s = e/F, z = h(s) with h odd, increasing and h'(0) = 1, so along
any flow  dz/dt = mu (de/dt - (dF/dt / F) e)  with  mu = h'(s)/F = dz/de  -- the identity the backstepping design is
built on. Each transformation also gives r = e/z (finite and smooth, also at e = 0), which the design uses to cancel
the coupling term of its Lyapunov derivative, and the inverse |e|/F = h^{-1}(|z|) that turns a bound on z into a
funnel margin.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..core.registry import Registry

TRANSFORMS = Registry("error transformation", "design.transform")


@TRANSFORMS.register("funnel", "z = e/(F - |e|), the funnel-control transformation of the paper")
class FunnelTransform:
    """z = e zeta with zeta = 1/(F - |e|); mu = F zeta^2; r = e/z = F - |e|."""

    name = "funnel"
    extra_signals = {"zeta": "1/(F - |e|)"}
    #: degree of each output in (e, F) jointly: build(c e, c F)[k] = c^deg build(e, F)[k] for c > 0 (a function of
    #: s = e/F times a power of F); `symfunnel.certificates` rewrites the design over s with it once sympy proves it
    HOMOGENEITY = {"z": 0, "mu": -1, "r": 1, "zeta": -1}

    def build(self, e: ca.SX, F: ca.SX) -> dict[str, ca.SX]:
        """z, mu = dz/de, r = e/z and the transformation's own named signals (zeta)."""
        zeta = 1 / (F - ca.fabs(e))
        return {"z": e * zeta, "mu": F * zeta ** 2, "r": 1 / zeta, "zeta": zeta}

    @staticmethod
    def usage(z_bound: np.ndarray) -> np.ndarray:
        """|e|/F implied by |z| <= z_bound (the inverse of s -> s/(1 - s))."""
        z = np.asarray(z_bound, dtype=float)
        return z / (1 + z)


@TRANSFORMS.register("log", "z = 1/2 ln((F + e)/(F - e)), the prescribed-performance transformation")
class LogTransform:
    """z = atanh(e/F); mu = F/(F^2 - e^2); r = e/z = F s/atanh(s), by its series near s = 0."""

    name = "log"
    extra_signals: dict[str, str] = {}
    #: see FunnelTransform.HOMOGENEITY
    HOMOGENEITY = {"z": 0, "mu": -1, "r": 1}
    #: below this |s| the ratio s/atanh(s) is its Taylor polynomial (error < 1e-16 there)
    SERIES_BELOW = 1e-3
    #: |s| where r's formula switches (series below): interval evaluation cannot take s/atanh(s) on a box around 0,
    #: so `symfunnel.certificates` cuts the normalised errors there before branching
    BREAKPOINTS = (SERIES_BELOW,)

    def build(self, e: ca.SX, F: ca.SX) -> dict[str, ca.SX]:
        """z, mu = dz/de and r = e/z (smooth through e = 0)."""
        s = e / F
        z = 0.5 * ca.log((F + e) / (F - e))
        s2 = s * s
        series = 1 - s2 / 3 - 4 * s2 * s2 / 45
        ratio = ca.if_else(ca.fabs(s) < self.SERIES_BELOW, series, s / ca.atanh(s))
        return {"z": z, "mu": F / (F * F - e * e), "r": F * ratio}

    @staticmethod
    def usage(z_bound: np.ndarray) -> np.ndarray:
        """|e|/F implied by |z| <= z_bound (tanh)."""
        return np.tanh(np.asarray(z_bound, dtype=float))

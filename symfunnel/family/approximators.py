"""Approximators of the unknown dynamics, one registered class each: the regressor Phi the adaptive weights multiply,
the approximator's own states (if any) with their dynamics, and the box their states stay in (for sampling).

The design asks an approximator for its layout instead of knowing `x_esn`: adding one is adding a class here.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from ..errors import InputError
from ..registry import Registry

APPROXIMATORS = Registry("approximator", "approximator.type")


@APPROXIMATORS.register("esn", "echo state network (continuous-time reservoir, settings in `[esn]`), the paper's")
class ESNApproximator:
    """The paper's echo state network: a seeded reservoir x_esn driven by design signals; Phi = [x_esn; 1]."""

    name = "esn"
    #: design signals the reservoir may be driven by (validated by the scenario)
    INPUTS = ("q", "dq", "e1", "e2", "qd", "dqd", "ddqd", "alpha2", "alpha2_dot")

    def __init__(self, scenario):
        from ..esn import ESN, ESNConfig
        es = scenario.esn
        self.spec = es
        try:
            self.esn = ESN(ESNConfig(size=es.size, leak=es.leak, time_constant=es.time_constant,
                                     spectral_radius=es.spectral_radius, input_scaling=es.input_scaling,
                                     sparsity=es.sparsity, seed=es.seed, bias=es.bias),
                           n_inputs=scenario.n * len(es.inputs))
        except ValueError as exc:
            key = getattr(exc, "key", "")
            raise InputError(getattr(exc, "reason", str(exc)), file=scenario.file, key="esn." + key if key else "esn",
                             expected=getattr(exc, "expected", None)) from None

    @property
    def n_regressor(self) -> int:
        """Length of Phi."""
        return self.esn.n_regressor

    def states(self) -> list[tuple[str, tuple[int, int]]]:
        """The approximator's own controller states: the reservoir."""
        return [("x_esn", (self.esn.size, 1))]

    def regressor(self, sym: dict[str, ca.SX]) -> ca.SX:
        """Phi in the approximator's states."""
        return self.esn.regressor(sym["x_esn"])

    def dynamics(self, sym: dict[str, ca.SX], signals: dict[str, ca.SX]) -> dict[str, ca.SX]:
        """x_esn_dot, the reservoir driven by the normalised input signals."""
        feeds = [(signals[k] if k in signals else sym[k]) / self.spec.scales.get(k, 1.0) for k in self.spec.inputs]
        return {"x_esn": self.esn.xdot(sym["x_esn"], ca.vertcat(*feeds))}

    def initial(self, scenario) -> dict[str, np.ndarray]:
        """Initial reservoir state."""
        return {"x_esn": np.asarray(scenario.x_esn0, dtype=float)}

    def box(self) -> dict[str, float]:
        """Half-widths of the invariant box of each state (tanh reservoir: |x| <= 1/leak)."""
        return {"x_esn": 1.0 / self.spec.leak}

    def summary(self) -> dict[str, Any]:
        """Facts for the report."""
        return self.esn.summary()


@APPROXIMATORS.register("none", "no approximator: the model-based controller (the unknown term is left to robustness)")
class NoApproximator:
    """No regressor and no adaptive weights: tau is the model's inverse dynamics of v."""

    name = "none"

    def __init__(self, scenario):
        pass

    n_regressor = 0

    def states(self) -> list[tuple[str, tuple[int, int]]]:
        """No states."""
        return []

    def regressor(self, sym: dict[str, ca.SX]) -> ca.SX:
        """An empty regressor."""
        return ca.SX(0, 1)

    def dynamics(self, sym, signals) -> dict[str, ca.SX]:
        """No dynamics."""
        return {}

    def initial(self, scenario) -> dict[str, np.ndarray]:
        """No states."""
        return {}

    def box(self) -> dict[str, float]:
        """No states."""
        return {}

    def summary(self) -> dict[str, Any]:
        """Facts for the report."""
        return {"type": "none"}

"""Approximators of the unknown dynamics, one registered class each: the regressor Phi the adaptive weights multiply,
the approximator's own states (if any) with their dynamics, and the box their states stay in (for sampling).

The design asks an approximator for its layout instead of knowing `x_esn`: adding one is adding a class here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from ..core import validate as V
from ..core.errors import InputError
from ..core.registry import Registry

APPROXIMATORS = Registry("approximator", "approximator.type")


@APPROXIMATORS.register("esn", "echo state network (continuous-time reservoir, settings in `[esn]`), the paper's")
class ESNApproximator:
    """The paper's echo state network: a seeded reservoir x_esn driven by design signals; Phi = [x_esn; 1]."""

    name = "esn"
    #: the scenario section holding this approximator's settings
    SETTINGS = "esn"
    #: design signals the reservoir may be driven by (validated by the scenario)
    INPUTS = ("q", "dq", "e1", "e2", "qd", "dqd", "ddqd", "alpha2", "alpha2_dot")

    def __init__(self, scenario):
        from .esn import ESN, ESNConfig
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

    def inputs(self, sym: dict[str, ca.SX], signals: dict[str, ca.SX]) -> ca.SX:
        """u, the normalised input signals that drive the reservoir."""
        return ca.vertcat(*[(signals[k] if k in signals else sym[k]) / self.spec.scales.get(k, 1.0)
                            for k in self.spec.inputs])

    def dynamics(self, sym: dict[str, ca.SX], signals: dict[str, ca.SX]) -> dict[str, ca.SX]:
        """x_esn_dot, the reservoir driven by the normalised input signals."""
        return {"x_esn": self.esn.xdot(sym["x_esn"], self.inputs(sym, signals))}

    def initial(self, scenario) -> dict[str, np.ndarray]:
        """Initial reservoir state."""
        return {"x_esn": np.asarray(scenario.x_esn0, dtype=float)}

    def box(self) -> dict[str, float]:
        """Half-widths of the invariant box of each state (tanh reservoir: |x| <= 1/leak)."""
        return {"x_esn": 1.0 / self.spec.leak}

    def summary(self) -> dict[str, Any]:
        """Facts for the report."""
        return self.esn.summary()


class _Stateless:
    """An approximator without states of its own: Phi is a function of the design's base inputs only."""

    def states(self) -> list[tuple[str, tuple[int, int]]]:
        """No states."""
        return []

    def dynamics(self, sym, signals) -> dict[str, ca.SX]:
        """No dynamics."""
        return {}

    def initial(self, scenario) -> dict[str, np.ndarray]:
        """No states."""
        return {}

    def box(self) -> dict[str, float]:
        """No states."""
        return {}


@APPROXIMATORS.register("none", "no approximator: the model-based controller (the unknown term is left to robustness)")
class NoApproximator(_Stateless):
    """No regressor and no adaptive weights: tau is the model's inverse dynamics of v."""

    name = "none"
    SETTINGS = None

    def __init__(self, scenario):
        pass

    n_regressor = 0

    def regressor(self, sym: dict[str, ca.SX]) -> ca.SX:
        """An empty regressor."""
        return ca.SX(0, 1)


    def summary(self) -> dict[str, Any]:
        """Facts for the report."""
        return {"type": "none"}


@dataclass
class RBFSpec:
    """`[rbf]` settings: which base inputs feed the network, where its centres sit and how wide they are."""

    inputs: list[str] = field(default_factory=lambda: ["q", "dq"])
    centres: str = "sobol"
    size: int = 32                       # centres, for "sobol"
    per_dim: int = 3                     # centres per input dimension, for "grid" (per_dim ** dims in all)
    width_factor: float = 1.0            # Gaussian width = width_factor * spacing of the centres
    bias: bool = True
    seed: int = 0
    box: dict[str, tuple[list[float], list[float]]] = field(default_factory=dict)   # input -> (lower, upper)


#: base inputs an RBF network may read (the regressor is a function of the design's own inputs, no states)
RBF_INPUTS = ("q", "dq", "qd", "dqd", "ddqd")
#: most centres a network may have (the weights are n_centres x n controller states)
RBF_MAX_CENTRES = 4096


def parse_rbf(table: Any, n: int, *, file: str, joint_lower, joint_upper, velocity_range) -> RBFSpec:
    """Validate `[rbf]`; the default box is the audit's joint range for q/qd and +-velocity_range for the rest."""
    p = "rbf"
    V.check_keys(table, ["inputs", "centres", "size", "per_dim", "width_factor", "bias", "seed", "box"],
                 file=file, prefix=p)
    d = RBFSpec()
    inputs = V.get_names(table, "inputs", d.inputs, file=file, prefix=p, choices=RBF_INPUTS)
    if not inputs or len(set(inputs)) != len(inputs):
        raise InputError(f"is {inputs!r}", file=file, key="rbf.inputs", expected="distinct input names, at least one")
    centres = V.get_str(table, "centres", d.centres, file=file, prefix=p, choices=["sobol", "grid"])
    size = V.get_int(table, "size", d.size, file=file, prefix=p, minimum=1, maximum=RBF_MAX_CENTRES)
    per_dim = V.get_int(table, "per_dim", d.per_dim, file=file, prefix=p, minimum=2, maximum=64)
    dims = n * len(inputs)
    if centres == "grid" and per_dim ** dims > RBF_MAX_CENTRES:
        raise InputError(f"gives {per_dim}^{dims} = {per_dim ** dims} centres", file=file, key="rbf.per_dim",
                         expected=f"at most {RBF_MAX_CENTRES} centres (fewer points per dimension, fewer inputs, "
                                  "or centres = \"sobol\")")
    box_raw = table.get("box", {})
    V.check_keys(box_raw, list(inputs), file=file, prefix="rbf.box")
    box = {}
    for k in inputs:
        if k in box_raw:
            box[k] = _pairs(box_raw[k], n, file, f"rbf.box.{k}")
        elif k in ("q", "qd"):
            box[k] = (list(joint_lower), list(joint_upper))
        else:
            box[k] = ([-float(v) for v in velocity_range], [float(v) for v in velocity_range])
    return RBFSpec(inputs=list(inputs), centres=centres, size=size, per_dim=per_dim,
                   width_factor=V.get_float(table, "width_factor", d.width_factor, file=file, prefix=p, minimum=0,
                                            strict_min=True),
                   bias=V.get_bool(table, "bias", d.bias, file=file, prefix=p),
                   seed=V.get_int(table, "seed", d.seed, file=file, prefix=p, minimum=0, maximum=2**32 - 1),
                   box=box)


def _pairs(value: Any, n: int, file: str, key: str) -> tuple[list[float], list[float]]:
    """[lo, hi] for every joint, or n such pairs, with lo < hi."""
    if isinstance(value, list) and len(value) == 2 and not isinstance(value[0], list):
        value = [value] * n
    if not isinstance(value, list) or len(value) != n:
        raise InputError(f"is {V.type_name(value)}", file=file, key=key, expected=f"[lower, upper] or {n} such pairs")
    lo, hi = [], []
    for i, v in enumerate(value):
        k = f"{key}[{i}]"
        if not (isinstance(v, list) and len(v) == 2):
            raise InputError(f"is {V.type_name(v)}", file=file, key=k, expected="a pair [lower, upper]")
        a, b = V.as_float(v[0], file=file, key=k + "[0]"), V.as_float(v[1], file=file, key=k + "[1]")
        if not a < b:
            raise InputError(f"is [{a:g}, {b:g}]", file=file, key=k, expected="lower < upper")
        lo.append(a)
        hi.append(b)
    return lo, hi


def rbf_centres(spec: RBFSpec, dims: int) -> tuple[np.ndarray, float]:
    """(centres as (N, dims) in the unit box, their spacing there): a full grid, or scrambled Sobol points."""
    if spec.centres == "grid":
        axis = np.linspace(0.0, 1.0, spec.per_dim)
        mesh = np.meshgrid(*[axis] * dims, indexing="ij")
        return np.stack([m.ravel() for m in mesh], axis=1), 1.0 / (spec.per_dim - 1)
    from ..core.sobol import sobol               # scipy's points without importing scipy.stats
    pts = sobol(dims, spec.size, spec.seed)
    return pts, float(spec.size) ** (-1.0 / dims)


@APPROXIMATORS.register("rbf", "Gaussian radial basis functions of base inputs (default q, dq), centres on a grid or "
                               "Sobol points over the input box; settings in `[rbf]`")
class RBFApproximator(_Stateless):
    """Phi = [exp(-||u - c_j||^2 / w^2)]_j (+ a bias 1), u the inputs scaled to the unit box, w = width_factor times
    the spacing of the centres; no states of its own, so Phi is a function of the design's base inputs only."""

    name = "rbf"
    SETTINGS = "rbf"

    def __init__(self, scenario):
        self.spec: RBFSpec = scenario.rbf
        n = scenario.n
        self.dims = n * len(self.spec.inputs)
        self.lower = np.concatenate([self.spec.box[k][0] for k in self.spec.inputs])
        self.upper = np.concatenate([self.spec.box[k][1] for k in self.spec.inputs])
        self.centres, self.spacing = rbf_centres(self.spec, self.dims)
        self.width = self.spec.width_factor * self.spacing

    @property
    def n_regressor(self) -> int:
        """Length of Phi: one per centre, plus the bias."""
        return self.centres.shape[0] + (1 if self.spec.bias else 0)

    def regressor(self, sym: dict[str, ca.SX]) -> ca.SX:
        """Phi in the base inputs."""
        x = ca.vertcat(*[sym[k] for k in self.spec.inputs])
        u = (x - ca.DM(self.lower)) / ca.DM(self.upper - self.lower)
        g = [ca.exp(-ca.sumsqr(u - ca.DM(c)) / self.width ** 2) for c in self.centres]
        return ca.vertcat(*g, *([ca.SX(1)] if self.spec.bias else []))

    def numeric(self, x: np.ndarray) -> np.ndarray:
        """Phi at input vectors x (dims, K) with numpy: the independent implementation tests compare against."""
        u = (x - self.lower[:, None]) / (self.upper - self.lower)[:, None]
        d2 = ((u[None, :, :] - self.centres[:, :, None]) ** 2).sum(axis=1)
        g = np.exp(-d2 / self.width ** 2)
        return np.vstack([g, np.ones((1, x.shape[1]))]) if self.spec.bias else g


    def summary(self) -> dict[str, Any]:
        """Facts for the report."""
        return {"type": "rbf", "inputs": list(self.spec.inputs), "centres": self.spec.centres,
                "n_centres": int(self.centres.shape[0]), "dims": self.dims, "width_unit_box": self.width,
                "bias": self.spec.bias, "box": {k: [list(lo), list(hi)] for k, (lo, hi) in self.spec.box.items()}}

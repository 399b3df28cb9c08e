"""What a validated scenario is: one dataclass per section and the `Scenario` that holds them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ..expr import Expression
from ..family.approximators import RBFSpec
from ..family.funnels import FunnelSpec
from ..plant.nonlinearities import DeadZoneSpec

if TYPE_CHECKING:
    from ..model.base import RigidBodyModel
    from .implementation import ImplementationSpec
    from .tune import TuneSpec
    from .uncertainty import Campaign


@dataclass
class Claim:
    """An equation or parameter set as printed in the source, audited against the exact derivation."""

    name: str
    source: str
    description: str
    kind: str                            # "signal", "funnel" or "decay"
    signal: str | None = None
    expression: Expression | None = None
    funnel: str | None = None
    spec: FunnelSpec | None = None
    rho: Expression | None = None        # decay claims: V_dot <= -rho V + delta with these printed constants
    delta: Expression | None = None
    lhs: Expression | None = None        # inequality claims: lhs <= rhs at every state (counterexamples searched)
    rhs: Expression | None = None
    parameters: dict = field(default_factory=dict)   # numbers the printed expression names (e.g. d, a slope)
    expect: str = "pass"                 # the outcome the scenario declares: "pass" (holds) or "fail" (known wrong)


@dataclass
class Expectation:
    """A declared outcome of a check other than a claim (`[[expect]]`), with the reason the report shows."""

    check: str
    status: str
    reason: str


@dataclass
class MujocoSpec:
    """`[plant.mujoco]`: the MuJoCo engine's settings and its engine-only mismatch (the controller's model stays nominal)."""

    mass_scale: list[float] | None = None     # per joint: the body each joint moves (fixed links included); None = 1
    damping: list[float] | None = None        # per joint, added to the URDF's <dynamics damping>
    armature: list[float] | None = None       # per joint (rotor inertia on the joint's diagonal of M)
    urdf_dynamics: bool = True                # keep the URDF's <dynamics damping friction> in the engine
    substeps: int | None = None               # MuJoCo steps per sample period (None: timestep or the stability rule)
    timestep: float | None = None             # MuJoCo's step in s; must divide the sample period
    integrator: str = "implicitfast"          # MuJoCo's integrator: "implicitfast" or "RK4" (deployed.engine)
    mjcf: str | None = None                   # the user's own MJCF of the robot (absolute path); None: the model's


@dataclass
class PlantSpec:
    """What the true plant has and the controller does not know."""

    viscous: list[float]
    coulomb: list[float]
    disturbance: list[Expression]
    dead_zone: DeadZoneSpec | None
    mass_scale: float
    parameters: dict[str, float]
    coriolis: str = "christoffel"        # the plant's C: "christoffel" (physical, from M) or "model" (as given)
    disturbance_scale: list[float] | None = None   # per joint factor on the disturbance; None = 1
    engine: str = "symfunnel"            # which physics plays the robot in the sampled loop (plant.engines.ENGINES)
    mujoco: MujocoSpec = field(default_factory=MujocoSpec)


@dataclass
class ESNSpec:
    """Echo state network settings (eq. 8)."""

    size: int = 50
    leak: float = 1.0
    time_constant: float = 0.05
    spectral_radius: float = 0.9
    input_scaling: float = 0.5
    sparsity: float = 0.9
    seed: int = 0
    bias: bool = True
    inputs: list[str] = field(default_factory=lambda: ["q", "dq", "alpha2", "alpha2_dot"])
    scales: dict[str, float] = field(default_factory=dict)

    @property
    def n_regressor(self) -> int:
        """Length of Phi: N reservoir states plus one bias entry when `bias`."""
        return self.size + (1 if self.bias else 0)


@dataclass
class DesignSpec:
    """Which design is derived: the variant, its error transformation and its approximator (registry names)."""

    variant: str = "backstepping"
    transform: str = "funnel"
    approximator: str = "esn"


@dataclass
class SimulationSpec:
    """Closed-loop simulation settings."""

    t_final: float = 20.0
    dt: float = 0.01
    integrator: str = "cvodes"
    rtol: float = 1e-6
    atol: float = 1e-8
    smoothing_width: float = 1e-3
    convergence_widths: list[float] = field(default_factory=lambda: [1e-2, 1e-3])
    wall_limit: float = 300.0
    rk_substeps: int = 10
    max_step: float = 0.0            # CVODES' largest step in seconds, 0 = unlimited
    settle_time: float | None = None  # start of the post-transient margins [s]; None: where the funnels settle


@dataclass
class AuditSpec:
    """Sampling settings of the audit's numeric checks."""

    samples: int = 1000
    claim_samples: int = 200
    seed: int = 0
    joint_lower: list[float] = field(default_factory=list)
    joint_upper: list[float] = field(default_factory=list)
    velocity_range: list[float] = field(default_factory=list)
    tolerance: float = 1e-9
    sympy_timeout: float = 10.0


@dataclass
class Deviation:
    """A value the scenario chose where the paper gives none or gives a wrong one."""

    key: str
    paper: str
    value: str
    reason: str


@dataclass
class Scenario:
    """A validated scenario: model, reference, initial state, funnels, gains, plant, ESN, simulation, claims."""

    name: str
    path: Path
    title: str
    description: str
    source: str
    deviations: list[Deviation]
    model: RigidBodyModel
    reference: list[Expression]
    q0: list[float]
    dq0: list[float]
    x_esn0: list[float]
    w_hat0: float
    funnels: dict[str, FunnelSpec]
    k1: list[float]
    k2: list[float]
    gamma: float
    sigma: float
    esn: ESNSpec
    plant: PlantSpec
    simulation: SimulationSpec
    audit: AuditSpec
    claims: list[Claim]
    design: DesignSpec = field(default_factory=DesignSpec)
    expectations: list[Expectation] = field(default_factory=list)
    raw: dict = field(repr=False, default_factory=dict)
    campaign: Campaign | None = None                # of [[uncertainty]] / [sweep], None without them
    implementation: ImplementationSpec | None = None  # None: the continuous-time controller
    rbf: RBFSpec | None = None      # `[rbf]` settings (approximator type "rbf"), None otherwise
    tune: TuneSpec | None = None    # of [tune], or None
    #: [adaptation] projection: W_hat's ball radius R of the projected law (family.projection), None: no projection
    projection: float | None = None
    #: [adaptation] projection_layer: the boundary layer's relative width eps (the ball kept is R (1 + eps))
    projection_layer: float = 0.05
    #: every file read to build it ({resolved path: sha256 of the content read}: the TOML, a URDF, ...)
    inputs: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_sealed", True)

    def __setattr__(self, name, value):
        if self.__dict__.get("_sealed") and not name.startswith("_"):
            raise AttributeError(f"a Scenario is validated as a whole when it is loaded, so {name} cannot be set on "
                                 f"it; use scenario.replace(**{{'<table>.<key>': value}}) (e.g. "
                                 f"scenario.replace(**{{'controller.k2': [1, 1]}}) or controller__k2=[1, 1]), which "
                                 "validates the changed document like the loader")
        object.__setattr__(self, name, value)

    def __repr__(self) -> str:
        """Short: the name, the file and the size (not the model, the expressions, every table)."""
        return (f"Scenario({self.name!r}, file={str(self.path)!r}, {self.n} joints, "
                f"t_final={self.simulation.t_final:g} s)")

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.model.n

    @property
    def file(self) -> str:
        """The scenario's path as a string, for messages."""
        return str(self.path)

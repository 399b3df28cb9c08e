"""Scenario files (TOML) loaded into validated, typed objects; every error names the file, the key and what was expected."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..core import validate as V
from ..core.errors import InputError
from ..expr import Expression, parse_expression
from ..family.approximators import APPROXIMATORS, ESNApproximator, RBFSpec, parse_rbf
from ..family.funnels import FunnelSpec, check_positive, parse_funnel
from ..family.transforms import TRANSFORMS
from ..family.variants import VARIANTS
from ..family.integrators import INTEGRATORS
from ..model import MODEL_TYPES
from ..plant.nonlinearities import DeadZoneSpec
from ..plant.nonlinearities import check_dead_zone_spec as _check_dead_zone
from ..core.names import CONSTANTS, EXPECT_STATUSES, IDENT, SIGNALS, check_ids

if TYPE_CHECKING:
    from .implementation import ImplementationSpec
    from ..model.base import RigidBodyModel
    from .tune import TuneSpec
    from .uncertainty import Campaign

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
BUILTIN = {"paper": "paper_2dof.toml", "arm7": "arm7.toml"}

TOP_KEYS = ["name", "title", "description", "source", "deviations", "model", "reference", "initial",
            "funnel", "controller", "adaptation", "esn", "plant", "simulation", "audit", "claims", "design",
            "approximator", "expect", "uncertainty", "sweep", "implementation", "rbf", "tune"]
ESN_INPUTS = list(ESNApproximator.INPUTS)


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

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.model.n

    @property
    def file(self) -> str:
        """The scenario's path as a string, for messages."""
        return str(self.path)


def resolve(name_or_path: str | Path | None) -> Path:
    """A built-in scenario name or a path to a TOML file -> the file's path (InputError if neither)."""
    if name_or_path is None:
        name_or_path = "paper"
    s = str(name_or_path)
    p = Path(s)
    if p.exists():
        if p.is_dir():
            raise InputError("is a directory", file=s, expected="a scenario TOML file or a built-in name")
        return p
    if s in BUILTIN:
        return DATA_DIR / BUILTIN[s]
    hint = V.did_you_mean(s, BUILTIN)
    raise InputError(f"no such file or built-in scenario{hint}", file=s,
                     expected="a path to a .toml file or one of " + ", ".join(BUILTIN))


def is_builtin(path: str | Path) -> bool:
    """Whether `path` is one of the scenario files shipped with symfunnel."""
    try:
        p = Path(path).resolve()
    except OSError:
        return False
    return any(p == (DATA_DIR / f).resolve() for f in BUILTIN.values())


def load_scenario(name_or_path: str | Path | None = None) -> Scenario:
    """Load and validate a scenario (a path or a built-in name such as 'paper')."""
    path = resolve(name_or_path)
    file = str(path)
    from ..core.inputs import loads_toml, read_text
    text = read_text(path, expected="a scenario TOML file")
    raw = loads_toml(text, file=file)
    default_name = path.stem if str(name_or_path) not in BUILTIN else str(name_or_path)
    return from_dict(raw, file=file, base_dir=path.parent, default_name=default_name)


def from_dict(raw: dict, *, file: str, base_dir: Path, default_name: str = "scenario") -> Scenario:
    """Validate a parsed TOML document into a Scenario."""
    V.check_keys(raw, TOP_KEYS, file=file, prefix="", required=["model", "reference", "initial"])
    name = V.get_str(raw, "name", default_name, file=file, prefix="")
    if not re.match(r"^[A-Za-z0-9_.-]{1,64}$", name):
        raise InputError(f"is '{name}'", file=file, key="name",
                         expected="1-64 characters of letters, digits, '_', '-', '.'")
    title = V.get_str(raw, "title", name, file=file, prefix="")
    description = V.get_str(raw, "description", "", file=file, prefix="")
    source = V.get_str(raw, "source", "", file=file, prefix="")
    deviations = _deviations(raw.get("deviations", []), file)

    model = build_model(raw["model"], file=file, base_dir=base_dir)
    n = model.n

    reference = _reference(raw["reference"], n, file, model)
    q0, dq0, init = _initial(raw["initial"], n, file)

    funnel_raw = raw.get("funnel", {})
    V.check_keys(funnel_raw, ["e1", "e2"], file=file, prefix="funnel")
    funnels = {
        "e1": _funnel(funnel_raw.get("e1", {}), n, file, "funnel.e1", (0.5, 0.02, 1.0), model.parameter_dict()),
        "e2": _funnel(funnel_raw.get("e2", {}), n, file, "funnel.e2", (2.0, 0.1, 1.0), model.parameter_dict()),
    }

    ctl = raw.get("controller", {})
    V.check_keys(ctl, ["k1", "k2"], file=file, prefix="controller")
    k1 = V.per_joint(ctl, "k1", n, 5.0, file=file, prefix="controller", minimum=0, strict_min=True)
    k2 = V.per_joint(ctl, "k2", n, 10.0, file=file, prefix="controller", minimum=0, strict_min=True)

    ad = raw.get("adaptation", {})
    V.check_keys(ad, ["gamma", "sigma", "w_hat0"], file=file, prefix="adaptation")
    gamma = V.get_float(ad, "gamma", 10.0, file=file, prefix="adaptation", minimum=0, strict_min=True)
    sigma = V.get_float(ad, "sigma", 0.02, file=file, prefix="adaptation", minimum=0)
    w_hat0 = V.get_float(ad, "w_hat0", 0.0, file=file, prefix="adaptation")
    if "w_hat" in init:
        w_hat0 = V.as_float(init["w_hat"], file=file, key="initial.w_hat")

    esn = _esn(raw.get("esn", {}), file)
    x_esn0 = _x_esn0(init, esn.size, file)
    plant = _plant(raw.get("plant", {}), n, file, model)
    sim = _simulation(raw.get("simulation", {}), file)
    for key, shape in funnels.items():
        check_positive(shape, sim.t_final, file=file, key=f"funnel.{key}" + (".F" if "F" in shape.KEYS else ""))
    audit = _audit(raw.get("audit", {}), n, file, model)
    if model.kind == "matrices":
        from ..model.matrices_check import check_inertia_matrix
        check_inertia_matrix(model, q0, audit.joint_lower, audit.joint_upper, file=file)
    claims = _claims(raw.get("claims", []), n, file, model, funnels)
    design = _design(raw.get("design", {}), raw.get("approximator", {}), file)
    _settings_match(raw, design.approximator, file)
    rbf = None
    if design.approximator == "rbf":
        rbf = parse_rbf(raw.get("rbf", {}), n, file=file, joint_lower=audit.joint_lower,
                        joint_upper=audit.joint_upper, velocity_range=audit.velocity_range)
    expectations = _expectations(raw.get("expect", []), n, claims, file)
    from .uncertainty import parse_campaign
    campaign = parse_campaign(raw, file=file, n=n, model=model, plant=plant)
    impl = None
    if "implementation" in raw:
        from .implementation import parse_implementation
        impl = parse_implementation(raw["implementation"], n=n, file=file, raw_model=raw["model"], base_dir=base_dir)
    tune = None
    if "tune" in raw:
        from .tune import parse_tune
        tune = parse_tune(raw["tune"], file=file, has_implementation=impl is not None, funnels=funnels, n=n,
                          raw_model=raw["model"], base_dir=base_dir)

    return Scenario(name=name, path=Path(file), title=title, description=description, source=source,
                    deviations=deviations, model=model, reference=reference, q0=q0, dq0=dq0,
                    x_esn0=x_esn0, w_hat0=w_hat0, funnels=funnels, k1=k1, k2=k2, gamma=gamma,
                    sigma=sigma, esn=esn, plant=plant, simulation=sim, audit=audit, claims=claims,
                    design=design, expectations=expectations, raw=raw, campaign=campaign, implementation=impl,
                    rbf=rbf, tune=tune)


# --- sections -------------------------------------------------------------------------------------

def build_model(table: Any, *, file: str, base_dir: Path):
    """Dispatch `[model]` on its `type` to the model builder that owns that type."""
    V.check_keys(table, ["type", "coordinates", "parameters", "matrices", "path", "gravity", "links",
                         "convention", "joint_range"], file=file, prefix="model", required=["type"])
    kind = V.get_str(table, "type", file=file, prefix="model", choices=MODEL_TYPES.names())
    return MODEL_TYPES.get(kind)(table, file=file, base_dir=base_dir)


def _reference(table: Any, n: int, file: str, model) -> list[Expression]:
    V.check_keys(table, ["q"], file=file, prefix="reference", required=["q"])
    return _expr_list(table, "q", n, file, "reference", {"t"})


def _expr_list(table: dict, key: str, n: int, file: str, prefix: str, names: set[str],
               default: Any = None) -> list[Expression]:
    """One expression string for every joint, or an array of n strings."""
    full = V.join(prefix, key)
    value = table.get(key, default)
    if isinstance(value, str):
        e = parse_expression(value, names, file=file, key=full)
        return [e] * n
    if not isinstance(value, list) or len(value) != n:
        raise InputError(f"is {_describe(value)}", file=file, key=full,
                         expected=f"a string or an array of {n} strings (one per joint)")
    out = []
    for i, s in enumerate(value):
        if isinstance(s, (int, float)) and not isinstance(s, bool):
            s = repr(float(s))
        if not isinstance(s, str):
            raise InputError(f"is a {V.type_name(s)}", file=file, key=V.join(full, i),
                             expected="an expression string")
        out.append(parse_expression(s, names, file=file, key=V.join(full, i)))
    return out


def _describe(value: Any) -> str:
    if isinstance(value, list):
        return f"an array of {len(value)}"
    return f"a {V.type_name(value)}"


def _initial(table: Any, n: int, file: str):
    V.check_keys(table, ["q", "dq", "x_esn", "w_hat"], file=file, prefix="initial", required=["q"])
    q0 = V.per_joint(table, "q", n, file=file, prefix="initial")
    dq0 = V.per_joint(table, "dq", n, 0.0, file=file, prefix="initial")
    return q0, dq0, table


def _x_esn0(init: dict, size: int, file: str) -> list[float]:
    return V.per_joint(init, "x_esn", size, 0.0, file=file, prefix="initial")


def _funnel(table: Any, n: int, file: str, prefix: str, defaults, parameters: dict | None = None):
    return parse_funnel(table, n, file, prefix, defaults, parameters)


def _design(table: Any, approx: Any, file: str) -> DesignSpec:
    """`[design]` (variant, transform) and `[approximator]` (type), validated against their registries."""
    d = DesignSpec()
    V.check_keys(table, ["variant", "transform"], file=file, prefix="design")
    V.check_keys(approx, ["type"], file=file, prefix="approximator")
    out = DesignSpec(variant=V.get_str(table, "variant", d.variant, file=file, prefix="design"),
                     transform=V.get_str(table, "transform", d.transform, file=file, prefix="design"),
                     approximator=V.get_str(approx, "type", d.approximator, file=file, prefix="approximator"))
    VARIANTS.get(out.variant, file=file, key="design.variant")
    TRANSFORMS.get(out.transform, file=file, key="design.transform")
    APPROXIMATORS.get(out.approximator, file=file, key="approximator.type")
    return out


def _settings_match(raw: dict, chosen: str, file: str) -> None:
    """A settings section of another approximator type (e.g. `[rbf]` with type "esn") is an input error."""
    for entry in APPROXIMATORS:
        section = getattr(entry.obj, "SETTINGS", None)
        if section and section in raw and entry.name != chosen:
            raise InputError(f"gives settings of approximator '{entry.name}', but approximator.type is '{chosen}'",
                             file=file, key=section, expected=f'approximator.type = "{entry.name}", or no [{section}]')


def _esn(table: Any, file: str) -> ESNSpec:
    p = "esn"
    V.check_keys(table, ["size", "leak", "time_constant", "spectral_radius", "input_scaling", "sparsity",
                         "seed", "bias", "inputs", "scales"], file=file, prefix=p)
    d = ESNSpec()
    inputs = V.get_names(table, "inputs", d.inputs, file=file, prefix=p, choices=ESN_INPUTS)
    if not inputs:
        raise InputError("is empty", file=file, key="esn.inputs", expected="at least one input signal")
    scales_raw = table.get("scales", {})
    V.check_keys(scales_raw, ESN_INPUTS, file=file, prefix="esn.scales")
    scales = {k: V.as_float(v, file=file, key=f"esn.scales.{k}", minimum=0, strict_min=True)
              for k, v in scales_raw.items()}
    return ESNSpec(
        size=V.get_int(table, "size", d.size, file=file, prefix=p, minimum=1, maximum=2000),
        leak=V.get_float(table, "leak", d.leak, file=file, prefix=p, minimum=0, strict_min=True),
        time_constant=V.get_float(table, "time_constant", d.time_constant, file=file, prefix=p,
                                  minimum=0, strict_min=True),
        spectral_radius=V.get_float(table, "spectral_radius", d.spectral_radius, file=file, prefix=p,
                                    minimum=0, maximum=1, strict_min=True, strict_max=True),
        input_scaling=V.get_float(table, "input_scaling", d.input_scaling, file=file, prefix=p, minimum=0),
        sparsity=V.get_float(table, "sparsity", d.sparsity, file=file, prefix=p, minimum=0, maximum=1,
                             strict_max=True),
        seed=V.get_int(table, "seed", d.seed, file=file, prefix=p, minimum=0, maximum=2**63 - 1),
        bias=V.get_bool(table, "bias", d.bias, file=file, prefix=p),
        inputs=list(inputs),
        scales=scales,
    )


def _plant(table: Any, n: int, file: str, model) -> PlantSpec:
    p = "plant"
    V.check_keys(table, ["viscous", "coulomb", "disturbance", "dead_zone", "mass_scale", "parameters", "coriolis",
                         "disturbance_scale"], file=file, prefix=p)
    coriolis = V.get_str(table, "coriolis", "christoffel", file=file, prefix=p, choices=["christoffel", "model"])
    viscous = V.per_joint(table, "viscous", n, 0.0, file=file, prefix=p, minimum=0)
    coulomb = V.per_joint(table, "coulomb", n, 0.0, file=file, prefix=p, minimum=0)
    names = {"t"} | set(model.coordinates) | {"d" + c for c in model.coordinates}
    disturbance = _expr_list(table, "disturbance", n, file, p, names, default="0")
    d_scale = V.per_joint(table, "disturbance_scale", n, 1.0, file=file, prefix=p, minimum=0)
    mass_scale = V.get_float(table, "mass_scale", 1.0, file=file, prefix=p, minimum=0, strict_min=True)
    params_raw = table.get("parameters", {})
    V.check_keys(params_raw, model.p_names, file=file, prefix="plant.parameters")
    params = {k: V.as_float(v, file=file, key=f"plant.parameters.{k}") for k, v in params_raw.items()}
    dz = None
    if "dead_zone" in table:
        t = table["dead_zone"]
        q = "plant.dead_zone"
        V.check_keys(t, ["b_l", "b_r", "left", "right", "left_scale", "right_scale"], file=file, prefix=q,
                     required=["b_l", "b_r"])
        b_l = V.per_joint(t, "b_l", n, file=file, prefix=q, maximum=0, strict_max=True)
        b_r = V.per_joint(t, "b_r", n, file=file, prefix=q, minimum=0, strict_min=True)
        left = parse_expression(V.get_str(t, "left", "u - b_l", file=file, prefix=q), {"u", "b_l", "b_r"},
                                file=file, key=q + ".left")
        right = parse_expression(V.get_str(t, "right", "u - b_r", file=file, prefix=q), {"u", "b_l", "b_r"},
                                 file=file, key=q + ".right")
        scales = [V.per_joint(t, k, n, 1.0, file=file, prefix=q, minimum=0, strict_min=True)
                  for k in ("left_scale", "right_scale")]
        dz = DeadZoneSpec(b_l, b_r, left, right, *scales)
        _check_dead_zone(dz, n, file)
    return PlantSpec(viscous, coulomb, disturbance, dz, mass_scale, params, coriolis, d_scale)


def _simulation(table: Any, file: str) -> SimulationSpec:
    p = "simulation"
    V.check_keys(table, ["t_final", "dt", "integrator", "rtol", "atol", "smoothing_width",
                         "convergence_widths", "wall_limit", "rk_substeps", "max_step"], file=file, prefix=p)
    d = SimulationSpec()
    t_final = V.get_float(table, "t_final", d.t_final, file=file, prefix=p, minimum=0, strict_min=True,
                          maximum=1e6)
    dt = V.get_float(table, "dt", d.dt, file=file, prefix=p, minimum=0, strict_min=True)
    if t_final / dt > 1e6:
        raise InputError(f"gives {t_final / dt:.3g} output points", file=file, key="simulation.dt",
                         expected="at most 1e6 output points (t_final/dt)")
    widths = V.get_list(table, "convergence_widths", d.convergence_widths, file=file, prefix=p)
    widths = [V.as_float(w, file=file, key=f"simulation.convergence_widths[{i}]", minimum=0, strict_min=True)
              for i, w in enumerate(widths)]
    return SimulationSpec(
        t_final=t_final, dt=dt,
        integrator=V.get_str(table, "integrator", d.integrator, file=file, prefix=p, choices=INTEGRATORS.names()),
        rtol=V.get_float(table, "rtol", d.rtol, file=file, prefix=p, minimum=0, strict_min=True),
        atol=V.get_float(table, "atol", d.atol, file=file, prefix=p, minimum=0, strict_min=True),
        smoothing_width=V.get_float(table, "smoothing_width", d.smoothing_width, file=file, prefix=p,
                                    minimum=0),
        convergence_widths=widths,
        wall_limit=V.get_float(table, "wall_limit", d.wall_limit, file=file, prefix=p, minimum=0,
                               strict_min=True),
        rk_substeps=V.get_int(table, "rk_substeps", d.rk_substeps, file=file, prefix=p, minimum=1,
                              maximum=10000),
        max_step=V.get_float(table, "max_step", d.max_step, file=file, prefix=p, minimum=0),
    )


def _audit(table: Any, n: int, file: str, model) -> AuditSpec:
    p = "audit"
    V.check_keys(table, ["samples", "claim_samples", "seed", "joint_range", "velocity_range", "tolerance",
                         "sympy_timeout"], file=file, prefix=p)
    d = AuditSpec()
    lower = [-math.pi] * n
    upper = [math.pi] * n
    if model.joint_lower is not None:
        lower = [float(x) if math.isfinite(x) else -math.pi for x in model.joint_lower]
    if model.joint_upper is not None:
        upper = [float(x) if math.isfinite(x) else math.pi for x in model.joint_upper]
    if "joint_range" in table:
        lower, upper = _ranges(table["joint_range"], n, file, "audit.joint_range")
    return AuditSpec(
        samples=V.get_int(table, "samples", d.samples, file=file, prefix=p, minimum=1000, maximum=10**7),
        claim_samples=V.get_int(table, "claim_samples", d.claim_samples, file=file, prefix=p, minimum=200,
                                maximum=10**7),
        seed=V.get_int(table, "seed", d.seed, file=file, prefix=p, minimum=0, maximum=2**63 - 1),
        joint_lower=lower, joint_upper=upper,
        velocity_range=V.per_joint(table, "velocity_range", n, 2.0, file=file, prefix=p, minimum=0,
                                   strict_min=True),
        tolerance=V.get_float(table, "tolerance", d.tolerance, file=file, prefix=p, minimum=0, strict_min=True),
        sympy_timeout=V.get_float(table, "sympy_timeout", d.sympy_timeout, file=file, prefix=p, minimum=0),
    )


def _ranges(value: Any, n: int, file: str, key: str):
    """[lo, hi] for every joint, or an array of n [lo, hi] pairs."""
    def pair(v, k):
        if not (isinstance(v, list) and len(v) == 2):
            raise InputError(f"is {_describe(v)}", file=file, key=k, expected="a pair [lower, upper]")
        lo = V.as_float(v[0], file=file, key=k + "[0]")
        hi = V.as_float(v[1], file=file, key=k + "[1]")
        if not lo < hi:
            raise InputError(f"is [{lo:g}, {hi:g}]", file=file, key=k, expected="lower < upper")
        return lo, hi
    if isinstance(value, list) and len(value) == 2 and not isinstance(value[0], list):
        lo, hi = pair(value, key)
        return [lo] * n, [hi] * n
    if not isinstance(value, list) or len(value) != n:
        raise InputError(f"is {_describe(value)}", file=file, key=key,
                         expected=f"a pair [lower, upper] or {n} pairs")
    pairs = [pair(v, f"{key}[{i}]") for i, v in enumerate(value)]
    return [a for a, _ in pairs], [b for _, b in pairs]


def claim_names(n: int, model) -> set[str]:
    """Every name a claim expression may use: time, coordinates, parameters, signals and design constants."""
    names = {"t", "x_esn", "w_hat", "q", "dq"} | set(SIGNALS) | set(CONSTANTS)
    names |= set(model.coordinates) | {"d" + c for c in model.coordinates} | set(model.p_names)
    return names


def _expression_pair(c: dict, p: str, keys: tuple[str, str], exclusive: tuple[str, ...], kind: str, whose: str,
                     names: set[str], file: str) -> tuple[Expression, Expression]:
    """The two expressions of a claim kind given by a pair of keys (lhs/rhs, rho/delta), alone of their kind."""
    a, b = keys
    for k in exclusive:
        if k in c:
            raise InputError(f"cannot be combined with '{a}'/'{b}'", file=file, key=f"{p}.{k}",
                             expected=f"{kind} has {a} and {b} only")
    for k in keys:
        if k not in c:
            raise InputError("is missing", file=file, key=f"{p}.{k}", expected=f"{a} and {b} {whose}")
    return tuple(parse_expression(V.get_str(c, k, file=file, prefix=p), names, file=file, key=f"{p}.{k}")
                 for k in keys)


#: what an inequality claim may name besides a signal claim's names: the design's V and its exact derivative along
#: the nominal model plus W*^T Phi (eps = 0: the ideal approximation such printed steps assume), and W*
INEQUALITY_NAMES = {"V", "V_dot", "W_star"}


def _claims(items: Any, n: int, file: str, model, funnels) -> list[Claim]:
    if not isinstance(items, list):
        raise InputError(f"is a {V.type_name(items)}", file=file, key="claims",
                         expected="an array of tables ([[claims]])")
    names = claim_names(n, model)
    seen = set()
    out = []
    for i, c in enumerate(items):
        p = f"claims[{i}]"
        V.check_keys(c, ["name", "source", "description", "signal", "expression", "funnel", "phi0",
                         "phi_inf", "a", "rho", "delta", "lhs", "rhs", "expect", "parameters"], file=file, prefix=p,
                     required=["name"])
        name = V.get_str(c, "name", file=file, prefix=p)
        if not IDENT.match(name) or len(name) > 64:
            raise InputError(f"is '{name}'", file=file, key=p + ".name", expected="an identifier")
        if name in seen:
            raise InputError(f"'{name}' is used twice", file=file, key=p + ".name", expected="unique claim names")
        seen.add(name)
        source = V.get_str(c, "source", "", file=file, prefix=p)
        desc = V.get_str(c, "description", "", file=file, prefix=p)
        expect = V.get_str(c, "expect", "pass", file=file, prefix=p, choices=list(EXPECT_STATUSES))
        params_raw = c.get("parameters", {})
        V.check_keys(params_raw, list(params_raw) if isinstance(params_raw, dict) else [], file=file,
                     prefix=p + ".parameters")
        params = {}
        for k, v in params_raw.items():
            if not IDENT.match(k) or k in names:
                raise InputError(f"'{k}' is not a new identifier", file=file, key=f"{p}.parameters.{k}",
                                 expected="a name the claim's expression uses that is not a signal, symbol or parameter")
            params[k] = V.as_float(v, file=file, key=f"{p}.parameters.{k}")
        cnames = names | set(params)
        if "lhs" in c or "rhs" in c:
            lhs, rhs = _expression_pair(c, p, ("lhs", "rhs"), ("signal", "expression", "funnel", "rho", "delta"),
                                        "an inequality claim", "of the inequality", cnames | INEQUALITY_NAMES, file)
            out.append(Claim(name, source, desc, "inequality", lhs=lhs, rhs=rhs, expect=expect, parameters=params))
            continue
        if "rho" in c or "delta" in c:
            rho, delta = _expression_pair(c, p, ("rho", "delta"), ("signal", "expression", "funnel"),
                                          "a decay claim", "of the claim", names | {"W_star_norm2"}, file)
            out.append(Claim(name, source, desc, "decay", rho=rho, delta=delta, expect=expect))
            continue
        if "funnel" in c:
            for k in ("signal", "expression"):
                if k in c:
                    raise InputError("cannot be combined with 'funnel'", file=file, key=f"{p}.{k}",
                                     expected="either funnel + phi0/phi_inf/a, or signal + expression")
            fn = V.get_str(c, "funnel", file=file, prefix=p, choices=["e1", "e2"])
            base = funnels[fn]
            inherit = (base.phi0, base.phi_inf, base.a) if hasattr(base, "phi0") else None
            spec = _funnel({k: c[k] for k in ("phi0", "phi_inf", "a") if k in c}, n, file, p, inherit)
            out.append(Claim(name, source, desc, "funnel", funnel=fn, spec=spec, expect=expect))
            continue
        for k in ("phi0", "phi_inf", "a"):
            if k in c:
                raise InputError("is only allowed with 'funnel'", file=file, key=f"{p}.{k}",
                                 expected="signal + expression for an equation claim")
        if "signal" not in c or "expression" not in c:
            missing = "signal" if "signal" not in c else "expression"
            raise InputError("is missing", file=file, key=f"{p}.{missing}",
                             expected="signal + expression, or funnel + phi0/phi_inf/a")
        sig = V.get_str(c, "signal", file=file, prefix=p, choices=sorted(SIGNALS))
        expr = parse_expression(V.get_str(c, "expression", file=file, prefix=p), cnames, file=file,
                                key=p + ".expression")
        out.append(Claim(name, source, desc, "signal", signal=sig, expression=expr, expect=expect, parameters=params))
    return out


def _expectations(items: Any, n: int, claims: list[Claim], file: str) -> list[Expectation]:
    """`[[expect]]`: declared outcomes of non-claim checks, each naming a known check id and giving a reason."""
    if not isinstance(items, list):
        raise InputError(f"is a {V.type_name(items)}", file=file, key="expect",
                         expected="an array of tables ([[expect]])")
    known = check_ids(n)
    out, seen = [], set()
    for i, e in enumerate(items):
        p = f"expect[{i}]"
        V.check_keys(e, ["check", "status", "reason"], file=file, prefix=p, required=["check", "status", "reason"])
        cid = V.get_str(e, "check", file=file, prefix=p)
        if cid.startswith("claim."):
            raise InputError(f"is '{cid}'", file=file, key=p + ".check",
                             expected="a non-claim check id (a claim declares its outcome with `expect`)")
        if cid not in known:
            raise InputError(f"is '{cid}', not a check id{V.did_you_mean(cid, known)}", file=file, key=p + ".check",
                             expected="a check id of audit or verify (see docs/scenario.md)")
        if cid in seen:
            raise InputError(f"'{cid}' is declared twice", file=file, key=p + ".check", expected="one entry per check")
        seen.add(cid)
        status = V.get_str(e, "status", file=file, prefix=p, choices=list(EXPECT_STATUSES))
        reason = V.get_str(e, "reason", file=file, prefix=p).strip()
        if not reason:
            raise InputError("is empty", file=file, key=p + ".reason", expected="why the outcome is expected")
        out.append(Expectation(cid, status, reason))
    return out


def _deviations(items: Any, file: str) -> list[Deviation]:
    if not isinstance(items, list):
        raise InputError(f"is a {V.type_name(items)}", file=file, key="deviations",
                         expected="an array of tables ([[deviations]])")
    out = []
    for i, d in enumerate(items):
        p = f"deviations[{i}]"
        V.check_keys(d, ["key", "paper", "value", "reason"], file=file, prefix=p, required=["key", "reason"])
        out.append(Deviation(V.get_str(d, "key", file=file, prefix=p), V.get_str(d, "paper", "", file=file, prefix=p),
                             V.get_str(d, "value", "", file=file, prefix=p), V.get_str(d, "reason", file=file, prefix=p)))
    return out

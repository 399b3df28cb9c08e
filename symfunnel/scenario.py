"""Scenario files (TOML) loaded into validated, typed objects; every error names the file, the key and what was expected."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import validate as V
from .errors import InputError
from .expr import Expression, parse_expression
from .names import CONSTANTS, SIGNALS

DATA_DIR = Path(__file__).parent / "data"
BUILTIN = {"paper": "paper_2dof.toml", "arm7": "arm7.toml"}

TOP_KEYS = ["name", "title", "description", "source", "deviations", "model", "reference", "initial",
            "funnel", "controller", "adaptation", "esn", "plant", "simulation", "audit", "claims"]
ESN_INPUTS = ["q", "dq", "e1", "e2", "qd", "dqd", "ddqd", "alpha2", "alpha2_dot"]
IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
RESERVED = {"t", "u", "pi", "e"} | set(SIGNALS) | set(CONSTANTS) | {"x_esn", "w_hat", "q", "dq"}


@dataclass
class FunnelSpec:
    """F(t) = phi0*exp(-a*t) + phi_inf, per joint."""

    phi0: list[float]
    phi_inf: list[float]
    a: list[float]

    def value(self, t: float) -> list[float]:
        """F at time t, per joint."""
        return [p0 * math.exp(-a * t) + pi for p0, pi, a in zip(self.phi0, self.phi_inf, self.a)]


@dataclass
class Claim:
    """An equation or parameter set as printed in the source, audited against the exact derivation."""

    name: str
    source: str
    description: str
    kind: str                            # "signal" or "funnel"
    signal: str | None = None
    expression: Expression | None = None
    funnel: str | None = None
    spec: FunnelSpec | None = None


@dataclass
class DeadZoneSpec:
    """Asymmetric dead zone of eq. 2: branch expressions in u, b_l and b_r, per joint breakpoints."""

    b_l: list[float]
    b_r: list[float]
    left: Expression
    right: Expression


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
    model: Any                      # RigidBodyModel
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
    raw: dict = field(repr=False, default_factory=dict)

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
    from .inputs import loads_toml, read_text
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
        "e1": _funnel(funnel_raw.get("e1", {}), n, file, "funnel.e1", (0.5, 0.02, 1.0)),
        "e2": _funnel(funnel_raw.get("e2", {}), n, file, "funnel.e2", (2.0, 0.1, 1.0)),
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
    audit = _audit(raw.get("audit", {}), n, file, model)
    if model.kind == "matrices":
        from .model.matrices_check import check_inertia_matrix
        check_inertia_matrix(model, q0, audit.joint_lower, audit.joint_upper, file=file)
    claims = _claims(raw.get("claims", []), n, file, model, funnels)

    return Scenario(name=name, path=Path(file), title=title, description=description, source=source,
                    deviations=deviations, model=model, reference=reference, q0=q0, dq0=dq0,
                    x_esn0=x_esn0, w_hat0=w_hat0, funnels=funnels, k1=k1, k2=k2, gamma=gamma,
                    sigma=sigma, esn=esn, plant=plant, simulation=sim, audit=audit, claims=claims,
                    raw=raw)


# --- sections -------------------------------------------------------------------------------------

def build_model(table: Any, *, file: str, base_dir: Path):
    """Dispatch `[model]` on its `type` to the model builder that owns that type."""
    V.check_keys(table, ["type", "coordinates", "parameters", "matrices", "path", "gravity", "links",
                         "convention", "joint_range"], file=file, prefix="model", required=["type"])
    kind = V.get_str(table, "type", file=file, prefix="model", choices=["matrices", "planar", "dh", "urdf"])
    if kind == "matrices":
        from .model.matrices import build_matrices
        return build_matrices(table, file=file)
    if kind == "planar":
        from .model.links import build_planar
        return build_planar(table, file=file)
    if kind == "dh":
        from .model.links import build_dh
        return build_dh(table, file=file)
    from .model.urdf import build_urdf
    return build_urdf(table, file=file, base_dir=base_dir)


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


def _funnel(table: Any, n: int, file: str, prefix: str, defaults) -> FunnelSpec:
    V.check_keys(table, ["phi0", "phi_inf", "a"], file=file, prefix=prefix)
    phi0 = V.per_joint(table, "phi0", n, defaults[0], file=file, prefix=prefix, minimum=0)
    phi_inf = V.per_joint(table, "phi_inf", n, defaults[1], file=file, prefix=prefix, minimum=0,
                          strict_min=True)
    a = V.per_joint(table, "a", n, defaults[2], file=file, prefix=prefix, minimum=0)
    return FunnelSpec(phi0, phi_inf, a)


def _esn(table: Any, file: str) -> ESNSpec:
    p = "esn"
    V.check_keys(table, ["size", "leak", "time_constant", "spectral_radius", "input_scaling", "sparsity",
                         "seed", "bias", "inputs", "scales"], file=file, prefix=p)
    d = ESNSpec()
    inputs = V.get_list(table, "inputs", d.inputs, file=file, prefix=p)
    for i, s in enumerate(inputs):
        if not isinstance(s, str) or s not in ESN_INPUTS:
            hint = V.did_you_mean(s, ESN_INPUTS) if isinstance(s, str) else ""
            raise InputError(f"is {s!r}{hint}", file=file, key=f"esn.inputs[{i}]",
                             expected="one of " + ", ".join(ESN_INPUTS))
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
    V.check_keys(table, ["viscous", "coulomb", "disturbance", "dead_zone", "mass_scale", "parameters", "coriolis"],
                 file=file, prefix=p)
    coriolis = V.get_str(table, "coriolis", "christoffel", file=file, prefix=p, choices=["christoffel", "model"])
    viscous = V.per_joint(table, "viscous", n, 0.0, file=file, prefix=p, minimum=0)
    coulomb = V.per_joint(table, "coulomb", n, 0.0, file=file, prefix=p, minimum=0)
    names = {"t"} | set(model.coordinates) | {"d" + c for c in model.coordinates}
    disturbance = _expr_list(table, "disturbance", n, file, p, names, default="0")
    mass_scale = V.get_float(table, "mass_scale", 1.0, file=file, prefix=p, minimum=0, strict_min=True)
    params_raw = table.get("parameters", {})
    V.check_keys(params_raw, model.p_names, file=file, prefix="plant.parameters")
    params = {k: V.as_float(v, file=file, key=f"plant.parameters.{k}") for k, v in params_raw.items()}
    dz = None
    if "dead_zone" in table:
        t = table["dead_zone"]
        q = "plant.dead_zone"
        V.check_keys(t, ["b_l", "b_r", "left", "right"], file=file, prefix=q, required=["b_l", "b_r"])
        b_l = V.per_joint(t, "b_l", n, file=file, prefix=q, maximum=0, strict_max=True)
        b_r = V.per_joint(t, "b_r", n, file=file, prefix=q, minimum=0, strict_min=True)
        left = parse_expression(V.get_str(t, "left", "u - b_l", file=file, prefix=q), {"u", "b_l", "b_r"},
                                file=file, key=q + ".left")
        right = parse_expression(V.get_str(t, "right", "u - b_r", file=file, prefix=q), {"u", "b_l", "b_r"},
                                 file=file, key=q + ".right")
        dz = DeadZoneSpec(b_l, b_r, left, right)
        _check_dead_zone(dz, n, file)
    return PlantSpec(viscous, coulomb, disturbance, dz, mass_scale, params, coriolis)


def _check_dead_zone(dz: DeadZoneSpec, n: int, file: str) -> None:
    """Branches must vanish at their breakpoints and increase beyond them (eq. 2-4), decided numerically."""
    import casadi as ca
    u = ca.SX.sym("u")
    for j in range(n):
        env = {"u": u, "b_l": dz.b_l[j], "b_r": dz.b_r[j]}
        for side, expr, b, span in (("right", dz.right, dz.b_r[j], 1.0), ("left", dz.left, dz.b_l[j], -1.0)):
            e = expr.to_casadi(env)
            f = ca.Function("f", [u], [e, ca.jacobian(e, u)])
            at_b = float(f(b)[0])
            if not math.isfinite(at_b) or abs(at_b) > 1e-9 * max(1.0, abs(b)):
                raise InputError(f"gives {at_b:g} at u = {b:g} for joint {j + 1}", file=file,
                                 key=f"plant.dead_zone.{side}",
                                 expected="a branch that is 0 at its breakpoint (continuous dead zone)")
            for s in (0.0, 0.5, 1.0, 5.0, 50.0):
                slope = float(f(b + span * s)[1])
                if not math.isfinite(slope) or slope <= 0:
                    raise InputError(f"has slope {slope:g} at u = {b + span * s:g} for joint {j + 1}",
                                     file=file, key=f"plant.dead_zone.{side}",
                                     expected="an increasing branch (positive slope, eq. 3-4)")


def _simulation(table: Any, file: str) -> SimulationSpec:
    p = "simulation"
    V.check_keys(table, ["t_final", "dt", "integrator", "rtol", "atol", "smoothing_width",
                         "convergence_widths", "wall_limit", "rk_substeps"], file=file, prefix=p)
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
        integrator=V.get_str(table, "integrator", d.integrator, file=file, prefix=p,
                             choices=["cvodes", "rk", "collocation"]),
        rtol=V.get_float(table, "rtol", d.rtol, file=file, prefix=p, minimum=0, strict_min=True),
        atol=V.get_float(table, "atol", d.atol, file=file, prefix=p, minimum=0, strict_min=True),
        smoothing_width=V.get_float(table, "smoothing_width", d.smoothing_width, file=file, prefix=p,
                                    minimum=0),
        convergence_widths=widths,
        wall_limit=V.get_float(table, "wall_limit", d.wall_limit, file=file, prefix=p, minimum=0,
                               strict_min=True),
        rk_substeps=V.get_int(table, "rk_substeps", d.rk_substeps, file=file, prefix=p, minimum=1,
                              maximum=10000),
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
                         "phi_inf", "a"], file=file, prefix=p, required=["name"])
        name = V.get_str(c, "name", file=file, prefix=p)
        if not IDENT.match(name) or len(name) > 64:
            raise InputError(f"is '{name}'", file=file, key=p + ".name", expected="an identifier")
        if name in seen:
            raise InputError(f"'{name}' is used twice", file=file, key=p + ".name", expected="unique claim names")
        seen.add(name)
        source = V.get_str(c, "source", "", file=file, prefix=p)
        desc = V.get_str(c, "description", "", file=file, prefix=p)
        if "funnel" in c:
            for k in ("signal", "expression"):
                if k in c:
                    raise InputError("cannot be combined with 'funnel'", file=file, key=f"{p}.{k}",
                                     expected="either funnel + phi0/phi_inf/a, or signal + expression")
            fn = V.get_str(c, "funnel", file=file, prefix=p, choices=["e1", "e2"])
            spec = _funnel({k: c[k] for k in ("phi0", "phi_inf", "a") if k in c}, n, file, p,
                           (funnels[fn].phi0, funnels[fn].phi_inf, funnels[fn].a))
            out.append(Claim(name, source, desc, "funnel", funnel=fn, spec=spec))
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
        expr = parse_expression(V.get_str(c, "expression", file=file, prefix=p), names, file=file,
                                key=p + ".expression")
        out.append(Claim(name, source, desc, "signal", signal=sig, expression=expr))
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

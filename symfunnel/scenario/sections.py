"""One parser per section of a scenario's set-up (model, reference, initial state, funnels, design, ESN, plant,
simulation, audit), each returning its validated spec."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from ..core import validate as V
from ..core.errors import InputError
from ..core.deadline import MAX_SECONDS
from ..expr import Expression, parse_expression
from ..family.approximators import APPROXIMATORS, ESNApproximator
from ..family.funnels import parse_funnel
from ..family.integrators import INTEGRATORS
from ..family.transforms import TRANSFORMS
from ..family.variants import VARIANTS
from ..model import MODEL_TYPES
from ..plant.nonlinearities import DeadZoneSpec
from ..plant.nonlinearities import check_dead_zone_spec as _check_dead_zone
from ..plant.engines import ENGINES, check_engine_model
from .document import AuditSpec, DesignSpec, ESNSpec, MujocoSpec, PlantSpec, SimulationSpec

ESN_INPUTS = list(ESNApproximator.INPUTS)


# --- sections -------------------------------------------------------------------------------------

def build_model(table: Any, *, file: str, base_dir: Path):
    """Dispatch `[model]` on its `type` to the model builder that owns that type."""
    V.check_keys(table, ["type", "coordinates", "parameters", "matrices", "path", "gravity", "links",
                         "convention", "joint_range", "fixed_joints"], file=file, prefix="model", required=["type"])
    kind = V.get_str(table, "type", file=file, prefix="model", choices=MODEL_TYPES.names())
    return MODEL_TYPES.get(kind)(table, file=file, base_dir=base_dir)


def parse_reference(table: Any, n: int, file: str, model) -> list[Expression]:
    V.check_keys(table, ["q"], file=file, prefix="reference", required=["q"])
    return expression_list(table, "q", n, file, "reference", {"t"})


def check_reference(reference: list, t_final: float, file: str) -> None:
    """qd, dqd and ddqd finite on a dense grid of [0, t_final] (the design differentiates the reference twice)."""
    import casadi as ca
    import numpy as np
    t = ca.SX.sym("t")
    grid = np.linspace(0.0, float(t_final), 401)
    for i, e in enumerate(reference):
        q = ca.SX(e.to_casadi({"t": t}))
        dq = ca.jacobian(q, t)
        f = ca.Function("ref", [t], [q, dq, ca.jacobian(dq, t)]).map(grid.size)
        vals = [np.asarray(v, dtype=float).ravel() for v in f(grid.reshape(1, -1))]
        for name, v in zip(("qd", "dqd/dt", "d2qd/dt2"), vals):
            bad = ~np.isfinite(v)
            if bad.any():
                k = int(np.argmax(bad))
                raise InputError(f"'{e.text}' gives {name} = {v[k]} at t = {grid[k]:.6g} s", file=file,
                                 key=f"reference.q[{i}]" if len(reference) > 1 else "reference.q",
                                 expected="a reference finite, with finite first and second derivatives, on "
                                          f"[0, t_final = {float(t_final):g}]")


def expression_list(table: dict, key: str, n: int, file: str, prefix: str, names: set[str],
               default: Any = None) -> list[Expression]:
    """One expression string for every joint, or an array of n strings."""
    full = V.join(prefix, key)
    value = table.get(key, default)
    if isinstance(value, str):
        e = parse_expression(value, names, file=file, key=full)
        return [e] * n
    if not isinstance(value, list) or len(value) != n:
        raise InputError(f"is {describe(value)}", file=file, key=full,
                         expected=f"a string or an array of {n} strings (one per joint)")
    out = []
    for i, s in enumerate(value):
        if isinstance(s, (int, float)) and not isinstance(s, bool):
            s = repr(float(s))
        if not isinstance(s, str):
            raise InputError(f"is {V.a_type(s)}", file=file, key=V.join(full, i),
                             expected="an expression string")
        out.append(parse_expression(s, names, file=file, key=V.join(full, i)))
    return out


def describe(value: Any) -> str:
    if isinstance(value, list):
        return f"an array of {len(value)}"
    return f"a {V.type_name(value)}"


def parse_initial(table: Any, n: int, file: str):
    V.check_keys(table, ["q", "dq", "x_esn", "w_hat"], file=file, prefix="initial", required=["q"])
    q0 = V.per_joint(table, "q", n, file=file, prefix="initial")
    dq0 = V.per_joint(table, "dq", n, 0.0, file=file, prefix="initial")
    return q0, dq0, table


def parse_x_esn0(init: dict, size: int, file: str) -> list[float]:
    return V.per_joint(init, "x_esn", size, 0.0, file=file, prefix="initial")


def parse_funnel_table(table: Any, n: int, file: str, prefix: str, defaults, parameters: dict | None = None):
    return parse_funnel(table, n, file, prefix, defaults, parameters)


def parse_design(table: Any, approx: Any, file: str) -> DesignSpec:
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


def check_settings_match(raw: dict, chosen: str, file: str) -> None:
    """A settings section of another approximator type (e.g. `[rbf]` with type "esn") is an input error."""
    for entry in APPROXIMATORS:
        section = getattr(entry.obj, "SETTINGS", None)
        if section and section in raw and entry.name != chosen:
            raise InputError(f"gives settings of approximator '{entry.name}', but approximator.type is '{chosen}'",
                             file=file, key=section, expected=f'approximator.type = "{entry.name}", or no [{section}]')


def parse_esn(table: Any, file: str) -> ESNSpec:
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


def parse_plant(table: Any, n: int, file: str, model, base_dir: Path | None = None) -> PlantSpec:
    p = "plant"
    V.check_keys(table, ["viscous", "coulomb", "disturbance", "dead_zone", "mass_scale", "parameters", "coriolis",
                         "disturbance_scale", "engine", "mujoco"], file=file, prefix=p)
    engine = V.get_str(table, "engine", "symfunnel", file=file, prefix=p)
    ENGINES.get(engine, file=file, key="plant.engine")
    if engine != "symfunnel":
        check_engine_model(model, engine, file=file, key="plant.engine")
    mujoco = parse_mujoco(table.get("mujoco", {}), n, file, base_dir)
    coriolis = V.get_str(table, "coriolis", "christoffel", file=file, prefix=p, choices=["christoffel", "model"])
    viscous = V.per_joint(table, "viscous", n, 0.0, file=file, prefix=p, minimum=0)
    coulomb = V.per_joint(table, "coulomb", n, 0.0, file=file, prefix=p, minimum=0)
    names = {"t"} | set(model.coordinates) | {"d" + c for c in model.coordinates}
    disturbance = expression_list(table, "disturbance", n, file, p, names, default="0")
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
    return PlantSpec(viscous, coulomb, disturbance, dz, mass_scale, params, coriolis, d_scale, engine, mujoco)


#: the keys of `[plant.mujoco]`
MUJOCO_KEYS = ["mass_scale", "damping", "armature", "urdf_dynamics", "substeps", "timestep", "integrator", "mjcf"]
#: MuJoCo's integrators the engine loop offers (deployed.engine says how each treats the friction)
MUJOCO_INTEGRATORS = ["implicitfast", "RK4"]


def parse_mujoco(table: Any, n: int, file: str, base_dir: Path | None = None) -> MujocoSpec:
    """`[plant.mujoco]`: engine-only mass scale, damping and armature per joint, the URDF's joint dynamics, the step,
    and the user's own MJCF of the robot (a path relative to the scenario's directory, checked to exist)."""
    p = "plant.mujoco"
    V.check_keys(table, MUJOCO_KEYS, file=file, prefix=p)
    mjcf = None
    if "mjcf" in table:
        rel = V.get_str(table, "mjcf", "", file=file, prefix=p)
        path = Path(base_dir if base_dir is not None else ".") / rel
        from ..core.inputs import read_input
        try:        # read here so that a campaign's fingerprint covers it (Scenario.inputs); MuJoCo reads it again
            read_input(path, expected="an MJCF file")
        except InputError as exc:
            raise InputError(f"MJCF file '{path}': {exc.reason}", file=file, key=p + ".mjcf",
                             expected="a path to an MJCF file of the robot, relative to the scenario file's "
                                      "directory") from None
        mjcf = str(path.resolve())
    if "substeps" in table and "timestep" in table:
        raise InputError("is given together with plant.mujoco.timestep", file=file, key=p + ".substeps",
                         expected="either substeps (MuJoCo steps per sample period) or timestep, not both")
    opt = {}
    for k, strict in (("mass_scale", True), ("damping", False), ("armature", False)):
        if k in table:
            opt[k] = V.per_joint(table, k, n, file=file, prefix=p, minimum=0, strict_min=strict)
    return MujocoSpec(
        **opt, urdf_dynamics=V.get_bool(table, "urdf_dynamics", True, file=file, prefix=p),
        substeps=V.get_int(table, "substeps", None, file=file, prefix=p, minimum=1, maximum=100000)
        if "substeps" in table else None,
        timestep=V.get_float(table, "timestep", None, file=file, prefix=p, minimum=0, strict_min=True, maximum=1.0)
        if "timestep" in table else None,
        integrator=V.get_str(table, "integrator", MujocoSpec.integrator, file=file, prefix=p,
                             choices=MUJOCO_INTEGRATORS), mjcf=mjcf)


def parse_simulation(table: Any, file: str) -> SimulationSpec:
    p = "simulation"
    V.check_keys(table, ["t_final", "dt", "integrator", "rtol", "atol", "smoothing_width",
                         "convergence_widths", "wall_limit", "rk_substeps", "max_step", "settle_time"], file=file,
                 prefix=p)
    d = SimulationSpec()
    t_final = V.get_float(table, "t_final", d.t_final, file=file, prefix=p, minimum=0, strict_min=True,
                          maximum=1e6)
    dt = V.get_float(table, "dt", d.dt, file=file, prefix=p, minimum=0, strict_min=True)
    if t_final / dt > 1e6:
        raise InputError(f"gives {t_final / dt:.3g} output points", file=file, key="simulation.dt",
                         expected="at most 1e6 output points (t_final/dt)")
    V.check_horizon(t_final, dt, key="simulation.t_final", file=file)
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
                               strict_min=True, maximum=MAX_SECONDS),
        rk_substeps=V.get_int(table, "rk_substeps", d.rk_substeps, file=file, prefix=p, minimum=1,
                              maximum=10000),
        max_step=V.get_float(table, "max_step", d.max_step, file=file, prefix=p, minimum=0),
        settle_time=(None if "settle_time" not in table else
                     V.get_float(table, "settle_time", 0.0, file=file, prefix=p, minimum=0, maximum=t_final)),
    )


def parse_audit(table: Any, n: int, file: str, model) -> AuditSpec:
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
        lower, upper = parse_ranges(table["joint_range"], n, file, "audit.joint_range")
    return AuditSpec(
        samples=V.get_int(table, "samples", d.samples, file=file, prefix=p, minimum=1000, maximum=10**7),
        claim_samples=V.get_int(table, "claim_samples", d.claim_samples, file=file, prefix=p, minimum=200,
                                maximum=10**7),
        seed=V.get_int(table, "seed", d.seed, file=file, prefix=p, minimum=0, maximum=2**63 - 1),
        joint_lower=lower, joint_upper=upper,
        velocity_range=V.per_joint(table, "velocity_range", n, 2.0, file=file, prefix=p, minimum=0,
                                   strict_min=True),
        tolerance=V.get_float(table, "tolerance", d.tolerance, file=file, prefix=p, minimum=0, strict_min=True),
        sympy_timeout=V.get_float(table, "sympy_timeout", d.sympy_timeout, file=file, prefix=p, minimum=0,
                                  maximum=MAX_SECONDS),
    )


def parse_ranges(value: Any, n: int, file: str, key: str):
    """[lo, hi] for every joint, or an array of n [lo, hi] pairs."""
    def pair(v, k):
        if not (isinstance(v, list) and len(v) == 2):
            raise InputError(f"is {describe(v)}", file=file, key=k, expected="a pair [lower, upper]")
        lo = V.as_float(v[0], file=file, key=k + "[0]")
        hi = V.as_float(v[1], file=file, key=k + "[1]")
        if not lo < hi:
            raise InputError(f"is [{lo:g}, {hi:g}]", file=file, key=k, expected="lower < upper")
        return lo, hi
    if isinstance(value, list) and len(value) == 2 and not isinstance(value[0], list):
        lo, hi = pair(value, key)
        return [lo] * n, [hi] * n
    if not isinstance(value, list) or len(value) != n:
        raise InputError(f"is {describe(value)}", file=file, key=key,
                         expected=f"a pair [lower, upper] or {n} pairs")
    pairs = [pair(v, f"{key}[{i}]") for i, v in enumerate(value)]
    return [a for a, _ in pairs], [b for _, b in pairs]

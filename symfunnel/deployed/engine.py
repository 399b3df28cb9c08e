"""The sampled-data loop with a physics engine as the robot: the compiled generated C step drives MuJoCo.

The loop is the one of `deployed.loop` (measurement noise, quantisation, the step at every sample, zero-order hold,
optional one-sample delay, saturation inside the step), run in C (templates/mujoco_loop.c): between samples
MuJoCo advances `substeps` times (`mj_step`) at timestep h / substeps under the held torque. What MuJoCo does not
model is applied exactly as in symfunnel's plant, from the same SX (`plant.equations.plant_forces`): the dead
zone on the held torque (held too, so exact once per period), the viscous and smoothed Coulomb friction and the
disturbance d(t, q, dq) as a passive force evaluated at every step or stage (MuJoCo's `mjcb_passive`). The plant's
mass scale and the engine-only `[plant.mujoco]` mismatch change the engine's bodies and joints; the controller
keeps its nominal model.

The integrator (`[plant.mujoco] integrator`):
* `implicitfast` (the default, MuJoCo's own recommendation): at every step the callback puts the slope of the
  friction and disturbance in each joint's velocity (>= 0, from the same SX by automatic differentiation) into the
  engine's joint damping and cancels the damper force that damping makes, so the force is unchanged and MuJoCo's
  implicit step uses the slope as its derivative: a linearly implicit Euler step, stable on the stiff smoothed
  Coulomb friction at any step. First order; h/substeps <= 0.25 ms by default (accuracy, not stability, bounds it).
* `RK4`: explicit, 4th order; by default the smallest number of steps keeping h / substeps * rho <= 1.5 (and
  h / substeps <= 1 ms), rho the largest spectral radius of M_engine(q)^-1 (D + the engine's joint damping) over the
  reference's configurations: inside RK4's real stability interval (2.78).
`[plant.mujoco] substeps` or `timestep` (which must divide the period) overrides either rule.
"""

from __future__ import annotations

import ctypes
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from ..core.errors import InputError

if TYPE_CHECKING:
    from ..plant.mujoco import Engine

__all__ = ["EngineSetup", "engine_setup", "engine_substeps", "run_engine_loop", "EngineRunPlant"]

#: one engine loop at a time per process: MuJoCo's passive-force callback is a process-wide pointer
_LOCK = threading.Lock()
#: RK4's step times the stiffest rate kept below this (its real stability interval ends at 2.78)
STABILITY = 1.5
MAX_SUBSTEP = 1e-3
#: implicitfast's default step: first order, so accuracy bounds it (on arm7 the minimum rate found at 0.5 ms and
#: finer equals RK4's, at 1 ms it is 14 % higher; 0.25 ms keeps a factor 2)
MAX_SUBSTEP_IMPLICIT = 2.5e-4
#: `[plant.mujoco] integrator` -> MuJoCo's mjtIntegrator member
INTEGRATORS = {"implicitfast": "mjINT_IMPLICITFAST", "RK4": "mjINT_RK4"}


@dataclass
class EngineRunPlant:
    """One run's plant on the engine: the plant quantities (layout `plant_parameters`) and the engine-only settings."""

    p: np.ndarray
    mujoco: object                    # a scenario.document.MujocoSpec
    q0: np.ndarray
    dq0: np.ndarray


class _Fun(ctypes.Structure):
    _fields_ = [("f", ctypes.c_void_p), ("arg", ctypes.c_void_p), ("res", ctypes.c_void_p),
                ("iw", ctypes.c_void_p), ("w", ctypes.c_void_p)]


def _fun_struct(cf) -> _Fun:
    return _Fun(ctypes.cast(cf._f, ctypes.c_void_p), ctypes.addressof(cf._arg), ctypes.addressof(cf._res),
                ctypes.addressof(cf._iw), ctypes.addressof(cf._w))


@dataclass
class EngineSetup:
    """What every engine run of one scenario shares: the loaded engine, the compiled plant-force functions with the
    plant quantities as a parameter vector (so a sweep's runs reuse them), and the compiled loop."""

    engine: Engine
    p_names: list[str]
    p0: np.ndarray
    force: object                      # _CFun: (t, q, dq, p) -> (-(friction + disturbance), its slopes in dq)
    force_sx: ca.Function               # the same as a casadi.Function (to see whether a run's force is zero)
    applied: object | None             # _CFun: (tau, p) -> torque after the dead zone (None: no dead zone)
    loop: object                       # the compiled mujoco_loop.c
    mj_lib: object                     # libmujoco, as loaded by the mujoco package
    extra: dict = field(default_factory=dict)


def _libmujoco(mujoco):
    """The libmujoco the Python bindings loaded (the same handle: its globals are the ones mj_step uses)."""
    pkg = Path(mujoco.__file__).parent
    cands = sorted(pkg.glob("libmujoco.so*")) + sorted(pkg.glob("libmujoco*.dylib"))
    if not cands:
        raise InputError(f"has no libmujoco in {pkg}", key="plant.engine",
                         expected="the mujoco wheel's shared library (pip install 'symfunnel[mujoco]')")
    return ctypes.CDLL(str(cands[0]))


def _compile_loop(mujoco, on_build=None):
    from ..core.ccompile import SHARED_FLAGS, compile_cached
    from ..emit.c import template
    include = str(Path(mujoco.HEADERS_DIR).parent)
    src = template("mujoco_loop.c").replace("@MJVERSION@", mujoco.mj_versionString())
    built = compile_cached({"mujoco_loop.c": src}, ["mujoco_loop.c"], "libsfs_mjloop.so",
                           SHARED_FLAGS + ("-I" + include,), on_build=on_build)
    lib = ctypes.CDLL(str(built.path))
    lib.sfs_mj_header_version.restype = ctypes.c_int
    if lib.sfs_mj_header_version() != mujoco.mj_version():
        raise InputError(f"MuJoCo's headers (version {lib.sfs_mj_header_version()}) do not match its library "
                         f"({mujoco.mj_version()})", key="plant.engine",
                         expected="one consistent mujoco installation")
    vp = ctypes.c_void_p
    f = lib.sfs_mj_loop
    f.restype = ctypes.c_int
    f.argtypes = [vp, vp, vp, vp, vp, vp, vp, ctypes.c_int, vp, vp, ctypes.c_int, vp, vp, ctypes.c_long,
                  ctypes.c_double, vp, vp, ctypes.c_double, ctypes.c_int, ctypes.c_int, vp, vp, vp, vp]
    lib.sfs_mj_set_slopes.argtypes = [ctypes.c_int, vp, ctypes.c_int]
    lib.sfs_mj_last_warning.restype = ctypes.c_char_p
    lib.sfs_mj_warning_count.restype = ctypes.c_int
    return lib


def engine_setup(scenario, on_build=None) -> EngineSetup:
    """The scenario's EngineSetup, built once per Scenario object (the rate search and a sweep reuse it)."""
    cache = scenario.__dict__.setdefault("_engine_setup", {})
    width = float(scenario.simulation.smoothing_width)
    if width in cache:
        return cache[width]
    from ..plant.mujoco import load_engine, require_mujoco
    from ..plant.equations import plant_forces, plant_parameters
    from .cfun import _compiled
    mujoco = require_mujoco(file=scenario.file)
    engine = load_engine(scenario.model, file=scenario.file, mjcf=scenario.plant.mujoco.mjcf)
    names, p0 = plant_parameters(scenario)
    n = scenario.n
    q, dq, tau = ca.SX.sym("q", n), ca.SX.sym("dq", n), ca.SX.sym("tau", n)
    t, p = ca.SX.sym("t"), ca.SX.sym("p", len(names))
    parts = plant_forces(scenario, q, dq, t, tau, width, p)
    resist = parts["friction"] + parts["disturbance"]
    # per joint, the resisting force's slope in dq (the diagonal implicitfast integrates implicitly; >= 0)
    slope = ca.fmax(0, ca.diag(ca.jacobian(resist, dq)))
    fsx = ca.Function("sfs_mj_force", [t, q, dq, p], [-resist, slope])
    force = _compiled(fsx, on_build=on_build)
    applied = None
    if scenario.plant.dead_zone is not None:
        applied = _compiled(ca.Function("sfs_mj_applied", [tau, p], [parts["tau_applied"]]), on_build=on_build)
    setup = EngineSetup(engine, names, p0, force, fsx, applied, _compile_loop(mujoco, on_build), _libmujoco(mujoco))
    cache[width] = setup
    return setup


def _force_is_zero(setup: EngineSetup, p: np.ndarray) -> bool:
    """True when this run's friction and disturbance vanish identically (the callback can be left out)."""
    f = setup.force_sx
    t, q, dq = (ca.SX.sym(s, f.size1_in(i)) for i, s in enumerate(("t", "q", "dq")))
    expr = f(t, q, dq, ca.DM(p))[0]
    return bool(ca.SX(expr).is_zero())


def configure(setup: EngineSetup, run: EngineRunPlant) -> None:
    """Put one run's plant into the engine: mass scale (the plant's times [plant.mujoco]'s), damping, armature."""
    mj = run.mujoco
    s = float(run.p[setup.p_names.index("plant.mass_scale")])
    scale = s * (np.ones(setup.engine.n) if mj.mass_scale is None else np.asarray(mj.mass_scale, dtype=float))
    setup.engine.configure(mass_scale=scale, damping=mj.damping, armature=mj.armature,
                           urdf_dynamics=mj.urdf_dynamics)


#: the most MuJoCo steps per sample period (as plant.mujoco.substeps allows)
MAX_ENGINE_SUBSTEPS = 100000


def engine_substeps(setup: EngineSetup, run: EngineRunPlant, h: float, *, width: float, reference=None,
                    file: str | None = None) -> tuple[int, str]:
    """MuJoCo steps per sample period h and where the number comes from (the engine configured for the run)."""
    mj = run.mujoco
    if mj.substeps is not None:
        return int(mj.substeps), "plant.mujoco.substeps"
    if mj.timestep is not None:
        k = h / mj.timestep
        if abs(k - round(k)) > 1e-9 * max(k, 1.0) or round(k) < 1:
            raise InputError(f"is {mj.timestep:g} s, which does not divide the sample period {h:g} s "
                             f"({k:.6g} steps)", file=file, key="plant.mujoco.timestep",
                             expected="a MuJoCo step h/k for an integer k >= 1, or plant.mujoco.substeps")
        if round(k) > MAX_ENGINE_SUBSTEPS:           # the cap plant.mujoco.substeps has, for the same work
            raise InputError(f"is {mj.timestep:g} s, {k:.3g} MuJoCo steps per sample period of {h:g} s",
                             file=file, key="plant.mujoco.timestep",
                             expected=f"at most {MAX_ENGINE_SUBSTEPS} steps per period (a timestep of at least "
                             f"{h / MAX_ENGINE_SUBSTEPS:.3g} s)")
        return int(round(k)), "plant.mujoco.timestep"
    if mj.integrator == "implicitfast":
        return max(1, int(math.ceil(h / MAX_SUBSTEP_IMPLICIT - 1e-9))), (
            f"implicitfast accuracy: h/substeps <= {MAX_SUBSTEP_IMPLICIT * 1e3:g} ms (the friction's slopes implicit)")
    rho = stiffest_rate(setup, run, width=width, reference=reference)
    h_max = min(MAX_SUBSTEP, STABILITY / rho if rho > 0 else MAX_SUBSTEP)
    return max(1, int(math.ceil(h / h_max - 1e-9))), (
        f"RK4 stability: h/substeps <= min(1 ms, {STABILITY:g}/rho), rho = {rho:.4g} 1/s")


def friction_slopes(setup: EngineSetup, run: EngineRunPlant, *, width: float) -> np.ndarray:
    """Per joint, the friction's largest slope in dq: viscous + Coulomb / width (smoothed Coulomb's slope at 0;
    without smoothing Coulomb is a jump, and only the viscous part is linear)."""
    n = setup.engine.n
    idx = {k: i for i, k in enumerate(setup.p_names)}
    visc = np.array([run.p[idx[f"plant.viscous[{j + 1}]"]] for j in range(n)])
    coul = np.array([run.p[idx[f"plant.coulomb[{j + 1}]"]] for j in range(n)])
    return visc + (coul / width if width > 0 else 0.0)


def stiffest_rate(setup: EngineSetup, run: EngineRunPlant, *, width: float, reference=None) -> float:
    """The largest spectral radius of M_engine(q)^-1 D at the initial and the reference's configurations, D the
    diagonal of friction slopes (`friction_slopes`) and joint damping."""
    from ..plant.mujoco import require_mujoco
    mujoco = require_mujoco()
    eng = setup.engine
    n = eng.n
    D = friction_slopes(setup, run, width=width) + np.asarray(eng.model.dof_damping)[eng.dadr]
    if not np.any(D > 0):
        return 0.0
    qs = [np.asarray(run.q0, dtype=float)] + list(reference if reference is not None else [])
    data = mujoco.MjData(eng.model)
    rho = 0.0
    for q in qs:
        M, _ = eng.mass_and_bias(data, q, np.zeros(n))
        rho = max(rho, float(np.max(np.abs(np.linalg.eigvals(np.linalg.solve(M, np.diag(D)))))))
    return rho


def run_engine_loop(setup: EngineSetup, run: EngineRunPlant, controller, *, n: int, K: int, h: float, nq, ndq,
                    resolution: float, delay: int, stop: bool, X: np.ndarray, TAU: np.ndarray, width: float,
                    reference=None, file: str | None = None) -> dict:
    """The C loop on the engine, configured for the run (substeps by `engine_substeps`); X[0] is set here from the
    run's initial state. Returns the loop's code, where it ended, the first sample outside and the engine's notes."""
    from ..plant.mujoco import require_mujoco
    mujoco = require_mujoco()
    eng = setup.engine
    model = eng.model
    with _LOCK:
        configure(setup, run)
        engine_only = eng.engine_only()
        substeps, why = engine_substeps(setup, run, h, width=width, reference=reference, file=file)
        integrator = run.mujoco.integrator
        model.opt.timestep = h / substeps
        model.opt.integrator = int(getattr(mujoco.mjtIntegrator, INTEGRATORS[integrator]))
        p = np.asarray(run.p, dtype=float)
        use_force = not _force_is_zero(setup, p)
        setup.force.inputs[3][:] = p
        base = np.ascontiguousarray(np.asarray(model.dof_damping)[eng.dadr], dtype=float)
        setup.loop.sfs_mj_set_slopes(int(use_force and integrator == "implicitfast"), base.ctypes.data, n)
        data = mujoco.MjData(model)
        data.qpos[eng.qadr] = run.q0
        data.qvel[eng.dadr] = run.dq0
        X[0, :n], X[0, n:] = run.q0, run.dq0
        force = _fun_struct(setup.force) if use_force else None
        applied = None
        if setup.applied is not None:
            setup.applied.inputs[1][:] = p
            applied = _fun_struct(setup.applied)
        lib = setup.loop
        mjl = setup.mj_lib
        vp = ctypes.c_void_p
        cb_slot = ctypes.addressof(vp.in_dll(mjl, "mjcb_passive"))
        warn_slot = ctypes.addressof(vp.in_dll(mjl, "mju_user_warning"))
        qadr, dadr = np.ascontiguousarray(eng.qadr, dtype=np.int32), np.ascontiguousarray(eng.dadr, dtype=np.int32)
        nqa = None if nq is None else np.ascontiguousarray(nq)
        ndqa = None if ndq is None else np.ascontiguousarray(ndq)
        k_end, outside = ctypes.c_long(), ctypes.c_long()
        rc = lib.sfs_mj_loop(ctypes.cast(controller._step, vp), controller._state_p,
                             ctypes.cast(mjl.mj_step, vp), cb_slot, warn_slot, model._address, data._address,
                             int(substeps), qadr.ctypes.data, dadr.ctypes.data, n,
                             None if applied is None else ctypes.addressof(applied),
                             None if force is None else ctypes.addressof(force), K, h,
                             None if nqa is None else nqa.ctypes.data, None if ndqa is None else ndqa.ctypes.data,
                             float(resolution), int(delay), int(bool(stop)), X.ctypes.data, TAU.ctypes.data,
                             ctypes.byref(k_end), ctypes.byref(outside))
        warnings = int(lib.sfs_mj_warning_count())
        last = lib.sfs_mj_last_warning().decode(errors="replace").strip()
    return {"rc": int(rc), "k_end": int(k_end.value), "outside": None if outside.value < 0 else int(outside.value),
            "warnings": warnings, "last_warning": last, "engine_only": engine_only, "force_callback": use_force,
            "substeps": substeps, "substeps_rule": why, "integrator": integrator}

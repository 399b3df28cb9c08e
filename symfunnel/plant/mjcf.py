"""A user's own MJCF of the scenario's robot as the engine (`[plant.mujoco] mjcf`): read by MuJoCo, made a
dynamics-only model in the scenario's world, and its joints checked against symfunnel's by name, type and axis.

The MJCF is the user's model, not a translation of ours: its bodies, frames, inertias and joint order are its own
(MuJoCo's order need not be symfunnel's: coordinates are matched by name, never by position). What is changed, as
for a URDF (plant.mujoco), and listed in the engine's notes: static bodies fused into their parent (`fusestatic`,
so that a per-joint mass scale reaches every link a joint carries); the scenario's gravity; contacts, joint
limits, equality constraints, actuators, sleeping and automatic reset disabled; fluid forces (density, viscosity,
wind) and joint springs removed. What is kept: the MJCF's joint damping, friction loss and armature, which are
dynamics of the engine the controller's model does not have (reported like a URDF's `<dynamics>`).

A joint the model has and the MJCF has not, another type, another axis at q = 0 (in the world frame, so a base
mounted differently is found too), a `ref` other than 0 or an extra degree of freedom are InputErrors at
`plant.mujoco.mjcf`; everything else the agreement check (`plant.engine_agreement`) compares by computation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import InputError

__all__ = ["MJCF_KEY", "load_mjcf", "check_axes", "mjcf_joint_error", "mjcf_extra_error"]

#: the scenario key every error about a user's MJCF points to
MJCF_KEY = "plant.mujoco.mjcf"
#: a joint axis differs when the cosine of the angle between the two unit axes is below this
AXIS_COS = 1.0 - 1e-9
_EXPECTED = "an MJCF of the scenario's robot: a hinge or slide joint named as each movable joint of the model"


def load_mjcf(mujoco, path, *, gravity, timestep: float, flags: dict, file: str) -> tuple[object, list[str]]:
    """The compiled MjModel of the MJCF at `path` in the scenario's world (see the module doc) and what was changed,
    as sentences; MuJoCo's refusal is an InputError naming the scenario `file` and plant.mujoco.mjcf."""
    path = Path(path)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as exc:  # noqa: BLE001 - MuJoCo's parser raises ValueError, missing includes others
        raise InputError(f"MuJoCo refuses {path.name}: {' '.join(str(exc).split())}", file=file, key=MJCF_KEY,
                         expected="an MJCF file MuJoCo loads") from None
    changed = []
    fused = [b.name or "(unnamed)" for b in spec.bodies[1:] if len(b.joints) == 0]
    if fused:
        changed.append("static bodies fused into their parent (fusestatic): " + ", ".join(fused))
    spec.compiler.fusestatic = True
    opt = spec.option
    fluid = [k for k in ("density", "viscosity") if float(getattr(opt, k)) != 0.0]
    if np.any(np.asarray(opt.wind) != 0.0):
        fluid.append("wind")
    if fluid:
        changed.append("fluid forces removed (dynamics only): " + ", ".join(fluid))
    opt.density, opt.viscosity, opt.wind = 0.0, 0.0, [0.0, 0.0, 0.0]
    if np.any(np.asarray(opt.gravity) != np.asarray(gravity, dtype=float)):
        changed.append(f"gravity {_vec(opt.gravity)} replaced by the model's {_vec(gravity)}")
    opt.gravity = [float(g) for g in gravity]
    opt.timestep = float(timestep)
    opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)
    for name, how in flags.items():
        assert how == "disable", how
        bit = getattr(mujoco.mjtDisableBit, "mjDSBL_" + name.upper(), None)
        if bit is not None:
            opt.disableflags |= int(bit)
        else:                                 # sleeping is an enable flag
            opt.enableflags &= ~int(getattr(mujoco.mjtEnableBit, "mjENBL_" + name.upper()))
    try:
        mj = spec.compile()
    except Exception as exc:  # noqa: BLE001 - the compiler's refusal (masses, inertias, references)
        raise InputError(f"MuJoCo refuses {path.name}: {' '.join(str(exc).split())}", file=file, key=MJCF_KEY,
                         expected="an MJCF file MuJoCo compiles") from None
    springs = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(mj.njnt)
               if float(mj.jnt_stiffness[j]) != 0.0]
    if springs:
        changed.append("joint springs removed (as in symfunnel's model): " + ", ".join(springs))
    return mj, changed


def check_axes(mujoco, mj, tree, names: list[str], jid: list[int], *, mjcf, file: str) -> None:
    """Each joint's zero and axis at q = 0, in the world frame, as in symfunnel's model (`tree`'s bodies)."""
    from ..model.tree import bodies_from_tree
    bodies = bodies_from_tree(tree)
    Rw: list[np.ndarray] = []
    for b in bodies:
        Rw.append((Rw[b.parent] if b.parent >= 0 else np.eye(3)) @ b.R0)
    data = mujoco.MjData(mj)
    data.qpos[:] = 0.0
    mujoco.mj_kinematics(mj, data)
    name = Path(mjcf).name
    for k, (nm, j) in enumerate(zip(names, jid)):
        ref = float(mj.qpos0[mj.jnt_qposadr[j]])
        if ref != 0.0:
            raise InputError(f"joint '{nm}' of {name} has ref = {ref:g} (MuJoCo's zero is not the model's)",
                             file=file, key=MJCF_KEY, expected="ref = 0 on every joint (the model's zero pose)")
        ours = Rw[k] @ np.asarray(bodies[k].joint.axis, dtype=float)
        ours = ours / np.linalg.norm(ours)
        theirs = np.asarray(data.xaxis[j], dtype=float)
        if float(ours @ theirs) < AXIS_COS:
            raise InputError(f"joint '{nm}' of {name} has axis {_vec(theirs)} at q = 0 (world frame), the model "
                             f"{_vec(ours)}", file=file, key=MJCF_KEY,
                             expected="each joint's axis and direction as in the model, in the same world frame")


def mjcf_joint_error(mujoco, mj, nm: str, j: int, names: list[str], *, mjcf, file: str) -> InputError:
    """The error for a model joint the MJCF lacks (j < 0) or has with another type."""
    from ..core.validate import did_you_mean
    name = Path(mjcf).name
    if j < 0:
        mj_names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, i) or "" for i in range(mj.njnt)]
        return InputError(f"{name} has no joint '{nm}'{did_you_mean(nm, mj_names)}", file=file, key=MJCF_KEY,
                          expected=_EXPECTED + " (" + ", ".join(names) + ")")
    kind = {int(v): k for k, v in (("free", mujoco.mjtJoint.mjJNT_FREE), ("ball", mujoco.mjtJoint.mjJNT_BALL),
                                   ("slide", mujoco.mjtJoint.mjJNT_SLIDE), ("hinge", mujoco.mjtJoint.mjJNT_HINGE))}
    return InputError(f"joint '{nm}' of {name} is a {kind.get(int(mj.jnt_type[j]), '?')} joint, not the model's "
                      "joint type", file=file, key=MJCF_KEY,
                      expected="a hinge joint for a revolute or continuous joint, a slide joint for a prismatic one")


def mjcf_extra_error(mujoco, mj, names: list[str], *, mjcf, file: str) -> InputError:
    """The error for an MJCF with degrees of freedom the model has not."""
    extra = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, i) or f"(unnamed joint {i})" for i in range(mj.njnt)
             if mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, i) not in names]
    return InputError(f"{Path(mjcf).name} has {mj.nv} degrees of freedom, the model {len(names)} (joints not in the "
                      f"model: {', '.join(extra)})", file=file, key=MJCF_KEY,
                      expected="exactly the model's movable joints (" + ", ".join(names) + ")")


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in np.ravel(v)) + ")"

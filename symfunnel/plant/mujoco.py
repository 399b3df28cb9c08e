"""MuJoCo as the robot: a scenario's URDF read by MuJoCo's own parser (planar and dh models: MJCF written from the link
tree), as a dynamics-only model whose mass matrix, bias forces and engine-only dynamics symfunnel can compare and
change.

What is done to the robot description, and why (each is a MuJoCo convention that would otherwise change the dynamics):

* `<visual>` and `<collision>` are removed from the URDF text (meshes are `package://` paths MuJoCo cannot resolve,
  and a dynamics-only plant has no contacts); the `<inertial>` data stay as written.
* Any `<mujoco>` extension of the URDF is replaced by ours: `fusestatic` (fixed links merged into their parent body,
  exactly as symfunnel lumps them), `balanceinertia`, `inertiafromgeom` and `boundmass`/`boundinertia` off (MuJoCo
  never alters an inertia silently), `strippath` off; and an `<option>` with RK4, the model's gravity (MuJoCo's
  default (0, 0, -9.81) is wrong for a planar model) and contacts, joint limits, equality constraints, actuation
  and sleeping disabled, and `autoreset` disabled so that a diverging run gives non-finite states instead of a
  silent reset to the initial pose.
* A principal moment of inertia of (near) zero, which MuJoCo refuses (every planar link has I_xx = 0, a thin rod
  too), is raised to 1e-12 times the largest moment plus 1e-14 along its own axis only (listed in `notes.floored`).
* The joints of `model.fixed_joints` (which `init` fills with a URDF's mimic joints) are made `type="fixed"` in the
  text, at their zero position, as symfunnel's parser does: MuJoCo sees the same movable joints (listed in
  `notes.held`). Without this MuJoCo 4 would keep them as degrees of freedom that symfunnel's model does not have.
* `<mimic>` is removed from the text (MuJoCo 4's URDF parser turns it into a joint equality constraint, which a
  held joint would leave dangling); a mimic joint still movable is its own coordinate, as in symfunnel's model:
  listed.
* `<dynamics damping friction>` become MuJoCo's `dof_damping` and `dof_frictionloss`: dynamics of the engine that
  the controller's model does not have; kept unless `urdf_dynamics = false`, and always reported.
* Joints are matched to symfunnel's coordinates by name (never by position): MuJoCo orders a URDF's joints as
  symfunnel does (depth-first, children in joint document order, fixed links fused in place), but a user's own
  MJCF (`[plant.mujoco] mjcf`, plant.mjcf) orders them as it likes.

MuJoCo's message for a file it refuses, a missing `mujoco` package and a model it cannot load are InputErrors
(exit 2, one line). The engine's M and bias forces are read with `mj_fullM` (MuJoCo >= 4: `mjData.qM` is gone).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import InputError
from .engines import MIN_VERSION, require_mujoco

__all__ = ["require_mujoco", "Engine", "EngineNotes", "load_engine", "prepare_urdf", "mjcf_from_tree",
           "agreement", "ENGINE_KEY", "MIN_VERSION"]

#: the scenario key every engine error points to
ENGINE_KEY = "plant.engine"

#: compiler attributes that make MuJoCo read the inertial data as written
COMPILER = {"angle": "radian", "fusestatic": "true", "discardvisual": "true", "balanceinertia": "false",
            "inertiafromgeom": "false", "boundmass": "0", "boundinertia": "0", "strippath": "false",
            "autolimits": "true"}
#: a dynamics-only plant: no contacts, limits, equality constraints, actuators, sleeping or automatic reset
FLAGS = {"contact": "disable", "limit": "disable", "equality": "disable", "actuation": "disable",
         "sleep": "disable", "autoreset": "disable"}
#: principal moments below REL_FLOOR * largest + ABS_FLOOR are raised to it (MuJoCo's mjMINVAL is 1e-15)
REL_FLOOR, ABS_FLOOR = 1e-12, 1e-14


@dataclass
class EngineNotes:
    """What loading changed or found in the robot description: shown in reports and check details, never silent."""

    source: str                                              # how the model reached MuJoCo
    file: str = ""
    removed_geometry: int = 0                                # <visual>/<collision> elements removed
    mimic: list[str] = field(default_factory=list)           # movable joints whose <mimic> is ignored
    held: list[str] = field(default_factory=list)            # movable joints of the URDF held fixed (fixed_joints)
    fused: list[str] = field(default_factory=list)           # links merged into their parent body (fixed joints)
    floored: dict[str, float] = field(default_factory=dict)  # link -> amount added to its smallest moments
    replaced_extension: bool = False                         # the URDF had a <mujoco> element of its own
    urdf_dynamics: dict[str, dict] = field(default_factory=dict)   # joint -> {"damping", "friction"} of the URDF
    changed: list[str] = field(default_factory=list)         # what was changed in a user's MJCF (plant.mjcf)

    def lines(self) -> list[str]:
        """The notes as short sentences."""
        out = [self.source]
        if self.removed_geometry:
            out.append(f"{self.removed_geometry} <visual>/<collision> element(s) removed (dynamics only, no contacts)")
        if self.fused:
            out.append("fixed links merged into their parent body (fusestatic): " + ", ".join(self.fused))
        if self.held:
            out.append("joints held fixed at 0 (model.fixed_joints, as in symfunnel's model): " + ", ".join(self.held))
        if self.mimic:
            out.append("<mimic> ignored (each is its own coordinate, as in symfunnel's model): "
                       + ", ".join(self.mimic))
        if self.floored:
            out.append("zero principal moments raised for MuJoCo: " + ", ".join(
                f"{k} (+{v:.2g} kg m^2)" for k, v in self.floored.items()))
        out.extend(self.changed)
        if self.replaced_extension:
            out.append("the URDF's own <mujoco> element replaced by symfunnel's compiler and option settings")
        return out


def _inertia_floor(I: np.ndarray) -> tuple[np.ndarray, float]:
    """The tensor with each principal moment below the floor raised to it (along its own axis), and the largest
    raise."""
    lam, V = np.linalg.eigh(0.5 * (I + I.T))
    floor = REL_FLOOR * max(float(lam[-1]), 0.0) + ABS_FLOOR
    add = np.maximum(floor - lam, 0.0)
    return I + (V * add) @ V.T, float(add.max())


def _xml_floats(text: str | None, default: float = 0.0) -> float:
    try:
        return float(text) if text is not None else default
    except ValueError:
        return default


def prepare_urdf(path, *, gravity, timestep: float = 1e-3, point_masses: bool = False,
                 fixed=()) -> tuple[str, EngineNotes]:
    """The URDF's text ready for MuJoCo's parser (see the module doc) and the notes of what was changed; the joints
    named in `fixed` (the scenario's model.fixed_joints) are made fixed joints at their zero position."""
    path = Path(path)
    root = ET.fromstring(path.read_bytes())
    notes = EngineNotes(source=f"the URDF {path.name}, read by MuJoCo's own URDF parser", file=str(path))
    fixed = set(fixed)
    for j in root.findall("joint"):
        if j.get("name") in fixed and j.get("type") != "fixed":
            j.set("type", "fixed")
            for tag in ("axis", "limit", "dynamics", "calibration", "safety_controller"):
                for el in j.findall(tag):
                    j.remove(el)
            notes.held.append(j.get("name"))
    fixed_children = {j.find("child").get("link") for j in root.findall("joint")
                      if j.get("type") == "fixed" and j.find("child") is not None}
    notes.fused = [lk.get("name") for lk in root.findall("link") if lk.get("name") in fixed_children]
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for el in link.findall(tag):
                link.remove(el)
                notes.removed_geometry += 1
        inert = link.find("inertial")
        ie = None if inert is None else inert.find("inertia")
        if ie is None:
            continue
        v = {k: _xml_floats(ie.get(k)) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")}
        mass_el = inert.find("mass")
        mass = _xml_floats(None if mass_el is None else mass_el.get("value"))
        if mass <= 0 or (all(x == 0.0 for x in v.values()) and not point_masses):
            continue     # a massless link, or a point mass MuJoCo accepts on a fused or static body
        I = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]], [v["ixz"], v["iyz"], v["izz"]]])
        I2, raised = _inertia_floor(I)
        if raised > 0:
            for k, (a, b) in {"ixx": (0, 0), "iyy": (1, 1), "izz": (2, 2), "ixy": (0, 1), "ixz": (0, 2),
                              "iyz": (1, 2)}.items():
                ie.set(k, repr(float(I2[a, b])))
            notes.floored[link.get("name")] = raised
    for j in root.findall("joint"):
        for el in j.findall("mimic"):
            j.remove(el)
            if j.get("name") not in fixed:
                notes.mimic.append(j.get("name"))
        dyn = j.find("dynamics")
        if dyn is not None and j.get("type") in ("revolute", "continuous", "prismatic"):
            d = {k: _xml_floats(dyn.get(k)) for k in ("damping", "friction") if dyn.get(k) is not None}
            d = {k: x for k, x in d.items() if x != 0.0}
            if d:
                notes.urdf_dynamics[j.get("name")] = d
    for el in root.findall("mujoco"):
        root.remove(el)
        notes.replaced_extension = True
    root.insert(0, _extension(gravity, timestep))
    return ET.tostring(root, encoding="unicode"), notes


def _extension(gravity, timestep: float) -> ET.Element:
    mj = ET.Element("mujoco")
    ET.SubElement(mj, "compiler", COMPILER)
    opt = ET.SubElement(mj, "option", {"integrator": "RK4", "timestep": repr(float(timestep)),
                                       "gravity": " ".join(repr(float(g)) for g in gravity)})
    ET.SubElement(opt, "flag", FLAGS)
    return mj


def _quat(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    k = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 0.0))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 0.0))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def _f(x) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(x))


def mjcf_from_tree(tree, gravity, *, name: str = "symfunnel", timestep: float = 1e-3) -> tuple[str, EngineNotes]:
    """MJCF text of a planar/dh/urdf link tree: one MuJoCo body per movable joint, fixed links lumped into it.

    The bodies are symfunnel's (`model.tree.bodies_from_tree`: joint frame in the parent body, axis, lumped mass,
    first moment h = m c and inertia I about the joint origin), written with the inertia about the centre of mass
    I_c = I + m [c]x [c]x: the partition into bodies is the same as symfunnel's, the dynamics are MuJoCo's.
    """
    from ..model.tree import bodies_from_tree, skew
    bodies = bodies_from_tree(tree)
    notes = EngineNotes(source="MJCF written by symfunnel from the model's link tree (one body per movable joint)",
                        file=str(tree.file))
    movable = {b.joint.child for b in bodies}
    notes.fused = [k for k in tree.links if k not in movable and any(j.child == k for j in tree.joints)]
    children: dict[int, list[int]] = {}
    for k, b in enumerate(bodies):
        children.setdefault(b.parent, []).append(k)

    def body_xml(k: int, indent: str) -> str:
        b = bodies[k]
        j = b.joint
        m = float(b.mass)
        c = b.h / m if m > 0 else np.zeros(3)
        Ic = b.I + m * skew(c) @ skew(c)
        Ic, raised = _inertia_floor(0.5 * (Ic + Ic.T))
        if raised > 0:
            notes.floored[j.child] = raised
        if m <= 0:       # a massless joint body that carries inertia only: MuJoCo needs a positive mass
            m = 1e-12
            notes.floored[j.child] = max(notes.floored.get(j.child, 0.0), 1e-12)
        jtype = "slide" if j.type == "prismatic" else "hinge"
        full = [Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2]]
        s = (f'{indent}<body name="{j.child}" pos="{_f(b.p0)}" quat="{_f(_quat(b.R0))}">\n'
             f'{indent}  <joint name="{j.name}" type="{jtype}" axis="{_f(j.axis)}"/>\n'
             f'{indent}  <inertial pos="{_f(c)}" mass="{m!r}" fullinertia="{_f(full)}"/>\n')
        for ch in children.get(k, []):
            s += body_xml(ch, indent + "  ")
        return s + f"{indent}</body>\n"

    inner = "".join(body_xml(k, "    ") for k in children.get(-1, []))
    comp = " ".join(f'{k}="{v}"' for k, v in COMPILER.items() if k not in ("discardvisual", "strippath"))
    flags = " ".join(f'{k}="{v}"' for k, v in FLAGS.items())
    xml = (f'<mujoco model="{name}">\n  <compiler {comp}/>\n'
           f'  <option integrator="RK4" timestep="{timestep!r}" gravity="{_f(gravity)}">\n'
           f'    <flag {flags}/>\n  </option>\n  <worldbody>\n{inner}  </worldbody>\n</mujoco>\n')
    return xml, notes


@dataclass
class Engine:
    """A loaded MuJoCo model of a scenario's robot, its joints in symfunnel's coordinate order, and its nominal data.

    `configure` sets the engine-only changes of an experiment from the nominal data (so it can be called again for
    every run of a sweep); `mass_and_bias` reads M(q) and C(q, dq) dq + G(q) in symfunnel's order.
    """

    model: Any
    names: list[str]
    qadr: np.ndarray
    dadr: np.ndarray
    bodies: np.ndarray             # MuJoCo body id of each coordinate's joint
    notes: EngineNotes
    nominal: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of coordinates."""
        return len(self.names)

    def configure(self, *, mass_scale=1.0, damping=None, armature=None, urdf_dynamics: bool = True) -> None:
        """Engine-only dynamics from the nominal model: masses and inertias times mass_scale (one number: every link;
        one per joint: the body that joint moves, fixed links included), the URDF's damping and friction loss
        (unless urdf_dynamics is false) plus `damping` [N m s/rad or N s/m] and `armature` [kg m^2 or kg] per joint."""
        mj = self.model
        nom = self.nominal
        mj.body_mass[:] = nom["body_mass"]
        mj.body_inertia[:] = nom["body_inertia"]
        s = np.asarray(mass_scale, dtype=float)
        if s.ndim == 0:
            mj.body_mass[1:] *= float(s)
            mj.body_inertia[1:] *= float(s)
        else:
            for k, b in enumerate(self.bodies):
                mj.body_mass[b] *= s[k]
                mj.body_inertia[b] *= s[k]
        keep = 1.0 if urdf_dynamics else 0.0
        mj.dof_damping[:] = keep * nom["dof_damping"]
        mj.dof_frictionloss[:] = keep * nom["dof_frictionloss"]
        mj.dof_armature[:] = nom["dof_armature"]
        if damping is not None:
            mj.dof_damping[self.dadr] += np.asarray(damping, dtype=float)
        if armature is not None:
            mj.dof_armature[self.dadr] += np.asarray(armature, dtype=float)
        mujoco = require_mujoco()
        # friction loss is a constraint in MuJoCo: its solver runs only when some joint has friction loss
        off = int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT) | int(mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS)
        if np.any(mj.dof_frictionloss > 0):
            mj.opt.disableflags &= ~off
        else:
            mj.opt.disableflags |= off
        mujoco.mj_setConst(mj, mujoco.MjData(mj))

    def engine_only(self) -> dict[str, list[float]]:
        """Per joint, the dynamics in the engine and not in the controller's model (nonzero ones only)."""
        mj = self.model
        out = {}
        for key, arr in (("damping", mj.dof_damping), ("frictionloss", mj.dof_frictionloss),
                         ("armature", mj.dof_armature)):
            v = np.asarray(arr)[self.dadr]
            if np.any(v != 0):
                out[key] = [float(x) for x in v]
        return out

    def mass_and_bias(self, data, q, dq, Mfull: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """M(q) (armature included) and qfrc_bias = C(q, dq) dq + G(q), in symfunnel's coordinate order."""
        mujoco = require_mujoco()
        mj = self.model
        data.qpos[self.qadr] = q
        data.qvel[self.dadr] = dq
        mujoco.mj_kinematics(mj, data)
        mujoco.mj_comPos(mj, data)
        mujoco.mj_makeM(mj, data)
        mujoco.mj_comVel(mj, data)
        mujoco.mj_rne(mj, data, 0, data.qfrc_bias)
        if Mfull is None:
            Mfull = np.zeros((mj.nv, mj.nv))
        mujoco.mj_fullM(mj, data, Mfull)
        return Mfull[np.ix_(self.dadr, self.dadr)].copy(), data.qfrc_bias[self.dadr].copy()


def _compile(mujoco, text: str, file: str):
    try:
        return mujoco.MjModel.from_xml_string(text)
    except ValueError as exc:
        msg = " ".join(str(exc).split())
        raise _Refused(msg) from None


class _Refused(Exception):
    pass


def load_engine(model, *, file: str, timestep: float = 1e-3, mjcf: str | None = None) -> Engine:
    """The Engine of a scenario's RigidBodyModel (planar, dh or urdf; `file` is the scenario's, for messages): the
    URDF read by MuJoCo, the MJCF written from the link tree, or the user's own MJCF `mjcf` ([plant.mujoco] mjcf)."""
    from .engines import check_engine_model
    check_engine_model(model, "mujoco", file=file, key=ENGINE_KEY)
    mujoco = require_mujoco(file=file)
    gravity = np.asarray(model.gravity, dtype=float)
    tree = model.tree
    if mjcf is not None:
        from .mjcf import load_mjcf
        mj, changed = load_mjcf(mujoco, mjcf, gravity=gravity, timestep=timestep, flags=FLAGS, file=file)
        notes = EngineNotes(source=f"the MJCF {Path(mjcf).name} (plant.mujoco.mjcf), joints matched by name",
                            file=str(mjcf), changed=changed)
    elif model.kind == "urdf":
        urdf = tree.file
        held = [j.name for j in tree.joints if j.type == "fixed"]     # fixed in the URDF or by model.fixed_joints
        try:
            text, notes = prepare_urdf(urdf, gravity=gravity, timestep=timestep, fixed=held)
            try:
                mj = _compile(mujoco, text, urdf)
            except _Refused as first:
                # a point mass alone on a moving body: its composite inertia is singular for MuJoCo; floor it too
                if "moving bodies" not in str(first):
                    raise
                text, notes = prepare_urdf(urdf, gravity=gravity, timestep=timestep, point_masses=True,
                                           fixed=held)
                mj = _compile(mujoco, text, urdf)
        except _Refused as exc:
            raise InputError(f"MuJoCo refuses this URDF: {exc}", file=urdf, key=ENGINE_KEY,
                             expected="a URDF that MuJoCo's parser loads (or engine = 'symfunnel')") from None
    else:
        text, notes = mjcf_from_tree(tree, gravity, timestep=timestep)
        try:
            mj = _compile(mujoco, text, file)
        except _Refused as exc:
            raise InputError(f"MuJoCo refuses the MJCF written from the model: {exc}", file=file,
                             key=ENGINE_KEY, expected="a model whose links MuJoCo accepts") from None
    from ..model.tree import bodies_from_tree
    joints = [b.joint for b in bodies_from_tree(tree)]
    names = [j.name for j in joints]
    jid = joint_ids(mujoco, mj, joints, file=file, mjcf=mjcf, where=notes.file or file)
    if mjcf is not None:
        from .mjcf import check_axes
        check_axes(mujoco, mj, tree, names, jid, mjcf=mjcf, file=file)
    mj.jnt_limited[:] = 0            # belt and braces next to the disabled limit flag
    mj.geom_contype[:] = 0
    mj.geom_conaffinity[:] = 0
    mj.jnt_stiffness[:] = 0.0        # URDF has no joint springs; MJCF written here neither (a user's: noted)
    nominal = {k: np.array(getattr(mj, k), dtype=float) for k in
               ("body_mass", "body_inertia", "dof_damping", "dof_frictionloss", "dof_armature")}
    eng = Engine(mj, names, np.array([int(mj.jnt_qposadr[j]) for j in jid], dtype=np.int32),
                 np.array([int(mj.jnt_dofadr[j]) for j in jid], dtype=np.int32),
                 np.array([int(mj.jnt_bodyid[j]) for j in jid], dtype=np.int32), notes, nominal)
    eng.configure()
    return eng


def joint_ids(mujoco, mj, joints, *, file: str, mjcf=None, where: str = "") -> list[int]:
    """MuJoCo's joint id of each of symfunnel's movable joints, in symfunnel's coordinate order, found by name
    (never by position: MuJoCo's order is its own); each must be a hinge (revolute, continuous) or a slide
    (prismatic) joint, and MuJoCo must have no other degree of freedom."""
    want = {"prismatic": int(mujoco.mjtJoint.mjJNT_SLIDE)}
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    names = [j.name for j in joints]
    jid = []
    for jt in joints:
        j = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_JOINT, jt.name)
        if j < 0 or int(mj.jnt_type[j]) != want.get(jt.type, hinge):
            if mjcf is not None:
                from .mjcf import mjcf_joint_error
                raise mjcf_joint_error(mujoco, mj, jt.name, j, names, mjcf=mjcf, file=file)
            kind = "slide" if jt.type == "prismatic" else "hinge"
            raise InputError(f"joint '{jt.name}' of the model is not a {kind} joint of the MuJoCo model",
                             file=where or file, key=ENGINE_KEY,
                             expected="the same movable joints in MuJoCo as in symfunnel's model")
        jid.append(j)
    if mj.nv != len(names) or mj.nq != len(names):
        if mjcf is not None:
            from .mjcf import mjcf_extra_error
            raise mjcf_extra_error(mujoco, mj, names, mjcf=mjcf, file=file)
        raise InputError(f"the MuJoCo model has {mj.nv} degrees of freedom, symfunnel's {len(names)}",
                         file=where or file, key=ENGINE_KEY,
                         expected="the same movable joints in MuJoCo as in symfunnel's model")
    return jid


# --- agreement of the engine with another model of the same robot -------------------------------------------------

#: below this magnitude a reference vector counts as zero and the error is absolute (e.g. no gravity, dq = 0)
ZERO_SCALE = 1e-12


def agreement(engine: Engine, M_fn, bias_fn, lower, upper, velocity, *, samples: int = 200, seed: int = 0,
              others: dict | None = None) -> dict:
    """Normwise relative errors of the engine's M and C dq + G against M_fn(q), bias_fn(q, dq) at random states.

    q is uniform in [lower, upper], dq uniform in [-velocity, velocity] per joint. Per state the error of M is
    max|M_engine - M| / max|M| (likewise the bias, absolute when max|bias| < 1e-12); the result holds the worst
    over the states (`M`, `bias`, `value` = the larger), the state it occurs at, and per joint the worst error of
    that joint's column of M and entry of the bias (`per_joint_M`, `per_joint_bias`). `others` maps a name to
    (M_fn, bias_fn) of a third model (e.g. Pinocchio): its errors against the same reference and against the engine.
    The engine should be configured nominally (no mass scale, no armature: those are differences on purpose).
    """
    mujoco = require_mujoco()
    rng = np.random.default_rng(seed)
    n = engine.n
    lo, hi, vel = (np.broadcast_to(np.asarray(x, dtype=float), (n,)) for x in (lower, upper, velocity))
    data = mujoco.MjData(engine.model)
    Mfull = np.zeros((engine.model.nv, engine.model.nv))
    out = {"samples": samples, "seed": seed, "M": 0.0, "bias": 0.0, "per_joint_M": [0.0] * n,
           "per_joint_bias": [0.0] * n, "worst_state": None, "abs_M": 0.0, "abs_bias": 0.0}
    extra = {k: {"M": 0.0, "bias": 0.0, "M_vs_engine": 0.0, "bias_vs_engine": 0.0} for k in (others or {})}
    pj_M, pj_b = np.zeros(n), np.zeros(n)
    worst = -1.0
    for _ in range(samples):
        q = lo + (hi - lo) * rng.random(n)
        dq = vel * (2.0 * rng.random(n) - 1.0)
        Mr, br = np.asarray(M_fn(q), dtype=float), np.asarray(bias_fn(q, dq), dtype=float).ravel()
        Me, be = engine.mass_and_bias(data, q, dq, Mfull)
        sM, sb = max(float(np.max(np.abs(Mr))), ZERO_SCALE), max(float(np.max(np.abs(br))), ZERO_SCALE)
        dM, db = np.abs(Me - Mr), np.abs(be - br)
        eM, eb = float(dM.max()) / sM, float(db.max()) / sb
        pj_M = np.maximum(pj_M, dM.max(axis=0) / sM)
        pj_b = np.maximum(pj_b, db / sb)
        out["abs_M"] = max(out["abs_M"], float(dM.max()))
        out["abs_bias"] = max(out["abs_bias"], float(db.max()))
        out["M"], out["bias"] = max(out["M"], eM), max(out["bias"], eb)
        if max(eM, eb) > worst:
            worst = max(eM, eb)
            out["worst_state"] = {"q": q.tolist(), "dq": dq.tolist()}
        for k, (Mo_fn, bo_fn) in (others or {}).items():
            Mo, bo = np.asarray(Mo_fn(q), dtype=float), np.asarray(bo_fn(q, dq), dtype=float).ravel()
            x = extra[k]
            x["M"] = max(x["M"], float(np.max(np.abs(Mo - Mr))) / sM)
            x["bias"] = max(x["bias"], float(np.max(np.abs(bo - br))) / sb)
            x["M_vs_engine"] = max(x["M_vs_engine"], float(np.max(np.abs(Mo - Me))) / sM)
            x["bias_vs_engine"] = max(x["bias_vs_engine"], float(np.max(np.abs(bo - be))) / sb)
    out["per_joint_M"], out["per_joint_bias"] = pj_M.tolist(), pj_b.tolist()
    out["value"] = max(out["M"], out["bias"])
    if others:
        out["others"] = extra
    return out

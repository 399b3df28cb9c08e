"""Rigid-body trees, the common form of planar, dh and urdf models: links, joints, the movable bodies they make
(fixed joints merged), the physical checks of masses and inertias, and the TOML helpers the builders share."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..core.errors import InputError
from ..core.names import IDENT, KEYWORDS
from ..core.validate import as_float, did_you_mean, get_list, join, a_type

MOVABLE = ("revolute", "continuous", "prismatic")
SNAP = 1e-14           # rotation-matrix entries this close to 0 are exactly 0 (rpy of pi/2 and the like)
_INERTIA_RTOL = 1e-4   # triangle inequality / PSD slack, relative to the largest principal moment


@dataclass
class Link:
    """A rigid link: mass, centre of mass and inertia about the COM, in the link frame."""

    name: str
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    where: str = ""          # key or element path for error messages


@dataclass
class Joint:
    """A joint: the child link frame is parent frame * (R, p) * motion about or along `axis`."""

    name: str
    type: str                # revolute, continuous, prismatic, fixed
    parent: str
    child: str
    R: np.ndarray            # origin rotation (3 x 3) of the joint frame in the parent link frame
    p: np.ndarray            # origin translation
    axis: np.ndarray         # unit vector in the joint (= child link) frame
    lower: float | None = None
    upper: float | None = None
    where: str = ""


@dataclass
class Tree:
    """Links (by name, in document order) and joints of a robot, with the file they came from."""

    links: dict[str, Link]
    joints: list[Joint]
    file: str


@dataclass
class Body:
    """A movable joint with every link it carries rigidly (fixed joints merged), in its joint frame."""

    joint: Joint
    parent: int              # index of the parent body, -1 for the fixed base
    R0: np.ndarray           # constant pose of the joint frame in the parent body's frame
    p0: np.ndarray
    mass: float
    h: np.ndarray            # first moment of mass (mass * COM)
    I: np.ndarray            # rotational inertia about the body frame's origin


# ---------------------------------------------------------------- small numeric helpers

def rot_x(a: float) -> np.ndarray:
    """Rotation about x by angle a."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about y by angle a."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation about z by angle a."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return rot_z(rpy[2]) @ rot_y(rpy[1]) @ rot_x(rpy[0])


def snap_rotation(R: np.ndarray) -> np.ndarray:
    """Round rotation-matrix entries within 1e-14 of zero to zero, so they drop out of expressions."""
    R = np.array(R, dtype=float)
    R[np.abs(R) < SNAP] = 0.0
    return R


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix [v] with [v] w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# ---------------------------------------------------------------- physical checks

def check_mass(mass: float, *, file: str, key: str) -> None:
    """A mass must be finite and non-negative."""
    if not math.isfinite(mass) or mass < 0:
        raise InputError(f"mass is {mass:g}", file=file, key=key, expected="a mass >= 0")


def check_inertia(inertia: np.ndarray, *, file: str, key: str) -> None:
    """An inertia tensor about the COM must be symmetric positive semi-definite and obey Ixx+Iyy >= Izz etc."""
    I = np.asarray(inertia, dtype=float)
    if not np.all(np.isfinite(I)):
        raise InputError("has a non-finite entry", file=file, key=key, expected="finite numbers")
    lam = np.linalg.eigvalsh(0.5 * (I + I.T))
    tol = _INERTIA_RTOL * max(float(np.max(np.abs(lam))), 0.0) + 1e-15
    if lam[0] < -tol:
        raise InputError(f"is not positive semi-definite (principal moments {fmt_values(lam)})",
                         file=file, key=key, expected="an inertia tensor with principal moments >= 0")
    if lam[0] + lam[1] < lam[2] - tol:
        raise InputError(f"breaks the triangle inequality: principal moments {fmt_values(lam)} have "
                         f"{lam[0]:.6g} + {lam[1]:.6g} < {lam[2]:.6g}", file=file, key=key,
                         expected="principal moments with I1 + I2 >= I3 (a physical rigid body)")


def fmt_values(v: Sequence[float]) -> str:
    """Numbers for an error message: [a, b, c] with 6 significant digits."""
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


# ---------------------------------------------------------------- TOML helpers shared by the builders



def get_coordinates(table: dict, n: int, *, file: str, prefix: str) -> list[str]:
    """The coordinate names: `coordinates` (n distinct identifiers) or q1..qn."""
    if "coordinates" not in table:
        return [f"q{i + 1}" for i in range(n)]
    names = get_list(table, "coordinates", file=file, prefix=prefix)
    key = join(prefix, "coordinates")
    if len(names) != n:
        raise InputError(f"has {len(names)} names but the model has {n} movable joints", file=file,
                         key=key, expected=f"an array of {n} names")
    for i, c in enumerate(names):
        if not isinstance(c, str) or not IDENT.match(c) or c in KEYWORDS:
            raise InputError(f"is {c!r}", file=file, key=join(key, i),
                             expected="a name of letters, digits and '_' not starting with a digit, and not a "
                                      "Python or C keyword")
    dup = sorted({c for c in names if names.count(c) > 1})
    if dup:
        raise InputError(f"names '{dup[0]}' twice", file=file, key=key, expected="distinct names")
    return list(names)


def get_vector(table: dict, key: str, default: Sequence[float] | None, *, file: str, prefix: str,
               lengths: Sequence[int] = (3,)) -> np.ndarray:
    """An array of numbers of one of the allowed lengths."""
    full = join(prefix, key)
    if key not in table:
        return None if default is None else np.array(default, dtype=float)
    v = table[key]
    want = " or ".join(str(k) for k in lengths)
    if not isinstance(v, list):
        raise InputError(f"is {a_type(v)}", file=file, key=full, expected=f"an array of {want} numbers")
    if len(v) not in lengths:
        raise InputError(f"has {len(v)} entries", file=file, key=full, expected=f"an array of {want} numbers")
    return np.array([as_float(x, file=file, key=join(full, i)) for i, x in enumerate(v)])


def get_range(value: Any, *, file: str, key: str) -> tuple[float, float]:
    """A [lower, upper] pair with lower < upper."""
    if not isinstance(value, list) or len(value) != 2:
        raise InputError(f"is {value!r}", file=file, key=key, expected="[lower, upper]")
    lo = as_float(value[0], file=file, key=join(key, 0))
    hi = as_float(value[1], file=file, key=join(key, 1))
    if not lo < hi:
        raise InputError(f"has lower {lo:g} >= upper {hi:g}", file=file, key=key,
                         expected="[lower, upper] with lower < upper")
    return lo, hi


def get_joint_range(table: dict, n: int, *, file: str, prefix: str) -> list[tuple[float, float]] | None:
    """`joint_range`: one [lower, upper] for every joint, or an array of n such pairs; None if absent."""
    if "joint_range" not in table:
        return None
    key = join(prefix, "joint_range")
    v = table["joint_range"]
    if isinstance(v, list) and v and all(isinstance(x, list) for x in v):
        if len(v) != n:
            raise InputError(f"has {len(v)} pairs", file=file, key=key,
                             expected=f"[lower, upper] or {n} such pairs (one per joint)")
        return [get_range(x, file=file, key=join(key, i)) for i, x in enumerate(v)]
    return [get_range(v, file=file, key=key)] * n


# ---------------------------------------------------------------- tree -> bodies

#: The most movable joints of a URDF/DH/planar tree (the symbolic M grows like n^3; 50 covers humanoids).
MAX_JOINTS = 50


def bodies_from_tree(tree: Tree) -> list[Body]:
    """Check the tree's structure and mass, merge fixed joints and list the movable joints depth-first (children in document order)."""
    file = tree.file
    links = tree.links
    children: dict[str, list[Joint]] = {name: [] for name in links}
    parent_of: dict[str, Joint] = {}
    for j in tree.joints:
        for role, lk in (("parent", j.parent), ("child", j.child)):
            if lk not in links:
                raise InputError(f"refers to {role} link '{lk}', which does not exist", file=file,
                                 key=j.where, expected="the name of a link" + _hint(lk, links))
        if j.parent == j.child:
            raise InputError(f"has link '{j.child}' as both parent and child", file=file, key=j.where,
                             expected="two different links")
        if j.child in parent_of:
            raise InputError(f"link '{j.child}' is the child of joints '{parent_of[j.child].name}' and "
                             f"'{j.name}' (a closed kinematic loop)", file=file, key=j.where,
                             expected="a kinematic tree: every link the child of at most one joint")
        parent_of[j.child] = j
        children[j.parent].append(j)
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        if not roots:
            raise InputError("every link is the child of a joint (a closed kinematic loop)", file=file,
                             key="robot", expected="one root link")
        raise InputError(f"has {len(roots)} root links ({', '.join(repr(r) for r in roots)})", file=file,
                         key="robot", expected="one root link (a single kinematic tree)")

    bodies: list[Body] = []
    visited: set[str] = set()
    # per body (-1: the fixed base): lumped mass, first moment and inertia about the body frame origin
    lumped = {-1: [0.0, np.zeros(3), np.zeros((3, 3))]}

    # Depth-first with an explicit stack (a chain of thousands of links must not hit Python's recursion limit);
    # children are pushed in reverse so that they are visited in document order. An entry is (link, body it
    # belongs to, its frame in that body) or, for a movable joint, (joint, parent body, joint frame).
    stack: list = [("link", roots[0], -1, np.eye(3), np.zeros(3))]
    while stack:
        what, name_or_joint, body, R, p = stack.pop()
        if what == "joint":
            j = name_or_joint
            bodies.append(Body(joint=j, parent=body, R0=R, p0=p, mass=0.0, h=np.zeros(3), I=np.zeros((3, 3))))
            if len(bodies) > MAX_JOINTS:
                raise InputError(f"has more than {MAX_JOINTS} movable joints", file=file, key="robot",
                                 expected=f"at most {MAX_JOINTS} revolute, continuous or prismatic joints")
            k = len(bodies) - 1
            lumped[k] = [0.0, np.zeros(3), np.zeros((3, 3))]
            stack.append(("link", j.child, k, np.eye(3), np.zeros(3)))
            continue
        link_name = name_or_joint
        visited.add(link_name)
        lk = links[link_name]
        acc = lumped[body]
        if lk.mass > 0 or np.any(lk.inertia != 0):
            c = R @ lk.com + p
            acc[0] += lk.mass
            acc[1] = acc[1] + lk.mass * c
            acc[2] = acc[2] + R @ lk.inertia @ R.T - lk.mass * skew(c) @ skew(c)
        for j in reversed(children[link_name]):
            Rj = snap_rotation(R @ j.R)
            pj = R @ j.p + p
            stack.append(("link", j.child, body, Rj, pj) if j.type == "fixed" else ("joint", j, body, Rj, pj))
    unreached = [name for name in links if name not in visited]
    if unreached:
        raise InputError(f"link '{unreached[0]}' is not connected to the root '{roots[0]}' "
                         "(a closed kinematic loop)", file=file, key=links[unreached[0]].where or "robot",
                         expected="a kinematic tree")
    for k, b in enumerate(bodies):
        b.mass, b.h, b.I = lumped[k][0], lumped[k][1], 0.5 * (lumped[k][2] + lumped[k][2].T)
    if not bodies:
        raise InputError("has no movable joint", file=file, key="robot",
                         expected="at least one revolute, continuous or prismatic joint")
    _check_moves_mass(bodies, file)
    return bodies


def _hint(word: str, choices) -> str:
    h = did_you_mean(word, choices)
    return h.replace("; did you mean", ", did you mean").rstrip("?") + "?" if h else ""


def _check_moves_mass(bodies: list[Body], file: str) -> None:
    """Every movable joint must carry some mass or inertia downstream, or M is singular."""
    carries = [b.mass > 0 or bool(np.any(b.I != 0)) for b in bodies]
    for k in range(len(bodies) - 1, -1, -1):
        if carries[k] and bodies[k].parent >= 0:
            carries[bodies[k].parent] = True
    for k, b in enumerate(bodies):
        if not carries[k]:
            raise InputError(f"joint '{b.joint.name}' moves no mass: every link downstream of it is massless "
                             "(M would be singular)", file=file, key=b.joint.where,
                             expected="a link with mass or inertia after every movable joint")


"""Rigid-body trees (the common form of planar, dh and urdf models) to M by composite rigid bodies, G by RNEA at rest, C by Christoffel."""

# Expressions are built entry by entry from Python floats and SX scalars so that products with
# the constant zeros and ones of joint axes and origins never reach the expression graph.

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import casadi as ca
import numpy as np

from ..errors import InputError
from ..names import IDENT
from ..validate import as_float, did_you_mean, get_list, join, type_name
from .base import RigidBodyModel, symbols

MOVABLE = ("revolute", "continuous", "prismatic")
_SNAP = 1e-14          # rotation-matrix entries this close to 0 are exactly 0 (rpy of pi/2 and the like)
_INERTIA_RTOL = 1e-4   # triangle inequality / PSD slack, relative to the largest principal moment
_SINGULAR_RTOL = 1e-12


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
    R[np.abs(R) < _SNAP] = 0.0
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
        raise InputError(f"is not positive semi-definite (principal moments {_fmt(lam)})",
                         file=file, key=key, expected="an inertia tensor with principal moments >= 0")
    if lam[0] + lam[1] < lam[2] - tol:
        raise InputError(f"breaks the triangle inequality: principal moments {_fmt(lam)} have "
                         f"{lam[0]:.6g} + {lam[1]:.6g} < {lam[2]:.6g}", file=file, key=key,
                         expected="principal moments with I1 + I2 >= I3 (a physical rigid body)")


def _fmt(v: Sequence[float]) -> str:
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
        if not isinstance(c, str) or not IDENT.match(c):
            raise InputError(f"is {c!r}", file=file, key=join(key, i),
                             expected="a name of letters, digits and '_' not starting with a digit")
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
        raise InputError(f"is a {type_name(v)}", file=file, key=full, expected=f"an array of {want} numbers")
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


# ---------------------------------------------------------------- scalar algebra on floats and SX

def _num(x) -> bool:
    return isinstance(x, float)


def _mul(a, b):
    if _num(a):
        if a == 0.0:
            return 0.0
        if _num(b):
            return a * b
        if a == 1.0:
            return b
        if a == -1.0:
            return -b
    elif _num(b):
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
        if b == -1.0:
            return -a
    return a * b


def _add(a, b):
    if _num(a):
        if a == 0.0:
            return b
        if _num(b):
            return a + b
    elif _num(b) and b == 0.0:
        return a
    return a + b


def _sum(terms) -> Any:
    out = 0.0
    for t in terms:
        out = _add(out, t)
    return out


def _dot(u, v):
    return _sum(_mul(a, b) for a, b in zip(u, v))


def _matvec(A, v):
    return [_dot(A[i], v) for i in range(3)]


def _matTvec(A, v):
    return [_sum(_mul(A[k][i], v[k]) for k in range(3)) for i in range(3)]


def _cross(a, b):
    return [_add(_mul(a[1], b[2]), _neg(_mul(a[2], b[1]))),
            _add(_mul(a[2], b[0]), _neg(_mul(a[0], b[2]))),
            _add(_mul(a[0], b[1]), _neg(_mul(a[1], b[0])))]


def _neg(a):
    return -a if not _num(a) else (0.0 if a == 0.0 else -a)


def _vadd(u, v):
    return [_add(a, b) for a, b in zip(u, v)]


def _floats(a: np.ndarray) -> list:
    """A numpy vector or matrix as nested lists of Python floats."""
    return [float(x) for x in a] if a.ndim == 1 else [[float(x) for x in row] for row in a]


def _joint_rotation(axis: np.ndarray, c, s) -> list:
    """R = a a^T + (E - a a^T) cos + [a] sin, with the constant coefficients folded in."""
    aa = np.outer(axis, axis)
    K = skew(axis)
    R = []
    for i in range(3):
        row = []
        for j in range(3):
            const = float(aa[i, j]) if abs(aa[i, j]) > _SNAP else 0.0
            kc = float((1.0 if i == j else 0.0) - aa[i, j])
            kc = kc if abs(kc) > _SNAP else 0.0
            ks = float(K[i, j]) if abs(K[i, j]) > _SNAP else 0.0
            row.append(_add(_add(const, _mul(kc, c)), _mul(ks, s)))
        R.append(row)
    return R


def _matmul(A, B):
    return [[_sum(_mul(A[i][k], B[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]


# ---------------------------------------------------------------- dynamics

def mass_and_gravity(bodies: list[Body], q: ca.SX, gravity: np.ndarray) -> tuple[ca.SX, ca.SX]:
    """M(q) by the composite-rigid-body algorithm and G(q) by RNEA at rest, in body frames to keep expressions small."""
    # In each joint's own frame M_ij does not depend on q_1..q_min(i,j) even structurally (a
    # world-frame Lagrangian gives 3x the operations for the 7-joint arm).
    n = len(bodies)
    Rs, ps = [], []
    for k, b in enumerate(bodies):
        qk = q[k]
        R0 = _floats(b.R0)
        p0 = _floats(b.p0)
        if b.joint.type == "prismatic":
            Rs.append(R0)
            ps.append(_vadd(p0, [_mul(float(x), qk) for x in b.R0 @ b.joint.axis]))
        else:
            Rj = _joint_rotation(b.joint.axis, ca.cos(qk), ca.sin(qk))
            Rs.append(_matmul(R0, Rj))
            ps.append(p0)

    # composite inertias (mass, first moment h, rotational inertia about the frame origin), leaves first
    mc = [b.mass for b in bodies]
    hc = [_floats(b.h) for b in bodies]
    Ic = [_floats(b.I) for b in bodies]
    for k in range(n - 1, -1, -1):
        par = bodies[k].parent
        if par < 0:
            continue
        m2, h2, I2 = _transform_inertia(mc[k], hc[k], Ic[k], Rs[k], ps[k])
        mc[par] = mc[par] + m2
        hc[par] = _vadd(hc[par], h2)
        Ic[par] = [[_add(Ic[par][i][j], I2[i][j]) for j in range(3)] for i in range(3)]

    M = ca.SX.zeros(n, n)
    for i, b in enumerate(bodies):
        a = _floats(b.joint.axis)
        if b.joint.type == "prismatic":
            nf = _cross(hc[i], a)                       # moment about the origin: h x v
            ff = [_mul(float(mc[i]), x) for x in a]
        else:
            nf = _matvec(Ic[i], a)                      # I w
            ff = _cross(a, hc[i])                       # w x h
        j = i
        while j >= 0:
            bj = bodies[j]
            aj = _floats(bj.joint.axis)
            mij = _dot(aj, ff) if bj.joint.type == "prismatic" else _dot(aj, nf)
            M[i, j] = mij
            if j != i:
                M[j, i] = mij
            if bj.parent < 0:
                break
            fr = _matvec(Rs[j], ff)
            nf = _vadd(_matvec(Rs[j], nf), _cross(ps[j], fr))
            ff = fr
            j = bj.parent

    g_frame: list[list] = []
    G = ca.SX.zeros(n, 1)
    g0 = _floats(np.asarray(gravity, dtype=float))
    for k, b in enumerate(bodies):
        gp = g0 if b.parent < 0 else g_frame[b.parent]
        gk = _matTvec(Rs[k], gp)
        g_frame.append(gk)
        a = _floats(b.joint.axis)
        if b.joint.type == "prismatic":
            G[k] = _neg(_mul(float(mc[k]), _dot(a, gk)))
        else:
            G[k] = _neg(_dot(a, _cross(hc[k], gk)))
    return M, G


def _transform_inertia(m: float, h, I, R, p):
    """Express (m, h, I about the child origin) in the parent frame, where the child frame is at (R, p)."""
    hr = _matvec(R, h)
    RI = [[_sum(_mul(R[i][k], I[k][j]) for k in range(3)) for j in range(3)] for i in range(3)]
    Ir = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            Ir[i][j] = Ir[j][i] = _sum(_mul(RI[i][k], R[j][k]) for k in range(3))
    # I_P = R I R^T + 2 (h.p) E - p h^T - h p^T + m (|p|^2 E - p p^T)
    hp2 = _mul(2.0, _dot(hr, p))
    pp = _dot(p, p)
    out = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            e = Ir[i][j]
            e = _add(e, _neg(_add(_mul(p[i], hr[j]), _mul(hr[i], p[j]))))
            e = _add(e, _neg(_mul(m, _mul(p[i], p[j]))))
            if i == j:
                e = _add(e, _add(hp2, _mul(m, pp)))
            out[i][j] = out[j][i] = e
    return m, _vadd(hr, [_mul(m, x) for x in p]), out


def christoffel_from_M(M: ca.SX, q: ca.SX, dq: ca.SX) -> ca.SX:
    """The Christoffel-symbol C of M as 1/2 (dM/dt + J - J^T), J = d(M dq)/dq: base.christoffel_C's matrix, at half the size."""
    # sum_i 1/2 (dM_kj/dq_i + dM_ki/dq_j - dM_ij/dq_k) dq_i: the first term is (dM/dt)_kj, the
    # second J_kj, the third J_jk (M symmetric); dM/dt - 2C = J^T - J is skew by construction.
    n = q.numel()
    Mdot = ca.reshape(ca.jtimes(ca.vec(M), q, dq), n, n)
    J = ca.jacobian(ca.mtimes(M, dq), q)
    return ca.densify(0.5 * (Mdot + J - J.T))


def check_regular(M: ca.SX, q: ca.SX, bodies: list[Body], lower: np.ndarray, upper: np.ndarray,
                  file: str, samples: int = 5) -> None:
    """M must be positive definite at a few random configurations; name the joint where it is not."""
    f = ca.Function("M", [q], [M])
    rng = np.random.default_rng(0)
    n = len(bodies)
    for s in range(samples):
        qv = np.clip(np.zeros(n), lower, upper) if s == 0 else lower + (upper - lower) * rng.random(n)
        Mv = np.array(f(qv))
        lam, vec = np.linalg.eigh(0.5 * (Mv + Mv.T))
        scale = max(float(np.max(np.abs(lam))), 1e-300)
        if lam[0] > _SINGULAR_RTOL * scale:
            continue
        diag = np.diag(Mv)
        k = int(np.argmin(diag)) if np.min(diag) <= _SINGULAR_RTOL * scale else int(np.argmax(np.abs(vec[:, 0])))
        what = ("its row and column of M are zero: it moves no mass or inertia about its axis"
                if diag[k] <= _SINGULAR_RTOL * scale else
                f"M is singular (smallest eigenvalue {lam[0]:.3g}) along this joint")
        raise InputError(f"joint '{bodies[k].joint.name}': {what} at q = {_fmt(qv)}", file=file,
                         key=bodies[k].joint.where,
                         expected="links with mass/inertia such that M(q) is positive definite")


def sample_box(bodies: list[Body], lower: np.ndarray | None, upper: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Finite sampling bounds per joint: the limits where known, else [-pi, pi] (revolute) or [-1, 1] (prismatic)."""
    lo, hi = [], []
    for k, b in enumerate(bodies):
        d = 1.0 if b.joint.type == "prismatic" else math.pi
        l = lower[k] if lower is not None and np.isfinite(lower[k]) else -d
        u = upper[k] if upper is not None and np.isfinite(upper[k]) else d
        lo.append(l)
        hi.append(u)
    return np.array(lo), np.array(hi)


def build_model(kind: str, tree: Tree, *, coordinates: list[str] | None, gravity: np.ndarray,
                joint_range: list[tuple[float, float]] | None, cse: bool = True) -> RigidBodyModel:
    """The RigidBodyModel of a tree: M, C, G as SX with numbers embedded, joint types and limits."""
    bodies = bodies_from_tree(tree)
    n = len(bodies)
    coordinates = coordinates or [f"q{i + 1}" for i in range(n)]
    q, dq = symbols(coordinates)
    M, G = mass_and_gravity(bodies, q, gravity)
    if joint_range is not None:
        lower = np.array([r[0] for r in joint_range])
        upper = np.array([r[1] for r in joint_range])
    else:
        lower = np.array([np.nan if b.joint.lower is None else b.joint.lower for b in bodies])
        upper = np.array([np.nan if b.joint.upper is None else b.joint.upper for b in bodies])
    check_regular(M, q, bodies, *sample_box(bodies, lower, upper), tree.file)
    C = christoffel_from_M(M, q, dq)
    if cse:
        M, C, G = _cse(M, C, G)
    if np.all(np.isnan(lower)) and np.all(np.isnan(upper)):
        lower = upper = None
    return RigidBodyModel(kind=kind, coordinates=coordinates, q=q, dq=dq, M=M, C=C, G=G,
                          C_source="christoffel", joint_types=[b.joint.type for b in bodies],
                          joint_lower=lower, joint_upper=upper)


def _cse(M: ca.SX, C: ca.SX, G: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
    """Merge equal subexpressions of M, C and G in one pass (casadi.cse), keeping shapes."""
    if not hasattr(ca, "cse"):
        return M, C, G
    n = M.size1()
    v = ca.cse(ca.vertcat(ca.vec(M), ca.vec(C), G))
    return ca.reshape(v[: n * n], n, n), ca.reshape(v[n * n: 2 * n * n], n, n), v[2 * n * n:]

"""`type = "planar"` and `type = "dh"`: manipulator models from a table of links, turned into a rigid-body tree."""

# planar: revolute joints about z, links along their x axis in the x-y plane, gravity default [0, -9.81, 0].
# dh: rows as in the Robotics Toolbox for Python (DHRobot; RevoluteDH/PrismaticDH for "standard", link
# frame at the distal end; RevoluteMDH/PrismaticMDH for "modified", link frame at the proximal end),
# gravity default [0, 0, -9.81] in the base frame.

from __future__ import annotations

import numpy as np

from ..core.errors import InputError
from ..core.validate import check_keys, get_float, get_list, get_str, join
from .base import RigidBodyModel
from .rigid import build_model
from .tree import (Joint, Link, Tree, check_inertia, check_mass, get_coordinates, get_joint_range, get_range,
                   get_vector, rot_x, rot_z)

COMMON = ("type", "coordinates", "gravity", "joint_range")
PLANAR_LINK = ("mass", "length", "com", "inertia")
DH_LINK = ("a", "alpha", "d", "theta", "joint", "mass", "com", "inertia", "qlim")


def _links(table: dict, *, file: str, prefix: str) -> list:
    links = get_list(table, "links", file=file, prefix=prefix)
    if not links:
        raise InputError("is empty", file=file, key=join(prefix, "links"), expected="at least one link")
    return links


def build_planar(table: dict, *, file: str, prefix: str = "model") -> RigidBodyModel:
    """A planar serial arm: each link's joint turns about z at the end of the previous link."""
    check_keys(table, COMMON + ("links",), file=file, prefix=prefix, required=("links",))
    rows = _links(table, file=file, prefix=prefix)
    gravity = get_vector(table, "gravity", (0.0, -9.81, 0.0), file=file, prefix=prefix, lengths=(2, 3))
    if gravity.size == 2:
        gravity = np.append(gravity, 0.0)
    links = {"base": Link("base", where=join(prefix, "links"))}
    joints = []
    previous_length = 0.0
    for i, row in enumerate(rows):
        key = join(join(prefix, "links"), i)
        check_keys(row, PLANAR_LINK, file=file, prefix=key, required=("mass", "length"))
        mass = get_float(row, "mass", file=file, prefix=key, minimum=0.0)
        length = get_float(row, "length", file=file, prefix=key, minimum=0.0)
        com = get_float(row, "com", 0.5 * length, file=file, prefix=key)
        inertia = get_float(row, "inertia", mass * length ** 2 / 12.0, file=file, prefix=key, minimum=0.0)
        name = f"link{i + 1}"
        # a thin body in the x-y plane: only Izz acts; Iyy = Izz keeps the tensor physical
        links[name] = Link(name, mass=mass, com=np.array([com, 0.0, 0.0]),
                           inertia=np.diag([0.0, inertia, inertia]), where=key)
        joints.append(Joint(name=f"joint{i + 1}", type="revolute", parent="base" if i == 0 else f"link{i}",
                            child=name, R=np.eye(3), p=np.array([previous_length, 0.0, 0.0]),
                            axis=np.array([0.0, 0.0, 1.0]), where=key))
        previous_length = length
    n = len(rows)
    coordinates = get_coordinates(table, n, file=file, prefix=prefix)
    joint_range = get_joint_range(table, n, file=file, prefix=prefix)
    tree = Tree(links=links, joints=joints, file=file)
    return build_model("planar", tree, coordinates=coordinates, gravity=gravity, joint_range=joint_range)


def build_dh(table: dict, *, file: str, prefix: str = "model") -> RigidBodyModel:
    """A serial arm from DH rows; for a revolute joint theta = q + `theta`, for a prismatic one d = q + `d`."""
    check_keys(table, COMMON + ("links", "convention"), file=file, prefix=prefix,
               required=("links", "convention"))
    convention = get_str(table, "convention", file=file, prefix=prefix, choices=("standard", "modified"))
    rows = _links(table, file=file, prefix=prefix)
    gravity = get_vector(table, "gravity", (0.0, 0.0, -9.81), file=file, prefix=prefix)
    links = {"base": Link("base", where=join(prefix, "links"))}
    joints = []
    qlims = []
    z = np.array([0.0, 0.0, 1.0])
    for i, row in enumerate(rows):
        key = join(join(prefix, "links"), i)
        if "offset" in row:
            raise InputError("unknown key", file=file, key=join(key, "offset"),
                             expected="the joint offset as 'theta' (revolute joint) or 'd' (prismatic joint)")
        check_keys(row, DH_LINK, file=file, prefix=key, required=("mass",))
        a = get_float(row, "a", 0.0, file=file, prefix=key)
        alpha = get_float(row, "alpha", 0.0, file=file, prefix=key)
        d = get_float(row, "d", 0.0, file=file, prefix=key)
        theta = get_float(row, "theta", 0.0, file=file, prefix=key)
        jtype = get_str(row, "joint", "revolute", file=file, prefix=key, choices=("revolute", "prismatic"))
        mass = get_float(row, "mass", file=file, prefix=key)
        check_mass(mass, file=file, key=join(key, "mass"))
        com = get_vector(row, "com", (0.0, 0.0, 0.0), file=file, prefix=key)
        inertia = _inertia(row, file=file, prefix=key)
        qlims.append(get_range(row["qlim"], file=file, key=join(key, "qlim")) if "qlim" in row else None)

        parent = "base" if i == 0 else f"link{i}"
        name = f"link{i + 1}"
        lk = Link(name, mass=mass, com=com, inertia=inertia, where=key)
        # the joint frame: where the joint variable acts about / along its z axis
        if convention == "standard":
            # A = Rz(theta) Tz(d) Tx(a) Rx(alpha); joint about z_{i-1}; link frame i = joint frame * Tx(a) Rx(alpha)
            origin_R, origin_p = rot_z(theta), np.array([0.0, 0.0, d])
            jname = f"joint{i + 1}"
            joints.append(Joint(name=jname, type=jtype, parent=parent, child=f"{name}_joint", R=origin_R,
                                p=origin_p, axis=z, where=key))
            links[f"{name}_joint"] = Link(f"{name}_joint", where=key)
            joints.append(Joint(name=f"{jname}_link", type="fixed", parent=f"{name}_joint", child=name,
                                R=rot_x(alpha), p=np.array([a, 0.0, 0.0]), axis=z, where=key))
        else:
            # A = Rx(alpha) Tx(a) Rz(theta) Tz(d); the link frame is the joint frame
            R = rot_x(alpha) @ rot_z(theta)
            p = np.array([a, 0.0, 0.0]) + rot_x(alpha) @ np.array([0.0, 0.0, d])
            joints.append(Joint(name=f"joint{i + 1}", type=jtype, parent=parent, child=name, R=R, p=p,
                                axis=z, where=key))
        links[name] = lk
    n = len(rows)
    coordinates = get_coordinates(table, n, file=file, prefix=prefix)
    joint_range = get_joint_range(table, n, file=file, prefix=prefix)
    for j, r in zip([j for j in joints if j.type != "fixed"], qlims):
        j.lower, j.upper = (None, None) if r is None else r
    tree = Tree(links=links, joints=joints, file=file)
    return build_model("dh", tree, coordinates=coordinates, gravity=gravity, joint_range=joint_range)


def _inertia(row: dict, *, file: str, prefix: str) -> np.ndarray:
    """`inertia`: [Ixx, Iyy, Izz] or [Ixx, Iyy, Izz, Ixy, Iyz, Ixz] about the COM in the link frame."""
    v = get_vector(row, "inertia", (0.0, 0.0, 0.0), file=file, prefix=prefix, lengths=(3, 6))
    if v.size == 3:
        v = np.concatenate([v, np.zeros(3)])
    ixx, iyy, izz, ixy, iyz, ixz = v
    I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    check_inertia(I, file=file, key=join(prefix, "inertia"))
    return I

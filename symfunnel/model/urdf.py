"""`type = "urdf"`: a manipulator's M, C, G from a URDF file (fixed base; revolute, continuous, prismatic, fixed joints)."""

from __future__ import annotations

import math
import pathlib
import xml.etree.ElementTree as ET

import numpy as np

from ..core.errors import InputError
from ..core.validate import check_keys, did_you_mean, get_str, join
from .base import RigidBodyModel
from .rigid import build_model
from .tree import (MOVABLE, Joint, Link, Tree, bodies_from_tree, check_inertia, check_mass, get_coordinates,
                   get_joint_range, get_vector, rpy_matrix)

KEYS = ("type", "path", "coordinates", "gravity", "joint_range", "fixed_joints")
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")


def build_urdf(table: dict, *, file: str, base_dir: pathlib.Path, prefix: str = "model") -> RigidBodyModel:
    """Build the model of the URDF at `path` (relative to the scenario's directory) from the `[model]` table."""
    check_keys(table, KEYS, file=file, prefix=prefix, required=("path",))
    rel = get_str(table, "path", file=file, prefix=prefix)
    path = pathlib.Path(base_dir) / rel
    if not path.exists():       # a directory, FIFO or device is refused by parse_urdf's reader, by name
        raise InputError(f"URDF file '{path}' does not exist", file=file, key=join(prefix, "path"),
                         expected="a path to a URDF file, relative to the scenario file's directory")
    gravity = get_vector(table, "gravity", (0.0, 0.0, -9.81), file=file, prefix=prefix)
    fixed = table.get("fixed_joints", [])
    if not (isinstance(fixed, list) and all(isinstance(x, str) for x in fixed)):
        raise InputError("is not a list of joint names", file=file, key=join(prefix, "fixed_joints"),
                         expected='joint names of the URDF, e.g. ["finger_joint2"]')
    tree = parse_urdf(path)
    movable = [j.name for j in tree.joints if j.type in MOVABLE]
    for i, x in enumerate(fixed):
        if x not in movable:
            raise InputError(f"is '{x}', not a movable joint of the URDF{did_you_mean(x, movable)}", file=file,
                             key=join(prefix, f"fixed_joints[{i}]"), expected="one of " + ", ".join(movable))
    if fixed:
        tree = parse_urdf(path, fixed=fixed)
    n = len(movable_joint_names(tree))
    coordinates = get_coordinates(table, n, file=file, prefix=prefix)
    joint_range = get_joint_range(table, n, file=file, prefix=prefix)
    return build_model("urdf", tree, coordinates=coordinates, gravity=gravity, joint_range=joint_range)


def movable_joint_names(tree: Tree) -> list[str]:
    """Names of the movable joints in the model's coordinate order (depth-first, children in document order)."""
    return [b.joint.name for b in bodies_from_tree(tree)]


def mimic_joints(path: str | pathlib.Path) -> list[str]:
    """The names of a URDF's joints that carry a <mimic> element (they follow another joint)."""
    from ..core.inputs import read_input
    try:
        root = ET.fromstring(read_input(pathlib.Path(path), expected="a URDF file"))
    except ET.ParseError:
        return []
    return [el.get("name", "") for el in root.findall("joint") if el.find("mimic") is not None]


def parse_urdf(path: str | pathlib.Path, fixed=()) -> Tree:
    """Read a URDF file into a Tree, checking every element the dynamics use; visuals and meshes are ignored.
    The joints named in `fixed` are held at their zero position (made fixed joints)."""
    path = pathlib.Path(path)
    file = str(path)
    from ..core.inputs import read_input
    text = read_input(path, expected="a URDF file")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        line, col = e.position
        raise InputError(f"is not well-formed XML at line {line}, column {col + 1}: {_parse_reason(e)}",
                         file=file, expected="a URDF (XML) file") from None
    if root.tag != "robot":
        raise InputError(f"has root element <{root.tag}>", file=file, key=root.tag,
                         expected="a URDF file with root element <robot>")
    links: dict[str, Link] = {}
    for el in root.findall("link"):
        lk = _parse_link(el, file)
        if lk.name in links:
            raise InputError(f"link '{lk.name}' is defined twice", file=file, key=lk.where,
                             expected="distinct link names")
        links[lk.name] = lk
    joints: list[Joint] = []
    names: set[str] = set()
    for el in root.findall("joint"):
        j = _parse_joint(el, file)
        if j.name in names:
            raise InputError(f"joint '{j.name}' is defined twice", file=file, key=j.where,
                             expected="distinct joint names")
        names.add(j.name)
        if j.name in fixed:
            import dataclasses
            j = dataclasses.replace(j, type="fixed")
        joints.append(j)
    if not links:
        raise InputError("has no <link>", file=file, key="robot", expected="a URDF with links and joints")
    return Tree(links=links, joints=joints, file=file)


def _parse_reason(e: ET.ParseError) -> str:
    msg = str(e)
    return msg.split(":")[0] if ":" in msg else msg


def _name(el: ET.Element, what: str, file: str, where: str) -> str:
    name = el.get("name")
    if not name:
        raise InputError(f"a <{what}> has no name", file=file, key=where, expected=f'<{what} name="...">')
    return name


#: the largest magnitude of a number in a URDF, as in a scenario (masses, inertias, lengths; a larger one overflows
#: M and its derivatives: a 1e300 kg link came out as one that "moves no mass")
MAX_URDF_NUMBER = 1e12
#: a joint limit beyond this magnitude is read as no limit (exporters write 1e16 or DBL_MAX for "unlimited")
UNLIMITED = 1e6


def _floats_attr(el: ET.Element | None, attr: str, count: int, default, *, file: str, key: str,
                 maximum: float = MAX_URDF_NUMBER) -> np.ndarray:
    """Parse an attribute of `count` whitespace-separated finite numbers of magnitude at most `maximum`."""
    if el is None or el.get(attr) is None:
        if default is None:
            raise InputError("is missing", file=file, key=key, expected=f"{count} number(s)")
        return np.array(default, dtype=float)
    parts = el.get(attr).split()
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        vals = None
    if vals is None or len(vals) != count or not all(math.isfinite(v) for v in vals):
        raise InputError(f"is '{el.get(attr)}'", file=file, key=key, expected=f"{count} finite number(s)")
    if not all(abs(v) <= maximum for v in vals):
        raise InputError(f"is '{el.get(attr)}'", file=file, key=key,
                         expected=f"{count} number(s) of magnitude at most {maximum:g}")
    return np.array(vals)


def _origin(el: ET.Element, file: str, where: str) -> tuple[np.ndarray, np.ndarray]:
    o = el.find("origin")
    xyz = _floats_attr(o, "xyz", 3, (0, 0, 0), file=file, key=f"{where}/origin@xyz")
    rpy = _floats_attr(o, "rpy", 3, (0, 0, 0), file=file, key=f"{where}/origin@rpy")
    return rpy_matrix(rpy), xyz


def _parse_link(el: ET.Element, file: str) -> Link:
    name = _name(el, "link", file, "link")
    where = f"link[{name}]"
    inert = el.find("inertial")
    if inert is None:
        return Link(name=name, where=where)
    R, com = _origin(inert, file, f"{where}/inertial")
    mass_el = inert.find("mass")
    if mass_el is None:
        raise InputError("is missing", file=file, key=f"{where}/inertial/mass",
                         expected='<mass value="..."/> inside <inertial>')
    mass = float(_floats_attr(mass_el, "value", 1, None, file=file, key=f"{where}/inertial/mass@value")[0])
    check_mass(mass, file=file, key=f"{where}/inertial/mass@value")
    ie = inert.find("inertia")
    if ie is None:
        raise InputError("is missing", file=file, key=f"{where}/inertial/inertia",
                         expected='<inertia ixx="..." ixy="..." ixz="..." iyy="..." iyz="..." izz="..."/>')
    v = {k: float(_floats_attr(ie, k, 1, None, file=file, key=f"{where}/inertial/inertia@{k}")[0])
         for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    I = np.array([[v["ixx"], v["ixy"], v["ixz"]],
                  [v["ixy"], v["iyy"], v["iyz"]],
                  [v["ixz"], v["iyz"], v["izz"]]])
    check_inertia(I, file=file, key=f"{where}/inertial/inertia")
    return Link(name=name, mass=mass, com=com, inertia=R @ I @ R.T, where=where)


def _parse_joint(el: ET.Element, file: str) -> Joint:
    name = _name(el, "joint", file, "joint")
    where = f"joint[{name}]"
    jtype = el.get("type")
    if jtype in ("floating", "planar"):
        raise InputError(f"has type '{jtype}': a floating base or planar joint is not supported", file=file,
                         key=f"{where}@type", expected="a fixed-base robot with " + ", ".join(JOINT_TYPES)
                         + " joints")
    if jtype not in JOINT_TYPES:
        raise InputError(f"has type '{jtype}'{did_you_mean(jtype or '', JOINT_TYPES)}", file=file,
                         key=f"{where}@type", expected="one of " + ", ".join(JOINT_TYPES))
    ends = {}
    for role in ("parent", "child"):
        e = el.find(role)
        if e is None or not e.get("link"):
            raise InputError("is missing", file=file, key=f"{where}/{role}@link",
                             expected=f'<{role} link="..."/>')
        ends[role] = e.get("link")
    R, p = _origin(el, file, where)
    axis = _floats_attr(el.find("axis"), "xyz", 3, (1, 0, 0), file=file, key=f"{where}/axis@xyz")
    norm = float(np.linalg.norm(axis))
    if jtype in MOVABLE and norm < 1e-12:
        raise InputError("is the zero vector", file=file, key=f"{where}/axis@xyz",
                         expected="a non-zero joint axis")
    axis = axis / norm if norm > 0 else axis
    lower = upper = None
    lim = el.find("limit")
    if lim is not None and jtype in ("revolute", "prismatic") and (lim.get("lower") is not None
                                                                    or lim.get("upper") is not None):
        lower = float(_floats_attr(lim, "lower", 1, (0.0,), file=file, key=f"{where}/limit@lower",
                                   maximum=math.inf)[0])
        upper = float(_floats_attr(lim, "upper", 1, (0.0,), file=file, key=f"{where}/limit@upper",
                                   maximum=math.inf)[0])
        if lower > upper:
            raise InputError(f"has lower {lower:g} > upper {upper:g}", file=file, key=f"{where}/limit",
                             expected="lower <= upper")
        if lower == upper:
            lower = upper = None        # a zero-width range carries no sampling information
        elif max(abs(lower), abs(upper)) > UNLIMITED:
            lower = upper = None        # "unlimited" as an exporter writes it: a range that wide overflows
    return Joint(name=name, type=jtype, parent=ends["parent"], child=ends["child"], R=R, p=p, axis=axis,
                 lower=lower, upper=upper, where=where)


def limit_attributes(path: str | pathlib.Path, attr: str) -> dict[str, str | None]:
    """Each joint's `<limit attr>` as the file writes it (the text; None where absent), by joint name: one reading
    of the URDF's limits for the effort (the torque limit) and the velocity (`checks.limits`)."""
    root = ET.fromstring(pathlib.Path(path).read_bytes())
    out: dict[str, str | None] = {}
    for el in root.findall("joint"):
        lim = el.find("limit")
        out[el.get("name", "")] = None if lim is None else lim.get(attr)
    return out


def effort_limits(path: str | pathlib.Path) -> list[float | None]:
    """Each movable joint's `<limit effort>` (N m or N) in the model's coordinate order; None where absent."""
    tree = parse_urdf(path)
    effort: dict[str, float | None] = {}
    for name, value in limit_attributes(path, "effort").items():
        try:
            effort[name] = None if value is None else float(value)
            if value is not None and not (math.isfinite(effort[name])):
                raise ValueError(value)
        except ValueError:
            raise InputError(f"has effort '{value}'", file=str(path), key=f"joint[{name}]/limit@effort",
                             expected="a finite number") from None
    return [effort.get(name) for name in movable_joint_names(tree)]

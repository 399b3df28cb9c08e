"""Models from link data (planar, dh, urdf) against Pinocchio, closed forms, Christoffel structure and bad input."""

from __future__ import annotations

import math
import pathlib
import time

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from symfunnel.core.errors import InputError
from symfunnel.model.base import christoffel_C
from symfunnel.model.links import build_dh, build_planar
from symfunnel.model.urdf import build_urdf, movable_joint_names, parse_urdf

pin = pytest.importorskip("pinocchio")

DATA = pathlib.Path(__file__).parent / "data"
BUILTIN = pathlib.Path(__file__).parent.parent / "symfunnel" / "data"
SCEN = "scenario.toml"


# ---------------------------------------------------------------- helpers

def model_functions(m):
    """Numeric M, C, G and dM/dt (by casadi.jtimes) of a RigidBodyModel."""
    n = m.n
    Mdot = ca.reshape(ca.jtimes(ca.vec(m.M), m.q, m.dq), n, n)
    return ca.Function("f", [m.q, m.dq], [m.M, m.C, m.G, Mdot])


class PinocchioRef:
    """Pinocchio's M, C dq and G for a URDF, permuted into our coordinate order by joint name."""

    def __init__(self, urdf: str | pathlib.Path, names: list[str], gravity, *, xml: str | None = None):
        self.model = (pin.buildModelFromXML(xml) if xml is not None
                      else pin.buildModelFromUrdf(str(urdf), mimic=False))
        self.model.gravity = pin.Motion(np.concatenate([np.asarray(gravity, float), np.zeros(3)]))
        self.data = self.model.createData()
        pin_names = [self.model.names[i] for i in range(1, self.model.njoints)]
        assert sorted(pin_names) == sorted(names)
        self.joints = [self.model.joints[self.model.getJointId(nm)] for nm in names]
        self.v_idx = np.array([j.idx_v for j in self.joints])

    def q_pin(self, q):
        """Our angles as Pinocchio's configuration ([cos, sin] for continuous joints)."""
        out = np.zeros(self.model.nq)
        for j, x in zip(self.joints, q):
            if j.nq == 2:
                out[j.idx_q:j.idx_q + 2] = [math.cos(x), math.sin(x)]
            else:
                out[j.idx_q] = x
        return out

    def v_pin(self, dq):
        out = np.zeros(self.model.nv)
        out[self.v_idx] = dq
        return out

    def __call__(self, q, dq):
        qp, vp = self.q_pin(q), self.v_pin(dq)
        M = pin.crba(self.model, self.data, qp)
        M = np.triu(M) + np.triu(M, 1).T
        Cdq = pin.computeCoriolisMatrix(self.model, self.data, qp, vp) @ vp
        G = pin.computeGeneralizedGravity(self.model, self.data, qp)
        Cdq_rnea = pin.rnea(self.model, self.data, qp, vp, np.zeros(self.model.nv)) - G
        ix = self.v_idx
        return M[np.ix_(ix, ix)], Cdq[ix], G[ix], Cdq_rnea[ix]


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.linalg.norm(a - b) / max(1.0, np.linalg.norm(b)))


def compare_with_pinocchio(m, ref: PinocchioRef, states: int = 100, seed: int = 0) -> None:
    f = model_functions(m)
    rng = np.random.default_rng(seed)
    lo = np.where(np.isnan(m.joint_lower), -math.pi, m.joint_lower) if m.joint_lower is not None else -math.pi
    hi = np.where(np.isnan(m.joint_upper), math.pi, m.joint_upper) if m.joint_upper is not None else math.pi
    for _ in range(states):
        q = rng.uniform(lo, hi, m.n) if rng.random() < 0.5 else rng.uniform(-4, 4, m.n)
        dq = rng.uniform(-3, 3, m.n)
        M, C, G, _ = (np.array(x) for x in f(q, dq))
        Mp, Cdqp, Gp, Cdq_rnea = ref(q, dq)
        assert rel_err(M, Mp) < 1e-9
        assert rel_err(C @ dq, Cdqp) < 1e-9
        assert rel_err(C @ dq, Cdq_rnea) < 1e-9
        assert rel_err(G.ravel(), Gp) < 1e-9


def check_skew_and_christoffel(m, states: int = 100, seed: int = 1, against_base: bool = True) -> None:
    """dM/dt - 2C is skew-symmetric, M symmetric, and C is base.christoffel_C's matrix."""
    f = model_functions(m)
    g = ca.Function("g", [m.q, m.dq], [christoffel_C(m.M, m.q, m.dq)]) if against_base else None
    rng = np.random.default_rng(seed)
    for _ in range(states):
        q, dq = rng.uniform(-4, 4, m.n), rng.uniform(-3, 3, m.n)
        M, C, _, Mdot = (np.array(x) for x in f(q, dq))
        N = Mdot - 2 * C
        assert np.abs(N + N.T).max() <= 1e-11 * max(1.0, np.abs(N).max())
        assert np.array_equal(M, M.T)
        if g is not None:
            assert rel_err(C, np.array(g(q, dq))) < 1e-12


def urdf_model(path: pathlib.Path, **extra):
    table = {"type": "urdf", "path": path.name, **extra}
    return build_urdf(table, file=SCEN, base_dir=path.parent)


# ---------------------------------------------------------------- URDF against Pinocchio

def test_arm7_matches_pinocchio():
    path = BUILTIN / "arm7.urdf"
    m = urdf_model(path)
    names = movable_joint_names(parse_urdf(path))
    ref = PinocchioRef(path, names, [0, 0, -9.81])
    assert [ref.model.names[i] for i in range(1, 8)] == names == [f"joint{i}" for i in range(1, 8)]
    assert m.kind == "urdf" and m.coordinates == [f"q{i}" for i in range(1, 8)]
    assert m.C_source == "christoffel" and m.joint_types == ["revolute"] * 7
    assert m.M.shape == (7, 7) and m.C.shape == (7, 7) and m.G.shape == (7, 1)
    assert m.joint_lower[3] == -3.0718 and m.joint_upper[5] == 3.7525
    compare_with_pinocchio(m, ref)


def test_arm7_full_coriolis_matrix_equals_pinocchio():
    """Not required by the Christoffel contract, but Pinocchio's C is also the Christoffel one."""
    path = BUILTIN / "arm7.urdf"
    m = urdf_model(path)
    ref = PinocchioRef(path, movable_joint_names(parse_urdf(path)), [0, 0, -9.81])
    f = model_functions(m)
    rng = np.random.default_rng(5)
    for _ in range(20):
        q, dq = rng.uniform(-3, 3, 7), rng.uniform(-2, 2, 7)
        Cp = pin.computeCoriolisMatrix(ref.model, ref.data, q, dq)
        assert rel_err(np.array(f(q, dq)[1]), Cp) < 1e-9


def test_arm7_other_gravity_and_structure():
    path = BUILTIN / "arm7.urdf"
    g = [1.5, -2.0, -9.0]
    m = urdf_model(path, gravity=g)
    ref = PinocchioRef(path, movable_joint_names(parse_urdf(path)), g)
    compare_with_pinocchio(m, ref, states=30, seed=3)
    # body-frame CRBA: M (and hence C) does not depend on q1 even structurally
    assert not ca.depends_on(m.M, m.q[0])
    check_skew_and_christoffel(m, states=100)


def test_arm7_build_is_fast_and_small():
    t0 = time.perf_counter()
    m = urdf_model(BUILTIN / "arm7.urdf")
    elapsed = time.perf_counter() - t0
    ops = ca.Function("dyn", [m.q, m.dq], [m.M, m.C, m.G]).n_instructions()
    assert elapsed < 3.0
    assert ops < 20000


def test_prismatic_robot_matches_pinocchio():
    path = DATA / "prismatic.urdf"
    m = urdf_model(path)
    names = movable_joint_names(parse_urdf(path))
    assert names == ["slide_x", "lift", "turn", "tele"]
    assert m.joint_types == ["prismatic", "prismatic", "revolute", "prismatic"]
    np.testing.assert_array_equal(m.joint_lower, [-0.5, 0, -2, -0.1])
    compare_with_pinocchio(m, PinocchioRef(path, names, [0, 0, -9.81]))
    check_skew_and_christoffel(m)


def test_branched_continuous_fixed_massless_mimic_matches_pinocchio():
    path = DATA / "branched.urdf"
    m = urdf_model(path)
    names = movable_joint_names(parse_urdf(path))
    # depth-first, children in document order (Pinocchio sorts siblings by name: compared by name)
    assert names == ["z_shoulder", "b_elbow", "a_wrist", "a_side"]
    assert m.joint_types == ["continuous", "continuous", "revolute", "revolute"]
    assert np.isnan(m.joint_lower[0]) and np.isnan(m.joint_upper[1])
    assert m.joint_lower[2] == -1 and m.joint_upper[3] == 2.5
    ref = PinocchioRef(path, names, [0.3, 0.0, -9.81])
    assert ref.model.nq == 6      # the mimic tag did not couple b_elbow to z_shoulder
    m = urdf_model(path, gravity=[0.3, 0.0, -9.81])
    compare_with_pinocchio(m, ref)
    check_skew_and_christoffel(m)


def test_urdf_coordinates_and_joint_range():
    path = DATA / "branched.urdf"
    m = urdf_model(path, coordinates=["a", "b", "c", "d"], joint_range=[-1, 1])
    assert [str(x) for x in ca.vertsplit(m.q)] == ["a", "b", "c", "d"]
    assert [str(x) for x in ca.vertsplit(m.dq)] == ["da", "db", "dc", "dd"]
    np.testing.assert_array_equal(m.joint_lower, [-1] * 4)
    m = urdf_model(path, joint_range=[[-1, 1], [-2, 2], [-3, 3], [-4, 4]])
    np.testing.assert_array_equal(m.joint_upper, [1, 2, 3, 4])


# ---------------------------------------------------------------- planar

def test_planar_two_link_closed_form():
    m1, m2, l1, l2, c1, c2, I1, I2, g = 1.3, 0.9, 0.7, 0.5, 0.3, 0.2, 0.05, 0.03, 9.81
    table = {"type": "planar", "links": [
        {"mass": m1, "length": l1, "com": c1, "inertia": I1},
        {"mass": m2, "length": l2, "com": c2, "inertia": I2}]}
    m = build_planar(table, file=SCEN)
    assert m.kind == "planar" and m.joint_types == ["revolute", "revolute"] and m.joint_lower is None
    f = model_functions(m)
    rng = np.random.default_rng(0)
    for _ in range(100):
        q, dq = rng.uniform(-4, 4, 2), rng.uniform(-3, 3, 2)
        M, C, G, _ = (np.array(x) for x in f(q, dq))
        cq2 = math.cos(q[1])
        Me = np.array([[m1 * c1**2 + I1 + m2 * (l1**2 + c2**2 + 2 * l1 * c2 * cq2) + I2,
                        m2 * (c2**2 + l1 * c2 * cq2) + I2],
                       [m2 * (c2**2 + l1 * c2 * cq2) + I2, m2 * c2**2 + I2]])
        h = -m2 * l1 * c2 * math.sin(q[1])
        Ce = np.array([[h * dq[1], h * (dq[0] + dq[1])], [-h * dq[0], 0.0]])   # the Christoffel C
        Ge = np.array([(m1 * c1 + m2 * l1) * g * math.cos(q[0]) + m2 * c2 * g * math.cos(q[0] + q[1]),
                       m2 * c2 * g * math.cos(q[0] + q[1])])
        assert rel_err(M, Me) < 1e-12 and rel_err(C, Ce) < 1e-12 and rel_err(G.ravel(), Ge) < 1e-12


def test_planar_defaults_gravity_and_range():
    table = {"type": "planar", "gravity": [0.0, -3.0], "joint_range": [[-1, 1], [-2, 2]],
             "links": [{"mass": 2.0, "length": 1.0}, {"mass": 1.0, "length": 0.5}]}
    m = build_planar(table, file=SCEN)
    np.testing.assert_array_equal(m.joint_upper, [1, 2])
    G = np.array(ca.Function("G", [m.q], [m.G])([0.0, 0.0])).ravel()
    # rods with COM at mid-length, horizontal: G1 = g (m1 l1/2 + m2 (l1 + l2/2)), G2 = g m2 l2/2
    np.testing.assert_allclose(G, [3.0 * (1.0 + 1.0 * 1.25), 3.0 * 0.25], rtol=1e-14)
    M = np.array(ca.Function("M", [m.q], [m.M])([0.0, 0.0]))
    assert M[1, 1] == pytest.approx(1.0 * 0.25**2 + 1.0 * 0.5**2 / 12)


def planar_urdf(links) -> str:
    """An independent URDF of a planar arm (joints about z, links along x)."""
    parts = ['<robot name="planar"><link name="l0"/>']
    x = 0.0
    for i, (mass, length, com, inertia) in enumerate(links, start=1):
        parts.append(f'<link name="l{i}"><inertial><origin xyz="{com!r} 0 0"/><mass value="{mass!r}"/>'
                     f'<inertia ixx="0" ixy="0" ixz="0" iyy="{inertia!r}" iyz="0" izz="{inertia!r}"/>'
                     '</inertial></link>')
        parts.append(f'<joint name="j{i}" type="continuous"><parent link="l{i - 1}"/><child link="l{i}"/>'
                     f'<origin xyz="{x!r} 0 0"/><axis xyz="0 0 1"/></joint>')
        x = length
    parts.append("</robot>")
    return "".join(parts)


def test_planar_three_link_matches_pinocchio():
    links = [(1.0, 0.8, 0.35, 0.06), (0.7, 0.6, 0.25, 0.03), (0.4, 0.3, 0.1, 0.004)]
    table = {"type": "planar", "links": [dict(mass=a, length=b, com=c, inertia=d) for a, b, c, d in links]}
    m = build_planar(table, file=SCEN)
    ref = PinocchioRef(None, ["j1", "j2", "j3"], [0, -9.81, 0], xml=planar_urdf(links))
    compare_with_pinocchio(m, ref)
    check_skew_and_christoffel(m)


# ---------------------------------------------------------------- DH

def dh_urdf(rows, convention: str) -> str:
    """An independent URDF of a DH table: massless joint links plus fixed joints (Rx, Tx commute)."""
    parts = ['<robot name="dh"><link name="L0"/>']
    for i, r in enumerate(rows, start=1):
        jt = r["joint"]
        c = r["com"]
        I = r["inertia"]
        inertial = (f'<inertial><origin xyz="{c[0]!r} {c[1]!r} {c[2]!r}"/><mass value="{r["mass"]!r}"/>'
                    f'<inertia ixx="{I[0]!r}" iyy="{I[1]!r}" izz="{I[2]!r}" ixy="{I[3]!r}" iyz="{I[4]!r}" '
                    f'ixz="{I[5]!r}"/></inertial>')
        limit = '<limit lower="-10" upper="10" effort="1" velocity="1"/>'
        zjoint = (f'<joint name="j{i}" type="{jt}"><parent link="{{p}}"/><child link="{{c}}"/>'
                  f'<origin xyz="0 0 {r["d"]!r}" rpy="0 0 {r["theta"]!r}"/><axis xyz="0 0 1"/>{limit}</joint>')
        xfixed = (f'<joint name="x{i}" type="fixed"><parent link="{{p}}"/><child link="{{c}}"/>'
                  f'<origin xyz="{r["a"]!r} 0 0" rpy="{r["alpha"]!r} 0 0"/></joint>')
        if convention == "standard":      # Rz(theta) Tz(d) [joint] Tx(a) Rx(alpha); link frame distal
            parts.append(f'<link name="J{i}"/><link name="L{i}">{inertial}</link>')
            parts.append(zjoint.format(p=f"L{i - 1}", c=f"J{i}"))
            parts.append(xfixed.format(p=f"J{i}", c=f"L{i}"))
        else:                              # Rx(alpha) Tx(a) Rz(theta) Tz(d) [joint]; link frame proximal
            parts.append(f'<link name="X{i}"/><link name="L{i}">{inertial}</link>')
            parts.append(xfixed.format(p=f"L{i - 1}", c=f"X{i}"))
            parts.append(zjoint.format(p=f"X{i}", c=f"L{i}"))
    parts.append("</robot>")
    return "".join(parts)


def random_dh_rows(rng, n: int) -> list[dict]:
    rows = []
    for k in range(n):
        mass = float(rng.uniform(0.2, 3.0))
        box = rng.uniform(0.02, 0.3, 3)
        moments = mass / 12 * np.array([box[1]**2 + box[2]**2, box[0]**2 + box[2]**2, box[0]**2 + box[1]**2])
        A = rng.normal(size=(3, 3))
        Q, _ = np.linalg.qr(A)
        I = Q @ np.diag(moments) @ Q.T
        rows.append({"a": float(rng.uniform(-0.5, 0.5)), "alpha": float(rng.uniform(-math.pi, math.pi)),
                     "d": float(rng.uniform(-0.4, 0.4)), "theta": float(rng.uniform(-math.pi, math.pi)),
                     "joint": "prismatic" if (k > 0 and rng.random() < 0.3) else "revolute",
                     "mass": mass, "com": [float(x) for x in rng.uniform(-0.2, 0.2, 3)],
                     "inertia": [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]),
                                 float(I[0, 1]), float(I[1, 2]), float(I[0, 2])]})
    return rows


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_dh_matches_pinocchio(convention):
    rows = random_dh_rows(np.random.default_rng(7), 5)
    rows[2]["joint"] = "prismatic"
    m = build_dh({"type": "dh", "convention": convention, "links": rows}, file=SCEN)
    assert m.kind == "dh" and m.joint_types[2] == "prismatic"
    ref = PinocchioRef(None, [f"j{i}" for i in range(1, 6)], [0, 0, -9.81], xml=dh_urdf(rows, convention))
    compare_with_pinocchio(m, ref)
    check_skew_and_christoffel(m)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4),
       convention=st.sampled_from(["standard", "modified"]))
def test_dh_random_tables_match_pinocchio(seed, n, convention):
    rng = np.random.default_rng(seed)
    rows = random_dh_rows(rng, n)
    gravity = [float(x) for x in rng.uniform(-10, 10, 3)]
    m = build_dh({"type": "dh", "convention": convention, "links": rows, "gravity": gravity}, file=SCEN)
    ref = PinocchioRef(None, [f"j{i}" for i in range(1, n + 1)], gravity, xml=dh_urdf(rows, convention))
    compare_with_pinocchio(m, ref, states=10, seed=seed % 1000)


def test_dh_standard_and_modified_differ_and_qlim():
    rows = [{"a": 0.0, "alpha": math.pi / 2, "d": 0.3, "mass": 2.0, "com": [0, -0.1, 0],
             "inertia": [0.02, 0.01, 0.02], "qlim": [-2, 2]},
            {"a": 0.4, "mass": 1.5, "com": [-0.2, 0, 0], "inertia": [0.001, 0.02, 0.02, 0, 0, 0]}]
    s = build_dh({"type": "dh", "convention": "standard", "links": rows}, file=SCEN)
    mo = build_dh({"type": "dh", "convention": "modified", "links": rows}, file=SCEN)
    assert s.joint_lower[0] == -2 and np.isnan(s.joint_lower[1])
    q = [0.3, -0.7]
    Ms = np.array(ca.Function("M", [s.q], [s.M])(q))
    Mm = np.array(ca.Function("M", [mo.q], [mo.M])(q))
    assert np.abs(Ms - Mm).max() > 1e-3


def test_dh_vertical_two_link_closed_form():
    """Standard DH with alpha = 0 about a horizontal base z is the planar arm; compare G with the closed form."""
    g = 9.81
    rows = [{"a": 1.0, "mass": 2.0, "com": [-0.5, 0, 0], "inertia": [0, 0.1, 0.1]},
            {"a": 0.8, "mass": 1.0, "com": [-0.4, 0, 0], "inertia": [0, 0.05, 0.05]}]
    m = build_dh({"type": "dh", "convention": "standard", "links": rows, "gravity": [0, -g, 0]}, file=SCEN)
    q = np.array([0.4, -1.1])
    G = np.array(ca.Function("G", [m.q], [m.G])(q)).ravel()
    Ge = [(2.0 * 0.5 + 1.0 * 1.0) * g * math.cos(q[0]) + 1.0 * 0.4 * g * math.cos(q.sum()),
          1.0 * 0.4 * g * math.cos(q.sum())]
    np.testing.assert_allclose(G, Ge, rtol=1e-13)


# ---------------------------------------------------------------- bad input

ROBOT = """<?xml version="1.0"?>
<robot name="t">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0.1 0 0"/><mass value="{mass}"/>
    <inertia ixx="{ixx}" ixy="0" ixz="0" iyy="{iyy}" iyz="0" izz="{izz}"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.1 0 0"/><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <joint name="j1" type="{jtype}"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="{child2}"/><axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  {extra}
</robot>
"""


def write_robot(tmp_path, **kw) -> pathlib.Path:
    args = dict(mass="1", ixx="0.01", iyy="0.01", izz="0.01", jtype="revolute", child2="l2", extra="")
    args.update(kw)
    path = tmp_path / "robot.urdf"
    path.write_text(ROBOT.format(**args))
    return path


def test_template_robot_is_good(tmp_path):
    assert urdf_model(write_robot(tmp_path)).n == 2


@pytest.mark.parametrize("kw, words", [
    (dict(mass="-1"), ["link[l1]/inertial/mass@value", "mass >= 0"]),
    (dict(ixx="-0.01"), ["link[l1]/inertial/inertia", "positive semi-definite"]),
    (dict(ixx="0.01", iyy="0.01", izz="0.05"), ["link[l1]/inertial/inertia", "triangle inequality"]),
    (dict(jtype="floating"), ["joint[j1]@type", "floating base"]),
    (dict(jtype="planar"), ["joint[j1]@type", "not supported"]),
    (dict(jtype="revolut"), ["joint[j1]@type", "did you mean 'revolute'"]),
    (dict(child2="l3"), ["joint[j2]", "'l3', which does not exist"]),
    (dict(extra='<joint name="j3" type="revolute"><parent link="base"/><child link="l2"/></joint>'),
     ["joint[j3]", "closed kinematic loop"]),
    (dict(extra='<link name="stray"/>'), ["2 root links", "'stray'"]),
    (dict(extra='<link name="l3"/><joint name="j3" type="prismatic"><parent link="l2"/><child link="l3"/>'
                '<axis xyz="1 0 0"/></joint>'), ["joint[j3]", "moves no mass"]),
    (dict(extra='<link name="l3"><inertial><mass value="1"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" '
                'iyz="0" izz="0"/></inertial></link><joint name="j3" type="continuous"><parent link="l2"/>'
                '<child link="l3"/><axis xyz="1 0 0"/></joint>'), ["joint[j3]", "M(q) is positive definite"]),
    (dict(extra='<link name="l3"/><joint name="j3" type="fixed"><parent link="l2"/><child link="l3"/>'
                '<origin xyz="1 2"/></joint>'), ["joint[j3]/origin@xyz", "3 finite number"]),
    (dict(extra='<link name="l3"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" '
                'iyz="0" izz="1"/></inertial></link><joint name="j3" type="revolute"><parent link="l2"/>'
                '<child link="l3"/><axis xyz="0 0 0"/></joint>'), ["joint[j3]/axis@xyz", "non-zero"]),
])
def test_bad_urdf(tmp_path, kw, words):
    path = write_robot(tmp_path, **kw)
    with pytest.raises(InputError) as e:
        urdf_model(path)
    text = str(e.value)
    assert str(path) in text and e.value.exit_code == 2
    for w in words:
        assert w in text, text


def test_urdf_xml_syntax_error(tmp_path):
    path = tmp_path / "bad.urdf"
    path.write_text('<robot name="x">\n  <link name="a">\n</robot>\n')
    with pytest.raises(InputError, match=r"bad\.urdf.*not well-formed XML at line 3"):
        urdf_model(path)


def test_urdf_missing_file(tmp_path):
    with pytest.raises(InputError) as e:
        build_urdf({"type": "urdf", "path": "nope.urdf"}, file=SCEN, base_dir=tmp_path)
    assert "scenario.toml" in str(e.value) and "model.path" in str(e.value) and "nope.urdf" in str(e.value)


@pytest.mark.parametrize("extra, words", [
    ({"gravty": [0, 0, -9.81]}, ["model.gravty", "did you mean 'gravity'"]),
    ({"gravity": [0, -9.81]}, ["model.gravity", "3 numbers"]),
    ({"coordinates": ["a", "b", "c"]}, ["model.coordinates", "2 names"]),
    ({"coordinates": ["a", "a"]}, ["model.coordinates", "distinct"]),
    ({"coordinates": ["a", "1b"]}, ["model.coordinates[1]"]),
    ({"joint_range": [1, -1]}, ["model.joint_range", "lower < upper"]),
    ({"joint_range": [[-1, 1]]}, ["model.joint_range", "2 such pairs"]),
])
def test_bad_urdf_table(tmp_path, extra, words):
    path = write_robot(tmp_path)
    with pytest.raises(InputError) as e:
        urdf_model(path, **extra)
    for w in ["scenario.toml"] + words:
        assert w in str(e.value), str(e.value)


PLANAR = {"type": "planar", "links": [{"mass": 1.0, "length": 1.0}, {"mass": 1.0, "length": 1.0}]}


@pytest.mark.parametrize("change, words", [
    (lambda t: t["links"][1].update(mass=-1.0), ["model.links[1].mass", ">= 0"]),
    (lambda t: t["links"][0].update(lenght=1.0), ["model.links[0].lenght", "did you mean 'length'"]),
    (lambda t: t["links"][1].pop("length"), ["model.links[1].length", "missing"]),
    (lambda t: t["links"][1].update(mass=0.0, inertia=0.0), ["model.links[1]", "moves no mass"]),
    (lambda t: t.update(links=[]), ["model.links", "at least one link"]),
    (lambda t: t.update(links="two"), ["model.links", "an array"]),
    (lambda t: t.update(gravity=[0, -9.81, 0, 0]), ["model.gravity", "2 or 3 numbers"]),
])
def test_bad_planar(change, words):
    import copy
    table = copy.deepcopy(PLANAR)
    change(table)
    with pytest.raises(InputError) as e:
        build_planar(table, file=SCEN)
    for w in ["scenario.toml"] + words:
        assert w in str(e.value), str(e.value)


DH = {"type": "dh", "convention": "standard",
      "links": [{"a": 0.5, "mass": 1.0, "com": [-0.25, 0, 0], "inertia": [0.001, 0.02, 0.02]},
                {"a": 0.5, "alpha": 0.3, "mass": 1.0, "com": [-0.25, 0, 0], "inertia": [0.001, 0.02, 0.02]}]}


@pytest.mark.parametrize("change, words", [
    (lambda t: t.update(convention="standrad"), ["model.convention", "did you mean 'standard'"]),
    (lambda t: t.pop("convention"), ["model.convention", "missing"]),
    (lambda t: t["links"][1].update(mass=-2.0), ["model.links[1].mass", "mass >= 0"]),
    (lambda t: t["links"][1].update(inertia=[0.001, 0.001, 0.02]), ["model.links[1].inertia", "triangle"]),
    (lambda t: t["links"][1].update(inertia=[0.02, 0.02, 0.02, 0.03, 0, 0]),
     ["model.links[1].inertia", "positive semi-definite"]),
    (lambda t: t["links"][0].update(joint="rotary"), ["model.links[0].joint", "'revolute'"]),
    (lambda t: t["links"][0].update(qlim=[1, 0]), ["model.links[0].qlim", "lower < upper"]),
    (lambda t: t["links"][1].update(com=[0, 0]), ["model.links[1].com", "3 numbers"]),
    (lambda t: t["links"][1].update(offset=0.1), ["model.links[1].offset", "unknown key"]),
])
def test_bad_dh(change, words):
    import copy
    table = copy.deepcopy(DH)
    change(table)
    with pytest.raises(InputError) as e:
        build_dh(table, file=SCEN)
    for w in ["scenario.toml"] + words:
        assert w in str(e.value), str(e.value)


def test_dh_point_mass_on_last_axis_is_singular():
    """A revolute joint carrying only a point mass on its own axis has M_nn = 0: named, not a crash."""
    table = {"type": "dh", "convention": "modified",
             "links": [{"a": 0.0, "mass": 1.0, "com": [0.3, 0, 0], "inertia": [0.01, 0.01, 0.01]},
                       {"a": 0.5, "mass": 1.0, "com": [0, 0, 0.2]}]}
    with pytest.raises(InputError, match=r"model\.links\[1\].*joint 'joint2'.*zero"):
        build_dh(table, file=SCEN)

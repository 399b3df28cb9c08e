"""MuJoCo as an independent plant: loading a robot into it, `plant.engine_agreement`, the sampled loop on the engine
(against symfunnel's own plant and against itself at halved substeps), engine-only mismatch, sweeps, the report's
section and every bad input of `[plant] engine` / `--plant`."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mujoco  # noqa: E402,F401 - a declared test dependency ([test] extra): missing, these tests error, never skip

from symfunnel.checks.engine import check_engine_agreement  # noqa: E402
from symfunnel.cli import main  # noqa: E402
from symfunnel.core.errors import InputError  # noqa: E402
from symfunnel.deployed.engine import EngineRunPlant, engine_setup  # noqa: E402
from symfunnel.deployed.loop import plant_substeps, simulate_sampled  # noqa: E402
from symfunnel.design import derive  # noqa: E402
from symfunnel.plant.mujoco import agreement, load_engine, prepare_urdf  # noqa: E402
from symfunnel.scenario import DATA_DIR, load_scenario  # noqa: E402

from .pins import pins  # noqa: E402

TESTS = Path(__file__).parent
URDFS = {"branched": TESTS / "data" / "branched.urdf", "prismatic": TESTS / "data" / "prismatic.urdf",
         "panda": TESTS / "data" / "third_party" / "panda.urdf"}
RATE = 3512.5        # twice arm7's minimum rate (1756 Hz by `symfunnel rate arm7`, on either plant)


@pytest.fixture(scope="module")
def arm7():
    sc = load_scenario("arm7")
    return sc, derive(sc)


def init_scenario(tmp_path: Path, urdf: Path | None = None, extra: str = "", name: str = "s.toml") -> Path:
    """`symfunnel init` (a 2-link planar arm, or a URDF's joints) plus extra TOML, as a file."""
    out = tmp_path / name
    args = ["init", "--out", str(out), "--force", "-q"] + (["--urdf", str(urdf)] if urdf else [])
    assert main(args) == 0
    if extra:
        out.write_text(out.read_text() + "\n" + extra + "\n")
    return out


def arm7_with(tmp_path: Path, extra: str, name: str = "a.toml") -> Path:
    """arm7 with extra TOML (its URDF copied beside it)."""
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    p = tmp_path / name
    p.write_text((DATA_DIR / "arm7.toml").read_text() + "\n" + extra + "\n")
    return p


def run_plant(sc, **mujoco):
    """The scenario's nominal run plant on the engine with [plant.mujoco] settings replaced."""
    setup = engine_setup(sc)
    return EngineRunPlant(setup.p0.copy(), dataclasses.replace(sc.plant.mujoco, **mujoco),
                          np.asarray(sc.q0, dtype=float), np.asarray(sc.dq0, dtype=float))


# --- loading and agreement ---------------------------------------------------------------------------

@pins("plant.engine_agreement", "pass")
@pytest.mark.parametrize("robot", ["arm7", "branched", "prismatic", "panda", "planar"])
def test_engine_agreement_passes_on_the_shipped_and_test_robots(tmp_path, robot):
    """MuJoCo's M and C dq + G equal symfunnel's (and Pinocchio's) to round-off at 200 states: <= 1e-8 required."""
    if robot == "arm7":
        sc = load_scenario("arm7")
    else:
        sc = load_scenario(init_scenario(tmp_path, None if robot == "planar" else URDFS[robot]))
    c = check_engine_agreement(sc)
    assert c.status == "pass" and c.value <= 1e-12, c.detail
    assert c.evidence["samples"] >= 200 and c.to_json()["value"] == c.value
    if robot != "planar":             # a URDF: Pinocchio is the third, independent opinion
        p = c.evidence["others"]["pinocchio"]
        assert max(p["M"], p["bias"], p["M_vs_engine"], p["bias_vs_engine"]) < 1e-12
    else:
        assert "MJCF written by symfunnel" in c.detail and c.evidence["notes"]
    if robot in ("panda", "branched"):  # init holds a mimic joint fixed: the engine holds it too, and says so
        held = {"panda": "panda_finger_joint2", "branched": "b_elbow"}[robot]
        assert any("held fixed" in s and held in s for s in c.evidence["notes"])
        assert not any("<mimic> ignored" in s for s in c.evidence["notes"])
        assert f"held fixed at 0 by both (model.fixed_joints): {held}" in c.detail
    if robot == "panda":              # its <dynamics damping> is the engine's, not the controller's
        assert c.evidence["engine_only"]["damping"] == [0.003] * 7 + [0.3]
        assert "in the engine, not in the controller's model: joint damping" in c.detail
        assert c.evidence["engine_only"].get("frictionloss") is None



def test_engine_keeps_a_mimic_joint_left_movable_as_its_own_coordinate():
    """Without model.fixed_joints the mimic joint is a coordinate in both models: MuJoCo 4's parser would make its
    <mimic> an equality constraint; the engine drops it (as symfunnel ignores it), says so, and agrees."""
    import casadi as ca

    from symfunnel.model.urdf import build_urdf
    urdf = URDFS["panda"]
    model = build_urdf({"type": "urdf", "path": urdf.name}, file="s.toml", base_dir=urdf.parent)
    eng = load_engine(model, file="s.toml")
    assert eng.n == eng.model.nv == 9 and eng.names[-1] == "panda_finger_joint2"
    assert eng.notes.mimic == ["panda_finger_joint2"] and eng.notes.held == []
    assert any("<mimic> ignored" in s and "panda_finger_joint2" in s for s in eng.notes.lines())
    Mf = ca.Function("M", [model.q], [model.numeric(model.M)])
    Cf = ca.Function("C", [model.q, model.dq], [model.numeric(model.C)])
    Gf = ca.Function("G", [model.q], [model.numeric(model.G)])
    r = agreement(eng, lambda q: np.array(Mf(q)),
                  lambda q, dq: (np.array(Cf(q, dq)) @ np.asarray(dq).reshape(-1, 1)).ravel() + np.array(Gf(q)).ravel(),
                  -1.0, 1.0, 1.0, samples=50)
    assert r["value"] <= 1e-12, r
    text, notes = prepare_urdf(urdf, gravity=[0.0, 0.0, -9.81])
    assert "<mimic" not in text and notes.held == []
    text, notes = prepare_urdf(urdf, gravity=[0.0, 0.0, -9.81], fixed=["panda_finger_joint2"])
    assert notes.held == ["panda_finger_joint2"] and notes.mimic == [] and "<mimic" not in text

def dh_table(convention: str, seed: int) -> dict:
    """A random 4-joint DH arm (one prismatic joint) with full inertia tensors."""
    rng = np.random.default_rng(seed)
    links = []
    for k in range(4):
        m = float(rng.uniform(0.3, 3.0))
        box = rng.uniform(0.03, 0.3, 3)
        mom = m / 12 * np.array([box[1] ** 2 + box[2] ** 2, box[0] ** 2 + box[2] ** 2, box[0] ** 2 + box[1] ** 2])
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        I = Q @ np.diag(mom) @ Q.T
        links.append({"a": float(rng.uniform(-0.4, 0.4)), "alpha": float(rng.uniform(-3, 3)),
                      "d": float(rng.uniform(-0.3, 0.3)), "theta": float(rng.uniform(-3, 3)),
                      "joint": "prismatic" if k == 2 else "revolute", "mass": m,
                      "com": rng.uniform(-0.2, 0.2, 3).tolist(),
                      "inertia": [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[1, 2], I[0, 2]]})
    return {"type": "dh", "convention": convention, "links": links, "gravity": [0.3, -1.0, -9.81]}


@pytest.mark.parametrize("convention", ["standard", "modified"])
def test_mjcf_written_from_a_dh_table_agrees(convention):
    import casadi as ca

    from symfunnel.model.links import build_dh
    m = build_dh(dh_table(convention, 3), file="dh.toml")
    eng = load_engine(m, file="dh.toml")
    Mf = ca.Function("M", [m.q], [m.M])
    b = ca.Function("b", [m.q, m.dq], [ca.mtimes(m.C, m.dq) + m.G])
    r = agreement(eng, lambda q: np.array(Mf(q)), lambda q, dq: np.array(b(q, dq)).ravel(), -2.0, 2.0, 2.0)
    assert r["M"] < 1e-12 and r["bias"] < 1e-12, r


ROTATED = """<?xml version="1.0"?>
<robot name="rotated">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0 0 0.1"/><mass value="2.0"/>
    <inertia ixx="0.02" iyy="0.02" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.1 0.02 0.2" rpy="0.4 -0.7 1.1"/><mass value="1.5"/>
    <inertia ixx="0.02" iyy="0.015" izz="0.01" ixy="0.001" ixz="-0.002" iyz="0.0015"/></inertial></link>
  <link name="l3"><inertial><origin xyz="0 0 0.15"/><mass value="0.8"/>
    <inertia ixx="0.004" iyy="0.004" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.3"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/><dynamics damping="0.7" friction="0.0"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0 0 0.4"/><axis xyz="1 0 0"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/><dynamics damping="0.2"/></joint>
</robot>
"""


@pytest.fixture
def rotated(tmp_path):
    """A URDF whose link l2 has its inertia in a frame rotated about all three axes, and joint damping."""
    urdf = tmp_path / "rotated.urdf"
    urdf.write_text(ROTATED)
    return init_scenario(tmp_path, urdf)


def test_rotated_inertia_frame_and_joint_damping_agree(rotated):
    sc = load_scenario(rotated)
    c = check_engine_agreement(sc)
    assert c.status == "pass" and c.value < 1e-12, c.detail
    assert c.evidence["engine_only"]["damping"] == [0.0, 0.7, 0.2]
    assert "in the engine, not in the controller's model: joint damping [0, 0.7, 0.2]" in c.detail


@pins("plant.engine_agreement", "fail")
def test_a_wrong_rpy_convention_in_symfunnels_import_is_found_at_its_joint(rotated, monkeypatch):
    """The mutant: symfunnel's URDF import composes rpy in the wrong order (R = Rx Ry Rz instead of Rz Ry Rx). Only
    l2's inertial frame has a rotation about several axes, so the models part at joint j2, and Pinocchio (which
    reads the file itself) sides with MuJoCo."""
    import symfunnel.model.urdf as U
    from symfunnel.model.tree import rot_x, rot_y, rot_z
    monkeypatch.setattr(U, "rpy_matrix", lambda rpy: rot_x(rpy[0]) @ rot_y(rpy[1]) @ rot_z(rpy[2]))
    sc = load_scenario(rotated)
    c = check_engine_agreement(sc)
    assert c.status == "fail" and c.value > 1e-4
    assert c.where["joint"] == "j2" and c.evidence["per_joint_M"]["j3"] < 1e-12
    assert "deepest joint that disagrees is 'j2'" in c.detail and "Pinocchio sides with MuJoCo" in c.detail
    assert not c.unexpected or c.expected == "pass"


@pins("plant.engine_agreement", "fail")
def test_an_engine_that_reads_a_mass_wrong_is_found_at_its_joint(tmp_path):
    """The other side's mutant: the engine's body of the prismatic robot's third joint 0.1 % too heavy."""
    sc = load_scenario(init_scenario(tmp_path, URDFS["prismatic"]))
    setup = engine_setup(sc)
    eng = setup.engine
    b = eng.bodies[2]
    eng.nominal["body_mass"][b] *= 1.001
    try:
        c = check_engine_agreement(sc, setup=setup)
    finally:
        eng.nominal["body_mass"][b] /= 1.001
    assert c.status == "fail" and 1e-6 < c.value < 1e-2
    assert c.where["joint"] == eng.names[2]
    assert c.evidence["per_joint_M"][eng.names[2]] > 1e-6
    assert "Pinocchio sides with symfunnel" in c.detail


@pins("plant.engine_agreement", "fail", "pass")
def test_agreement_fails_at_1_5_times_its_tolerance_and_passes_at_0_6_times(tmp_path):
    """Near the boundary: the engine's body of the prismatic robot's joint 'turn' heavier by 4.1e-8 (relative
    error of C dq + G about 1.5e-8 > 1e-8: fail, at a joint carrying that body) and by 1.65e-8 (about 6e-9: pass). A tolerance doubled
    or halved, or a relative error taken against the wrong scale, moves one of the two outcomes."""
    sc = load_scenario(init_scenario(tmp_path, URDFS["prismatic"]))
    setup = engine_setup(sc)
    eng = setup.engine
    k = eng.names.index("turn")
    b = eng.bodies[k]
    m0 = eng.nominal["body_mass"][b]
    out = {}
    try:
        for eps in (4.14e-8, 1.65e-8):
            eng.nominal["body_mass"][b] = m0 * (1 + eps)
            out[eps] = check_engine_agreement(sc, setup=setup)
    finally:
        eng.nominal["body_mass"][b] = m0
    bad, ok = out[4.14e-8], out[1.65e-8]
    assert bad.status == "fail" and 1.2e-8 < bad.value < 2e-8 and bad.margin < 0, bad.detail
    pj = bad.evidence["per_joint_bias"]
    worst = max(pj, key=pj.get)
    assert bad.where["largest_bias"] == worst and pj[worst] == pytest.approx(bad.value)
    assert worst in ("slide_x", "lift", "turn")            # the joints that carry the body ...
    assert max(bad.evidence["per_joint_M"]["tele"], pj["tele"]) < 1e-12      # ... not its child's
    assert ok.status == "pass" and 4e-9 < ok.value < 8e-9 and ok.margin > 0, ok.detail
    assert ok.value == pytest.approx(bad.value * 1.65 / 4.14, rel=1e-3)      # linear in the mass error
    assert ok.to_json()["value"] == ok.value


def test_zero_principal_moments_are_raised_and_reported(tmp_path):
    """Planar links have I_xx = 0, which MuJoCo refuses: the floor is reported and does not move M."""
    sc = load_scenario(init_scenario(tmp_path))
    eng = engine_setup(sc).engine
    assert set(eng.notes.floored) == {"link1", "link2"} and max(eng.notes.floored.values()) < 1e-12
    assert any("zero principal moments raised" in s for s in eng.notes.lines())


# --- the sampled loop on the engine ------------------------------------------------------------------

def test_engine_and_symfunnel_plant_agree_to_round_off_at_the_same_substeps(arm7):
    """Same compiled step, same ODE (dead zone, friction, disturbance applied as in symfunnel's plant), same RK4
    substeps: the two plants' trajectories differ by round-off only."""
    sc, d = arm7
    h = 1.0 / RATE
    k = plant_substeps(sc, h)
    sym = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.3)
    mj = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.3, engine="mujoco",
                          plant=run_plant(sc, substeps=k, integrator="RK4"))
    assert sym.ok and mj.ok and mj.stats["plant_substeps"] == k == sym.stats["plant_substeps"]
    assert mj.stats["engine"] == "mujoco" and mj.stats["engine_force_callback"]
    assert np.abs(mj.q - sym.q).max() < 1e-10 and np.abs(mj.dq - sym.dq).max() < 1e-8
    assert np.abs(mj.tau - sym.tau).max() < 1e-6
    assert mujoco.get_mjcb_passive() is None          # the callback slot is restored


def test_without_friction_or_disturbance_the_callback_is_left_out(tmp_path):
    """The planar arm of `symfunnel init` without friction: no passive-force callback, and the MJCF written from its
    link tree gives the same trajectory as symfunnel's plant (dead zone on the held torque only)."""
    p = init_scenario(tmp_path)
    p.write_text(p.read_text().replace("viscous = 0.5 ", "viscous = 0.0 ").replace("coulomb = 0.2 ", "coulomb = 0.0 "))
    sc = load_scenario(p)
    assert sc.plant.viscous == [0.0, 0.0] and sc.plant.coulomb == [0.0, 0.0] and sc.plant.dead_zone is not None
    d = derive(sc)
    k = plant_substeps(sc, 1 / 400.0)
    sym = simulate_sampled(sc, d, rate_hz=400.0, t_final=1.0)
    mj = simulate_sampled(sc, d, rate_hz=400.0, t_final=1.0, engine="mujoco",
                          plant=run_plant(sc, substeps=k, integrator="RK4"))
    assert not mj.stats["engine_force_callback"] and sym.ok and mj.ok
    assert np.abs(mj.q - sym.q).max() < 1e-10


def test_engine_substeps_converge_at_fourth_order(arm7):
    """Halving MuJoCo's step: the error against a 128-step reference falls about 16x per halving (RK4, with the
    time-varying disturbance evaluated at each stage's time), and the default step is already well converged."""
    sc, d = arm7
    runs = {k: simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco",
                                plant=run_plant(sc, substeps=k, integrator="RK4")) for k in (16, 32, 64, 128)}
    default = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco", plant=run_plant(sc, integrator="RK4"))
    ref = runs[128].q
    err = {k: np.abs(r.q - ref).max() for k, r in runs.items() if k != 128}
    assert 10 < err[16] / err[32] < 25 and 10 < err[32] / err[64] < 25, err
    k0 = default.stats["plant_substeps"]
    assert 2 <= k0 < 16 and default.stats["engine_substeps_rule"].startswith("RK4 stability")
    assert default.stats["engine_integrator"] == "RK4"
    half = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco",
                            plant=run_plant(sc, substeps=2 * k0, integrator="RK4"))
    e0, e1 = np.abs(default.q - ref).max(), np.abs(half.q - ref).max()
    assert e0 < 1e-7 and e1 < e0 / 2


def test_implicitfast_converges_at_first_order_with_the_friction_slopes_implicit(arm7, monkeypatch):
    """The default integrator: halving implicitfast's step halves its distance from a 128-step RK4 reference (first
    order); the default step is the stated rule's and leaves the model's damping as it was. Over a 20 s run at one
    step per period, the smallest margin stays within 3e-3 of the 4-step run's because the friction's slope
    reaches MuJoCo's implicit step as damping: with the slopes switched off (the friction explicit), the same step
    moves it by more than 1e-2."""
    sc, d = arm7
    assert sc.plant.mujoco.integrator == "implicitfast"
    ref = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco",
                           plant=run_plant(sc, substeps=128, integrator="RK4"))
    runs = {k: simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco", plant=run_plant(sc, substeps=k))
            for k in (1, 2, 4, 8)}
    assert all(r.ok and r.stats["engine_integrator"] == "implicitfast" for r in runs.values())
    err = {k: np.abs(r.q - ref.q).max() for k, r in runs.items()}
    assert all(1.6 < err[k] / err[2 * k] < 2.5 for k in (1, 2, 4)), err
    assert err[1] < 1e-3
    default = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco")
    assert default.stats["plant_substeps"] == math.ceil(1 / RATE / 2.5e-4)
    assert default.stats["engine_substeps_rule"].startswith("implicitfast accuracy")
    assert np.array_equal(default.q, runs[default.stats["plant_substeps"]].q)
    eng = engine_setup(sc).engine
    assert np.array_equal(eng.model.dof_damping, eng.nominal["dof_damping"])
    assert mujoco.get_mjcb_passive() is None
    long = {k: simulate_sampled(sc, d, rate_hz=RATE, t_final=20.0, engine="mujoco",
                                plant=run_plant(sc, substeps=k)).min_margin for k in (1, 4)}
    setup = engine_setup(sc)
    real = setup.loop.sfs_mj_set_slopes
    monkeypatch.setattr(setup.loop, "sfs_mj_set_slopes", lambda on, base, n: real(0, base, n))
    off = simulate_sampled(sc, d, rate_hz=RATE, t_final=20.0, engine="mujoco", plant=run_plant(sc, substeps=1)).min_margin
    assert abs(long[1] - long[4]) < 3e-3 and abs(off - long[4]) > 1e-2, (long, off)


def test_engine_mass_scale_is_the_plants_mass_scale(arm7, tmp_path):
    """[plant.mujoco] mass_scale = 1.3 and damping 0.2 on arm7 (plant.mass_scale 1.1) are symfunnel's plant with
    mass_scale 1.43 and 0.2 more viscous friction: the trajectories agree to round-off at the same substeps."""
    sc, d = arm7
    text = (DATA_DIR / "arm7.toml").read_text()
    text = text.replace("mass_scale = 1.1 ", "mass_scale = 1.43 ").replace(
        "viscous = [0.5, 0.5, 0.4, 0.4, 0.1, 0.1, 0.05]", "viscous = [0.7, 0.7, 0.6, 0.6, 0.3, 0.3, 0.25]")
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    (tmp_path / "heavy.toml").write_text(text)
    heavy = load_scenario(tmp_path / "heavy.toml")
    assert heavy.plant.mass_scale == 1.43
    sym = simulate_sampled(heavy, d, rate_hz=RATE, t_final=0.2)
    k = sym.stats["plant_substeps"]
    mj = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco",
                          plant=run_plant(sc, substeps=k, mass_scale=[1.3] * 7, damping=[0.2] * 7, integrator="RK4"))
    assert np.abs(mj.q - sym.q).max() < 1e-10 and np.abs(mj.dq - sym.dq).max() < 1e-8
    assert mj.stats["engine_mass_scale"] == pytest.approx([1.43] * 7)
    assert mj.stats["engine_only"]["damping"] == pytest.approx([0.2] * 7)
    nominal = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco",
                               plant=run_plant(sc, substeps=k, integrator="RK4"))
    assert np.abs(nominal.q - mj.q).max() > 1e-5          # the mismatch does change the run


def test_armature_adds_to_the_diagonal_of_m(arm7):
    sc, _ = arm7
    setup = engine_setup(sc)
    eng = setup.engine
    data = mujoco.MjData(eng.model)
    q, dq = np.asarray(sc.q0, float), np.full(7, 0.3)
    eng.configure()
    M0, b0 = eng.mass_and_bias(data, q, dq)
    eng.configure(armature=[0.1 * (j + 1) for j in range(7)])
    M1, b1 = eng.mass_and_bias(data, q, dq)
    eng.configure()
    assert np.allclose(M1 - M0, np.diag([0.1 * (j + 1) for j in range(7)]), atol=1e-14)
    assert np.allclose(b1, b0, atol=1e-13)


def test_delay_noise_and_quantisation_are_the_same_loop(tmp_path, arm7):
    """[implementation] delay, noise and encoder resolution act identically on both plants."""
    _, d = arm7
    sc = load_scenario(arm7_with(tmp_path, f"[implementation]\nrate_hz = {RATE}\ndelay_samples = 1\n"
                                           "noise_q = 1e-5\nnoise_dq = 1e-4\nencoder_resolution = 1e-5\nseed = 3\n"))
    k = plant_substeps(sc, 1 / RATE)
    sym = simulate_sampled(sc, d, t_final=0.2)
    mj = simulate_sampled(sc, d, t_final=0.2, engine="mujoco", plant=run_plant(sc, substeps=k, integrator="RK4"))
    assert sym.rate_hz == mj.rate_hz == RATE and mj.stats["delay_samples"] == 1
    assert np.all(mj.tau[0] == 0) and np.abs(mj.q - sym.q).max() < 1e-10


def test_saturation_on_the_engine(tmp_path, arm7):
    """implementation.saturation on the mujoco plant: with a torque limit below the run's peak it fails, with the
    fraction per joint; the limit is the step's (the same on both plants)."""
    from symfunnel.checks.implementation import implementation_checks
    _, d = arm7
    sc = load_scenario(arm7_with(tmp_path, f"[implementation]\nrate_hz = {RATE}\ntau_max = 30.0\n"))
    checks = {c.id: c for c in implementation_checks(sc, d, t_final=0.2, engine="mujoco")}
    sat = checks["implementation.saturation"]
    assert sat.status == "fail" and max(sat.evidence["saturated_fraction"]) > 0
    assert checks["implementation.containment"].evidence["engine"] == "mujoco"
    assert max(checks["implementation.containment"].evidence["max_abs_tau"]) <= 30.0 + 1e-9
    ok = {c.id: c for c in implementation_checks(load_scenario(arm7_with(
        tmp_path, f"[implementation]\nrate_hz = {RATE}\ntau_max = 500.0\n", name="b.toml")), d, t_final=0.2,
        engine="mujoco")}
    assert ok["implementation.saturation"].status == "pass"


def test_the_engine_from_the_scenario_file(arm7):
    """derivations/arm7_mujoco_heavy.toml names the engine and an engine-only mass scale of 1.3 itself."""
    _, d = arm7
    sc = load_scenario(TESTS.parent / "derivations" / "arm7_mujoco_heavy.toml")
    assert sc.plant.engine == "mujoco" and sc.plant.mujoco.mass_scale == [1.3] * 7
    r = simulate_sampled(sc, d, t_final=0.1)
    assert r.stats["engine"] == "mujoco" and r.rate_hz == RATE
    assert r.stats["engine_mass_scale"] == pytest.approx([1.43] * 7)


def test_a_diverging_engine_run_fails_without_a_log_file(tmp_path, arm7, monkeypatch):
    """At a rate far too low the closed loop diverges: the run says so (breach or non-finite state), MuJoCo's
    warnings are kept (not written to MUJOCO_LOG.TXT in the working directory), nothing is reset silently."""
    sc, d = arm7
    monkeypatch.chdir(tmp_path)
    r = simulate_sampled(sc, d, rate_hz=200.0, t_final=2.0, engine="mujoco", stop_on_breach=False)
    assert r.status in ("breach", "failed") and r.min_margin < 0
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert mujoco.get_mjcb_passive() is None


# --- CLI, verify, rate, sweep, report -----------------------------------------------------------------

@pytest.mark.slow
def test_verify_arm7_on_the_engine(capsys):
    """`verify arm7 --plant mujoco --rate 2x minimum`: the agreement check and containment on the engine."""
    code = main(["verify", "arm7", "--plant", "mujoco", "--rate", str(RATE), "--t-final", "1", "--samples", "1000",
                 "--json", "-q"])
    out = json.loads(capsys.readouterr().out)
    ids = {c["id"]: c for c in out["checks"]}
    assert code == 0 and out["status"] == "pass"
    a = ids["plant.engine_agreement"]
    assert a["status"] == "pass" and a["value"] <= 1e-8 and "value" in a
    c = ids["implementation.containment"]
    assert c["status"] == "pass" and c["evidence"]["engine"] == "mujoco"
    assert "plant = MuJoCo implicitfast with 2 step(s)" in c["detail"]


def test_rate_on_the_engine_and_simulate_without_a_rate(tmp_path, capsys):
    """`rate --plant mujoco` on the planar arm; `simulate --plant mujoco` without a rate runs at twice it."""
    p = init_scenario(tmp_path, extra="")
    capsys.readouterr()
    assert main(["rate", str(p), "--plant", "mujoco", "--t-final", "1", "--json", "-q"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["engine"] == "mujoco" and r["min_rate_hz"] > 0 and all(t["holds"] in (True, False) for t in r["tried"])
    assert main(["simulate", str(p), "--plant", "mujoco", "--t-final", "1", "--json", "-q"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["engine"] == "mujoco" and s["rate_hz"] == pytest.approx(2 * r["min_rate_hz"])


def test_sweep_on_the_engine_over_its_mass_scale(tmp_path, capsys):
    p = init_scenario(tmp_path, extra="[implementation]\nrate_hz = 400.0\n\n[[uncertainty]]\n"
                                       'key = "plant.mujoco.mass_scale"\ndist = "uniform"\nlow = 1.0\nhigh = 2.0\n\n'
                                       "[sweep]\nruns = 4\nt_final = 0.5\n")
    # on symfunnel's plant an engine-only key is bad input
    assert main(["sweep", str(p), "--out", str(tmp_path / "s0"), "-q"]) == 2
    assert "plant.mujoco.mass_scale" in capsys.readouterr().err
    out = tmp_path / "sw"
    assert main(["sweep", str(p), "--plant", "mujoco", "--out", str(out), "--workers", "1", "--json", "-q"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["engine"] == "mujoco" and s["runs"] == 4 and s["rate_hz"] == 400.0
    import pyarrow.parquet as pq
    t = pq.read_table(str(out / "results.parquet")).to_pydict()
    assert sorted(t["run"]) == [0, 1, 2, 3] and len(set(t["plant.mujoco.mass_scale"])) == 4
    # the engine's rows carry the post-transient margins the runs are ranked by (no worst run without them)
    assert all(x is not None and math.isfinite(x) for k in ("min_margin_e1_after_transient",
               "min_margin_e2_after_transient", "settle_time") for x in t[k])
    assert s["worst"]["min_margin_after_transient"] == min(min(t["min_margin_e1_after_transient"]),
                                                            min(t["min_margin_e2_after_transient"]))
    # worst.toml replays the worst run on the engine
    assert main(["simulate", str(out / "worst.toml"), "--json", "-q"]) in (0, 1)
    rep = json.loads(capsys.readouterr().out)
    w = s["worst"]
    assert rep["engine"] == "mujoco"
    assert min(rep["min_margin_e1"] + rep["min_margin_e2"]) == pytest.approx(w["min_margin"], abs=1e-12)


def test_engine_section_shows_both_plants_side_by_side(tmp_path):
    """The report's engine block: agreement, both plants' margins and torque, the trajectory difference, the minimum
    rate on each (the deployed section's data computed here without its design help, to keep the test short). On
    MuJoCo's RK4 the two plants integrate the same ODE with the same method, so they differ by round-off."""
    from symfunnel.deployed.summary import implementation_report
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting.engine import engine_section
    from symfunnel.reporting.html import environment
    sc = load_scenario(init_scenario(tmp_path, extra="[implementation]\nrate_hz = 400.0\n\n"
                                                    "[plant.mujoco]\nintegrator = \"RK4\"\n"))
    run = Run(sc, RunOptions(t_final=0.5, samples=1000, engine="mujoco"))
    run.__dict__["implementation"] = implementation_report(sc, run.design, sensitivity=False, t_final=0.5)
    data = run.engine_comparison
    assert set(data["plants"]) == {"symfunnel", "mujoco"} and data["difference"]["max_q"] < 1e-6
    assert data["min_rate"]["mujoco"]["min_rate_hz"] and data["min_rate"]["symfunnel"]["min_rate_hz"]
    ctx = engine_section(run, lambda s: None)
    assert ctx["available"] and ctx["agreement"]["status"] == "pass" and len(ctx["rows"]) == 2
    html = environment().get_template("engine.html.j2").render(engine=ctx)
    assert 'id="engine"' in html and "fig-engine-difference" in html and "fig-engine-margins" in html
    assert "plant.engine_agreement" in html and "symfunnel (CasADi RK4)" in html and "mujoco (its RK4)" in html
    off = engine_section(Run(sc, RunOptions(t_final=0.5)), lambda s: None)
    assert not off["available"] and environment().get_template("engine.html.j2").render(engine=off).strip() == ""


@pytest.mark.slow
def test_report_has_the_engine_section(tmp_path):
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting import build_report
    from symfunnel.deployed.summary import implementation_report
    sc = load_scenario(init_scenario(tmp_path, extra="[implementation]\nrate_hz = 400.0\n"))
    run = Run(sc, RunOptions(t_final=0.5, samples=1000, engine="mujoco"))
    # the deployed section without its design help (the rate per parameter has tests of its own), as above
    run.__dict__["implementation"] = implementation_report(sc, run.design, sensitivity=False, t_final=0.5)
    html = build_report(run, tmp_path / "r.html", codegen=False, mutants=False).read_text()
    assert 'id="engine"' in html and "fig-engine-difference" in html and "implementation.containment" in html


# --- bad input -----------------------------------------------------------------------------------------

def one_line_error(capsys, *fragments):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for f in fragments:
        assert f in err[0], err[0]


@pytest.mark.parametrize("cmd", ["simulate", "verify", "rate", "sweep"])
def test_plant_option_bad_values(capsys, cmd):
    assert main([cmd, "arm7", "--plant", "mujco", "-q"]) == 2
    one_line_error(capsys, "--plant", "did you mean 'mujoco'")
    assert main([cmd, "paper", "--plant", "mujoco", "-q"]) == 2
    one_line_error(capsys, "--plant", "'matrices'")


@pytest.mark.parametrize("body, key", [
    ('engine = "mujuco"', "plant.engine"),
    ('[plant.mujoco]\nsubsteps = 0', "plant.mujoco.substeps"),
    ('[plant.mujoco]\nsubsteps = 2\ntimestep = 1e-4', "plant.mujoco.substeps"),
    ('[plant.mujoco]\nmass_scale = 0.0', "plant.mujoco.mass_scale"),
    ('[plant.mujoco]\ndamping = [0.1, 0.2]', "plant.mujoco.damping"),
    ('[plant.mujoco]\narmature = -1.0', "plant.mujoco.armature"),
    ('[plant.mujoco]\nstep = 1e-4', "plant.mujoco.step"),
    ('[plant.mujoco]\nintegrator = "rk4"', "plant.mujoco.integrator"),
])
def test_bad_plant_tables(tmp_path, capsys, body, key):
    text = (DATA_DIR / "arm7.toml").read_text()
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    if body.startswith("engine"):
        text = text.replace("[plant]\n", "[plant]\n" + body + "\n", 1)
    else:
        text += "\n" + body + "\n"
    p = tmp_path / "a.toml"
    p.write_text(text)
    with pytest.raises(InputError) as ei:
        load_scenario(p)
    assert ei.value.key == key
    assert main(["simulate", str(p), "-q"]) == 2
    one_line_error(capsys, key, str(p))
    if key == "plant.engine":
        assert "did you mean 'mujoco'" in str(ei.value)
    if key == "plant.mujoco.integrator":
        assert "did you mean 'RK4'" in str(ei.value) and "'implicitfast'" in str(ei.value)


def test_engine_on_a_matrices_model_in_the_file(tmp_path, capsys):
    text = (DATA_DIR / "paper_2dof.toml").read_text().replace("[plant]\n", '[plant]\nengine = "mujoco"\n', 1)
    p = tmp_path / "p.toml"
    p.write_text(text)
    assert main(["simulate", str(p), "-q"]) == 2
    one_line_error(capsys, "plant.engine", "'matrices'", str(p))


def test_a_timestep_that_does_not_divide_the_period(tmp_path, capsys):
    p = init_scenario(tmp_path, extra="[implementation]\nrate_hz = 1000.0\n\n[plant.mujoco]\ntimestep = 3e-4\n")
    assert main(["simulate", str(p), "--plant", "mujoco", "--t-final", "0.1", "-q"]) == 2
    one_line_error(capsys, "plant.mujoco.timestep", "does not divide the sample period")
    p2 = init_scenario(tmp_path, extra="[implementation]\nrate_hz = 1000.0\n\n[plant.mujoco]\ntimestep = 2.5e-4\n",
                       name="ok.toml")
    capsys.readouterr()
    assert main(["simulate", str(p2), "--plant", "mujoco", "--t-final", "0.1", "--json", "-q"]) == 0
    assert json.loads(capsys.readouterr().out)["plant_substeps"] == 4
    assert main(["rate", str(p2), "--plant", "mujoco", "-q"]) == 2
    one_line_error(capsys, "plant.mujoco.timestep", "rate search")


def test_a_urdf_mujoco_refuses(tmp_path, capsys):
    """symfunnel accepts a tensor 5e-5 over the triangle inequality (its tolerance); MuJoCo does not: its message."""
    urdf = tmp_path / "tri.urdf"
    urdf.write_text(ROTATED.replace('ixx="0.004" iyy="0.004" izz="0.001"', 'ixx="0.5" iyy="0.5" izz="1.00005"'))
    p = init_scenario(tmp_path, urdf)
    assert main(["simulate", str(p), "--plant", "mujoco", "--t-final", "0.1", "-q"]) == 2
    one_line_error(capsys, "MuJoCo refuses this URDF", "A + B >= C", "plant.engine", str(urdf))


def test_mujoco_not_installed(tmp_path):
    """Without the mujoco package: one line naming the install command, exit 2 (a stand-in module that fails to
    import takes its place on the path)."""
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "mujoco.py").write_text("raise ImportError('No module named mujoco')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", ""),
                                                       str(TESTS.parent)]))
    for args in (["simulate", "arm7", "--plant", "mujoco"], ["rate", "arm7", "--plant", "mujoco"]):
        p = subprocess.run([sys.executable, "-m", "symfunnel", *args, "-q"], capture_output=True, text=True,
                           env=env, timeout=300)
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(err) == 1 and "pip install 'symfunnel[mujoco]'" in err[0], p.stderr

"""MuJoCo's joint order differs from symfunnel's: a user's own MJCF (`[plant.mujoco] mjcf`) of tests/data/mjorder.urdf
writes the slider branch first, so MuJoCo numbers the joints s, b, a, c where symfunnel's coordinates are s, a, c, b.
The engine matches joints by name: its M, bias forces and sampled runs agree with symfunnel's CasADi plant, and a
mutant that maps by position fails both. Every bad MJCF is one line at plant.mujoco.mjcf."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import mujoco  # a declared test dependency ([test] extra): missing, these tests error, never skip

import symfunnel.plant.mjcf as plant_mjcf
import symfunnel.plant.mujoco as plant_mujoco
from symfunnel.checks.engine import check_engine_agreement
from symfunnel.cli import main
from symfunnel.core.errors import InputError
from symfunnel.deployed.engine import EngineRunPlant, engine_setup
from symfunnel.deployed.loop import plant_substeps, simulate_sampled
from symfunnel.design import derive
from symfunnel.model.urdf import movable_joint_names, parse_urdf
from symfunnel.plant.mujoco import load_engine
from symfunnel.scenario import load_scenario

DATA = Path(__file__).parent / "data"
RATE = 2000.0


def mujoco_order(mj) -> list[str]:
    """Joint names in MuJoCo's dof order, read from MuJoCo's own model."""
    return [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, int(np.flatnonzero(mj.jnt_dofadr == d)[0]))
            for d in range(mj.nv)]


def scenario_file(tmp_path: Path, mjcf_text: str | None = None, extra: str = "") -> Path:
    """`symfunnel init --urdf mjorder.urdf` with `[plant.mujoco] mjcf` naming the MJCF copied beside it."""
    shutil.copy(DATA / "mjorder.urdf", tmp_path / "mjorder.urdf")
    (tmp_path / "mjorder.xml").write_text(mjcf_text if mjcf_text is not None else (DATA / "mjorder.xml").read_text())
    out = tmp_path / "s.toml"
    assert main(["init", "--urdf", str(tmp_path / "mjorder.urdf"), "--out", str(out), "--force", "-q"]) == 0
    out.write_text(out.read_text() + '\n[plant.mujoco]\nmjcf = "mjorder.xml"\n' + extra)
    return out


def by_position(mujoco_, mj, joints, **kw) -> list[int]:
    """The mutant: symfunnel's k-th coordinate is MuJoCo's k-th degree of freedom."""
    return [int(np.flatnonzero(mj.jnt_dofadr == k)[0]) for k in range(len(joints))]


def positional(monkeypatch) -> None:
    """Install the mutant, and silence the axis check that would refuse it at load, so that what the agreement check
    and the runs see is the mapping alone."""
    monkeypatch.setattr(plant_mujoco, "joint_ids", by_position)
    monkeypatch.setattr(plant_mjcf, "check_axes", lambda *a, **k: None)


def test_mujocos_order_differs_from_symfunnels_and_the_engine_maps_by_name():
    """(a) MuJoCo's own model of mjorder.xml orders the dofs s, b, a, c; symfunnel's URDF order is s, a, c, b."""
    ours = movable_joint_names(parse_urdf(DATA / "mjorder.urdf"))
    mj = mujoco.MjModel.from_xml_path(str(DATA / "mjorder.xml"))
    theirs = mujoco_order(mj)
    assert ours == ["s_joint", "a_joint", "c_joint", "b_joint"]
    assert sorted(theirs) == sorted(ours) and theirs != ours
    sc_model = load_scenario_model()
    eng = load_engine(sc_model, file="s.toml", mjcf=str(DATA / "mjorder.xml"))
    assert eng.names == ours
    assert [theirs[d] for d in eng.dadr] == ours                   # each coordinate's dof is its namesake's
    assert list(eng.dadr) != list(range(4))                         # ... and not the one at its position
    assert any("fusestatic" in s and "tool" in s for s in eng.notes.lines())


def test_the_positional_mutant_is_refused_at_load_by_the_axis_check(monkeypatch):
    """Mapped by position, coordinate a_joint would be MuJoCo's slider: its axis at q = 0 differs, one line."""
    monkeypatch.setattr(plant_mujoco, "joint_ids", by_position)
    with pytest.raises(InputError) as exc:
        load_engine(load_scenario_model(), file="s.toml", mjcf=str(DATA / "mjorder.xml"))
    assert exc.value.key == "plant.mujoco.mjcf" and "joint 'a_joint' of mjorder.xml has axis" in str(exc.value)


def load_scenario_model():
    from symfunnel.model.urdf import build_urdf
    return build_urdf({"type": "urdf", "path": "mjorder.urdf"}, file="s.toml", base_dir=DATA)


def test_engine_agreement_on_the_reordered_mjcf_and_a_positional_mutant_fails(tmp_path, monkeypatch):
    """(b) M and C dq + G of the MJCF engine equal symfunnel's CasADi model to round-off at 200 random states (the
    agreement check); mapped by position, the same engine disagrees by order 1."""
    sc = load_scenario(scenario_file(tmp_path))
    c = check_engine_agreement(sc)
    assert c.status == "pass" and c.value <= 1e-12, c.detail
    assert "the MJCF mjorder.xml (plant.mujoco.mjcf)" in c.detail
    p = c.evidence["others"]["pinocchio"]          # the third opinion reads the model's URDF, not the MJCF
    assert max(p["M"], p["bias"], p["M_vs_engine"], p["bias_vs_engine"]) < 1e-12
    positional(monkeypatch)
    bad = check_engine_agreement(load_scenario(scenario_file(tmp_path)))
    assert bad.status == "fail" and bad.value > 0.1, bad.detail
    # the URDF read by MuJoCo keeps symfunnel's order: there the mutant cannot be told apart (why the MJCF exists)
    urdf_sc = load_scenario(tmp_path / "s.toml")
    urdf_sc.plant.mujoco.mjcf = None
    assert check_engine_agreement(urdf_sc).status == "pass"


def test_sampled_runs_on_the_reordered_mjcf_agree_with_the_casadi_plant(tmp_path, monkeypatch):
    """(c) The sampled loop on the MJCF engine at symfunnel's RK4 substeps equals the loop on symfunnel's plant to
    round-off; (d) mapped by position it does not."""
    sc = load_scenario(scenario_file(tmp_path))
    d = derive(sc)
    k = plant_substeps(sc, 1.0 / RATE)
    setup = engine_setup(sc)
    run = EngineRunPlant(setup.p0.copy(), dataclasses.replace(sc.plant.mujoco, substeps=k, integrator="RK4"),
                         np.asarray(sc.q0, dtype=float), np.asarray(sc.dq0, dtype=float))
    sym = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2)
    mj = simulate_sampled(sc, d, rate_hz=RATE, t_final=0.2, engine="mujoco", plant=run)
    assert sym.ok and mj.ok and mj.stats["engine"] == "mujoco"
    assert np.abs(mj.q - sym.q).max() < 1e-10 and np.abs(mj.dq - sym.dq).max() < 1e-8
    assert np.abs(mj.tau - sym.tau).max() < 1e-6
    positional(monkeypatch)
    sc2 = load_scenario(tmp_path / "s.toml")
    setup2 = engine_setup(sc2)
    run2 = EngineRunPlant(setup2.p0.copy(), run.mujoco, run.q0, run.dq0)
    bad = simulate_sampled(sc2, d, rate_hz=RATE, t_final=0.2, engine="mujoco", plant=run2, stop_on_breach=False)
    n = min(len(bad.q), len(sym.q))
    assert not np.all(np.abs(bad.q[:n] - sym.q[:n]) < 1e-3)      # off by > 1 mrad, or diverged (nan)


def test_simulate_plant_mujoco_on_the_reordered_mjcf(tmp_path, capsys, monkeypatch):
    """(c) `simulate --plant mujoco` with the MJCF (RK4 at symfunnel's substeps) reports the margins and torques of
    `simulate` on symfunnel's plant; (d) the positional mutant's do not."""
    p = scenario_file(tmp_path)
    k = plant_substeps(load_scenario(p), 1.0 / RATE)
    p.write_text(p.read_text() + f'substeps = {k}\nintegrator = "RK4"\n')
    args = ["simulate", str(p), "--rate", str(RATE), "--t-final", "0.2", "--json", "-q"]
    capsys.readouterr()
    assert main(args) == 0
    sym = json.loads(capsys.readouterr().out)
    assert main(args + ["--plant", "mujoco"]) == 0
    mj = json.loads(capsys.readouterr().out)
    assert mj["engine"] == "mujoco" and mj["plant_substeps"] == k and "mjorder.xml" in mj["engine_notes"][0]
    for key in ("max_abs_tau", "min_margin_e1", "min_margin_e2"):
        assert np.allclose(mj[key], sym[key], rtol=1e-7, atol=1e-9), key
    positional(monkeypatch)
    main(args + ["--plant", "mujoco"])
    bad = json.loads(capsys.readouterr().out)
    assert not np.allclose(bad["max_abs_tau"], sym["max_abs_tau"], rtol=1e-3)


EDITS = {
    "missing": (('name="a_joint"', 'name="arm_joint"'), "has no joint 'a_joint'"),
    "type": (('name="b_joint" type="slide"', 'name="b_joint" type="hinge"'), "'b_joint' of mjorder.xml is a hinge"),
    "axis": (('name="a_joint" type="hinge" axis="0 1 0"', 'name="a_joint" type="hinge" axis="0 -1 0"'),
             "joint 'a_joint' of mjorder.xml has axis (0, -1, 0)"),
    "frame": (('euler="1.5707963267948966 0 0"', 'euler="1.5707963267948966 0 0.5"'),
              "joint 'b_joint' of mjorder.xml has axis"),
    "ref": (('name="c_joint" type="hinge"', 'name="c_joint" type="hinge" ref="0.3"'), "ref = 0.3"),
    "extra": (('<body name="tool" pos="0.25 0 0">', '<body name="tool" pos="0.25 0 0"><joint name="wrist"/>'),
              "joints not in the model: wrist"),
    "refused": (("</worldbody>", ""), "MuJoCo refuses mjorder.xml"),
}


@pytest.mark.parametrize("case", sorted(EDITS))
def test_a_bad_mjcf_is_one_line_at_its_key(tmp_path, case):
    """A joint missing, of another type, turned about another axis (or in another frame), with a nonzero ref, an
    extra degree of freedom or a file MuJoCo refuses: an InputError at plant.mujoco.mjcf naming what differs."""
    (old, new), words = EDITS[case]
    text = (DATA / "mjorder.xml").read_text()
    assert old in text
    sc = load_scenario(scenario_file(tmp_path, text.replace(old, new, 1)))
    with pytest.raises(InputError) as exc:
        load_engine(sc.model, file=sc.file, mjcf=sc.plant.mujoco.mjcf)
    assert exc.value.key == "plant.mujoco.mjcf" and words in str(exc.value), str(exc.value)
    assert "\n" not in str(exc.value)


def test_a_missing_mjcf_file_exits_2_in_one_line(tmp_path, capsys):
    p = scenario_file(tmp_path)
    p.write_text(p.read_text().replace('mjcf = "mjorder.xml"', 'mjcf = "nowhere.xml"'))
    assert main(["simulate", str(p), "--plant", "mujoco", "--rate", "2000", "--t-final", "0.1", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "plant.mujoco.mjcf" in err and "nowhere.xml" in err


def test_the_mjcf_is_an_input_of_the_scenario_and_a_directory_is_refused(tmp_path, capsys):
    """Scenario.inputs (a campaign's fingerprint) holds the MJCF's sha256; a directory named as the MJCF: one line."""
    import hashlib
    sc = load_scenario(scenario_file(tmp_path))
    xml = str((tmp_path / "mjorder.xml").resolve())
    assert sc.inputs[xml] == hashlib.sha256((tmp_path / "mjorder.xml").read_bytes()).hexdigest()
    p = tmp_path / "s.toml"
    (tmp_path / "dir.xml").mkdir()
    p.write_text(p.read_text().replace('mjcf = "mjorder.xml"', 'mjcf = "dir.xml"'))
    assert main(["simulate", str(p), "--plant", "mujoco", "--rate", "2000", "--t-final", "0.1", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "plant.mujoco.mjcf" in err and "is a directory" in err


def test_an_mjcf_with_the_wrong_gravity_and_fluid_gets_the_models_world(tmp_path):
    """The MJCF's own gravity and fluid forces are replaced by the scenario's world (and said so): agreement holds."""
    text = (DATA / "mjorder.xml").read_text().replace(
        "<worldbody>", '<option gravity="0 0 -1.62" density="1.2" viscosity="0.5"/>\n  <worldbody>')
    sc = load_scenario(scenario_file(tmp_path, text))
    c = check_engine_agreement(sc, samples=50)
    assert c.status == "pass" and c.value <= 1e-12, c.detail
    notes = " ".join(c.evidence["notes"])
    assert "gravity (0, 0, -1.62) replaced" in notes and "density, viscosity" in notes


def _link(name: str, k: int) -> str:
    m = 0.5 + 0.3 * k
    return (f'<link name="{name}"><inertial><origin xyz="{0.05 + 0.01 * k} 0.02 {0.03 * k}"/><mass value="{m}"/>'
            f'<inertia ixx="{0.01 + 0.001 * k}" iyy="0.012" izz="0.013" ixy="0.001" ixz="0" iyz="0"/>'
            '</inertial></link>')


def _joint(name: str, parent: str, child: str, kind: str = "revolute", axis: str = "0 1 0") -> str:
    tail = "" if kind == "fixed" else f'<axis xyz="{axis}"/><limit lower="-2" upper="2" effort="10" velocity="3"/>'
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="0.1 0 0.2" rpy="0.3 0 0"/>{tail}</joint>')


#: URDF trees where MuJoCo's order could plausibly differ from symfunnel's (MuJoCo 4.0.1: it never does)
TREES = {
    "fixed link first, its child fused in place": (
        ["base", "f", "la", "lb"], [("jf", "base", "f", "fixed"), ("ja", "base", "la"), ("jb", "f", "lb")]),
    "fused between siblings, deep branch": (
        ["base", "l1", "f", "la", "lb", "lc"],
        [("j1", "base", "l1", "revolute", "0 0 1"), ("jf", "l1", "f", "fixed"), ("ja", "l1", "la"),
         ("jb", "f", "lb"), ("jc", "lb", "lc")]),
    "links reversed, joints before their parent's": (
        ["lc", "lb", "la", "l1", "base"],
        [("jc", "la", "lc"), ("jb", "l1", "lb"), ("j1", "base", "l1", "revolute", "0 0 1"), ("ja", "l1", "la")]),
}


@pytest.mark.parametrize("tree", sorted(TREES))
def test_urdf_trees_declared_out_of_order_agree_whatever_order_mujoco_gives(tmp_path, tree):
    """MuJoCo reads these URDFs itself; whatever its joint order (today symfunnel's), the engine's M and C dq + G
    equal symfunnel's at random states."""
    import casadi as ca

    from symfunnel.model.urdf import build_urdf
    links, joints = TREES[tree]
    (tmp_path / "t.urdf").write_text('<robot name="t">' + "".join(_link(n, k) for k, n in enumerate(links))
                                     + "".join(_joint(*j) for j in joints) + "</robot>")
    model = build_urdf({"type": "urdf", "path": "t.urdf"}, file="s.toml", base_dir=tmp_path)
    eng = load_engine(model, file="s.toml")
    assert sorted(mujoco_order(eng.model)) == sorted(eng.names) == sorted(j[0] for j in joints if len(j) == 3
                                                                         or j[3] != "fixed")
    Mf = ca.Function("M", [model.q], [model.numeric(model.M)])
    bf = ca.Function("b", [model.q, model.dq], [model.numeric(ca.mtimes(model.C, model.dq) + model.G)])
    r = plant_mujoco.agreement(eng, lambda q: np.array(Mf(q)), lambda q, dq: np.array(bf(q, dq)).ravel(),
                               -2.0, 2.0, 2.0, samples=30)
    assert r["value"] <= 1e-12, r


def test_per_joint_engine_settings_reach_the_namesake_joint_in_the_reordered_mjcf(monkeypatch):
    """[plant.mujoco] mass_scale, damping and armature per coordinate: the MJCF engine (MuJoCo order s, b, a, c) and
    the URDF engine (symfunnel's order) give the same M (armature on its diagonal) and engine-only lists; mapped by
    position, the slider's mass scale lands on the arm."""
    model = load_scenario_model()
    settings = {"mass_scale": [1.0, 1.5, 1.0, 2.0], "damping": [0.1, 0.2, 0.3, 0.4],
                "armature": [0.01, 0.02, 0.03, 0.04]}
    rng = np.random.default_rng(3)
    states = [(rng.uniform(-1, 1, 4), rng.uniform(-1, 1, 4)) for _ in range(10)]

    def matrices(eng):
        eng.configure(**settings)
        data = mujoco.MjData(eng.model)
        return [eng.mass_and_bias(data, q, dq) for q, dq in states], eng.engine_only()

    urdf, urdf_only = matrices(load_engine(model, file="s.toml"))
    mine, mine_only = matrices(load_engine(model, file="s.toml", mjcf=str(DATA / "mjorder.xml")))
    assert mine_only == urdf_only == {"damping": settings["damping"], "armature": settings["armature"]}
    for (Mu, bu), (Mm, bm) in zip(urdf, mine):
        assert np.abs(Mm - Mu).max() <= 1e-12 * np.abs(Mu).max() and np.abs(bm - bu).max() <= 1e-12 * np.abs(bu).max()
    positional(monkeypatch)
    bad, _ = matrices(load_engine(model, file="s.toml", mjcf=str(DATA / "mjorder.xml")))
    assert max(np.abs(Mb - Mu).max() / np.abs(Mu).max() for (Mu, _), (Mb, _) in zip(urdf, bad)) > 0.01


def test_a_sweep_on_the_mjcf_engine_writes_a_worst_case_that_replays(tmp_path, capsys):
    """`sweep --plant mujoco` over the engine's mass scale on the MJCF; its worst.toml (in the output directory)
    names the MJCF by its absolute path, as it does the URDF, so `simulate worst.toml --plant mujoco` replays it."""
    p = scenario_file(tmp_path, extra='\n[implementation]\nrate_hz = 2000.0\n\n[[uncertainty]]\n'
                      'key = "plant.mujoco.mass_scale"\ndist = "uniform"\nlow = 1.0\nhigh = 1.5\n\n'
                      '[sweep]\nruns = 2\nt_final = 0.2\n')
    out = tmp_path / "sw"
    assert main(["sweep", str(p), "--workers", "1", "--plant", "mujoco", "--out", str(out), "-q"]) == 0
    assert f'mjcf = "{(tmp_path / "mjorder.xml").resolve()}"' in (out / "worst.toml").read_text()
    capsys.readouterr()
    assert main(["simulate", str(out / "worst.toml"), "--plant", "mujoco", "--json", "-q"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["engine"] == "mujoco" and "mjorder.xml" in s["engine_notes"][0] and s["rate_hz"] == 2000.0


def test_init_from_a_scenario_with_an_mjcf_names_it_where_it_is(tmp_path):
    """`init --from` copies the URDF beside the output but names the MJCF by its full path (it may include files
    relative to itself): the copy in another directory loads and reads the same MJCF (before: exit 2 at its key)."""
    src = scenario_file(tmp_path)
    (tmp_path / "elsewhere").mkdir()
    out = tmp_path / "elsewhere" / "copy.toml"
    assert main(["init", "--from", str(src), "--out", str(out), "-q"]) == 0
    import tomllib
    load_scenario(str(out))
    named = tomllib.loads(out.read_text())["plant"]["mujoco"]["mjcf"]
    assert Path(named) == (tmp_path / "mjorder.xml").resolve()
    assert (tmp_path / "elsewhere" / "mjorder.urdf").is_file()

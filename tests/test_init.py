"""`symfunnel init`: the written scenario is commented, loads, derives and simulates inside its funnels as written."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from symfunnel.cli import main
from tests.conftest import REPO

DATA = REPO / "tests" / "data"


def _runs_as_written(path, t_final: float):
    from symfunnel.design import derive, evaluate
    from symfunnel.scenario import load_scenario
    from symfunnel.simulation import simulate
    text = path.read_text()
    assert sum(line.lstrip().startswith("#") or " # " in line for line in text.splitlines()) >= 10
    sc = load_scenario(path)
    d = derive(sc)
    vals = evaluate(d, {"t": 0.0, "q": sc.q0, "dq": sc.dq0}, warn=lambda s: pytest.fail(s))
    e1, e2 = np.abs(vals["e1"]), np.abs(vals["e2"])
    F1, F2 = np.asarray(vals["F1"]), np.asarray(vals["F2"])
    assert np.all(e1 < F1) and np.all(e2 < F2)                 # the funnels contain the initial state
    r = simulate(sc, d, t_final=t_final)
    assert r.status == "ok", r.message
    return sc, vals


def test_init_from_scratch(tmp_path, capsys):
    out = tmp_path / "arm.toml"
    assert main(["init", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    sc, _ = _runs_as_written(out, 3.0)
    assert sc.name == "arm" and sc.n == 2 and sc.model.kind == "planar"


def test_init_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "a.toml"
    out.write_text("keep")
    assert main(["init", "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == "keep"
    assert main(["init", "--out", str(tmp_path / "a.txt")]) == 2


@pytest.mark.parametrize("urdf", ["prismatic.urdf", "branched.urdf"])
def test_init_from_urdf(tmp_path, urdf):
    from symfunnel.model.urdf import movable_joint_names, parse_urdf
    src = tmp_path / "robots" / urdf
    src.parent.mkdir()
    shutil.copy(DATA / urdf, src)
    out = tmp_path / "scen" / "r.toml"                       # a directory that does not exist yet
    assert main(["init", "--urdf", str(src), "--out", str(out), "-q"]) == 0
    assert '"../robots/' in out.read_text()                  # the path is relative to the scenario file
    sc, vals = _runs_as_written(out, 2.0)
    from symfunnel.model.urdf import mimic_joints
    # every movable joint is a coordinate, but a mimic joint (branched.urdf has one) is held fixed
    assert sc.n == len(movable_joint_names(parse_urdf(src))) - len(mimic_joints(src))
    # e2's initial funnel is twice the largest |e2(0)| plus 0.1, as documented in the command
    assert sc.funnels["e2"].phi0[0] == pytest.approx(2 * np.max(np.abs(vals["e2"])) + 0.1, rel=1e-5)
    assert np.all(np.abs(np.asarray(vals["e1"])) <= 0.02 + 1e-12)


def test_init_from_a_bad_urdf_exits_2(tmp_path, capsys):
    bad = tmp_path / "x.urdf"
    bad.write_text("<robot><link name='a'/></robot>")
    assert main(["init", "--urdf", str(bad), "--out", str(tmp_path / "s.toml")]) == 2
    assert "movable joint" in capsys.readouterr().err and not (tmp_path / "s.toml").exists()

"""The URDF's joint limits (`checks.limits`): a run that leaves the position and velocity ranges fails
limits.position / limits.velocity, a funnel that allows leaving the range warns limits.funnel, and a URDF whose
limits the design respects passes; the margins against an independent computation (the reference and the funnel
in closed form, the run's own q and dq)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from symfunnel.checks.limits import check_limits, urdf_joint_limits
from symfunnel.cli import main
from symfunnel.pipeline import Run, RunOptions
from symfunnel.scenario import load_scenario

T = 3.0
LINK = ('<link name="{n}"><inertial><origin xyz="{x} 0 0"/><mass value="{m}"/><inertia ixx="0.01" ixy="0" ixz="0" '
        'iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')
JOINT = ('<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/><origin xyz="{o} 0 0"/>'
         '<axis xyz="0 0 1"/><limit lower="{lo}" upper="{hi}" effort="50" velocity="{v}"/></joint>')


def _urdf(limits) -> str:
    (lo1, hi1, v1), (lo2, hi2, v2) = limits
    return ('<?xml version="1.0"?><robot name="two"><link name="base"/>' + LINK.format(n="l1", x=0.2, m=1.0)
            + LINK.format(n="l2", x=0.15, m=0.5)
            + JOINT.format(n="j1", p="base", c="l1", o=0, lo=lo1, hi=hi1, v=v1)
            + JOINT.format(n="j2", p="l1", c="l2", o=0.4, lo=lo2, hi=hi2, v=v2) + "</robot>")


@pytest.fixture(scope="module")
def scenario_file(tmp_path_factory):
    """`symfunnel init`'s scenario around a 2-joint URDF: qd = 0.2 sin(0.5 t), 0.2 sin(0.6 t); F1 = 0.1 e^-t + 0.01."""
    d = tmp_path_factory.mktemp("limits")
    (d / "two.urdf").write_text(_urdf([(-1, 1, 2), (-1, 1, 2)]), encoding="utf-8")
    assert main(["init", "--urdf", str(d / "two.urdf"), "--out", str(d / "two.toml"), "-q"]) == 0
    text = (d / "two.toml").read_text(encoding="utf-8")
    assert '"0.2*sin(0.5*t)"' in text and '"0.2*sin(0.6*t)"' in text and "phi0 = 0.1\n" in text
    return d


def _checks(d, limits):
    (d / "two.urdf").write_text(_urdf(limits), encoding="utf-8")
    sc = load_scenario(d / "two.toml")
    run = Run(sc, RunOptions(t_final=T))
    return {c.id: c for c in check_limits(sc, run.design, run.simulation, T)}, run


def _funnel_margin(lo, hi):
    """min over [0, T] and joints of the room between qd +- F1 and the limits, on a grid 25x finer than the check's."""
    t = np.linspace(0.0, T, 100001)
    F1 = 0.1 * np.exp(-t) + 0.01
    out = []
    for j, w in enumerate((0.5, 0.6)):
        qd = 0.2 * np.sin(w * t)
        out.append(np.min(np.minimum(qd - F1 - lo[j], hi[j] - qd - F1)))
    return min(out)


def test_limits_the_design_respects_pass(scenario_file):
    c, run = _checks(scenario_file, [(-1, 1, 2), (-1, 1, 2)])
    assert {k: v.status for k, v in c.items()} == {"limits.position": "pass", "limits.velocity": "pass",
                                                   "limits.funnel": "pass"}
    q, dq = run.simulation.signals["q"], run.simulation.signals["dq"]
    assert c["limits.position"].margin == pytest.approx(float(np.min(1 - np.abs(q))), abs=1e-12)
    assert c["limits.velocity"].margin == pytest.approx(float(np.min(2 - np.abs(dq))), abs=1e-12)
    assert c["limits.funnel"].margin == pytest.approx(_funnel_margin([-1, -1], [1, 1]), abs=1e-5)
    assert "rad" in c["limits.position"].detail and "rad/s" in c["limits.velocity"].detail


def test_a_run_leaving_the_limits_fails_and_a_funnel_beyond_them_warns(scenario_file):
    """Joint 1 up to 0.12 rad (its reference 0.2 sin(0.5 t) passes it at t = asin(0.6)/0.5 = 1.287 s), joint 2 at
    most 0.1 rad/s (its reference's speed is 0.12 cos(0.6 t))."""
    lims = [(-0.5, 0.12, 2), (-0.5, 0.5, 0.1)]
    c, run = _checks(scenario_file, lims)
    assert c["limits.position"].status == "fail" and c["limits.position"].where["joint"] == 1
    assert c["limits.velocity"].status == "fail" and c["limits.velocity"].where["joint"] == 2
    assert c["limits.funnel"].status == "warn"
    q, dq = run.simulation.signals["q"], run.simulation.signals["dq"]
    t = run.simulation.t
    assert c["limits.position"].margin == pytest.approx(float(np.min(0.12 - q[:, 0])), abs=1e-12)
    assert c["limits.velocity"].margin == pytest.approx(float(np.min(0.1 - np.abs(dq[:, 1]))), abs=1e-12)
    assert c["limits.funnel"].margin == pytest.approx(_funnel_margin([-0.5, -0.5], [0.12, 0.5]), abs=1e-5)
    # the run crosses 0.12 rad near where its reference does (the tracking error is far below the funnel's 0.01)
    first = float(t[np.argmax(q[:, 0] > 0.12)])
    assert abs(first - math.asin(0.6) / 0.5) < 0.05
    assert f"first outside at t = {first:.4g} s" in c["limits.position"].detail


def test_only_the_funnel_leaves_the_range(scenario_file):
    """Joint 2 up to 0.21 rad: the run (|q2| <= 0.2 + its small error) stays inside, qd2 + F1 reaches 0.2143."""
    c, _ = _checks(scenario_file, [(-1, 1, 2), (-1, 0.21, 2)])
    assert c["limits.position"].status == "pass"
    assert c["limits.funnel"].status == "warn" and c["limits.funnel"].where["joint"] == 2
    assert c["limits.funnel"].margin == pytest.approx(_funnel_margin([-1, -1], [1, 0.21]), abs=1e-5)


def test_models_without_urdf_limits_skip(paper_run):
    assert urdf_joint_limits(paper_run.scenario.model) is None
    c = check_limits(paper_run.scenario, paper_run.design, paper_run.simulation, 1.0)
    assert [x.status for x in c] == ["skip"] * 3
    assert [x.id for x in c] == ["limits.position", "limits.velocity", "limits.funnel"]

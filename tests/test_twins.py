"""One source for every numeric twin: the funnels and the reference the controller is fed come from the SX, and
verify fails when what it checks is not what the scenario declares (issue "Verify the verifier", item 3).

The two design-side defects found by seeding errors into the code: a controller fed a reference whose second
derivative is zero (the design identity holds for any reference signal), and a funnel whose SX differs from its
numeric twin (every containment check then passes against the wrong funnel). Each must fail verify on `paper`,
`arm7` and a URDF robot.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symfunnel.checks.consistency import check_funnel_consistency, check_reference_derivatives
from symfunnel.design import derive
from symfunnel.design.backstepping import Backstepping
from symfunnel.family.funnels import ExpressionFunnel, FunnelSpec
from symfunnel.pipeline import Run, RunOptions
from symfunnel.scenario import load_scenario

from .pins import pins

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def urdf_scenario(tmp_path_factory):
    """A scenario `symfunnel init` writes for the branched URDF robot of tests/data."""
    from symfunnel.commands.init import scenario_from_urdf
    d = tmp_path_factory.mktemp("urdf")
    shutil.copy(DATA / "branched.urdf", d / "branched.urdf")
    out = d / "branched.toml"
    out.write_text(scenario_from_urdf(str(d / "branched.urdf"), out, "branched"), encoding="utf-8")
    return str(out)


ROBOTS = ["paper", pytest.param("arm7", marks=pytest.mark.slow), pytest.param("urdf", marks=pytest.mark.slow)]


def _name(robot, urdf_scenario):
    return urdf_scenario if robot == "urdf" else robot


def _verify(name, t_final=0.5, jit=True):
    return Run(load_scenario(name), _options(t_final, jit)).verification


def _options(t_final=0.5, jit=True):
    """verify's options here: without the certificates. No test of this module asserts one, and a defective design's
    run read the correct design's certificates from the in-process cache (keyed by the scenario's content, which a
    patched derive does not change), so they could never be in `_killed_by`; on arm7 they were ~10 CPU-s of the
    correct run."""
    return RunOptions(t_final=t_final, samples=300, jit=jit, certify=False)


#: a defective design's closed loop is integrated by CasADi's virtual machine, not compiled: its C is compiled by no
#: other test and only once here (on arm7 gcc took ~9 CPU-s, the VM's 0.5 s run ~1.5 s), and what is checked is the
#: design's SX, which both evaluate (the correct designs' C is the compile cache's, shared with other modules)
DEFECT_JIT = False


def _killed_by(bad, good) -> set[str]:
    """Checks whose outcome is unexpected for the defective design but not for the correct one."""
    ok = {c.id for c in good.checks if c.unexpected}
    return {c.id for c in bad.checks if c.unexpected and c.id not in ok}


class _Lazy(dict):
    def __init__(self, urdf_scenario):
        super().__init__()
        self.urdf = urdf_scenario

    def __missing__(self, robot):
        self[robot] = _verify(_name(robot, self.urdf))
        return self[robot]


@pytest.fixture(scope="module")
def correct(urdf_scenario):
    """verify on each robot with the correct design (the reference outcomes), computed on first use."""
    return _Lazy(urdf_scenario)


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_correct_designs_pass_both_consistency_checks(robot, correct):
    for v in [correct[robot]]:
        c = {x.id: x for x in v.checks}
        assert c["funnel.consistency"].status == "pass", (robot, c["funnel.consistency"].detail)
        assert c["reference.derivatives"].status == "pass", (robot, c["reference.derivatives"].detail)
        assert c["funnel.consistency"].evidence["comparisons"][0]["max_relative"] < 1e-13
        worst = max(r["max_relative"] for r in c["reference.derivatives"].evidence["comparisons"])
        assert worst < 1e-9


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_controller_fed_a_zero_reference_acceleration_fails_verify(robot, urdf_scenario, correct, monkeypatch):
    good = correct[robot]           # the reference outcome, computed before anything is patched
    real = Backstepping.derive

    def zero_ddqd(self, *a, **k):
        d = real(self, *a, **k)
        d.reference_t["ddqd"] = ca.SX.zeros(*d.reference_t["ddqd"].shape)
        return d
    monkeypatch.setattr(Backstepping, "derive", zero_ddqd)
    v = _verify(_name(robot, urdf_scenario), jit=DEFECT_JIT)
    assert v.status == "fail"
    assert _killed_by(v, good) == {"reference.derivatives"}
    c = next(x for x in v.checks if x.id == "reference.derivatives")
    failing = {r["comparison"] for r in c.evidence["comparisons"] if r["max_relative"] > r["tolerance"]}
    assert {"ddq_d = d/dt dq_d (AD)", "ddq_d = d2/dt2 declared", "generated ddq_d = FD of generated dq_d"} <= failing
    assert "dq_d = d/dt q_d (AD)" not in failing                   # the first derivative is still right


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_funnel_widened_in_its_sx_fails_verify(robot, urdf_scenario, correct, monkeypatch):
    """The issue's arm7 defect: the SX funnel of e2 decays at half the declared rate (a wider funnel), and every
    containment check passes against it; only the comparison with the declaration notices."""
    good = correct[robot]           # the reference outcome, computed before anything is patched
    real = FunnelSpec.sx
    widened = {}

    def sx(self, t, **values):
        if self is widened.get("e2"):
            values.setdefault("a", ca.DM(self.a) / 2)
        return real(self, t, **values)
    monkeypatch.setattr(FunnelSpec, "sx", sx)
    sc = load_scenario(_name(robot, urdf_scenario))
    assert isinstance(sc.funnels["e2"], FunnelSpec) and min(sc.funnels["e2"].a) > 0
    widened["e2"] = sc.funnels["e2"]
    v = Run(sc, _options(jit=DEFECT_JIT)).verification
    assert v.status == "fail"
    assert "funnel.consistency" in _killed_by(v, good)
    assert all(c.status == "pass" for c in v.checks if c.id.startswith("funnel.containment."))
    c = next(x for x in v.checks if x.id == "funnel.consistency")
    assert "declared funnel e2" in c.detail


@pytest.mark.parametrize("robot", ROBOTS)
def test_a_numeric_value_twin_that_differs_from_its_sx_fails_verify(robot, urdf_scenario, correct, monkeypatch):
    """A numeric twin (value()) re-implemented with its own error: the initial-condition check reads it, the design
    does not; funnel.consistency compares the two."""
    good = correct[robot]           # the reference outcome, computed before anything is patched
    def value(self, t):
        return [p0 * math.exp(-a * t / 2) + pi for p0, pi, a in zip(self.phi0, self.phi_inf, self.a)]
    monkeypatch.setattr(FunnelSpec, "value", value)
    v = _verify(_name(robot, urdf_scenario))
    assert v.status == "fail"
    assert _killed_by(v, good) == {"funnel.consistency"}
    c = next(x for x in v.checks if x.id == "funnel.consistency")
    assert "value() against its SX" in c.detail


def test_value_is_evaluated_from_the_sx(paper):
    """The twins are gone: value() of both shapes is the SX evaluated, whatever sx computes."""
    shape = paper.funnels["e1"]
    t = ca.SX.sym("t")
    exact = np.asarray(ca.Function("F", [t], [shape.sx(t)])(0.7)).ravel()
    assert shape.value(0.7) == pytest.approx(exact, rel=0, abs=0)
    assert shape.value(0.7)[0] == pytest.approx(0.18 * math.exp(-2 * 0.7) + 0.01, rel=1e-15)


# --- near the boundary: the checks' own numbers ---------------------------------------------------------------

def _one_joint(write_scenario, F2='phi0 = 2.0\nphi_inf = 0.2\na = 1.0', ref='0.3*sin(t)'):
    text = f"""
[model]
type = "matrices"
coordinates = ["q1"]
[model.matrices]
M = [["2.0"]]
C = [["0"]]
G = ["0"]
[reference]
q = ["{ref}"]
[initial]
q = [0.01]
dq = [0.3]
[funnel.e1]
phi0 = 0.5
phi_inf = 0.05
a = 1.0
[funnel.e2]
{F2}
[approximator]
type = "none"
[simulation]
t_final = 2.0
"""
    return load_scenario(write_scenario(text))


@pins("funnel.consistency", "fail", "pass")
def test_funnel_consistency_fails_on_a_relative_error_of_3e_7_and_passes_at_1e_12(write_scenario, monkeypatch):
    sc = _one_joint(write_scenario)
    d = derive(sc)
    assert check_funnel_consistency(d, 2.0).status == "pass"
    for factor, status in ((1 + 3e-7, "fail"), (1 + 1e-12, "pass"), (1 + 3e-9, "fail")):      # tolerance 1e-9
        bad = derive(sc)
        bad.signals["F2"] = bad.signals["F2"] * factor
        c = check_funnel_consistency(bad, 2.0)
        assert c.status == status, (factor, c.detail)
        row = next(r for r in c.evidence["comparisons"] if r["signal"] == "F2" and r["against"] == "declared")
        assert row["max_relative"] == pytest.approx(factor - 1, rel=1e-3)


@pins("funnel.consistency", "fail", "pass")
def test_funnel_consistency_compares_dF_and_expression_funnels(write_scenario):
    sc = _one_joint(write_scenario, F2='F = "1.5/(1 + t) + 0.2"')
    assert isinstance(sc.funnels["e2"], ExpressionFunnel)
    d = derive(sc)
    assert check_funnel_consistency(d, 2.0).status == "pass"
    bad = derive(sc)
    bad.signals["dF2"] = bad.signals["dF2"] * (1 + 1e-6)          # the derivative alone
    c = check_funnel_consistency(bad, 2.0)
    assert c.status == "fail" and "dF2" in c.detail and c.where["joint"] == 1


@pins("reference.derivatives", "fail", "pass")
def test_reference_derivatives_pins_each_comparison(write_scenario):
    sc = _one_joint(write_scenario)
    d = derive(sc)
    c = check_reference_derivatives(d, 2.0)
    assert c.status == "pass" and len(c.evidence["comparisons"]) == 7
    # fourth-order differences of the generated code: accurate far below FD_TOL for a smooth reference
    fd = [r["max_relative"] for r in c.evidence["comparisons"] if "FD" in r["comparison"]]
    assert max(fd) < 1e-8
    for key, eps, status in (("ddqd", 3e-7, "fail"), ("dqd", 3e-7, "fail"), ("ddqd", 1e-12, "pass")):
        bad = derive(sc)
        bad.reference_t[key] = bad.reference_t[key] + eps * ca.cos(bad.sym["t"]) * 0.3
        got = check_reference_derivatives(bad, 2.0)
        assert got.status == status, (key, eps, got.detail)
    # the finite differences of the generated code alone: dq_d off by 3e-6 of its peak fails them (tolerance 1e-6)
    bad = derive(sc)
    bad.reference_t["dqd"] = bad.reference_t["dqd"] * (1 + 3e-6)
    rows = {r["comparison"]: r for r in check_reference_derivatives(bad, 2.0).evidence["comparisons"]}
    fd_row = rows["generated dq_d = FD of generated q_d"]
    assert fd_row["tolerance"] == 1e-6 and fd_row["max_relative"] > fd_row["tolerance"]
    assert rows["generated ddq_d = FD of generated dq_d"]["max_relative"] == pytest.approx(3e-6, rel=1e-2)
    # a wrong q_d (shifted by 1e-6 of its peak): its derivatives are still the chain, the declaration is not
    bad = derive(sc)
    bad.reference_t["qd"] = bad.reference_t["qd"] + 0.3e-6
    got = check_reference_derivatives(bad, 2.0)
    assert got.status == "fail" and "declared" in got.detail

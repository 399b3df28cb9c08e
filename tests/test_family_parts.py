"""The family's parts beyond the paper's: funnels given as expressions (non-monotone ones included) and the RBF
approximator, on a hidden-style 3-link planar arm; their bad input; the shipped prescribed-performance scenario."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from symfunnel.cli import main

from symfunnel.reporting.sections import scenario_section

from .conftest import MINIMAL_2LINK, alpha2_dot_fd_error

REPO = Path(__file__).resolve().parent.parent

#: F1 with a bump: it falls, rises again around t = 0.8 s and falls once more (not monotone)
BUMP = "0.25*exp(-2*t) + 0.04 + 0.08*exp(-(t - 0.8)^2/0.02)"


def _bump(t):
    return 0.25 * np.exp(-2 * t) + 0.04 + 0.08 * np.exp(-(t - 0.8) ** 2 / 0.02)


def _bump_dot(t):
    return -0.5 * np.exp(-2 * t) - 0.08 * 2 * (t - 0.8) / 0.02 * np.exp(-(t - 0.8) ** 2 / 0.02)


ARM3 = f"""
name = "hidden3"
[model]
type = "planar"
links = [{{ mass = 1.0, length = 0.4 }}, {{ mass = 0.7, length = 0.35 }}, {{ mass = 0.4, length = 0.25 }}]
[reference]
q = ["0.4*sin(t)", "0.3 + 0.2*sin(1.3*t)", "-0.2*cos(0.7*t)"]
[initial]
q = [0.03, 0.27, -0.17]
[funnel.e1]
F = "{BUMP}"
[funnel.e2]
F = ["2.2*exp(-t) + 0.3", "2*exp(-t) + 0.3", "2*exp(-1.5*t) + 0.3"]
[design]
transform = "log"
[approximator]
type = "rbf"
[rbf]
size = 16
[rbf.box]
q = [-1.0, 1.0]
dq = [-2.0, 2.0]
[controller]
k1 = 4.0
k2 = 12.0
[adaptation]
gamma = 5.0
sigma = 0.05
[plant]
viscous = 0.3
disturbance = "0.2*sin(3*t)"
mass_scale = 1.05
[simulation]
t_final = 1.5
[[expect]]
check = "certify.invariance"
status = "fail"
reason = "V(0) of the initial errors and weights exceeds every level set inside the funnels: the barrier argument cannot close (the run itself stays inside)"
"""


@pytest.fixture(scope="module")
def arm3(tmp_path_factory):
    """The hidden-style arm through the pipeline (each stage computed once for this module)."""
    from symfunnel.pipeline import Run
    from symfunnel.scenario import load_scenario
    p = tmp_path_factory.mktemp("arm3") / "arm3.toml"
    p.write_text(ARM3, encoding="utf-8")
    return Run(load_scenario(p))


def test_expression_funnel_is_the_written_function_and_its_exact_derivative(arm3):
    d = arm3.design
    f = d.function("funnels", ["t"], ["F1", "dF1", "F2", "dF2"])
    for t in np.linspace(0.0, 1.5, 31):
        F1, dF1, F2, dF2 = (np.array(v).ravel() for v in f(t))
        assert F1 == pytest.approx([_bump(t)] * 3, rel=1e-14)
        assert dF1 == pytest.approx([_bump_dot(t)] * 3, rel=1e-12, abs=1e-14)
        assert F2 == pytest.approx([2.2 * math.exp(-t) + 0.3, 2 * math.exp(-t) + 0.3,
                                    2 * math.exp(-1.5 * t) + 0.3], rel=1e-14)
        assert dF2[2] == pytest.approx(-3 * math.exp(-1.5 * t), rel=1e-13)
    rows = dict(scenario_section(arm3.scenario)["params"])
    assert rows["funnel F1(t)"] == BUMP and rows["funnel F2(t)"].startswith("joint 1: 2.2*exp(-t) + 0.3; joint 2:")


def test_extremes_of_a_non_monotone_funnel_are_taken_over_the_horizon(arm3):
    """sup F1 is the bump's start or its peak, not F1(0); inf F1 is the end: sampled against numpy."""
    from symfunnel.family.funnels import extremes
    lo, hi, t_lo = extremes(arm3.scenario.funnels["e1"], 1.5)
    ts = np.linspace(0, 1.5, 150001)
    assert lo == pytest.approx([_bump(ts).min()] * 3, rel=1e-6)
    assert hi == pytest.approx([_bump(ts).max()] * 3, rel=1e-6)
    # the bump makes F1 rise on part of the horizon
    assert np.any(np.diff(_bump(ts)) > 0) and t_lo == pytest.approx([1.5] * 3)


def test_rbf_regressor_against_an_independent_numpy_implementation(arm3):
    d = arm3.design
    ap = d.approximator
    assert ap.name == "rbf" and d.states == [("w_hat", (17, 3))] and ap.states() == [] and ap.box() == {}
    phi = d.function("Phi", ["q", "dq"])
    rng = np.random.default_rng(5)
    lower = np.array([-1.0] * 3 + [-2.0] * 3)
    span = np.array([2.0] * 3 + [4.0] * 3)
    width = 16 ** (-1 / 6)                       # spacing of 16 points in 6 unit dimensions, width_factor 1
    for _ in range(20):
        x = rng.uniform(-1.5, 1.5, 6)
        u = (x - lower) / span
        want = [math.exp(-sum((u[k] - c[k]) ** 2 for k in range(6)) / width ** 2) for c in ap.centres] + [1.0]
        got = np.array(phi(x[:3], x[3:])).ravel()
        assert got == pytest.approx(want, rel=1e-13, abs=1e-300)
    # the centres are Sobol points of the unit box: all distinct, inside it, and not all in one corner
    c = ap.centres
    assert c.shape == (16, 6) and np.all((c >= 0) & (c <= 1)) and len({tuple(r) for r in c}) == 16
    assert np.all(np.abs(c.mean(axis=0) - 0.5) < 0.2)


def test_rbf_grid_centres_and_width(write_scenario):
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="") + ('\n[approximator]\ntype = "rbf"\n[rbf]\ninputs = ["q"]\ncentres = "grid"\n'
                                         'per_dim = 3\nbias = false\nwidth_factor = 2.0\n[rbf.box]\nq = [-1.0, 1.0]\n')
    d = derive(load_scenario(write_scenario(text)))
    ap = d.approximator
    assert ap.n_regressor == 9 and sorted(map(tuple, ap.centres)) == [(a, b) for a in (0, .5, 1) for b in (0, .5, 1)]
    assert ap.width == pytest.approx(1.0)           # 2 * spacing 0.5
    phi = np.array(d.function("Phi", ["q"])([0.0, 1.0])).ravel()
    # u = (0.5, 1): the centre (0.5, 1) gives 1, (0, 0) gives exp(-(0.25 + 1))
    k = list(map(tuple, ap.centres))
    assert phi[k.index((0.5, 1.0))] == pytest.approx(1.0) and phi[k.index((0.0, 0.0))] == pytest.approx(math.exp(-1.25))


def test_hidden_arm_alpha2_dot_is_exact(arm3):
    worst, used = alpha2_dot_fd_error(arm3.design, 60, 3, fill=0.9)
    assert used > 40
    assert worst <= 1e-6, worst


def test_hidden_arm_stays_in_its_funnels_and_passes_verify_with_its_identity(arm3):
    sim = arm3.simulation
    assert sim.status == "ok", sim.message
    v = arm3.verification
    by = {c.id: c for c in v.checks}
    assert by["design.identity.vdot"].status == "pass"
    assert by["funnel.parameters"].status == "skip" and "expression" in by["funnel.parameters"].detail
    assert all(c.status == "pass" for k, c in by.items() if k.startswith("funnel.containment"))
    # rho's constant lower bound uses sup F over the horizon (the bump's peak), not F(0)
    sup1 = _bump(np.linspace(0, 1.5, 150001)).max()
    terms = by["lyapunov.rho_positive"].evidence["terms"]
    assert terms["2 k1/sup F1"] == pytest.approx(2 * 4.0 / sup1, rel=1e-6)
    assert terms["k2/sup F2"] == pytest.approx(12.0 / 2.5, rel=1e-6)
    assert not v.unexpected and [c.id for c in v.failed] == ["certify.invariance"], [c.id for c in v.failed]
    inv = by["certify.invariance"]
    assert inv.status == "fail" and "V(0)" in str(inv.evidence)      # refuted by V(0), as declared


def test_hidden_arm_mutants_are_killed(arm3):
    from symfunnel.checks.theory import check_identity
    from symfunnel.design import derive
    sc = arm3.scenario
    variant = arm3.design.variant
    ids = [m.id for m in variant.mutants()]
    assert len(ids) >= 10 and "zeta_for_mu_in_adaptation" not in ids      # a funnel-transform mutant
    for m in ids:
        bad = derive(sc, mutant=m)
        assert check_identity(bad, np.random.default_rng(1), samples=200).status == "fail", m


def test_approximator_none_runs_end_to_end(write_scenario, capsys, tmp_path):
    text = MINIMAL_2LINK.format(C="") + (f'\n[funnel.e1]\nF = "{BUMP}"\n[simulation]\nt_final = 2.0\n'
                                         '[approximator]\ntype = "none"\n[design]\ntransform = "log"\n')
    path = str(write_scenario(text))
    assert main(["verify", path, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "pass"
    assert main(["codegen", path, "--lang", "c", "--rate", "2000", "--out", str(tmp_path / "c"), "--check"]) == 0
    capsys.readouterr()


# --- bad input ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("F, root", [("0.5 - 0.4*t", 1.25), ("0.3*cos(3*t)", math.pi / 6), ("log(t)", 0.0)])
def test_funnel_expression_not_positive_is_an_input_error_naming_the_key_and_time(write_scenario, capsys, F, root):
    """The time named is the first grid time at or after F's first zero (grid step 2 s / 4000)."""
    import re
    text = MINIMAL_2LINK.format(C="") + f'\n[funnel.e2]\nF = "{F}"\n[simulation]\nt_final = 2.0\n'
    assert main(["derive", str(write_scenario(text))]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("symfunnel: error:") and len(err.splitlines()) == 1
    assert "'funnel.e2.F'" in err
    when = float(re.search(r"at t = ([0-9.e+-]+) s", err).group(1))
    assert root <= when <= root + 2.0 / 4000 + 1e-9


def test_funnel_positive_on_the_horizon_only_is_accepted(write_scenario):
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="") + '\n[funnel.e1]\nF = "0.5 - 0.4*t"\n[simulation]\nt_final = 1.2\n'
    assert load_scenario(write_scenario(text)).funnels["e1"].value(1.2) == pytest.approx([0.02, 0.02])


@pytest.mark.parametrize("table, key, what", [
    ('F = "0.5"\nphi0 = 0.3', "funnel.e1.F", "cannot be combined with 'phi0'"),
    ('F = "0.5 + q1"', "funnel.e1.F", "q1"),
    ('F = ["0.5", "0.4", "0.3"]', "funnel.e1.F", "array of 3"),
    ('F = 0.5', "funnel.e1.F", "expected an expression string"),
])
def test_bad_funnel_expressions(write_scenario, capsys, table, key, what):
    text = MINIMAL_2LINK.format(C="") + f"\n[funnel.e1]\n{table}\n"
    assert main(["derive", str(write_scenario(text))]) == 2
    err = capsys.readouterr().err
    assert f"'{key}'" in err and what in err


def test_funnel_expression_may_name_model_parameters(write_scenario):
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="") + '\n[funnel.e2]\nF = "c*exp(-t) + b/10"\n'
    sc = load_scenario(write_scenario(text))
    assert sc.funnels["e2"].value(1.0) == pytest.approx([0.8 * math.exp(-1) + 0.1] * 2)


@pytest.mark.parametrize("extra, key, what", [
    ('[approximator]\ntype = "rbd"\n', "approximator.type", "did you mean 'rbf'"),
    ('[rbf]\nsize = 8\n', "rbf", "approximator.type is 'esn'"),
    ('[approximator]\ntype = "rbf"\n[esn]\nsize = 8\n', "esn", "approximator.type is 'rbf'"),
    ('[approximator]\ntype = "none"\n[rbf]\nsize = 8\n', "rbf", "approximator.type is 'none'"),
    ('[approximator]\ntype = "rbf"\n[rbf]\nsise = 8\n', "rbf.sise", "did you mean 'size'"),
    ('[approximator]\ntype = "rbf"\n[rbf]\ninputs = ["q", "e2"]\n', "rbf.inputs[1]", "one of q, dq"),
    ('[approximator]\ntype = "rbf"\n[rbf]\ncentres = "grid"\nper_dim = 9\n', "rbf.per_dim", "6561"),
    ('[approximator]\ntype = "rbf"\n[rbf.box]\ndq = [1.0, -1.0]\n', "rbf.box.dq[0]", "lower < upper"),
])
def test_bad_approximator_settings(write_scenario, capsys, extra, key, what):
    text = MINIMAL_2LINK.format(C="") + "\n" + extra
    assert main(["derive", str(write_scenario(text))]) == 2
    err = capsys.readouterr().err
    assert f"'{key}'" in err and what in err, err


def test_infeasible_expression_funnel_names_the_value_to_exceed(write_scenario):
    from symfunnel.checks.audit import check_funnel_initial
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="").replace("q = [0.0, 0.2]", "q = [0.0, 0.5]") + '\n[funnel.e1]\nF = "0.1 + 0.1*t"\n'
    c = check_funnel_initial(derive(load_scenario(write_scenario(text))))
    assert c.status == "fail" and "F(0) must exceed 0.3" in c.detail and "phi0" not in c.detail


# --- the shipped prescribed-performance scenario ------------------------------------------------------

def test_ppc_scenario_declares_its_source_and_deviations():
    from symfunnel.scenario import load_scenario
    sc = load_scenario(REPO / "derivations" / "ppc_log_rbf.toml")
    assert sc.n == 3 and sc.model.kind == "planar"
    assert (sc.design.transform, sc.design.approximator) == ("log", "rbf")
    assert all(hasattr(f, "exprs") for f in sc.funnels.values())
    assert "Prescribed Performance" in sc.source and "2008" in sc.source
    assert len(sc.deviations) >= 3 and all(d.reason for d in sc.deviations)


@pytest.mark.slow
def test_ppc_scenario_verifies_and_kills_its_mutants(capsys):
    path = str(REPO / "derivations" / "ppc_log_rbf.toml")
    assert main(["verify", path, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "pass"
    assert main(["verify", path, "--mutants", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["score"] >= 0.9


def test_rate_sensitivity_skips_phi_variations_of_an_expression_funnel(monkeypatch):
    """The design help varies phi_inf and a of funnel e2 only when it has them; its inner-loop gain is k2/inf F2."""
    import symfunnel.deployed.rate as rate
    from symfunnel.scenario import load_scenario
    sc = load_scenario(REPO / "derivations" / "ppc_log_rbf.toml")
    seen = []
    monkeypatch.setattr(rate, "min_rate", lambda s, d, **k: seen.append(s.k2) or {"min_rate_hz": 100.0, "tried": []})
    monkeypatch.setattr("symfunnel.design.derive", lambda s: object())    # each variation's design (unused here)
    out = rate.rate_sensitivity(sc, object(), t_final=1.0)
    status = {v["key"]: v.get("status") for v in out["variations"]}
    assert status == {"funnel.e2.phi_inf": "skip", "funnel.e2.a": "skip", "controller.k2": None}
    assert seen == [[10.0] * 3, [5.0] * 3]                  # the baseline, then k2 halved
    assert out["inner_loop_gain"] == pytest.approx([10.0 / (2.8 * math.exp(-1.0) + 0.2)] * 3, rel=1e-6)


@pytest.mark.parametrize("transform", ["funnel", "log"])
def test_rbf_with_either_transformation_satisfies_its_identity_and_kills_its_mutants(write_scenario, transform):
    from symfunnel.checks.theory import check_identity
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="") + (f'\n[design]\ntransform = "{transform}"\n[approximator]\ntype = "rbf"\n'
                                         '[rbf]\nsize = 8\n')
    sc = load_scenario(write_scenario(text))
    d = derive(sc)
    assert d.states == [("w_hat", (9, 2))]
    assert check_identity(d, np.random.default_rng(0), samples=300).status == "pass"
    for m in d.variant.mutants():
        bad = derive(sc, mutant=m.id)
        assert (check_identity(bad, np.random.default_rng(0), samples=200).status == "fail"
                or d.variant.equivalent(bad, m.id)), m.id

"""verify as a gate: declared expectations, the design identity, rho, the guarantee, the input gain, mutants.

Every check here gets a scenario or a mutant that makes it fail, and the gate's exit code is asserted both ways.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.scenario import DATA_DIR

from .conftest import MINIMAL_2LINK, VERIFY_PAPER_2S, main_once

FAST = ["--t-final", "2", "--samples", "1000"]
PAPER = (DATA_DIR / "paper_2dof.toml").read_text(encoding="utf-8")
PERFECT = MINIMAL_2LINK.format(C="")            # no plant unknowns: nothing for the proof to get wrong


def _verify(path, capsys, *extra):
    code = main(["verify", str(path), "--json", *FAST, *extra])
    out = json.loads(capsys.readouterr().out)
    return code, out, {c["id"]: c for c in out["checks"]}


@pytest.fixture(scope="module")
def perfect_verify(tmp_path_factory):
    """verify of PERFECT with the FAST options, run once for the module: (code, out, checks by id). The two tests
    that read it ran the same command on the same scenario text each."""
    import contextlib
    import io
    path = tmp_path_factory.mktemp("perfect") / "s.toml"
    path.write_text(PERFECT, encoding="utf-8")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["verify", str(path), "--json", *FAST])
    out = json.loads(buf.getvalue())
    return code, out, {c["id"]: c for c in out["checks"]}


def test_paper_passes_the_gate_with_its_findings_declared(tmp_path_factory):
    # conftest's `verify paper` over 2 s (FAST's horizon, 2000 samples), run once per session for test_verify and
    # test_certify too: this test ran the same command with 1000 samples
    p = main_once(tmp_path_factory, *VERIFY_PAPER_2S)
    code, out = p.returncode, json.loads(p.stdout)
    ids = {c["id"]: c for c in out["checks"]}
    assert code == 0 and out["status"] == "pass" and out["unexpected"] == []
    expected = {k for k, c in ids.items() if c["expected"] == "fail"}
    assert {"claim.eq26", "claim.eq33", "claim.theorem1", "model.skew_symmetry", "assumption.input_gain"} <= expected
    for k in expected:
        assert ids[k]["status"] == "fail" and ids[k]["reason"], k
    assert ids["design.identity.vdot"]["status"] == "pass"
    assert ids["lyapunov.guarantee"]["status"] == "warn" and "vacuous" in ids["lyapunov.guarantee"]["detail"]


def test_sigma_zero_is_valid_input_and_fails_rho_positive(write_scenario, capsys):
    text = re.sub(r"(?m)^sigma = .*$", "sigma = 0.0", PAPER)
    assert "sigma = 0.0" in text
    code, out, ids = _verify(write_scenario(text), capsys)
    assert code == 1
    assert ids["lyapunov.rho_positive"]["status"] == "fail" and ids["lyapunov.rho_positive"]["margin"] <= 0
    assert "lyapunov.rho_positive" in out["unexpected"]


def test_undeclared_input_gain_failure_fails_the_gate(write_scenario, capsys):
    text = PAPER.replace('check = "assumption.input_gain"\nstatus = "fail"', 'check = "assumption.input_gain"\nstatus = "pass"')
    code, out, ids = _verify(write_scenario(text), capsys)
    assert code == 1 and out["unexpected"] == ["assumption.input_gain"]
    ev = ids["assumption.input_gain"]["evidence"]
    assert ev["lambda_min"] < 0 < ev["lambda_min_without_dead_zone"]


def test_input_gain_passes_without_a_dead_zone_and_fails_with_disparate_slopes(write_scenario, capsys, perfect_verify):
    _, _, ids = perfect_verify
    assert ids["assumption.input_gain"]["status"] == "pass"
    # M^-1 D M with D = diag(1, 0.2): an independent numpy computation of the smallest eigenvalue it must find
    text = PERFECT + '\n[plant.dead_zone]\nb_l = -0.1\nb_r = 0.1\nleft = "u - b_l"\nright = "u - b_r"\n'
    text = text.replace('left = "u - b_l"\nright = "u - b_r"', 'left = "u - b_l"\nright = "u - b_r"')
    text = re.sub(r'right = "u - b_r"', 'right = "0.2*(u - b_r)"', text)
    code, out, ids = _verify(write_scenario(text), capsys)
    c = ids["assumption.input_gain"]
    q2 = c["where"]["q"][1]
    a, b, cc = 3.0, 1.0, 0.8
    M = np.array([[a + 2 * cc * np.cos(q2), b + cc * np.cos(q2)], [b + cc * np.cos(q2), b]])
    D = np.diag(c["where"]["slopes"])
    G = np.linalg.solve(M, D @ M)
    assert np.min(np.linalg.eigvalsh(0.5 * (G + G.T))) == pytest.approx(c["evidence"]["lambda_min"], rel=1e-9)
    assert c["status"] == "fail" and code == 1


def test_a_wrong_claim_declared_to_hold_fails_the_gate(write_scenario, capsys):
    text = PAPER.replace('name = "eq26"\nexpect = "fail"', 'name = "eq26"', 1)
    assert text != PAPER
    code, out, ids = _verify(write_scenario(text), capsys)
    assert code == 1 and out["unexpected"] == ["claim.eq26"]


def test_a_claim_declared_to_fail_that_holds_fails_the_gate(write_scenario, capsys):
    text = PAPER.replace('name = "eq20_z1"\n', 'name = "eq20_z1"\nexpect = "fail"\n', 1)
    code, out, _ = _verify(write_scenario(text), capsys)
    assert code == 1 and out["unexpected"] == ["claim.eq20_z1"]


def test_a_perfect_model_passes_with_a_real_guarantee(perfect_verify):
    code, out, ids = perfect_verify
    assert code == 0, out["unexpected"]
    g = ids["lyapunov.guarantee"]
    assert g["status"] == "pass" and g["margin"] > 0.05


@pytest.mark.parametrize("edit, key", [
    ('[[expect]]\ncheck = "lyapunov.decay"\nstatus = "maybe"\nreason = "x"\n', "expect[0].status"),
    ('[[expect]]\ncheck = "lyapunov.decay"\nstatus = "fail"\n', "expect[0].reason"),
    ('[[expect]]\ncheck = "lyapunov.decya"\nstatus = "fail"\nreason = "x"\n', "expect[0].check"),
    ('[[expect]]\ncheck = "claim.eq26"\nstatus = "fail"\nreason = "x"\n', "expect[0].check"),
])
def test_bad_expectations_are_input_errors(write_scenario, capsys, edit, key):
    code = main(["verify", str(write_scenario(PERFECT + "\n" + edit)), "--json"])
    err = capsys.readouterr().err
    assert code == 2 and f"'{key}'" in err and err.count("\n") == 1
    if "decya" in edit:
        assert "did you mean 'lyapunov.decay'" in err


def test_a_claims_expect_must_be_pass_or_fail(write_scenario, capsys):
    text = PAPER.replace('name = "eq26"\nexpect = "fail"', 'name = "eq26"\nexpect = "sometimes"', 1)
    assert main(["audit", str(write_scenario(text))]) == 2
    assert "claims[4].expect" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["paper", "arm7"])
def test_mutation_score_on_the_built_ins(name, capsys):
    assert main(["verify", name, "--mutants", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    ids = {m["id"] for m in out["mutants"]}
    assert len(ids) >= 12
    assert {"drop_cross_term", "drop_dF1_term", "drop_dF2_term", "flip_k1", "flip_k2", "drop_M_in_tau", "drop_C_dq",
            "zero_alpha2_dot", "flip_adaptation", "zeta_for_mu_in_adaptation", "flip_sigma", "drop_G"} <= ids
    assert out["score"] >= 0.9
    for m in out["mutants"]:
        assert m["killed"] != m["equivalent"] or not m["killed"]
        if m["killed"]:
            assert m["by"]
        if m["equivalent"]:
            assert m["proof"]
    assert out["score"] == out["killed"] / (out["total"] - out["equivalent"])


def test_drop_G_is_equivalent_exactly_when_G_is_zero(paper, capsys):
    from symfunnel.design import derive, variant_of
    v = variant_of(paper)
    d = derive(paper, mutant="drop_G")
    assert (v.equivalent(d, "drop_G") is not None) == bool(d.signals["G"].is_zero())


def test_mutants_the_identity_misses_go_through_the_full_gate(paper, monkeypatch):
    """The second stage of mutation testing: with the identity check disabled, the simulated gate still kills a
    controller error (its Lyapunov decay fails along the run), and names the checks that did."""
    import symfunnel.pipeline as P
    from symfunnel.checks.audit import CheckResult
    from symfunnel.design import variant_of
    monkeypatch.setattr(P, "check_identity", lambda design, rng: CheckResult("design.identity.vdot", "pass", "off"))
    keep = {"flip_adaptation"}
    cls = type(variant_of(paper))
    real = cls.mutants
    monkeypatch.setattr(cls, "mutants", lambda self: [m for m in real(self) if m.id in keep])
    out = P.run_mutants(paper, t_final=1.0, samples=500)
    (m,) = out["mutants"]
    assert m["killed"] and "design.identity.vdot" in m["by"] and "lyapunov.decay" in m["by"]

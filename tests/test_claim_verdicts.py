"""Claim verdicts with three values: proven (sympy), refuted (a counterexample, sampled or evaluated exactly), not
proven (samples agree, no proof) -- never "pass" on an unfinished proof (issue 21, row 15)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from symfunnel.checks.audit import check_claim
from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.scenario.load import from_dict


def _design_with_claims(tmp_path, claims):
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["claims"] = claims
    raw.pop("expect", None)
    raw.pop("deviations", None)
    sc = from_dict(raw, file=str(tmp_path / "s.toml"), base_dir=tmp_path, default_name="s")
    return derive(sc)


CASES = [
    # name, signal, expression, verdict, status
    ("exact", "F1", "0.18*exp(-2*t) + 0.01", "proven", "pass"),
    # equal on the horizon [0, 20] s, not identically: no proof, no counterexample
    ("late", "F1", "F1 + max(0, t - 1000)", "not proven", "warn"),
    # differs only within 0.1 % of the funnel's boundary: the boundary samples find it
    ("edge", "z1", "z1 + max(0, abs(e1) - 0.999*F1)", "refuted", "fail"),
    # below the sampling tolerance, yet sympy's difference 1e-12 t is no rounding: refuted at a point
    ("tiny", "F1", "F1 + 1e-12*t", "refuted", "fail"),
    ("wrong", "z1", "e1/(F1 + abs(e1))", "refuted", "fail"),
]


@pytest.fixture(scope="module")
def verdicts(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("claims")
    claims = [{"name": n, "signal": s, "expression": e} for n, s, e, _, _ in CASES]
    d = _design_with_claims(tmp, claims)
    rng = np.random.default_rng(0)
    return {c.name: check_claim(d, c, rng) for c in d.scenario.claims}


@pytest.mark.parametrize("name, signal, expression, verdict, status", CASES)
def test_claim_verdicts(verdicts, name, signal, expression, verdict, status):
    r = verdicts[name]
    assert (r.verdict, r.status) == (verdict, status), r.detail
    assert r.to_json()["verdict"] == verdict
    if verdict == "not proven":
        assert "not proven" in r.detail


def test_a_not_proven_claim_is_never_a_pass_of_the_gate(verdicts):
    r = verdicts["late"]
    assert r.status != "pass" and not r.unexpected      # warn: an informative finding, never "holds"


def test_inequality_claims_without_counterexample_are_not_proven(tmp_path):
    d = _design_with_claims(tmp_path, [
        {"name": "holds", "lhs": "dot(z1, z1)", "rhs": "dot(z1, z1) + 1"},
        {"name": "edge", "lhs": "dot(e1, e1)", "rhs": "0.9998*dot(F1, F1)"},
    ])
    rng = np.random.default_rng(0)
    out = {c.name: check_claim(d, c, rng) for c in d.scenario.claims}
    assert (out["holds"].status, out["holds"].verdict) == ("warn", "not proven")
    assert (out["edge"].status, out["edge"].verdict) == ("fail", "refuted")     # only near the boundary

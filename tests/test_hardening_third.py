"""Hardening, third pass (issue 44): verdicts that cannot be wrong, outputs that never destroy input, every signal one
line. Each test fails on the code before its fix."""

from __future__ import annotations

import copy

import pytest

from symfunnel.pipeline import Run, RunOptions
from symfunnel.scenario import load_scenario
from symfunnel.scenario.load import from_dict


def _paper_variant(tmp_path, **sections):
    """The paper scenario with some top-level tables replaced (its [[expect]] and [[deviations]] dropped)."""
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw.pop("expect", None)
    raw.pop("deviations", None)
    raw.update(sections)
    return from_dict(raw, file=str(tmp_path / "s.toml"), base_dir=tmp_path, default_name="s")


# --- 1. a claim never passes on samples alone ------------------------------------------------------

def test_a_decay_claim_that_holds_at_the_samples_is_not_proven_and_a_refuted_one_says_so(tmp_path):
    """rho = -1e12, delta = 1e12 holds at the 10000 sampled states and along the run (the issue's rho = 0,
    delta = 8.1e10 held at its samples and failed at 200000): agreement at samples is no proof, so the claim warns
    "not proven" (on the old code: pass). rho = 0, delta = -1e12 is refuted along the run itself."""
    sc = _paper_variant(tmp_path, claims=[{"name": "dd", "rho": "-1e12", "delta": "1e12"}])
    checks = {c.id: c for c in Run(sc, RunOptions(samples=10000)).verification.checks}
    c = checks["claim.dd"]
    assert (c.status, c.verdict) == ("warn", "not proven"), c.detail
    assert c.detail.startswith("not proven: held at ") and not c.unexpected
    assert c.to_json()["verdict"] == "not proven"
    sc = _paper_variant(tmp_path, claims=[{"name": "dd", "rho": "0", "delta": "-1e12"}])
    c = {c.id: c for c in Run(sc, RunOptions(t_final=1.0, samples=2000)).verification.checks}["claim.dd"]
    assert (c.status, c.verdict) == ("fail", "refuted"), c.detail

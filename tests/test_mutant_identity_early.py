"""Mutation testing reads only whether a mutant's identity check fails (issue 43): the check judges its first
`MUTANT_IDENTITY_FIRST` states first and a failing state there ends it (`check_identity(failure_first=...)`). The
mutation result is the full check's: compared here mutant by mutant and for the whole `run_mutants`."""

from __future__ import annotations

import numpy as np

from symfunnel.checks import theory as T
from symfunnel.design import derive, variant_of
from symfunnel.scenario import load_scenario


def test_the_first_states_decide_a_failing_identity_and_a_passing_one_is_checked_whole():
    sc = load_scenario("paper")
    statuses = {}
    for m in variant_of(sc).mutants():
        d = derive(sc, mutant=m.id)
        full = T.check_identity(d, np.random.default_rng([0, 11]))
        quick = T.check_identity(d, np.random.default_rng([0, 11]), failure_first=200)
        assert quick.status == full.status, m.id
        statuses[m.id] = full.status
        if full.status == "fail":
            assert quick.evidence["states"] == 200 and full.evidence["states"] == T.IDENTITY_SAMPLES
            assert quick.margin < 0
    assert sum(s == "fail" for s in statuses.values()) >= 14 and statuses["drop_G"] == "pass"   # G = 0: equivalent
    # a design that passes is judged on every state, as without the option: the same result, number for number
    d = derive(sc)
    full = T.check_identity(d, np.random.default_rng(3), samples=600)
    quick = T.check_identity(d, np.random.default_rng(3), samples=600, failure_first=100)
    assert (quick.status, quick.detail, quick.margin, quick.evidence) == (full.status, full.detail, full.margin,
                                                                          full.evidence)
    assert full.status == "pass" and full.evidence["states"] == 600


def test_run_mutants_gives_the_full_checks_result_with_a_tenth_of_the_states(monkeypatch):
    import symfunnel.pipeline as P
    counted = []
    real = T.eval_mapped

    def counting(f, pts, k):
        if f.name() == "identity":
            counted.append(k)
        return real(f, pts, k)
    monkeypatch.setattr(T, "eval_mapped", counting)
    sc = load_scenario("paper")
    quick = P.run_mutants(sc, samples=50)
    n_quick, first = sum(counted), P.MUTANT_IDENTITY_FIRST
    counted.clear()
    monkeypatch.setattr(P, "MUTANT_IDENTITY_FIRST", None)          # the full check, as before
    full = P.run_mutants(sc, samples=50)
    assert quick == full                                           # every row: killed, by, equivalent, proof
    assert full["killed"] == 15 and full["equivalent"] == 1
    assert sum(counted) == 15 * T.IDENTITY_SAMPLES                 # 30000 states judged before
    assert first == 200 and n_quick == 15 * first                   # 3000 now

"""The report's rate bracket reuses the containment certificate the report's certificates computed (the same
scenario, design, horizon and parameter box) instead of computing certify.containment a second time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from symfunnel.certificates import containment as C
from symfunnel.certificates.problem import Context
from symfunnel.certificates.region import parameter_box
from symfunnel.certificates.result import Certificate
from symfunnel.certificates.sampled_rate import reuse_containment, sampled_bracket, simulated_w_hat_range


@pytest.fixture(scope="module")
def run():
    """A paper Run of its own: the pipeline's in-process certificate cache is emptied for this module (another test
    of the worker may have certified the same scenario and horizon with other objects, whose containment the bracket
    rightly does not reuse) and restored after."""
    from symfunnel import pipeline
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.scenario import load_scenario
    saved = dict(pipeline._CERTIFICATIONS)
    pipeline._CERTIFICATIONS.clear()
    try:
        yield Run(load_scenario("paper"), RunOptions(t_final=2.0, samples=200))
    finally:
        pipeline._CERTIFICATIONS.clear()
        pipeline._CERTIFICATIONS.update(saved)


@pytest.fixture
def calls(monkeypatch):
    """The certify.containment computations of a test, counted."""
    seen = []
    real = C.certify_containment

    def counted(ctx, budget):
        seen.append(ctx)
        return real(ctx, budget)
    monkeypatch.setattr(C, "certify_containment", counted)
    return seen


def _without_seconds(x):
    if isinstance(x, dict):
        return {k: _without_seconds(v) for k, v in x.items() if k != "seconds"}
    if isinstance(x, list):
        return [_without_seconds(v) for v in x]
    return x


@pytest.mark.slow
def test_a_report_computes_containment_once(run, calls, tmp_path):
    from symfunnel.reporting import build_report
    build_report(run, tmp_path / "paper.html", codegen=False, mutants=False, deployed=True)
    assert len(calls) == 1                 # the certificates section's; the bracket reused it (was 2)
    assert run.certification.context is calls[0]
    assert "rate-bracket" in (tmp_path / "paper.html").read_text()


def test_the_bracket_with_the_reused_certificate_is_the_bracket_computed_afresh(run, calls):
    prior = run.certification.context
    before = len(calls)
    kw = dict(t_final=run.t_final, margin=0.05, f_sim=None,
              w_hat_range=simulated_w_hat_range(run.design, run.closed_loop, run.simulation))
    reused = sampled_bracket(run.scenario, run.design, prior=prior, **kw)
    assert len(calls) == before
    fresh = sampled_bracket(run.scenario, run.design, **kw)
    assert len(calls) == before + 1
    assert _without_seconds(reused) == _without_seconds(fresh)


def test_containment_is_reused_only_for_the_same_problem(run):
    prior = run.certification.context
    sc, d = run.scenario, run.design
    cert = prior.results[C.CID]
    assert cert.status in ("proven", "undecided")

    def fresh(**change):
        kw = dict(scenario=sc, design=d, t_final=float(run.t_final), params=parameter_box(sc), W_star=None,
                  w_hat_range=None)
        kw.update(change)
        return Context(**kw)
    same = fresh()
    assert reuse_containment(same, prior) and same.results[C.CID] is cert
    box = parameter_box(sc)
    wider = dataclasses.replace(box, hi=np.asarray(box.hi, float) * 1.01 + 1e-9)
    from symfunnel.design import derive
    for other in (fresh(t_final=float(run.t_final) / 2), fresh(params=wider), fresh(design=derive(sc)),
                  fresh(scenario=dataclasses.replace(sc) if dataclasses.is_dataclass(sc) else object())):
        assert not reuse_containment(other, prior) and C.CID not in other.results
    refuted = dataclasses.replace(prior, results={C.CID: Certificate(C.CID, "refuted", "a breach")})
    assert not reuse_containment(fresh(), refuted)
    assert not reuse_containment(fresh(), None)

"""The in-process certification cache (pipeline.Run.certification) gives a Run the certificates proven for its own
design only: the same scenario with another design (set on the Run, as a patched `derive` or an API caller does) is
certified afresh, the same design again is not."""

from __future__ import annotations

import dataclasses

import casadi as ca
import pytest

import symfunnel.certificates as certificates
import symfunnel.pipeline as pipeline
from symfunnel.pipeline import Run


@pytest.fixture
def counted(monkeypatch):
    """run_certificates replaced by a counter returning a fresh marker per call (no interval work), the cache empty."""
    calls = []

    def fake(scenario, design, **kw):
        calls.append(design)
        return object()
    monkeypatch.setattr(certificates, "run_certificates", fake)
    monkeypatch.setattr(pipeline, "_CERTIFICATIONS", {})
    return calls


def _run() -> Run:
    return Run.load("paper", t_final=1.0, certify_only=("certify.input_gain",))


def _widened(design):
    """The design with its first funnel-transformed error scaled by (1 + 2^-40): one constant's low bits differ."""
    name = "z1" if "z1" in design.signals else sorted(design.signals)[0]
    return dataclasses.replace(design, signals={**design.signals, name: design.signals[name] * (1 + 2.0 ** -40)},
                               _functions={})


def test_a_second_run_of_the_same_design_reads_the_cache(counted):
    first = _run().certification
    assert _run().certification is first
    assert len(counted) == 1


def test_another_design_of_the_same_scenario_is_certified_afresh(counted):
    first = _run().certification
    other = _run()
    other.__dict__["design"] = _widened(other.design)
    assert other.certification is not first
    assert len(counted) == 2 and counted[1] is other.design


def test_the_fingerprint_sees_a_constants_last_bits_and_not_a_rederivation():
    a, b = _run().design, _run().design
    assert a.fingerprint() == b.fingerprint()
    assert _widened(a).fingerprint() != a.fingerprint()
    x = ca.SX.sym("x")
    assert str(x * (1 + 2.0 ** -40)) == str(x * 1.0000001)    # printing would not have told them apart

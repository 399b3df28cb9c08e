"""The compiled closed loop takes the design's numbers (gains, adaptation rates, exponential funnels) as parameters z
beside the plant's: designs that differ only in them run on one compiled library, with the trajectories their
numbers folded in as constants give, bit for bit; a design that is not its scenario's derivation keeps its
numbers folded in."""

from __future__ import annotations

import shutil
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.simulation import compiled, simulate
from symfunnel.simulation.closedloop import build_closed_loop

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


def _retuned(sc):
    """The scenario with every number the loop takes as z moved (gains, rates, both funnels' shapes, the
    smoothing width)."""
    e1, e2 = sc.funnels["e1"], sc.funnels["e2"]
    return sc.replace({
        "controller.k1": [1.3 * v for v in sc.k1], "controller.k2": [0.8 * v for v in sc.k2],
        "adaptation.gamma": 2.0 * sc.gamma, "adaptation.sigma": 0.5 * sc.sigma + 0.01,
        "funnel.e1.phi0": [1.2 * v for v in e1.phi0], "funnel.e1.phi_inf": [0.9 * v for v in e1.phi_inf],
        "funnel.e1.a": [1.1 * v for v in e1.a], "funnel.e2.phi0": [1.25 * v for v in e2.phi0],
        "funnel.e2.phi_inf": [1.1 * v for v in e2.phi_inf], "funnel.e2.a": [0.9 * v for v in e2.a],
        "simulation.smoothing_width": 2.0 * sc.simulation.smoothing_width})


@pytest.mark.parametrize("robot", ["paper", pytest.param("arm7", marks=pytest.mark.slow), "urdf"])
def test_a_retuned_design_runs_on_the_compiled_loop_of_the_first(robot, urdf_scenario, monkeypatch):
    """The retuned design finds the first design's library without generating C, and that library at the retuned
    z gives, at random states, the right-hand side built with the retuned numbers folded in (CasADi's VM)."""
    sc = load_scenario(urdf_scenario if robot == "urdf" else robot)
    cl = build_closed_loop(sc, derive(sc))
    first = compiled.compile_closed_loop(cl)
    assert first.mode == "compiled" and len(first.design_values) == len(cl.z_names) > 0
    var = _retuned(sc)
    clv = build_closed_loop(var, derive(var))
    assert clv.z_names == cl.z_names and not np.allclose(clv.z0, cl.z0)
    monkeypatch.setattr(compiled, "_LOADED", {})

    def no_codegen(*a, **k):
        raise AssertionError("generated C for a design that differs only in its numbers")
    monkeypatch.setattr(compiled, "_newton_jacobian", no_codegen)
    comp = compiled.compile_closed_loop(clv).bind(clv.p0)
    assert comp.cached and comp.library == first.library
    rng = np.random.default_rng(5)
    inv = np.argsort(comp.perm)
    for _ in range(4):
        t = float(rng.uniform(0.0, 2.0))
        x = clv.x0 + rng.normal(scale=0.05, size=clv.nx)
        got = np.asarray(comp.dae(t, x[comp.perm], [], np.concatenate([[0.0], comp.pvals]), [])[0]).ravel()[inv]
        want = clv.rhs(t, x)
        assert np.allclose(got, want, rtol=1e-12, atol=1e-12 * np.max(np.abs(want)))
    # the Newton Jacobian computes d/dx alone: its blocks in t and in [plant p; z] are structurally zero
    jac = ca.external("jac_symfunnel_ode", comp.library)
    assert jac.nnz_out(jac.index_out("jac_ode_x")) > 0
    assert jac.nnz_out(jac.index_out("jac_ode_p")) == 0 and jac.nnz_out(jac.index_out("jac_ode_t")) == 0


def _errors(sc, design, reference, closed_loop=None, tf=3.0):
    """Largest |q, dq - reference| over rounding-level perturbations of one run (the run's own spread)."""
    out = []
    for eps in (0.0, 1e-12, -1e-11):
        r = simulate(sc, design, t_final=tf, closed_loop=closed_loop,
                     params={"plant.mass_scale": float(sc.plant.mass_scale) * (1 + eps)})
        assert r.status == "ok", r.message
        out.append(float(np.max(np.abs(r.x[:, :2 * sc.n] - reference.x[:, :2 * sc.n]))))
    return out


def test_a_retuned_paper_on_the_shared_library_is_within_the_integrators_tolerance_of_its_folded_numbers():
    """Against a tight run (rtol 1e-10) of the retuned paper with its numbers folded in as constants, the runs on
    the shared library (numbers as z) err by at most twice what the folded library's own runs err over rounding-
    level perturbations; a 1 % change of k1 on the same library is far outside that band. (Constant folding
    rounds a few products differently, so the two libraries agree to rounding, not bit for bit.)"""
    var = _retuned(load_scenario("paper"))
    d = derive(var)
    folded = build_closed_loop(var, d)
    folded.xdot_pz = None                     # this design's numbers compiled in as constants
    tight = simulate(var.replace({"simulation.rtol": 1e-10, "simulation.atol": 1e-12}), d, t_final=3.0,
                     closed_loop=folded)
    assert tight.status == "ok" and tight.stats["compiled_library"] != simulate(var, d, t_final=0.1).stats[
        "compiled_library"]
    band = _errors(var, d, tight, closed_loop=folded)
    shared = _errors(var, d, tight)
    assert max(shared) <= 2 * max(band), (shared, band)
    assert max(band) < 1e-3
    other = var.replace({"controller.k1": [v * 1.01 for v in var.k1]})
    assert min(_errors(other, derive(other), tight)) > 10 * max(band)


def test_a_design_that_is_not_its_scenarios_derivation_keeps_its_numbers_folded_in(urdf_scenario):
    """A design whose torque was edited by hand after derive (a twin): rebuilding it from the scenario with z would
    drop the edit, so the loop keeps the numbers folded in and the compiled code runs the edited torque."""
    sc = load_scenario(urdf_scenario)
    d = derive(sc)
    d.signals["tau"] = 1.5 * d.signals["tau"]
    cl = build_closed_loop(sc, d)
    assert cl.xdot_pz is None and cl.z_names == []
    comp = compiled.compile_closed_loop(cl).bind(cl.p0)
    assert comp.design_values.size == 0
    honest = build_closed_loop(sc, derive(sc))
    x = cl.x0 + 0.01
    got = np.asarray(comp.dae(0.2, x[comp.perm], [], np.concatenate([[0.0], comp.pvals]), [])[0]).ravel()
    want = cl.rhs(0.2, x)[comp.perm]
    assert np.allclose(got, want, rtol=1e-12, atol=1e-12 * np.max(np.abs(want)))
    assert not np.allclose(want, honest.rhs(0.2, x)[comp.perm], rtol=1e-6)

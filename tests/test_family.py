"""The declared design family: transformations against sympy, the identity for every combination, the pipeline
computing each stage once."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import sympy as sp

from symfunnel.cli import main
from symfunnel.family.transforms import TRANSFORMS

from .conftest import MINIMAL_2LINK


@pytest.mark.parametrize("name, exact", [
    ("funnel", lambda e, F: e / (F - sp.Abs(e))),
    ("log", lambda e, F: sp.Rational(1, 2) * sp.log((F + e) / (F - e))),
])
def test_transform_z_mu_r_against_sympy(name, exact):
    e, F = ca.SX.sym("e"), ca.SX.sym("F")
    out = TRANSFORMS.get(name)().build(e, F)
    f = ca.Function("T", [e, F], [out["z"], out["mu"], out["r"]])
    es, Fs = sp.symbols("e F", real=True)
    z = exact(es, Fs)
    mu = sp.diff(z, es)
    rng = np.random.default_rng(3)
    for _ in range(200):
        Fv = rng.uniform(0.05, 2.0)
        ev = Fv * rng.choice([rng.uniform(-0.999, 0.999), rng.uniform(-1e-4, 1e-4)])
        if ev == 0:
            continue
        zv, muv, rv = (float(v) for v in f(ev, Fv))
        sub = {es: sp.Float(ev, 30), Fs: sp.Float(Fv, 30)}
        assert zv == pytest.approx(float(z.subs(sub)), rel=1e-12)
        assert muv == pytest.approx(float(mu.subs(sub)), rel=1e-11)
        assert rv == pytest.approx(float((es / z).subs(sub)), rel=1e-12)
    # r = e/z is finite and smooth through e = 0 (the coupling term divides by nothing)
    r0, dr0 = (float(v) for v in ca.Function("r", [e, F], [out["r"], ca.jacobian(out["r"], e)])(0.0, 0.7))
    assert np.isfinite(r0) and np.isfinite(dr0)
    assert r0 == pytest.approx(0.7, rel=1e-15)             # e/z -> F at e = 0 for both (h'(0) = 1)


@pytest.mark.parametrize("transform", ["funnel", "log"])
@pytest.mark.parametrize("approximator", ["esn", "none"])
def test_every_combination_derives_and_satisfies_its_identity(write_scenario, transform, approximator):
    from symfunnel.checks.theory import check_identity
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    text = MINIMAL_2LINK.format(C="") + f'\n[design]\ntransform = "{transform}"\n[approximator]\ntype = "{approximator}"\n'
    sc = load_scenario(write_scenario(text))
    d = derive(sc)
    assert [k for k, _ in d.states] == (["x_esn", "w_hat"] if approximator == "esn" else [])
    c = check_identity(d, np.random.default_rng(0), samples=500)
    assert c.status == "pass", c.detail
    for m in d.variant.mutants():
        bad = check_identity(derive(sc, mutant=m.id), np.random.default_rng(0), samples=200)
        assert bad.status == "fail" or d.variant.equivalent(derive(sc, mutant=m.id), m.id), m.id


def test_unknown_transform_and_approximator_are_input_errors(write_scenario, capsys):
    base = MINIMAL_2LINK.format(C="")
    assert main(["derive", str(write_scenario(base + '\n[design]\ntransform = "lgo"\n'))]) == 2
    err = capsys.readouterr().err
    assert "'design.transform'" in err and "did you mean 'log'" in err
    assert main(["derive", str(write_scenario(base + '\n[approximator]\ntype = "rfb"\n'))]) == 2
    err = capsys.readouterr().err
    assert "'approximator.type'" in err and "one of esn" in err


def test_a_run_computes_each_stage_once(paper, monkeypatch):
    import symfunnel.checks.lyapunov as lyap
    import symfunnel.design as design_mod
    from symfunnel.pipeline import Run, RunOptions
    calls = {"derive": 0, "derive with the numbers as symbols": 0, "w_star": 0}
    real_derive, real_fit = design_mod.derive, lyap.estimate_w_star

    def counting_derive(*a, **k):
        # the closed loop derives the design once more with its numbers as symbols (what is compiled)
        calls["derive" if k.get("values") is None else "derive with the numbers as symbols"] += 1
        return real_derive(*a, **k)

    def counting_fit(*a, **k):
        calls["w_star"] += 1
        return real_fit(*a, **k)
    monkeypatch.setattr(design_mod, "derive", counting_derive)
    monkeypatch.setattr(lyap, "estimate_w_star", counting_fit)
    run = Run(paper, RunOptions(t_final=1.0, samples=500))
    v = run.verification
    run.trajectory_arrays()
    run.code("python")
    assert calls == {"derive": 1, "derive with the numbers as symbols": 1, "w_star": 1}
    assert v.design is run.design is run.closed_loop.design and v.lyapunov is run.lyapunov
    assert set(run.timings) >= {"derive", "closed_loop", "simulate", "lyapunov", "audit", "verify"}

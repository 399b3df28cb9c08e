"""The closed loop compiled once with the plant's uncertain quantities as parameters p (and x0 as the initial state)."""

from __future__ import annotations

import numpy as np
import pytest

from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.simulation import simulate

# The paper run's summary, recorded before the plant's quantities became parameters of the compiled loop
# (commit e9d59c2, values compiled into the code): parameterising must not change what `simulate` gives.
PINNED_PAPER = {"min_margin_e1": [0.9796013764050912, 0.9683783515271457],
                "min_margin_e2": [0.26829268292682934, 0.26829268292682934],
                "max_abs_tau": [501.5964766017037, 165.62490465631925]}


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def test_paper_run_unchanged_by_parameterisation(paper):
    """The pins are over the output points; the summary's extremes also cover the samples between them, so they
    can only be further out (a lower margin, a larger torque)."""
    r = simulate(paper, derive(paper))
    s = r.summary()
    assert s["status"] == "ok"
    at_points = {"min_margin_e1": np.min(r.signals["m1"], axis=0), "min_margin_e2": np.min(r.signals["m2"], axis=0),
                 "max_abs_tau": np.max(np.abs(r.signals["tau"]), axis=0)}
    for k, v in PINNED_PAPER.items():
        assert list(at_points[k]) == pytest.approx(v, rel=1e-6), k
        worse = np.asarray(s[k]) <= at_points[k] if k.startswith("min") else np.asarray(s[k]) >= at_points[k]
        assert worse.all(), k


def _variant(sc, edit, name="variant"):
    import copy

    from symfunnel.scenario import from_dict
    raw = copy.deepcopy(sc.raw)
    edit(raw)
    return from_dict(raw, file=f"{name}.toml", base_dir=sc.path.parent, default_name=name)


def _shaken(raw):
    pl = raw["plant"]
    pl["mass_scale"] = 1.3
    pl["viscous"] = [11.0, 17.0]
    pl["coulomb"] = 4.5
    pl.setdefault("parameters", {})["m4"] = 2.25
    pl["dead_zone"]["b_l"] = [-1.2, -0.7]
    pl["dead_zone"]["b_r"] = 1.4


def test_parametric_rhs_is_the_rhs_of_the_variant(paper):
    """p = a variant's values gives, at random states, the right-hand side and signals built for that variant."""
    import casadi as ca

    from symfunnel.plant.equations import plant_parameters
    from symfunnel.simulation.closedloop import build_closed_loop
    var = _variant(paper, _shaken)
    cl, clv = build_closed_loop(paper, derive(paper)), build_closed_loop(var, derive(var))
    names, pv = plant_parameters(var)
    assert names == cl.p_names
    assert not np.allclose(pv, cl.p0)
    f = ca.Function("f", [cl.t, cl.x, cl.p], [cl.xdot_p, cl.signals_p["tau_applied"], cl.signals_p["friction"]])
    rng = np.random.default_rng(3)
    for _ in range(5):
        t = float(rng.uniform(0, 5))
        x = cl.x0 + rng.normal(scale=0.3, size=cl.nx)
        x[cl.slices["x_esn"]] = np.tanh(x[cl.slices["x_esn"]])
        a, tau_a, fr = (np.asarray(v).ravel() for v in f(t, x, pv))
        o = clv.evaluate_outputs([t], x[None, :])
        assert np.allclose(a, clv.rhs(t, x), rtol=1e-12, atol=1e-10)
        assert np.allclose(tau_a, o["tau_applied"][0], rtol=1e-12, atol=1e-12)
        assert np.allclose(fr, o["friction"][0], rtol=1e-12, atol=1e-12)
        # and the nominal p gives the nominal loop
        assert np.allclose(np.asarray(f(t, x, cl.p0)[0]).ravel(), cl.rhs(t, x), rtol=1e-12, atol=1e-10)


def test_variant_runs_on_the_nominal_compiled_loop(paper):
    """simulate(nominal loop, params=variant's values) = simulate(variant, derive(variant)), with no second compilation."""
    from symfunnel.plant.equations import plant_parameters
    from symfunnel.simulation.closedloop import build_closed_loop
    var = _variant(paper, _shaken)
    cl = build_closed_loop(paper, derive(paper))
    simulate(paper, cl.design, t_final=1.0, closed_loop=cl)
    comp = cl._compiled
    names, pv = plant_parameters(var)
    x0 = cl.x0.copy()
    x0[:2] = [0.004, -0.002]
    a = simulate(paper, cl.design, t_final=1.0, closed_loop=cl, params=dict(zip(names, pv)), x0=x0)
    assert cl._compiled is comp and len(comp) == 1
    var2 = _variant(var, lambda r: r["initial"].update(q=[0.004, -0.002]))
    b = simulate(var2, derive(var2), t_final=1.0)
    assert b.stats["cache_hit"]            # the same generated code: loaded, not compiled again
    assert a.status == b.status == "ok"
    assert np.array_equal(a.x, b.x)
    assert not np.allclose(a.x[-1], simulate(paper, cl.design, t_final=1.0, closed_loop=cl).x[-1])


def test_scales_are_factors_of_disturbance_and_branches(paper):
    """disturbance_scale and the dead zone's left/right_scale multiply what the expressions give."""

    def scaled(raw):
        raw["plant"]["disturbance_scale"] = [2.0, 0.5]
        raw["plant"]["dead_zone"]["right_scale"] = 1.5
        raw["plant"]["dead_zone"]["left_scale"] = [0.5, 2.0]

    def written(raw):
        raw["plant"]["disturbance"] = ["2.0*0.5*sin(2*t)", "0.5*0.5*sin(2*t)"]
        raw["plant"]["dead_zone"]["right"] = "1.5*1.1*(u - b_r)"
        raw["plant"]["dead_zone"]["left"] = "0.9*(u - b_l)"

    a, b = _cl(_variant(paper, scaled)), _cl(_variant(paper, written))
    tau = np.array([[3.0, 0.2], [-4.0, 2.5]])
    for k in range(2):
        x = a.x0.copy()
        oa = a.evaluate_outputs([0.7], x[None, :])
        ob = b.evaluate_outputs([0.7], x[None, :])
        assert np.allclose(oa["disturbance"], ob["disturbance"], rtol=1e-14)
    # the dead zone alone, on given torques: right branch x1.5 on both joints, left x0.5 / x2
    import casadi as ca

    from symfunnel.plant.equations import plant_acceleration
    sc = _variant(paper, scaled)
    u = ca.SX.sym("u", 2)
    parts = plant_acceleration(sc, sc.model.q, sc.model.dq, ca.SX.sym("t"), u, 0.0)
    D = ca.Function("D", [u], [parts["tau_applied"]])
    for col in tau:
        got = np.asarray(D(col)).ravel()
        want = [1.5 * 1.1 * (v - 1.0) if v >= 1.0 else (s * 0.9 * (v + 1.5) if v <= -1.5 else 0.0)
                for v, s in zip(col, (0.5, 2.0))]
        assert np.allclose(got, want, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("key,value", [("left_scale", 0.0), ("right_scale", -1.0)])
def test_bad_branch_scale_is_rejected(paper, key, value):
    from symfunnel.core.errors import InputError
    with pytest.raises(InputError, match=f"plant.dead_zone.{key}"):
        _variant(paper, lambda r: r["plant"]["dead_zone"].update({key: value}))
    with pytest.raises(InputError, match="plant.disturbance_scale"):
        _variant(paper, lambda r: r["plant"].update(disturbance_scale=-0.5))


def _cl(sc):
    from symfunnel.simulation.closedloop import build_closed_loop
    return build_closed_loop(sc, derive(sc))


def _sd(sc):
    return sc, derive(sc)

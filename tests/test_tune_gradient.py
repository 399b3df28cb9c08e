"""tune's gradient path (IPOPT with CVODES sensitivities) and the report's original/tuned comparison, checked against
finite differences and independent simulations of both scenarios."""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.scenario import load_scenario
from symfunnel.core.toml_write import dumps


def paper_doc(t_final: float, tune: dict) -> dict:
    """The paper scenario without [implementation] (the continuous-time loop), short horizon, with a [tune] table."""
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = t_final
    raw.pop("implementation", None)
    raw["tune"] = tune
    return raw


def write(tmp_path, raw: dict, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(dumps(raw), encoding="utf-8")
    return p


def problem(tmp_path, t_final=0.5, grid=50, tune=None, tolerance=(1e-10, 1e-10), **kw):
    from symfunnel.synthesis.gradient import GradientProblem
    from symfunnel.synthesis.candidates import variables
    sc = load_scenario(write(tmp_path, paper_doc(t_final, tune or {"tau_max": 200.0})))
    vs = variables(sc, sc.tune)
    gp = GradientProblem(sc, sc.tune, vs, t_final=t_final, tau_max=sc.tune.tau_max, grid_points=grid,
                         tolerance=tolerance, **kw)
    return sc, vs, gp


def test_constraint_gradient_matches_central_differences(tmp_path):
    _, vs, gp = problem(tmp_path, tune={"tau_max": 200.0,
                                        "parameters": ["controller.k2", "funnel.e2.phi_inf", "adaptation.gamma"]})
    z0 = np.array([v.z_of(v.user_x()) for v in vs])
    J = np.asarray(gp.jacobian()(z0))
    assert J.shape == (gp.ng, 3) and np.all(np.isfinite(J))
    # the differences are taken on the same problem integrated at 1e-12: at the sensitivities' 1e-10 the constraints
    # carry ~4e-8 of CVODES' step-selection noise, which a central difference divides by h (about 1e-4 of the
    # derivative at h = 1e-4, and it moves with the integrator's state order); at 1e-12 J agrees to ~2e-6
    _, _, ref = problem(tmp_path, tune={"tau_max": 200.0,
                                        "parameters": ["controller.k2", "funnel.e2.phi_inf", "adaptation.gamma"]},
                        tolerance=(1e-12, 1e-12))
    h = 1e-4
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd = (np.asarray(ref.g(z0 + e)).ravel() - np.asarray(ref.g(z0 - e)).ravel()) / (2 * h)
        scale = np.max(np.abs(fd))
        assert scale > 1e-3                                    # the parameter does move the constraints
        assert np.max(np.abs(J[:, i] - fd)) <= 1e-4 * scale, i


def test_compiled_sensitivities_equal_the_vm_ones(tmp_path):
    """The gradient path's DAE, Newton Jacobian and forward derivative run as generated C
    (`simulation.compiled.compiled_dae`); constraints and Jacobian equal the same problem's on CasADi's VM (the SX
    DAE, exact Newton Jacobian) to the integration tolerance."""
    _, vs, gp = problem(tmp_path, coarse=None)
    _, _, vm = problem(tmp_path, coarse=None, compiled=False)
    assert gp.code == "compiled" and vm.code == "vm"
    z0 = np.array([v.z_of(v.user_x()) for v in vs])
    g1, g2 = np.asarray(gp.g(z0)), np.asarray(vm.g(z0))
    assert np.max(np.abs(g1 - g2)) <= 1e-7
    J1, J2 = np.asarray(gp.jacobian()(z0)), np.asarray(vm.jacobian()(z0))
    assert np.max(np.abs(J1 - J2)) <= 1e-6 * np.max(np.abs(J2))


def test_the_coarse_pass_runs_first_on_a_quarter_of_the_horizon(tmp_path):
    """solve() runs IPOPT over the first quarter of the horizon (a quarter of the grid) first and continues from
    its result over the whole horizon; both passes are reported."""
    sc, vs, gp = problem(tmp_path, t_final=0.5, grid=40)
    assert gp.coarse is not None and gp.coarse.coarse is None
    assert gp.coarse.T == pytest.approx(0.125) and gp.coarse.K == 10
    z0 = np.array([v.z_of(v.user_x()) for v in vs])
    lines = []
    r = gp.solve(z0, objective="peak_torque", ref=500.0, wall_s=120.0, max_iter=3, progress=lines.append)
    assert r["coarse"] is not None and r["coarse"]["iterations"] >= 1
    assert any("coarse pass" in s for s in lines) and np.all((0 <= r["z"]) & (r["z"] <= 1))
    assert problem(tmp_path, t_final=0.5, grid=40, coarse=None)[2].coarse is None


@pytest.mark.parametrize("path", ["now", "previous"])
def test_the_polish_after_a_feasible_coarse_result_is_short_and_never_worse(tmp_path, monkeypatch, path):
    """A coarse result that meets the whole horizon's constraints is only polished: at most the schedule's
    polish_iter IPOPT iterations (POLISH_ITER = 0 now: none, the coarse result is the answer; 15 on the previous
    schedule), warm-started, and the result's peak is never above the coarse result's on the whole horizon."""
    from symfunnel.synthesis.gradient import PREVIOUS, POLISH_ITER, GradientProblem
    monkeypatch.setenv("SYMFUNNEL_TUNE_PATH", "previous" if path == "previous" else "")
    polish_iter = PREVIOUS["polish_iter"] if path == "previous" else POLISH_ITER
    sc, vs, gp = problem(tmp_path, t_final=0.5, grid=40)
    z0 = np.array([v.z_of(v.user_x()) for v in vs])
    runs = []
    real = GradientProblem._solve

    def spy(self, z, **kw):
        r = real(self, z, **kw)
        runs.append({"T": self.T, "z0": np.array(z, float), "max_iter": kw["max_iter"], "warm": kw["warm"], **r})
        return r
    monkeypatch.setattr(GradientProblem, "_solve", spy)
    r = gp.solve(z0, objective="peak_torque", ref=500.0, wall_s=120.0, max_iter=20)
    coarse = runs[0]
    assert coarse["T"] == pytest.approx(0.125) and coarse["max_iter"] == 20 and not coarse["warm"]
    if polish_iter == 0:
        assert len(runs) == 1 and r["iterations"] == 0 and np.array_equal(r["z"], coarse["z"])
        assert np.min(np.asarray(gp.g(r["z"]))) >= 0                      # why it was not polished
        return
    polish = runs[1]
    assert polish["T"] == pytest.approx(0.5) and polish["warm"] and polish["max_iter"] == polish_iter
    assert np.min(np.asarray(gp.g(polish["z0"]))) >= 0                    # why it was only polished
    assert r["iterations"] <= polish_iter
    peak = lambda z: float(np.max(np.abs(np.asarray(gp.figures(z)[0]))))  # noqa: E731
    assert peak(r["z"]) <= peak(polish["z0"]) * 1.01


def test_symbolic_parameters_reproduce_an_independent_simulation(tmp_path):
    # the grid constraints at the user's values are the ordinary simulation's margins and torque at those times
    from symfunnel.pipeline import Run
    sc, vs, gp = problem(tmp_path, t_final=0.5, grid=50)
    z0 = np.array([v.z_of(v.user_x()) for v in vs])
    g = np.asarray(gp.g(z0)).ravel()
    tau, ise = gp.figures(z0)
    raw = copy.deepcopy(sc.raw)
    raw["simulation"].update(dt=0.01, rtol=1e-10, atol=1e-10)
    sim = Run(load_scenario(write(tmp_path, raw, "ind.toml"))).simulation
    assert sim.t.size == 51 and np.allclose(sim.t, gp.grid)
    n, K1 = sc.n, gp.K + 1
    m1 = g[:n * K1].reshape(K1, n) + 0.05                    # casadi vec: column-major (joint fastest)
    m2 = g[n * K1:2 * n * K1].reshape(K1, n) + 0.05
    assert np.allclose(m1, sim.signals["m1"], atol=1e-6) and np.allclose(m2, sim.signals["m2"], atol=1e-6)
    assert np.allclose(np.asarray(tau).T, sim.signals["tau"], rtol=1e-5, atol=1e-4)
    e1 = np.asarray(sim.signals["e1"]).reshape(K1, n)
    assert float(ise) == pytest.approx(float(np.trapezoid(np.sum(e1 ** 2, 1), sim.t)), rel=1e-5)
    assert np.allclose(g[2 * n * K1:3 * n * K1].reshape(K1, n), 1 - sim.signals["tau"] / 200.0, atol=1e-6)


@pytest.mark.slow
def test_gradient_path_tunes_the_continuous_loop_into_the_torque_limit(tmp_path, capsys):
    src = write(tmp_path, paper_doc(1.0, {"tau_max": 200.0, "parameters": ["controller.k2", "funnel.e2.phi_inf",
                                                                        "funnel.e2.phi0"]}))
    out = tmp_path / "tuned.toml"
    code = main(["tune", str(src), "--out", str(out), "--json", "--max-evals", "2", "-q", "--method", "gradient"])
    res = json.loads(capsys.readouterr().out)            # stdout is the JSON alone
    assert code == 0 and res["status"] == "ok", res
    assert res["method"].startswith("gradient: IPOPT") and "no [implementation]" in res["why"]
    assert res["gate"]["status"] == "pass"
    from symfunnel.pipeline import Run
    before = Run(load_scenario(src)).simulation           # the premise: the user's design needs 500 N m
    assert float(np.max(np.abs(before.signals["tau"]))) > 200.0
    after = Run(load_scenario(out)).simulation            # independent run of the written scenario
    peak = float(np.max(np.abs(after.signals["tau"])))
    assert after.ok and peak < 200.0
    assert min(float(np.min(after.signals["m1"])), float(np.min(after.signals["m2"]))) >= 0.05
    assert res["objective"]["after"] == pytest.approx(peak, rel=1e-9)


def test_without_ipopt_the_search_falls_back_and_says_why(tmp_path, monkeypatch):
    from symfunnel.synthesis import gradient as tune_gradient, search as tuning
    monkeypatch.setattr(tune_gradient, "ipopt_available", lambda: False)
    sc = load_scenario(write(tmp_path, paper_doc(0.5, {"tau_max": 200.0, "parameters": ["controller.k2"]})))
    r = tuning.tune(sc, max_evaluations=2, gate=False)
    assert r.method == tuning.METHOD and "has_nlpsol('ipopt')" in r.why
    assert set(r.constraints["values"]) == {"containment", "saturation"}


def test_saturation_constraint_of_the_continuous_loop_matches_an_independent_run(tmp_path):
    from symfunnel.pipeline import Run
    from symfunnel.synthesis.candidates import Evaluator, variables
    sc = load_scenario(write(tmp_path, paper_doc(0.5, {"tau_max": [300.0, 100.0]})))
    c = Evaluator(sc, sc.tune).evaluate(variables(sc, sc.tune), [v.user_x() for v in variables(sc, sc.tune)])
    tau = np.abs(Run(sc).simulation.signals["tau"])
    assert c.constraints["saturation"] == pytest.approx(1 - max(tau[:, 0].max() / 300, tau[:, 1].max() / 100))


@pytest.mark.parametrize("tune,implementation,key,words", [
    ({"tau_max": 200.0}, {"rate_hz": 1000.0}, "tune.tau_max", "implementation.tau_max"),
    ({"tau_max": "urdf"}, None, "tune.tau_max", "URDF"),
    ({"tau_max": -1.0}, None, "tune.tau_max", "> 0"),
])
def test_bad_tune_tau_max_exits_2(tmp_path, capsys, tune, implementation, key, words):
    raw = paper_doc(0.5, tune)
    if implementation:
        raw["implementation"] = implementation
    src = write(tmp_path, raw)
    assert main(["tune", str(src)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"'{key}'" in err and words in err


def test_original_document_undoes_tune_records(tmp_path):
    from symfunnel.synthesis.candidates import Candidate, Evaluator, apply, variables
    from symfunnel.synthesis.records import _record_deviations, original_document
    raw = paper_doc(0.5, {"parameters": ["controller.k1", "controller.k2", "adaptation.gamma"], "per_joint": True})
    raw["controller"]["k2"] = [10.0, 4.0]
    sc = load_scenario(write(tmp_path, raw))
    vs = variables(sc, sc.tune)
    xs = [0.3, 7.0, 2.5, 11.0, 0.7]                      # k1[1], k1[2] (per joint), k2[1], k2[2], gamma
    tuned = apply(sc.raw, vs, xs)
    changes = [{"key": v.name, "before": v.user_x(), "after": x} for v, x in zip(vs, xs)]
    _record_deviations(tuned, changes, sc.tune, Candidate(xs, {}, {"peak_torque": 1.0}), Evaluator(sc, sc.tune),
                       "ok")
    back = original_document(tuned, sc.n)
    assert back["controller"] == {"k1": [5.0, 5.0], "k2": [10.0, 4.0]} and back["adaptation"]["gamma"] == 10.0
    assert back["deviations"] == sc.raw["deviations"]
    assert original_document(sc.raw, sc.n) is None


@pytest.mark.slow
def test_report_compares_original_and_tuned_with_independent_numbers(tmp_path):
    from symfunnel.pipeline import Run
    from symfunnel.reporting import render_report
    orig = paper_doc(1.0, {"tau_max": 200.0})
    tuned = copy.deepcopy(orig)
    tuned["controller"]["k2"] = 4.0
    tuned["funnel"]["e2"]["phi0"] = 1.2
    why = "symfunnel tune (ok): a record as tune writes it"
    tuned["deviations"] = orig["deviations"] + [
        {"key": "controller.k2", "paper": "", "value": "10.0 -> 4.0", "reason": why},
        {"key": "funnel.e2.phi0", "paper": "", "value": "0.4 -> 1.2", "reason": why}]
    html = render_report(Run(load_scenario(write(tmp_path, tuned, "tuned.toml"))), codegen=False, mutants=False,
                         deployed=False)
    sec = re.search(r'<section id="tuning">(.*?)</section>', html, re.S)
    assert sec is not None and 'href="#tuning"' in html
    body = sec.group(1)
    rows = {m.group(1).strip(): (m.group(2), m.group(3)) for m in re.finditer(
        r"<tr><td>([^<]+)</td><td class=\"num\">([^<]*)</td><td class=\"num\">([^<]*)</td></tr>", body)}
    for label, raw in (("original", orig), ("tuned", tuned)):
        raw = copy.deepcopy(raw)
        raw.pop("deviations")
        sim = Run(load_scenario(write(tmp_path, raw, f"{label}.toml"))).simulation
        col = 0 if label == "original" else 1
        assert float(rows["peak |tau| [N m]"][col]) == pytest.approx(np.max(np.abs(sim.signals["tau"])), rel=1e-3)
        assert float(rows["min margin e1, whole run"][col]) == pytest.approx(np.min(sim.signals["m1"]), rel=1e-3)
        assert float(rows["min margin e2, whole run"][col]) == pytest.approx(np.min(sim.signals["m2"]), rel=1e-3)
    assert float(rows["peak |tau| [N m]"][0]) > 200 > float(rows["peak |tau| [N m]"][1])
    assert "<code>controller.k2</code>" in body and 'id="fig-tune-comparison"' in body and "<svg" in body
    import html5lib
    parser = html5lib.HTMLParser(strict=False)
    parser.parse(html)
    assert not [e for e in parser.errors if e[1] != "unexpected-end-tag-in-math"]
    # a scenario without tune records has no such section
    plain = render_report(Run(load_scenario(write(tmp_path, orig, "plain.toml"))), codegen=False, mutants=False,
                          deployed=False)
    assert 'id="tuning"' not in plain


@pytest.mark.slow
def test_arm7_is_tuned_within_its_urdf_effort_limits(tmp_path, capsys):
    import shutil
    import tomllib

    from symfunnel.model.urdf import effort_limits
    from symfunnel.pipeline import Run
    from symfunnel.scenario import DATA_DIR
    shutil.copy(DATA_DIR / "arm7.urdf", tmp_path / "arm7.urdf")
    raw = tomllib.loads((DATA_DIR / "arm7.toml").read_text())
    raw["simulation"]["t_final"] = 0.5                  # 261 states: a short horizon keeps the sensitivities cheap
    raw["tune"] = {"tau_max": "urdf", "parameters": ["controller.k2", "funnel.e2.phi_inf"]}
    src = write(tmp_path, raw, "arm7.toml")
    out = tmp_path / "tuned.toml"
    # --wall-limit bounds the whole command (IPOPT's 80 % and verify's gate on the 7-joint result)
    code = main(["tune", str(src), "--out", str(out), "--json", "--max-evals", "2", "--wall-limit", "240", "-q",
                 "--method", "gradient"])
    res = json.loads(capsys.readouterr().out)
    assert code == 0 and res["status"] == "ok" and res["method"].startswith("gradient: IPOPT")
    assert res["objective"]["after"] < res["objective"]["before"]      # IPOPT lowered the peak torque
    effort = np.array(effort_limits(tmp_path / "arm7.urdf"), float)
    assert effort.shape == (7,) and np.all(effort > 0)
    sim = Run(load_scenario(out)).simulation             # independent run of the written scenario
    peak = np.max(np.abs(sim.signals["tau"]), axis=0)
    assert sim.ok and np.all(peak < effort)
    assert min(float(np.min(sim.signals["m1"])), float(np.min(sim.signals["m2"]))) >= 0.05
    assert res["constraints"]["values"]["saturation"] == pytest.approx(1 - float(np.max(peak / effort)), rel=1e-9)


def test_report_comparison_has_the_minimum_rate_and_breach_probability(tmp_path):
    from symfunnel.pipeline import Run
    from symfunnel.design import derive
    from symfunnel.deployed.rate import min_rate
    from symfunnel.reporting.sections import tuning_section
    from symfunnel.scenario.uncertainty import scenario_edits
    orig = paper_doc(1.0, {"runs": 6})
    orig["implementation"] = {"rate_hz": 1000.0, "tau_max": 200.0}
    # an initial error of up to 0.06 rad: some runs breach, more of them with the original design
    orig["uncertainty"] = [{"key": "plant.mass_scale", "dist": "uniform", "low": 0.5, "high": 1.5},
                           {"key": "initial.q", "dist": "uniform", "low": -0.06, "high": 0.06}]
    tuned = copy.deepcopy(orig)
    tuned["controller"]["k2"] = 4.0
    tuned["funnel"]["e2"]["phi0"] = 1.2
    tuned["deviations"] = orig["deviations"] + [
        {"key": "controller.k2", "paper": "", "value": "10.0 -> 4.0", "reason": "symfunnel tune (ok): test"},
        {"key": "funnel.e2.phi0", "paper": "", "value": "0.4 -> 1.2", "reason": "symfunnel tune (ok): test"}]
    sec = tuning_section(Run(load_scenario(write(tmp_path, tuned, "tuned.toml"))), lambda s: None)
    rows = {k: (a, b) for k, a, b in sec["rows"]}
    counts = []
    for col, raw in enumerate((orig, tuned)):
        raw = copy.deepcopy(raw)
        raw.pop("deviations")
        sc = load_scenario(write(tmp_path, raw, f"side{col}.toml"))
        r = min_rate(sc, derive(sc), margin=0.05, rel_tol=0.1, start=1000.0)
        cell = rows["minimum sample rate [Hz]"][col]
        if r["min_rate_hz"] is None:                    # no rate holds within tau_max (the original design)
            assert cell == "\u2014" and col == 0
        else:
            assert float(cell) == pytest.approx(r["min_rate_hz"], rel=1e-3)
        breaches = 0                                    # the campaign's 4 runs, simulated one by one
        for v in sc.campaign.values(range(6), 6):
            d = copy.deepcopy(raw)
            for key, val in scenario_edits(sc.campaign, sc.n, v).items():
                *path, leaf = key.split(".")
                t = d
                for p in path:
                    t = t[p]
                t[leaf] = val
            breaches += Run(load_scenario(write(tmp_path, d, "run.toml"))).simulation.status != "ok"
        assert 0 < breaches < 6
        counts.append(breaches)
        assert rows["breach probability"][col].startswith(f"{breaches / 6:.4g} (95 % CI")
    assert rows["minimum sample rate [Hz]"][1] != "\u2014"      # the tuned design has one
    assert counts[0] > counts[1]


def test_when_ipopt_finds_nothing_that_holds_the_derivative_free_search_takes_over(tmp_path, monkeypatch):
    from symfunnel.synthesis import gradient as tune_gradient, search as tuning
    marker = tmp_path / "ipopt-called"                  # IPOPT runs in a killable child: a file, not a list

    def stuck(self, z0, **kw):                          # IPOPT "returns" its start: the user's infeasible design
        marker.write_text("called")
        return {"z": np.asarray(z0, float), "status": "Infeasible_Problem_Detected", "success": False,
                "iterations": 0, "f": float("nan")}
    monkeypatch.setattr(tune_gradient.GradientProblem, "solve", stuck)
    sc = load_scenario(write(tmp_path, paper_doc(0.5, {"tau_max": 200.0, "parameters": ["controller.k2"]})))
    r = tuning.tune(sc, max_evaluations=4, gate=False, method="gradient")
    assert marker.exists() and r.method == f"{tuning.GRADIENT_METHOD}; then {tuning.METHOD}"
    assert "fallback" in r.why and "no IPOPT result held" in r.why
    assert r.evaluations == 4                            # the derivative-free search ran on after IPOPT


def test_the_e2_funnel_must_narrow_in_the_nlp(tmp_path):
    """phi_inf above phi0 breaks verify's funnel.parameters (eq. 16): the NLP has a row 1 - phi_inf/phi0 >= 0 per
    joint, negative exactly there, computed from the tuned and the fixed values."""
    sc, vs, gp = problem(tmp_path, tune={"tau_max": 200.0, "parameters": ["controller.k2", "funnel.e2.phi_inf"]},
                         grid=10)
    i = [v.key for v in vs].index("funnel.e2.phi_inf")
    phi0 = np.asarray(sc.funnels["e2"].phi0, float)
    z = np.array([v.z_of(v.user_x()) for v in vs])
    rows = np.asarray(gp.g(z)).ravel()[-sc.n:]
    assert np.allclose(rows, 1 - np.asarray(sc.funnels["e2"].phi_inf) / phi0, rtol=1e-12)
    z[i] = vs[i].z_of(1.2 * float(np.max(phi0)))          # phi_inf above phi0 on every joint
    z_rows = np.asarray(gp.g(z)).ravel()[-sc.n:]
    assert np.all(z_rows < 0)
    assert np.allclose(z_rows, 1 - vs[i].x_of(z[i]) / phi0, rtol=1e-9)

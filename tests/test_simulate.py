"""Closed-loop simulation: paper run in its funnel, npz/JSON contract, breach, NaN, timeout, integrators, smoothing."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.scenario import from_dict, load_scenario
from symfunnel.design import derive
from symfunnel.simulation import convergence_study, simulate


def _sd(sc):
    return sc, derive(sc)

ROOT = Path(__file__).resolve().parents[1]
DERIV = ROOT / "derivations"
NPZ_KEYS = ["t", "q", "dq", "qd", "tau", "tau_applied", "e1", "F1", "e2", "F2", "z1", "z2", "x_esn", "w_hat", "V",
            "f_true", "w_phi"]
SUMMARY_KEYS = ["status", "message", "min_margin_e1", "min_margin_e2", "max_abs_tau", "rms_esn_error", "rms_f_true",
                "wall_time", "steps", "events", "integrator", "smoothing_width"]


@pytest.fixture(scope="module")
def sim(paper_run):
    """The paper's 20 s simulation (the session's one pipeline run)."""
    return paper_run.simulation


def _variant(sc, edit, name="variant"):
    raw = copy.deepcopy(sc.raw)
    edit(raw)
    raw["name"] = name
    return from_dict(raw, file=f"{name}.toml", base_dir=sc.path.parent, default_name=name)


def test_paper_stays_in_its_funnel_for_20s(sim, paper_run):
    r = sim
    assert r.status == "ok", r.message
    assert r.t[-1] == pytest.approx(20.0)
    assert np.all(np.abs(r.e1) < r.F1) and np.all(np.abs(r.e2) < r.F2)
    for k in ("q", "dq", "tau", "x_esn", "w_hat"):
        assert np.all(np.isfinite(r.signals[k])), k
    assert np.all(np.isfinite(paper_run.lyapunov.V))
    # Figures 6-8, qualitatively: tracking error small after the transient, torque bounded, ESN estimate useful
    late = r.t > 5
    assert np.max(np.abs(r.e1[late])) < 0.01
    s = r.summary()
    assert max(s["max_abs_tau"]) < 1e3
    assert all(e < f for e, f in zip(s["rms_esn_error"], s["rms_f_true"]))
    assert np.max(np.abs(r.x_esn)) <= 1.0 + 1e-9          # tanh reservoir stays in [-1/leak, 1/leak]
    # friction compensation: the applied torque carries the friction force while tracking
    corr = np.corrcoef(r.tau_applied[late, 0], r.friction[late, 0])[0, 1]
    assert corr > 0.5


def test_npz_and_summary_contract(paper_run, tmp_path):
    r = paper_run.simulation
    p = r.save_npz(tmp_path / "sub" / "run.npz", paper_run.trajectory_arrays())
    d = np.load(p)
    T = r.t.size
    for k in NPZ_KEYS:
        assert k in d.files, k
        assert d[k].shape[0] == T, k
    assert d["w_hat"].shape == (T, 51, 2) and d["x_esn"].shape == (T, 50)
    assert d["W_star"].shape == (51, 2)
    s = r.summary()
    for k in SUMMARY_KEYS:
        assert k in s, k
    json.dumps(s, allow_nan=False)
    # the smallest margin over the output points (recomputed here from e1 and F1) and the samples between them
    grid = np.min((r.F1 - np.abs(r.e1)) / r.F1, axis=0)
    between = np.array(r.between["min_margin_e1"], dtype=float)
    assert s["min_margin_e1"] == pytest.approx(list(np.fmin(grid, between)), rel=1e-12)
    assert r.between["points"] > r.t.size             # CVODES took more steps than there are output points


def test_integrators_agree_on_a_smooth_variant(paper):
    def edit(raw):
        raw["plant"]["coulomb"] = 0.0
        raw["plant"].pop("dead_zone")
        raw["esn"]["size"] = 5
        raw["simulation"]["rk_substeps"] = 20
    sc = _variant(paper, edit, "smooth")
    runs = {m: simulate(sc, derive(sc), t_final=1.0, integrator=m) for m in ("cvodes", "rk", "collocation")}
    for m, r in runs.items():
        assert r.status == "ok", (m, r.message)
        assert r.t.shape == runs["cvodes"].t.shape
    q = runs["cvodes"].q
    for m in ("rk", "collocation"):
        assert np.max(np.abs(runs[m].q - q)) < 1e-5, m


def test_breach_is_reported_with_the_trajectory_so_far(tmp_path):
    sc = load_scenario(DERIV / "sim_breach.toml")
    r = simulate(sc, derive(sc))
    assert r.status == "breach", r.message
    b = r.breach
    assert b["funnel"] in ("e1", "e2") and b["joint"] in (1, 2) and b["margin"] <= 0.05
    assert 0 < b["time"] < sc.simulation.t_final
    assert r.t[-1] <= b["time"] + 1e-12 and r.t[-1] >= b["time"] - sc.simulation.dt
    assert np.all(np.isfinite(r.x))
    assert f"t = {b['time']:.6g}" in r.message and f"joint {b['joint']}" in r.message
    out = tmp_path / "breach.npz"
    assert main(["simulate", str(DERIV / "sim_breach.toml"), "-q", "--out", str(out)]) == 1
    assert np.load(out)["t"][-1] == pytest.approx(r.t[-1])


def test_initial_error_outside_is_a_failed_check(paper, capsys):
    sc = _variant(paper, lambda raw: raw["initial"].update(q=[0.5, 0.0]), "outside")
    r = simulate(sc, derive(sc))
    assert r.status == "initial_outside"
    assert "funnel e1" in r.message and "joint 1" in r.message
    assert r.t.size == 1


def test_nan_never_passes_silently(paper):
    sc = _variant(paper, lambda raw: raw["plant"].update(disturbance="sqrt(0.5 - t)"), "nan")
    r = simulate(sc, derive(sc), t_final=1.0)
    assert r.status in ("failed", "breach")
    assert r.t[-1] <= 0.51
    assert np.all(np.isfinite(r.x))


def test_wall_clock_limit(paper):
    r = simulate(paper, derive(paper), wall_limit=1e-6)
    assert r.status == "timeout"
    assert "wall-clock limit" in r.message


def test_cli_exit_codes(tmp_path, capsys):
    out = tmp_path / "p.npz"
    assert main(["simulate", "-q", "--t-final", "1", "--json", "--out", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["status"] == "ok" and out.exists()
    assert main(["simulate", "-q", "--t-final", "0"]) == 2
    assert main(["simulate", "-q", "--t-final", "-3"]) == 2
    assert main(["simulate", str(tmp_path / "missing.toml"), "-q"]) == 2
    assert main(["simulate", "-q", "--t-final", "2", "--wall-limit", "1e-6"]) == 1
    assert "wall-clock limit" in capsys.readouterr().err


def test_smoothing_convergence(paper):
    c = convergence_study(paper, derive(paper), [1e-1, 1e-2], t_final=2.0)
    widths = [r["width"] for r in c["runs"]]
    diffs = [r["max_abs_q_diff_vs_smallest"] for r in c["runs"]]
    assert widths == [1e-1, 1e-2, 1e-3] and c["reference_width"] == pytest.approx(1e-4)   # never itself
    assert diffs[0] > diffs[1] > diffs[2] > 0
    expected = [np.log(diffs[i] / diffs[i + 1]) / np.log(widths[i] / widths[i + 1]) for i in range(2)]
    np.testing.assert_allclose(c["observed_rates"], expected, rtol=1e-12)
    assert all(rate > 0.3 for rate in c["observed_rates"])


@pytest.mark.parametrize("name", ["sim_fast_sine", "sim_offset_cosine"])
def test_untuned_scenarios_stay_inside(name):
    r = simulate(*_sd(load_scenario(DERIV / f"{name}.toml")))
    assert r.status == "ok", r.message
    assert min(r.summary()["min_margin_e1"]) > 0.5


def test_buffered_evaluation_matches_the_plain_call_with_per_call_statistics():
    """The simulation's numpy-buffer path gives the plain call's values and statistics, call after call (CasADi's
    n_call_* counters add up in a buffer's memory, a plain call restarts them)."""
    import casadi as ca

    from symfunnel.simulation.compiled import Buffered
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    ode = ca.vertcat(x[1], -p * x[0] - 0.1 * x[1] ** 3)
    F = ca.integrator("F", "cvodes", {"x": x, "p": p, "ode": ode}, 0.0, [0.5, 1.0, 1.5])
    assert Buffered.supports(F)
    B = Buffered(F, stats=True)
    for x0 in ([1.0, 0.0], [0.3, -2.0], [1.0, 0.0]):
        ref = np.asarray(F(x0=x0, p=4.0)["xf"])
        st = F.stats()
        B.args[F.index_in("x0")][:] = x0
        B.args[F.index_in("p")][:] = 4.0
        assert B.evaluate() == 0
        assert np.array_equal(B.res[F.index_out("xf")], ref.T.reshape(-1))      # column-major: point by point
        for k in ("nsteps", "nfevals", "n_call_jacF", "n_call_daeF"):
            assert B.stats[k] == st[k], k
    assert B.stats["n_call_daeF"] > 0
    f = ca.Function("g", [x, p], [x * p, ca.sumsqr(x)])
    m = f.map("gm", "serial", 4, [1], [])
    X = np.arange(8.0).reshape(4, 2)                                            # 4 points of x
    Bm = Buffered(m)
    Bm(X.T, 3.0)
    assert np.array_equal(Bm.res[0].reshape(4, 2), 3.0 * X)
    assert np.array_equal(Bm.res[1], np.sum(X ** 2, axis=1))


def test_max_step_caps_cvodes_steps_and_keeps_the_trajectory(paper):
    """simulation.max_step reaches CVODES: 0.5 s cannot take fewer than 0.5/max_step steps; q stays the same to
    the tolerance's order; a negative value is refused naming the key."""
    from symfunnel.core.errors import InputError
    free = simulate(paper, derive(paper), t_final=0.5)
    capped_sc = _variant(paper, lambda raw: raw["simulation"].update(max_step=5e-4), "capped")
    assert capped_sc.simulation.max_step == 5e-4 and paper.simulation.max_step == 0.0
    capped = simulate(capped_sc, derive(capped_sc), t_final=0.5)
    assert free.status == capped.status == "ok"
    assert capped.stats["steps"] >= 0.5 / 5e-4 > free.stats["steps"]
    assert np.max(np.abs(capped.q - free.q)) < 1e-5
    with pytest.raises(InputError) as exc:
        _variant(paper, lambda raw: raw["simulation"].update(max_step=-1.0), "bad")
    assert exc.value.key == "simulation.max_step"

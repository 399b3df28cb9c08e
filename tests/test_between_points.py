"""Containment and peaks between output points (issue 21, row 16): the samples between output points are the same
trajectory (bit for bit at the output points), they find what the output grid misses -- a torque peak of a funnel
that dips between output points, a margin minimum of arm7 -- as a 20x finer grid or RK4 at 1e-5 s does; the sampled
loop sees the plant leave a funnel between samples; degenerate horizons are refused."""

from __future__ import annotations

import dataclasses
import re

import casadi as ca
import numpy as np
import pytest

from symfunnel.checks.verify import check_bounded, check_containment
from symfunnel.cli import main
from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.simulation.between import BETWEEN_MAX, density
from symfunnel.simulation.closedloop import build_closed_loop
from symfunnel.simulation.compiled import compile_closed_loop
from symfunnel.simulation.run import simulate
from symfunnel.simulation.runner import Runner

from .conftest import PAPER, REPO

#: a funnel e1 that dips by a third for about a millisecond around t = 0.5025, between output points 0.50 and 0.51
DIP_F1 = "0.18*exp(-2*t) + 0.01 - 0.06*exp(-((t - 0.5025)/0.0005)^2)"


def _paper_variant(tmp_path, name: str, edits: dict[str, str], extra: str = "") -> object:
    text = PAPER.read_text()
    for old, new in edits.items():
        text, k = re.subn(old, new, text)
        assert k == 1, old
    p = tmp_path / f"{name}.toml"
    p.write_text(text + extra)
    return load_scenario(p)


def _dip(tmp_path, F1: str = DIP_F1, extra: str = ""):
    """The paper with funnel e1 = F1 and the initial state on the reference (e1(0) = e2(0) = 0: no start-up peak)."""
    return _paper_variant(tmp_path, "dip", {r"\[funnel\.e1\]\nphi0 = 0\.18\nphi_inf = 0\.01\na = 2\.0":
                                            f'[funnel.e1]\nF = "{F1}"',
                                            r"\[initial\]\nq = \[0\.0, 0\.0\]\ndq = \[0\.0, 0\.0\]":
                                            "[initial]\nq = [0.0, 0.0]\ndq = [0.3, 0.3]"}, extra)


def test_density_is_the_integrators_own_as_a_power_of_two():
    assert density(320, 25) == 16 and density(25, 25) == 1 and density(3, 25) == 1 and density(26, 25) == 2
    assert density(10 ** 6, 1) == BETWEEN_MAX


def _urdf_robot(tmp_path):
    s = tmp_path / "robot.toml"
    assert main(["init", "--urdf", str(REPO / "tests" / "data" / "branched.urdf"), "--out", str(s), "-q"]) == 0
    return load_scenario(s)


def _compiled_loop(sc):
    """The scenario's design, closed loop and compiled loop bound to its plant parameters."""
    d = derive(sc)
    cl = build_closed_loop(sc, d, width=sc.simulation.smoothing_width)
    return d, cl, compile_closed_loop(cl).bind(cl.p0)


@pytest.mark.parametrize("which", ["paper", "arm7", "urdf"])
def test_the_dense_grid_is_the_plain_grid_bit_for_bit_and_samples_the_same_trajectory(which, tmp_path):
    """CVODES takes the same steps with extra output points (no stop time at output points, the same first step):
    the output points are identical, and the samples between them agree with an integration at rtol 1e-11."""
    sc = _urdf_robot(tmp_path) if which == "urdf" else load_scenario(which)
    d, cl, comp = _compiled_loop(sc)
    h = sc.simulation.dt
    plain = Runner(cl, comp, "cvodes", h, sc.simulation)
    X = plain.run(0.0, cl.x0.copy(), 25)
    for sub in (4, 16):
        dense = Runner(cl, comp, "cvodes", h, sc.simulation)
        Xd, tb, Xb = dense.run_dense(0.0, cl.x0.copy(), 25, sub)
        assert np.array_equal(X, Xd), (which, sub)
        assert dense.stats["steps"] == plain.stats["steps"]
        assert tb.size == 25 * sub - 25 and np.all(np.diff(tb) > 0)
    tight = dataclasses.replace(sc.simulation, rtol=1e-11, atol=1e-13)
    ref = Runner(cl, comp, "cvodes", h / 16, tight).run(0.0, cl.x0.copy(), 25 * 16)
    t_ref = (h / 16) * np.arange(1, 25 * 16 + 1)
    k = np.searchsorted(t_ref, tb - 1e-12)
    assert np.allclose(t_ref[k], tb, rtol=0, atol=1e-12)
    q = cl.slices["q"]
    scale = np.max(np.abs(ref[:, q])) + 1e-3
    assert np.max(np.abs(Xb[:, q] - ref[k][:, q])) < 1e-4 * scale       # the integrator's tolerance, not the grid's


def test_a_funnel_dip_between_output_points_shows_its_torque_peak(tmp_path):
    """The issue's example: the output grid (dt = 0.01) sees 27 N m, the peak is ~199 N m at t = 0.50242 -- found
    here by the samples between points, checked against RK4 at fixed steps of 1e-5 s from the run's state at 0.5."""
    from symfunnel.simulation.compiled import evaluate_outputs
    sc = _dip(tmp_path)
    d = derive(sc)
    r = simulate(sc, d, t_final=0.6)
    assert r.ok, r.message
    grid_peak = np.max(np.abs(r.signals["tau"]), axis=0)
    peak = np.array(r.summary()["max_abs_tau"])
    cl = build_closed_loop(sc, d, width=sc.simulation.smoothing_width)
    comp = compile_closed_loop(cl).bind(cl.p0)
    i = int(np.argmin(np.abs(r.t - 0.5)))
    rk4 = Runner(cl, comp, "rk", 1e-5, dataclasses.replace(sc.simulation, rk_substeps=1))
    X = rk4.run(float(r.t[i]), r.x[i], 1000)
    t = r.t[i] + 1e-5 * np.arange(1, 1001)
    tau = np.abs(evaluate_outputs(comp, cl.n, t, X)["tau"])
    rk_peak, t_rk = tau.max(axis=0), t[np.argmax(tau, axis=0)]
    assert np.all(grid_peak < 0.2 * rk_peak)                              # the output points miss it
    assert peak == pytest.approx(rk_peak, rel=0.01)
    assert np.allclose(r.between["t_max_abs_tau"], t_rk, atol=2e-5)
    c = check_bounded(r, d, None)[0]
    assert c.id == "bounded.tau" and c.evidence["max_abs"] == pytest.approx(float(np.max(rk_peak)), rel=0.01)
    assert abs(c.where["t"] - t_rk[np.argmax(rk_peak)]) < 2e-5


@pytest.mark.slow
def test_arm7s_smallest_margin_lies_between_output_points_as_a_finer_grid_confirms():
    """arm7, joint 7: the e2 margin is 0.145 at the output points (dt = 0.01) but 0.131 between them at t = 1.698;
    a run on a 20x finer grid gives 0.131 on its own output points. verify's containment check takes the smaller."""
    sc = load_scenario("arm7")
    d = derive(sc)
    r = simulate(sc, d, t_final=2.0)
    fine = dataclasses.replace(sc, simulation=dataclasses.replace(sc.simulation, dt=0.0005))
    rf = simulate(fine, d, t_final=2.0)
    grid = r.signals["m2"].min(axis=0)
    truth = rf.signals["m2"].min(axis=0)
    seen = np.array(r.summary()["min_margin_e2"])
    assert np.max(np.abs(seen - truth)) < 1e-3 < np.max(np.abs(grid - truth))
    assert grid[6] - truth[6] > 0.01
    c = {x.id: x for x in check_containment(r, d.n)}["funnel.containment.e2.joint7"]
    assert c.status == "pass" and c.margin == pytest.approx(seen[6]) and "between output points" in c.detail
    assert abs(c.where["t"] - rf.t[np.argmin(rf.signals["m2"][:, 6])]) < 2e-3


def test_the_sampled_loop_sees_the_plant_leave_a_funnel_between_samples(tmp_path):
    """A dip of e1's funnel for ~0.1 ms between the samples at 0.500 and 0.501 s (1 kHz) makes alpha2 spike, so the
    plant's e2 leaves its funnel between samples while both samples are inside: a breach there."""
    from symfunnel.checks.implementation import implementation_checks
    from symfunnel.deployed.loop import simulate_sampled
    dip = "0.18*exp(-2*t) + 0.01 - (0.18*exp(-2*t) + 0.01 - 1e-6)*exp(-((t - 0.5005)/0.00005)^2)"
    sc = _dip(tmp_path, dip, "\n[implementation]\nrate_hz = 1000.0\n")
    d = derive(sc)
    r = simulate_sampled(sc, d, t_final=1.0)
    assert r.status == "breach", r.message
    b = r.breach
    assert b["between_samples"] == [pytest.approx(0.5), pytest.approx(0.501)] and 0.5 < b["time"] < 0.501
    assert np.all(r.margins[np.isclose(r.t, 0.5) | np.isclose(r.t, 0.501)] > 0)   # both samples are inside
    assert r.min_margin < 0
    (c,) = implementation_checks(sc, d, result=r)
    assert c.id == "implementation.containment" and c.status == "fail" and "between the samples" in c.detail
    # the margins between samples are the plant's RK4 steps, here against CasADi's integrator on the VM
    rs, smooth, ds = r, sc, d
    assert rs.between_margins.shape == (rs.tau.shape[0], 4)
    from symfunnel.deployed.loop import plant_substeps
    from symfunnel.simulation.between import margin_function
    from symfunnel.plant.equations import plant_acceleration
    subs = plant_substeps(smooth, 1e-3)
    n = smooth.n
    q, dq, s_, th, u = (ca.SX.sym(k, m) for k, m in (("q", n), ("dq", n), ("s", 1), ("th", 2), ("u", n)))
    ddq = plant_acceleration(smooth, q, dq, th[0] + th[1] * s_, u, smooth.simulation.smoothing_width)["ddq"]
    F = ca.integrator("p", "rk", {"x": ca.vertcat(q, dq), "p": ca.vertcat(th, u), "t": s_,
                                  "ode": th[1] * ca.vertcat(dq, ddq)}, 0.0, [(j + 1) / subs for j in range(subs)],
                      {"number_of_finite_elements": subs})
    mf = margin_function(ds)
    for k in (0, 17, 150, 499, rs.tau.shape[0] - 1):
        x0 = np.concatenate([rs.q[k], rs.dq[k]])
        xs = np.array(F(x0=x0, p=np.concatenate([[rs.t[k], 1e-3], rs.tau[k]]))["xf"])
        m = np.array(mf.map(subs)(rs.t[k] + 1e-3 * np.arange(1, subs + 1)[None, :] / subs, xs[:n], xs[n:]))
        assert np.allclose(rs.between_margins[k], m.min(axis=1), rtol=0, atol=1e-9)
    assert rs.min_margin == pytest.approx(min(np.nanmin(rs.margins), np.nanmin(rs.between_margins)))


@pytest.mark.parametrize("argv, key", [
    (["verify", "paper", "--t-final", "1e-300"], "--t-final"),
    (["simulate", "paper", "--t-final", "0.05"], "--t-final"),
    (["simulate", "paper", "--rate", "1000", "--t-final", "0.005"], "--t-final"),
])
def test_degenerate_horizons_are_refused_naming_the_key(argv, key, capsys):
    assert main(argv + ["-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0] and "at least 10" in err[0], err


@pytest.mark.parametrize("table, key", [("[simulation]\nt_final = 0.05\n", "simulation.t_final"),
                                        ("[simulation]\nt_final = 1e-300\n", "simulation.t_final")])
def test_a_scenario_with_a_degenerate_horizon_is_refused_at_load(table, key, write_scenario, capsys):
    from .conftest import MINIMAL_2LINK
    p = write_scenario(MINIMAL_2LINK.format(C="") + table)
    assert main(["simulate", str(p), "-q"]) == 2
    err = capsys.readouterr().err
    assert key in err and str(p) in err and "at least 10" in err


def test_a_sweep_horizon_of_a_few_output_steps_is_refused(write_scenario, capsys):
    from .conftest import MINIMAL_2LINK
    p = write_scenario(MINIMAL_2LINK.format(C="") + '[[uncertainty]]\nkey = "plant.mass_scale"\ndist = "uniform"\n'
                       'low = 0.9\nhigh = 1.1\n[sweep]\nruns = 2\nt_final = 0.03\n')
    assert main(["sweep", str(p), "--out", str(p.parent / "out"), "-q"]) == 2
    assert "sweep.t_final" in capsys.readouterr().err
    assert not (p.parent / "out").exists()


def test_ten_output_steps_are_enough():
    r = simulate(load_scenario("paper"), derive(load_scenario("paper")), t_final=0.1)
    assert r.ok and r.t.size == 11


@pytest.mark.parametrize("count", [1, 15, 16, 17, 768, 4096, 5000])
def test_margin_scan_blocks_give_the_pointwise_margins(paper_run, count):
    """The scan's evaluation -- all points in one call into the library, or CasADi's map in blocks of 4096, 1024,
    256, 64 and 16 points -- gives, bit for bit, its margin function called at each point alone, whatever the count
    (a tail shorter than the smallest block included): the loop's compiled one with the run's parameters, and the
    design's where the loop has none; the two agree to rounding (one from the closed loop's graph, the other from
    the design's signals)."""
    import dataclasses
    from symfunnel.simulation.between import MarginScan, margin_function
    from symfunnel.simulation.compiled import compile_closed_loop
    cl = paper_run.closed_loop
    comp = compile_closed_loop(cl).bind(cl.p0)
    assert comp.mode == "compiled" and comp.margins is not None and comp.margins.class_name() == "External"
    n = cl.n
    rng = np.random.default_rng(count)
    t = rng.uniform(0, 20, count)
    q, dq = rng.normal(0, 0.1, (count, n)), rng.normal(0, 0.3, (count, n))
    got = MarginScan(comp, cl.slices).margins(t, q, dq)
    want = np.array([np.asarray(comp.margins(t[i], q[i], dq[i], comp.pvals)).ravel() for i in range(count)])
    assert got.shape == (count, 2 * n) and np.array_equal(got, want)
    f = margin_function(paper_run.design)
    design = np.array([np.asarray(f(t[i], q[i], dq[i])).ravel() for i in range(count)])
    assert np.allclose(got, design, rtol=1e-13, atol=1e-13)
    vm = MarginScan(dataclasses.replace(comp, margins=None, margins_many=None), cl.slices,
                    paper_run.design).margins(t, q, dq)
    assert np.array_equal(vm, design)
    blocks = MarginScan(dataclasses.replace(comp, margins_many=None), cl.slices).margins(t, q, dq)
    assert np.array_equal(blocks, got)                 # CasADi's map of the library's function, block by block
    with pytest.raises(ValueError, match="not bound"):
        MarginScan(compile_closed_loop(cl), cl.slices)    # the margins need the run's [plant p; z]


@pytest.mark.parametrize("which", ["paper", "arm7", "urdf"])
def test_the_logged_signals_in_one_call_are_casadis_map_bit_for_bit(which, tmp_path):
    """evaluate_outputs calls the library's symfunnel_outputs_many once per chunk (compiled.Many): the signals are,
    bit for bit and in the same column-major layout, what CasADi's serial map of the same function gives, at any
    number of points; a wrong input size is refused before C reads past it."""
    import dataclasses
    from symfunnel.simulation.closedloop import OUTPUT_NAMES
    from symfunnel.simulation.compiled import evaluate_outputs
    sc = _urdf_robot(tmp_path) if which == "urdf" else load_scenario(which)
    d, cl, comp = _compiled_loop(sc)
    assert comp.outputs_many is not None
    via_map = dataclasses.replace(comp, outputs_many=None, maps={})
    rng = np.random.default_rng(3)
    for T in (1, 17, 500):
        t = rng.uniform(0, 5, T)
        X = cl.x0 + 0.05 * rng.standard_normal((T, cl.nx))
        a, b = evaluate_outputs(comp, cl.n, t, X), evaluate_outputs(via_map, cl.n, t, X)
        assert list(a) == list(OUTPUT_NAMES)
        for k in OUTPUT_NAMES:
            assert a[k].shape == b[k].shape and a[k].flags.f_contiguous == b[k].flags.f_contiguous
            assert np.array_equal(a[k], b[k], equal_nan=True), k
    with pytest.raises(ValueError, match="input 1"):
        comp.outputs_many(3, np.zeros(3), np.zeros((2, cl.nx)), comp.pvals)


def test_a_function_with_a_sparse_output_is_not_evaluated_in_one_call():
    """Many writes nnz values per point: a sparse output (whose signal CasADi's map densifies) is refused."""
    import casadi as ca
    from symfunnel.simulation.compiled import Many
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.vertcat(x[0], ca.SX(1, 1))])
    assert not f.sparsity_out(0).is_dense()
    with pytest.raises(ValueError, match="dense"):
        Many("no-such-library.so", f)


@pytest.mark.parametrize("which", ["paper", "arm7", "urdf"])
def test_a_chunk_sampled_again_counts_its_steps_once(which, tmp_path):
    """A chunk that took more steps than it was sampled for is integrated again, denser, over the same steps: the
    run's step count is the steps of its chunks once each (it counted the chunk twice: 8,651 steps for the paper's
    6,000 on the VM where it was found). Replayed here on the plain grid, chunk by chunk from the run's own chunk
    states, with the run's chunk sizes."""
    from symfunnel.simulation.run import CHUNK_SIZES, _grid
    sc = _urdf_robot(tmp_path) if which == "urdf" else load_scenario(which)
    tf = {"paper": sc.simulation.t_final, "arm7": 2.0, "urdf": 2.0}[which]
    d, cl, comp = _compiled_loop(sc)
    r = simulate(sc, d, t_final=tf, closed_loop=cl)
    assert r.ok, r.message
    M, h = _grid(tf, sc.simulation.dt)
    plain = Runner(cl, comp, "cvodes", h, sc.simulation)
    k, K, x = 0, 25, cl.x0.copy()
    while k < M:
        Kc = min(K, M - k)
        X = plain.run(k * h, x, Kc)
        np.testing.assert_array_equal(X[-1], r.x[k + Kc])       # the run's chunk ends, bit for bit
        k, x = k + Kc, X[-1]
        K = CHUNK_SIZES[min(CHUNK_SIZES.index(K) + 1, len(CHUNK_SIZES) - 1)]
    assert r.stats["steps"] == plain.stats["steps"]
    assert r.stats["jacobian_evaluations"] == plain.stats["jacobian_evaluations"]


@pytest.mark.parametrize("from_steps", [False, True])
def test_a_chunk_denser_than_it_was_sampled_for_is_counted_once_and_sampled_at_its_own_density(from_steps, paper,
                                                                                                monkeypatch):
    """The case the run meets whenever a chunk steps more densely than the one before, made certain: the paper's
    first 25 output points (~13 steps per point) asked for at 1 sample per output step. Integrated again (False) or
    sampled from the kept steps (True), the chunk is sampled at its own density, its steps counted once (the plain
    run's), with the output points of the plain run."""
    from symfunnel.simulation import runner as runner_mod
    monkeypatch.setattr(runner_mod, "SAMPLE_FROM_STEPS", from_steps)
    _, cl, comp = _compiled_loop(paper)
    h = paper.simulation.dt
    plain = Runner(cl, comp, "cvodes", h, paper.simulation)
    X = plain.run(0.0, cl.x0.copy(), 25)
    need = density(plain.stats["steps"], 25)
    assert need >= 4                                  # denser than the 1 sample per output step asked for
    dense = Runner(cl, comp, "cvodes", h, paper.simulation)
    Xd, tb, Xb = dense.run_dense(0.0, cl.x0.copy(), 25, 1, adapt=True)
    assert dense.last_density == need and tb.size == 25 * need - 25
    assert np.array_equal(Xd, X)
    for k in ("steps", "rhs_evaluations", "jacobian_evaluations"):
        assert dense.stats[k] == plain.stats[k], k


@pytest.mark.parametrize("K,h,sub", [(1, 0.01, 4), (2, 0.01, 2), (25, 0.01, 64), (500, 0.04, 4), (375, 1 / 3, 8),
                                     (7, 0.001, 1)])
def test_the_dense_grid_is_the_same_doubles_as_written_out_point_by_point(K, h, sub):
    """The vectorised grid is the scalar expressions h (k + 1) and h (k + 1) + j (h / sub), point for point and in
    order, bit for bit (the dense grid's output points must be the plain grid's doubles)."""
    ref = []
    for k in range(K):
        ref.append(h * (k + 1))
        if sub > 1 and k + 1 < K:
            ref += [h * (k + 1) + j * (h / sub) for j in range(1, sub)]
    got = Runner.grid(K, h, sub)
    assert got.dtype == np.float64 and got.tolist() == ref
    inner = [h * (k + 1) + j * (h / sub) for k in range(K - 1) for j in range(1, sub)] if sub > 1 else []
    assert Runner.between_times(K, h, sub).tolist() == inner
    assert np.array_equal(got[np.arange(got.size) % sub == 0], Runner.grid(K, h))

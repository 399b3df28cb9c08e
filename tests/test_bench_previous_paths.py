"""The bench's previous paths: what `symfunnel bench` measures each new path against in the same run.

bench.simulate.against_previous runs this path and the previous one in fresh processes on the same trajectory (the
same CVODES step counts: the changes they compare are copies and heap settings, not arithmetic);
bench.implementation.w_as_loops generates the C pair with W x as loops, and leaves the generator as it was;
bench.implementation.tanh_as_3div swaps in the previous tanh (three divisions per lane), the rest unchanged."""

import pytest

from symfunnel.bench.simulate import against_previous


def test_against_previous_runs_both_paths_on_the_same_trajectory():
    r = against_previous("paper", 1.0, perturbations=(0.0, 1e-11), rounds=1)
    assert len(r["this"]) == len(r["previous"]) == 2
    assert r["steps_this"] == r["steps_previous"] and min(r["steps_this"]) > 50
    assert all(c > 0 for c in r["this"] + r["previous"]) and r["paired_ratio"] > 0


def test_w_as_loops_is_the_loop_form_and_restores_the_generator(paper_design):
    from symfunnel.bench.implementation import w_as_loops
    from symfunnel.emit.files import generate
    from symfunnel.family.esn import ESN
    before = ESN.UNROLL_W_MAX
    loops = w_as_loops(paper_design, 1000.0)["symfunnel_controller.c"]
    now = generate(paper_design, "c", rate_hz=1000.0)["symfunnel_controller.c"]
    assert ESN.UNROLL_W_MAX == before
    assert "sk_xdot_Wx[247]" in loops and "sk_xdot_Wx[" not in now


def test_wx_scalar_is_the_scalar_rows_and_restores_the_generator(paper_design):
    """The baseline of `wx_scalar_ns`: the file without the fused blocks of W x, the rest the same; the generator's
    switch as it was afterwards."""
    from symfunnel.bench.implementation import wx_scalar
    from symfunnel.emit.files import generate
    from symfunnel.family.esn import ESN
    rows = wx_scalar(paper_design, 1000.0)
    now = generate(paper_design, "c", rate_hz=1000.0)
    assert ESN.VECTOR_WX is True
    c_rows, c_now = rows["symfunnel_controller.c"], now["symfunnel_controller.c"]
    assert "_mm256_fmadd_pd" not in c_rows and c_now.count("_mm256_fmadd_pd(") == 204
    assert c_rows.count("    s += ") == c_now.count("    s += ") == 247    # the scalar rows kept as the fallback
    assert all(rows[k] == v for k, v in now.items() if k not in ("symfunnel_controller.c", "manifest.json"))


def test_tanh_as_3div_is_the_previous_tanh_and_computes_the_same_step(paper_design):
    """The baseline of `tanh3div_ns`: only the tanh differs (three divisions per lane in its loop instead of one), and
    the step built from it agrees with the current one to the tanh's rounding."""
    import shutil
    import numpy as np
    from symfunnel.bench.implementation import tanh_as_3div
    from symfunnel.core.ccompile import compile_cached
    from symfunnel.emit.check import CLibrary
    from symfunnel.emit.files import generate
    from symfunnel.emit.step import etd_factors
    files = generate(paper_design, "c", prefix="arm_", rate_hz=2000.0)
    old = tanh_as_3div(files)
    c_new, c_old = files["arm_controller.c"], old["arm_controller.c"]
    body = lambda c: c[c.index("static double arm_sk_tanh("):c.index("#endif", c.index("static double arm_sk_tanh("))]
    assert body(c_new).count(" / ") == 1 and body(c_old).count(" / ") == 2     # + the exp's Pade quotient
    assert "arm_sk_exp_neg(" in c_old and "arm_sk_exp_neg(" not in c_new
    assert all(old[k] == v for k, v in files.items() if k != "arm_controller.c")
    if shutil.which("gcc") is None:
        return
    flags = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-fPIC", "-shared", "-O2", "-DSYMFUNNEL_FAST_TANH")
    names = ("arm_controller.c", "arm_controller.h")
    libs = [CLibrary(compile_cached({k: f[k] for k in names}, ["arm_controller.c"], "libarm_controller.so",
                                    flags).path).function("arm_step_core") for f in (files, old)]
    etd = np.array(etd_factors(paper_design.scenario, 2000.0))
    rng = np.random.default_rng(0)
    N, nr, n = paper_design.sym["x_esn"].numel(), paper_design.sym["w_hat"].shape[0], paper_design.n
    for _ in range(16):
        args = (rng.uniform(0, 20), rng.normal(0, 0.5, n), rng.normal(0, 1, n), rng.uniform(-1, 1, N),
                rng.normal(0, 3, (nr, n)), etd)
        for a, b in zip(*(f(*args) for f in libs)):
            a, b = np.asarray(a), np.asarray(b)
            assert np.max(np.abs(a - b)) <= 1e-13 * max(1.0, float(np.max(np.abs(a))))


@pytest.mark.slow
def test_cli_tune_runs_both_schedules_in_fresh_processes(tmp_path):
    """bench.tune.cli_tune (tune.paper_default_wall_s): each schedule's tune in its own process, its --json and the
    CPU of the process and its IPOPT child; a short horizon and one evaluation keep it cheap."""
    import copy

    from symfunnel.bench.tune import cli_tune
    from symfunnel.core.toml_write import dumps
    from symfunnel.scenario import load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = 0.3
    raw["tune"] = {"parameters": ["controller.k2"]}
    src = tmp_path / "s.toml"
    src.write_text(dumps(raw), encoding="utf-8")
    outs = {}
    for path, starts in (("", ""), ("previous", ""), ("", "sequential")):
        out = tmp_path / f"out{path}{starts}.toml"
        r = cli_tune(path, str(out), ("--max-evals", "1"), scenario=str(src), starts=starts)
        assert r["rc"] in (0, 1) and r["json"]["status"] in ("ok", "infeasible"), r
        assert r["cpu_s"] > 0 and r["wall_s"] > 0 and r["json"]["method"].startswith("gradient")
        outs[starts or path or "now"] = (r["json"]["objective"], out.read_bytes() if out.exists() else None)
    # tune.paper_side_by_side_wall_s's two paths: the same search, the same answer
    assert outs["now"] == outs["sequential"]


def test_c_loop_vs_python_runs_both_loops_on_the_same_trajectory(paper_run):
    """simulate.cpu_per_run's baseline: the Python loop over the same driver, the same steps as the C loop, and the
    switch left as it was."""
    from symfunnel.bench.simulate import PERTURBATIONS, c_loop_vs_python
    from symfunnel.simulation import crun
    r = c_loop_vs_python(paper_run.scenario, paper_run.design, paper_run.closed_loop, 0.5, rounds=1)
    assert len(r["c"]) == len(r["python"]) == len(PERTURBATIONS)
    assert r["steps_c"] == r["steps_python"] and min(r["steps_c"]) > 50
    assert r["paired_ratio"] > 0 and crun.RUN_IN_C is True


def test_driver_kernels_compares_both_forms_on_the_same_trajectory_and_restores_the_switches(paper_run):
    """bench.simulate.driver_kernels (`simulate.driver_kernels`): the kernels on and off give the same step counts
    (the same doubles), and the switches are as they were afterwards."""
    from symfunnel.bench.simulate import driver_kernels
    from symfunnel.simulation import sundials
    r = driver_kernels(paper_run.scenario, paper_run.design, paper_run.closed_loop, 0.5, rounds=1)
    assert len(r["this"]) == len(r["previous"]) == 9
    assert r["steps_this"] == r["steps_previous"] and min(r["steps_this"]) > 50
    assert r["paired_ratio"] > 0 and r["lu_paired_ratio"] > 0 and r["vectors_paired_ratio"] > 0
    assert sundials.SCHEDULED_LU is True and sundials.WIDE_VECTORS is True


def test_samples_in_place_compares_both_placements_on_the_same_trajectory(paper_run):
    """bench.simulate.samples_in_place (`simulate.samples_in_place`): the samples written in place and copied give
    the same step counts, and the switch is as it was afterwards."""
    from symfunnel.bench.simulate import PERTURBATIONS, samples_in_place
    from symfunnel.simulation import crun
    r = samples_in_place(paper_run.scenario, paper_run.design, paper_run.closed_loop, 0.5, rounds=1)
    assert len(r["in_place"]) == len(r["copied"]) == len(PERTURBATIONS)
    assert r["steps_in_place"] == r["steps_copied"] and min(r["steps_in_place"]) > 50
    assert r["paired_ratio"] > 0 and crun.SAMPLES_IN_PLACE is True


def test_fused_interpolation_compares_both_forms_on_the_same_trajectory(paper_run):
    """bench.simulate.fused_interpolation (`simulate.fused_interpolation`): the samples interpolated in one pass and
    through CVodeGetDky give the same step counts, and the switch is as it was afterwards."""
    from symfunnel.bench.simulate import PERTURBATIONS, fused_interpolation
    from symfunnel.simulation import sundials
    r = fused_interpolation(paper_run.scenario, paper_run.design, paper_run.closed_loop, 0.5, rounds=1)
    assert len(r["fused"]) == len(r["previous"]) == len(PERTURBATIONS)
    assert r["steps_fused"] == r["steps_previous"] and min(r["steps_fused"]) > 50
    assert r["paired_ratio"] > 0 and sundials.FUSED_DKY is True

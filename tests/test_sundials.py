"""The direct CVODES backend (simulation/sundials.py, csrc/cvodes_driver.c) against casadi.integrator: the same
algorithm (bit for bit while the LUs' rounding agrees), trajectories inside the integrator's own tolerance band, its
fixed-pattern LU against numpy, and the checks that keep it from running on a CVODES it was not written for."""

from __future__ import annotations

import copy
import ctypes
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symfunnel.simulation import sundials


def _variant(sc, **sim):
    """The scenario with [simulation] keys overridden."""
    from symfunnel.scenario import from_dict
    raw = copy.deepcopy(sc.raw)
    raw.setdefault("simulation", {}).update(sim)
    return from_dict(raw, file=sc.file, base_dir=Path(sc.file).parent, default_name=sc.name)


def _runner(run, K, backend_name, monkeypatch):
    from symfunnel.simulation.compiled import compile_closed_loop
    from symfunnel.simulation.runner import Runner
    monkeypatch.setenv("SYMFUNNEL_CVODES", backend_name)
    cl = run.closed_loop
    comp = compile_closed_loop(cl).bind(cl.p0)
    r = Runner(cl, comp, "cvodes", run.scenario.simulation.dt, run.scenario.simulation)
    X = r.run(0.0, cl.x0, K)
    return X, r.stats


def test_direct_backend_is_casadis_cvodes_bit_for_bit_on_the_first_chunk(paper_run, monkeypatch):
    """25 output points of the paper loop (320 CVODES steps): the same states to the last bit and the same step,
    right-hand-side, Jacobian and error-test counts as casadi.integrator with CSparse: the same algorithm, options
    and linear-solver contract, not merely a close one."""
    assert sundials.available(), sundials.unavailable_reason()
    Xc, sc_ = _runner(paper_run, 25, "casadi", monkeypatch)
    Xd, sd = _runner(paper_run, 25, "direct", monkeypatch)
    assert sc_["cvodes_backend"] == "casadi" and sd["cvodes_backend"] == "direct"
    assert np.array_equal(Xc, Xd)
    for k in ("steps", "rhs_evaluations", "jacobian_evaluations", "error_test_failures"):
        assert sc_[k] == sd[k] > 0, k


def test_a_changed_option_is_seen(paper_run, monkeypatch):
    """The bit-for-bit agreement is not vacuous: the direct run with another tolerance differs."""
    import dataclasses

    from symfunnel.simulation.compiled import compile_closed_loop
    from symfunnel.simulation.runner import Runner
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    cl = paper_run.closed_loop
    comp = compile_closed_loop(cl).bind(cl.p0)
    sim = paper_run.scenario.simulation
    X1 = Runner(cl, comp, "cvodes", sim.dt, sim).run(0.0, cl.x0, 5)
    X2 = Runner(cl, comp, "cvodes", sim.dt, dataclasses.replace(sim, rtol=sim.rtol * 2)).run(0.0, cl.x0, 5)
    assert not np.array_equal(X1, X2)


def _tolerance_band(sc, tf, backend_name, monkeypatch, tight):
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", backend_name)
    design = _design(sc)
    errs = []
    for eps in (0.0, 1e-12, -1e-11):          # rounding-level perturbations: the run's own spread
        r = simulate(sc, design, t_final=tf, params={"plant.mass_scale": float(sc.plant.mass_scale) * (1 + eps)})
        assert r.status == "ok", r.message
        assert r.stats["cvodes_backend"] == backend_name
        errs.append(float(np.max(np.abs(r.x[:, :2 * sc.n] - tight.x[:, :2 * sc.n]))))
    return errs


_DESIGNS: dict = {}


def _design(sc):
    from symfunnel.design import derive
    key = (sc.name, str(sc.file))
    if key not in _DESIGNS:
        _DESIGNS[key] = derive(sc)
    return _DESIGNS[key]


def _urdf_scenario(tmp_path_factory):
    from symfunnel.cli import main
    from symfunnel.scenario import load_scenario
    d = tmp_path_factory.mktemp("urdf")
    src = Path(__file__).parent / "data" / "branched.urdf"
    (d / "branched.urdf").write_bytes(src.read_bytes())
    assert main(["init", "--urdf", str(d / "branched.urdf"), "--out", str(d / "s.toml"), "-q"]) == 0
    return load_scenario(str(d / "s.toml"))


@pytest.mark.parametrize("name,tf", [("paper", 4.0), ("arm7", 1.0), ("urdf", 2.0)])
def test_trajectories_stay_in_the_integrators_tolerance_band(name, tf, monkeypatch, tmp_path_factory):
    """Against a tight reference (rtol 1e-10, atol 1e-12, casadi.integrator), the direct backend's error in q, dq
    is within twice the largest error of casadi.integrator itself over rounding-level perturbations of the same
    run: the trajectories are today's within the integrator's tolerance."""
    from symfunnel.scenario import load_scenario
    from symfunnel.simulation import simulate
    sc = _urdf_scenario(tmp_path_factory) if name == "urdf" else load_scenario(name)
    monkeypatch.setenv("SYMFUNNEL_CVODES", "casadi")
    tight = simulate(_variant(sc, rtol=1e-10, atol=1e-12), _design(sc), t_final=tf)
    assert tight.status == "ok"
    band = _tolerance_band(sc, tf, "casadi", monkeypatch, tight)
    direct = _tolerance_band(sc, tf, "direct", monkeypatch, tight)
    assert max(direct) <= 2 * max(band), (direct, band)
    assert max(band) < 1e-3                   # the band itself is an integrator tolerance, not a different run


def test_a_different_run_is_outside_the_band(paper, monkeypatch):
    """The band test can fail: a 1e-3 change of the plant's mass is far outside it."""
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", "casadi")
    tight = simulate(_variant(paper, rtol=1e-10, atol=1e-12), _design(paper), t_final=4.0)
    band = _tolerance_band(paper, 4.0, "casadi", monkeypatch, tight)
    other = simulate(paper, _design(paper), t_final=4.0, params={"plant.mass_scale": 1.001})
    assert float(np.max(np.abs(other.x[:, :4] - tight.x[:, :4]))) > 2 * max(band)


def _jacobian(cl, comp):
    """The loop's compiled Jacobian df/dx at (t, x) (x in the loop's order) with its own parameters."""
    jac = ca.external("jac_symfunnel_ode", comp.library)
    ix = jac.index_out("jac_ode_x")
    P = np.concatenate([[0.0], comp.bind(cl.p0).pvals])
    return lambda t, x: jac(t, x[comp.perm], ca.DM(0, 1), P, ca.DM(0, 1), 0, 0, 0, 0)[ix]


def _solver(run):
    from symfunnel.family.integrators import INTEGRATORS
    from symfunnel.simulation.compiled import compile_closed_loop
    cl = run.closed_loop
    comp = compile_closed_loop(cl)
    opts = INTEGRATORS.get("cvodes")(run.scenario.simulation, 0.01, 0.01, 1)
    return cl, comp, sundials.DirectCvodes(comp.library, cl.nx, 1 + len(comp.bind(cl.p0).pvals), opts)


def test_fixed_pattern_lu_solves_the_newton_system(paper_run):
    """(I - gamma J) x = b with the driver's LU equals numpy's dense solve on the loop's real Jacobian, from
    gamma = 1e-6 to gamma = 1 (far beyond CVODES' steps here)."""
    cl, comp, D = _solver(paper_run)
    jac = _jacobian(cl, comp)
    rng = np.random.default_rng(3)
    for x in (cl.x0, cl.x0 + rng.normal(0, 0.05, cl.nx)):
        J = jac(0.37, x)
        Jd = np.array(ca.densify(J))
        for gamma in (1e-6, 1e-3, 0.05, 1.0):
            b = rng.normal(size=cl.nx)
            got = D.factor_solve(np.array(J.nonzeros()), gamma, b)
            want = np.linalg.solve(np.eye(cl.nx) - gamma * Jd, b)
            assert got is not None
            assert np.max(np.abs(got - want)) <= 1e-12 * max(1.0, np.max(np.abs(want)))


def test_a_vanishing_pivot_or_growth_is_refused_not_used(paper_run):
    """gamma = 1/J_00 makes the first pivot 1 - gamma J_00 exactly 0, gamma = (1 - 1e-13)/J_00 a tiny one whose
    multipliers blow the eliminated entries up: the factorisation reports both (CVODES then retries with a smaller
    step) instead of solving with them; the next good factorisation works again."""
    cl, comp, D = _solver(paper_run)
    J = _jacobian(cl, comp)(0.0, cl.x0)
    Jx = np.array(J.nonzeros())
    J00 = float(J[0, 0])
    assert J00 != 0.0
    assert D.factor_solve(Jx, 1.0 / J00, np.ones(cl.nx)) is None
    assert D.factor_solve(Jx, 1e-3, np.ones(cl.nx)) is not None
    assert D.factor_solve(Jx, (1 - 1e-13) / J00, np.ones(cl.nx)) is None
    assert D.factor_solve(Jx, 1e-3, np.ones(cl.nx)) is not None


def test_growth_stays_far_from_the_refusal_threshold_on_a_run(paper_run, monkeypatch):
    """Over 2 s of the paper loop the factorisations' growth factor stays orders of magnitude below the threshold
    (1e8), though the joints' pivots are 1e-9 of their columns' largest entries at the start."""
    from symfunnel.simulation.compiled import compile_closed_loop
    from symfunnel.simulation.runner import Runner
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    cl = paper_run.closed_loop
    comp = compile_closed_loop(cl).bind(cl.p0)
    sim = paper_run.scenario.simulation
    r = Runner(cl, comp, "cvodes", sim.dt, sim)
    r.run(0.0, cl.x0, 200)
    assert 1.0 <= r.direct().max_growth() < 1e4


def _compile_driver(tmp_path, header_text: str):
    """The driver built from the package's source with a given memory-layout header, loaded."""
    import casadi as _ca

    from symfunnel.core.ccompile import compile_cached
    d = Path(_ca.__file__).resolve().parent
    csrc = resources.files("symfunnel.simulation").joinpath("csrc")
    src = {name: csrc.joinpath(name).read_text(encoding="utf-8") for name in sundials._SOURCES}
    src["cvodes_mem.h"] = header_text
    libs = (f"-L{d}", "-l:libcasadi_integrator_cvodes.so", "-l:libcasadi_sundials_common.so", f"-Wl,-rpath,{d}",
            "-lm")
    built = compile_cached(src, ["cvodes_driver.c"], "drv.so", sundials.DRIVER_FLAGS, libs=libs, cache=tmp_path)
    lib = ctypes.CDLL(str(built.path))
    lib.sf_create.restype = ctypes.c_void_p
    lib.sf_create.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p,
                              ctypes.POINTER(ctypes.c_longlong), ctypes.POINTER(ctypes.c_int),
                              ctypes.POINTER(ctypes.c_int), ctypes.c_double, ctypes.c_double, ctypes.c_long,
                              ctypes.c_double, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
    lib.sf_free.argtypes = [ctypes.c_void_p]
    return lib


def _create(lib, paper_run):
    cl, comp, _ = _solver(paper_run)
    cll = ctypes.CDLL(comp.library)
    ode = ca.external("symfunnel_ode", comp.library)
    jac = ca.external("jac_symfunnel_ode", comp.library)
    jx = jac.index_out("jac_ode_x")
    sp = jac.sparsity_out(jx)
    sizes = np.array([ode.sz_arg(), ode.sz_res(), ode.sz_iw(), ode.sz_w(), jac.sz_arg(), jac.sz_res(), jac.sz_iw(),
                      jac.sz_w(), jac.n_in(), jac.n_out(), jx], dtype=np.longlong)
    Jp, Ji = np.array(sp.colind(), dtype=np.intc), np.array(sp.row(), dtype=np.intc)
    err = ctypes.create_string_buffer(400)
    h = lib.sf_create(cl.nx, 1 + len(comp.bind(cl.p0).pvals), ctypes.cast(cll.symfunnel_ode, ctypes.c_void_p).value,
                      ctypes.cast(cll.jac_symfunnel_ode, ctypes.c_void_p).value,
                      sizes.ctypes.data_as(ctypes.POINTER(ctypes.c_longlong)),
                      Jp.ctypes.data_as(ctypes.POINTER(ctypes.c_int)), Ji.ctypes.data_as(ctypes.POINTER(ctypes.c_int)),
                      1e-6, 1e-8, 20000, 0.0, 0, err, len(err))
    return h, err.value.decode()


def test_the_memory_layout_check_refuses_a_wrong_layout(paper_run, tmp_path):
    """The driver reads CVODES' memory block through a copied struct: with one field added at the top (a CVODES
    whose block differs), sf_create refuses; with the shipped header it accepts."""
    header = resources.files("symfunnel.simulation").joinpath("csrc", "cvodes_mem.h").read_text(encoding="utf-8")
    good = _compile_driver(tmp_path / "good", header)
    h, err = _create(good, paper_run)
    assert h, err
    good.sf_free(h)
    shifted = header.replace("typedef struct CVodeMemRec {", "typedef struct CVodeMemRec {\n  int shifted_by_a_test;")
    assert shifted != header
    bad = _compile_driver(tmp_path / "bad", shifted)
    h, err = _create(bad, paper_run)
    assert not h and "memory layout" in err


def test_unknown_options_fall_back_to_casadi(paper_run):
    """An option the driver does not implement is refused (the runner then uses casadi.integrator)."""
    from symfunnel.family.integrators import INTEGRATORS
    from symfunnel.simulation.compiled import compile_closed_loop
    cl = paper_run.closed_loop
    comp = compile_closed_loop(cl)
    opts = INTEGRATORS.get("cvodes")(paper_run.scenario.simulation, 0.01, 0.01, 1)
    with pytest.raises(RuntimeError, match="does not implement"):
        sundials.DirectCvodes(comp.library, cl.nx, 1 + len(comp.bind(cl.p0).pvals), dict(opts, nonlin_conv_coeff=0.3))
    with pytest.raises(RuntimeError, match="does not implement"):
        sundials.DirectCvodes(comp.library, cl.nx, 1 + len(comp.bind(cl.p0).pvals), dict(opts, linear_solver="qr"))


def test_casadi_backend_on_request_and_on_the_vm(paper, paper_design, monkeypatch):
    """$SYMFUNNEL_CVODES=casadi selects casadi.integrator; the VM (no compiled library) never uses the driver."""
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", "casadi")
    assert simulate(paper, paper_design, t_final=0.1).stats["cvodes_backend"] == "casadi"
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    r = simulate(paper, paper_design, t_final=0.1, jit=False)
    assert r.stats["code"] == "vm" and r.stats["cvodes_backend"] == "casadi"
    assert simulate(paper, paper_design, t_final=0.1).stats["cvodes_backend"] == "direct"


def test_cvodes_failure_reads_as_casadis(paper, paper_design, monkeypatch):
    """A failing run gives CVODES' flag in CasADi's words ('CVode returned "CV_..."'), which the hints parse."""
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    sc = _variant(paper, max_step=0.0)
    import symfunnel.family.integrators as I
    monkeypatch.setattr(I, "MAX_STEPS_PER_OUTPUT", 3)
    r = simulate(sc, paper_design, t_final=0.2)
    assert r.status == "failed" and r.stats["cvodes_backend"] == "direct"
    assert 'CVode returned "CV_TOO_MUCH_WORK"' in r.message


def _direct_solver(run):
    """The run's direct CVODES solver, its parameter vector for a chunk starting at 0, and x0 in its state order."""
    from symfunnel.simulation.compiled import compile_closed_loop
    from symfunnel.simulation.runner import Runner
    cl = run.closed_loop
    comp = compile_closed_loop(cl).bind(cl.p0)
    sim = run.scenario.simulation
    r = Runner(cl, comp, "cvodes", sim.dt, sim)
    return r.direct(), np.concatenate([[0.0], comp.pvals]), cl.x0[r.perm]


def test_samples_from_kept_steps_are_cvodes_output_points_bit_for_bit(paper_run, monkeypatch):
    """`run_sampled` integrates on the plain grid keeping the steps, then interpolates where asked: the values are
    those CVODES returns with the same times as output points (`run` on the merged grid), to the last bit, and the
    plain grid's states and step counts are `run`'s -- for sample times that fall on several per step, one per
    step, and exactly on output points."""
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    D, p, x0 = _direct_solver(paper_run)
    h = paper_run.scenario.simulation.dt
    grid = h * np.arange(1, 101)
    Xp, stp = D.run(p, x0, grid)
    for extra in (np.array([h * (k + 1) + j * (h / 8) for k in range(99) for j in range(1, 8)]),
                  np.sort(np.random.default_rng(3).uniform(grid[0] + 1e-6, grid[-1] - 1e-6, 300)),
                  grid[10:20] + 0.0):
        got = D.run_sampled(p, x0, grid, lambda st, e=extra: e)
        assert got is not None
        X, st, Y = got
        assert np.array_equal(X, Xp) and st == stp
        merged = np.unique(np.concatenate([grid, extra]))
        Xm, _ = D.run(p, x0, merged)
        assert np.array_equal(Y, Xm[np.searchsorted(merged, extra)])
    # a history above its memory cap gives no samples (the caller integrates again), never samples from part of it
    X, st, Y = D.run_sampled(p, x0, grid, lambda st: grid[:3] + h / 2, max_bytes=1e4)
    assert Y is None and np.array_equal(X, Xp) and st == stp
    # the samples are chosen after the chunk, from its statistics
    seen = []

    def after(st):
        seen.append(st)
        return np.zeros(0)

    D.run_sampled(p, x0, grid, after)
    assert seen == [stp]


@pytest.mark.parametrize("which", ["paper", "arm7", "urdf"])
def test_a_run_sampled_from_its_steps_is_the_run_integrated_again_bit_for_bit(which, monkeypatch, tmp_path_factory):
    """The whole run with the samples between output points taken from the kept steps equals the run that
    integrates a chunk again on the denser grid: trajectory, every signal, the between-points statistics and the
    step counts, bit for bit; and it integrates less (the paper's 20 s: no chunk integrated twice)."""
    from symfunnel.pipeline import Run
    from symfunnel.scenario import load_scenario
    from symfunnel.simulation import runner as runner_mod
    from symfunnel.simulation import simulate
    monkeypatch.setenv("SYMFUNNEL_CVODES", "direct")
    sc = _urdf_scenario(tmp_path_factory) if which == "urdf" else load_scenario(which)
    run = Run(sc)
    tf = {"paper": sc.simulation.t_final, "arm7": 2.0, "urdf": 2.0}[which]
    calls = {True: 0, False: 0}
    real = sundials.DirectCvodes.run

    def counting(self, *a, **k):
        calls[runner_mod.SAMPLE_FROM_STEPS] += 1
        return real(self, *a, **k)

    monkeypatch.setattr(sundials.DirectCvodes, "run", counting)
    out = {}
    for flag in (False, True):
        monkeypatch.setattr(runner_mod, "SAMPLE_FROM_STEPS", flag)
        out[flag] = simulate(sc, run.design, t_final=tf, closed_loop=run.closed_loop)
    a, b = out[False], out[True]
    assert a.ok and b.ok, (a.message, b.message)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.x, b.x)
    for k in a.signals:
        assert np.array_equal(np.asarray(a.signals[k]), np.asarray(b.signals[k]), equal_nan=True), k
    assert a.stats["between"] == b.stats["between"]
    for k in ("steps", "rhs_evaluations", "jacobian_evaluations", "error_test_failures"):
        assert a.stats[k] == b.stats[k], k
    assert calls[True] < calls[False]       # the first output steps and refinements only, no chunk again
    if which == "paper":                    # kept steps that do not fit in memory: integrated again, the same run
        from symfunnel.simulation import crun
        monkeypatch.setattr(sundials, "HISTORY_BYTES", 1e4)
        monkeypatch.setattr(crun, "RUN_IN_C", False)    # counted here in the Python loop (C: tests/test_crun.py)
        before = calls[True]
        c = simulate(sc, run.design, t_final=tf, closed_loop=run.closed_loop)
        assert np.array_equal(c.x, b.x) and c.stats["between"] == b.stats["between"]
        assert c.stats["steps"] == b.stats["steps"]
        assert calls[True] - before > before       # the chunks integrated again for their samples


def test_states_written_in_the_callers_order_are_the_permuted_states(paper_run):
    """A driver told the public order returns x[order] of what the driver in CVODES' order returns, bit for bit, at
    the output points and at the samples from the kept steps; a non-permutation is refused."""
    from symfunnel.family.integrators import INTEGRATORS
    cl, comp, D = _solver(paper_run)
    inv = np.argsort(comp.perm)
    opts = INTEGRATORS.get("cvodes")(paper_run.scenario.simulation, 0.01, 0.01, 1)
    P = np.concatenate([[0.0], comp.bind(cl.p0).pvals])
    E = sundials.DirectCvodes(comp.library, cl.nx, P.size, opts, order=inv)
    grid = 0.01 * np.arange(1, 41)
    x0 = cl.x0[comp.perm]
    X, st = D.run(P, x0, grid)
    Xo, sto = E.run(P, x0, grid)
    assert np.array_equal(Xo, X[:, inv]) and st == sto
    assert not np.array_equal(Xo, X)                    # the order matters: the test can tell
    times = np.linspace(0.001, 0.399, 97)
    _, _, Y = D.run_sampled(P, x0, grid, lambda s: times)
    Xs, _, Yo = E.run_sampled(P, x0, grid, lambda s: times)
    assert np.array_equal(Xs, X[:, inv]) and np.array_equal(Yo, Y[:, inv])
    with pytest.raises(RuntimeError, match="permutation"):
        sundials.DirectCvodes(comp.library, cl.nx, P.size, opts, order=np.zeros(cl.nx, dtype=int))


@pytest.mark.parametrize("wide", [True, False])
def test_the_fused_interpolation_is_cvodegetdkys_bit_for_bit(paper_run, monkeypatch, wide):
    """`sundials.FUSED_DKY`: the samples from the kept steps interpolated in one pass straight into the caller's
    order are CVodeGetDky's values permuted (the previous path), to the last bit -- in CVODES' order and in the
    public one, with the four-wide and the scalar form, for several samples per step, samples on output points and
    on every order the run's steps take; a time outside the chunk is refused by both."""
    monkeypatch.setattr(sundials, "WIDE_VECTORS", wide)
    from symfunnel.family.integrators import INTEGRATORS
    cl, comp, D0 = _solver(paper_run)
    opts = INTEGRATORS.get("cvodes")(paper_run.scenario.simulation, 0.01, 0.01, 1)
    P = np.concatenate([[0.0], comp.bind(cl.p0).pvals])
    x0 = cl.x0[comp.perm]
    grid = 0.01 * np.arange(1, 61)
    rng = np.random.default_rng(7)
    times = np.sort(np.concatenate([rng.uniform(1e-6, grid[-1], 400), grid[5:15] + 0.0, [grid[-1]]]))
    for order in (None, np.argsort(comp.perm)):
        D = sundials.DirectCvodes(comp.library, cl.nx, P.size, opts, order=order)
        assert bool(D._lib.sf_has_wide_vectors(D._h)) == wide
        got = {}
        for fused in (True, False):
            monkeypatch.setattr(sundials, "FUSED_DKY", fused)
            X, st, Y = D.run_sampled(P, x0, grid, lambda s: times)
            assert Y is not None and np.isfinite(Y).all()
            got[fused] = (X, st, Y)
            assert D.run_sampled(P, x0, grid, lambda s: np.array([0.01, grid[-1] + 0.01]))[2] is None
        assert np.array_equal(got[True][0], got[False][0]) and got[True][1] == got[False][1]
        assert np.array_equal(got[True][2], got[False][2])
        assert got[True][1]["nsteps"] > 60            # several steps per output point, and their orders

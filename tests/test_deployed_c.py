"""The generated C step API (Pstate, Pinit, Pstep): prefixes, agreement with CasADi, discrete update, saturation."""

from __future__ import annotations

import math
import re
import shutil
import subprocess

import numpy as np
import pytest

from symfunnel import emit as cg
from symfunnel.cli import main
from symfunnel.emit import check
from symfunnel.emit.c import STRICT_CFLAGS
from symfunnel.emit.step import step_function
from symfunnel.design import derive
from symfunnel.deployed.loop import step_library
from symfunnel.scenario import load_scenario


GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc not available")


@pytest.fixture(scope="module")
def paper():
    return derive(load_scenario("paper"))


@pytest.fixture(scope="module")
def paper_files(paper):
    return cg.generate(paper, "c", prefix="paper_", rate_hz=2000.0)


@pytest.fixture(scope="module")
def step_lib(paper, paper_files):
    return step_library(paper, paper_files)


def casadi_tau(design, t, q, dq, x, w):
    qd, dqd, ddqd = (np.array(v).ravel() for v in design.reference(t))
    tau, xdot, wdot = design.controller()(t, q, dq, qd, dqd, ddqd, x, w)
    return np.array(tau).ravel(), np.array(xdot).ravel(), np.array(wdot)


def test_pstep_equals_the_casadi_controller_and_advances_by_exponential_euler(paper, step_lib):
    sc = paper.scenario
    pts = check.sample_points(paper, 200, seed=3)
    h = 1 / 2000.0
    lam_x = sc.esn.leak / sc.esn.time_constant
    lam_w = sc.gamma * sc.sigma
    worst_tau = worst_x = worst_w = 0.0
    for j in range(200):
        t = float(pts["t"][0, 0, j])
        q, dq = pts["q"][:, 0, j], pts["dq"][:, 0, j]
        # Pstep computes the reference itself: put the point's errors on the scenario's reference
        qd_pt = pts["qd"][:, 0, j]
        qd, dqd, _ = (np.array(v).ravel() for v in paper.reference(t))
        q = q - qd_pt + qd
        a2_pt = np.array(paper.function("alpha2", ["t", "q", "qd", "dqd"])(t, pts["q"][:, 0, j], qd_pt,
                                                                             pts["dqd"][:, 0, j])).ravel()
        a2 = np.array(paper.function("alpha2", ["t", "q", "qd", "dqd"])(t, q, qd, dqd)).ravel()
        dq = dq - a2_pt + a2
        x, w = pts["x_esn"][:, 0, j], pts["w_hat"][:, :, j]
        step_lib.x_esn[:] = x
        step_lib.w_hat[:] = w.reshape(-1, order="F")
        rc, tau = step_lib.step(t, q, dq)
        assert rc == 0
        ref, xdot, wdot = casadi_tau(paper, t, q, dq, x, w)
        worst_tau = max(worst_tau, np.max(np.abs(tau - ref)) / max(1.0, np.max(np.abs(ref))))
        # exponential Euler, written out independently: x+ = exp(-l h) x + (1 - exp(-l h)) (x + xdot / l)
        x_next = math.exp(-lam_x * h) * x + (1 - math.exp(-lam_x * h)) * (x + xdot / lam_x)
        w_next = math.exp(-lam_w * h) * w + (1 - math.exp(-lam_w * h)) * (w + wdot / lam_w)
        worst_x = max(worst_x, np.max(np.abs(step_lib.x_esn - x_next)))
        worst_w = max(worst_w, np.max(np.abs(step_lib.w_hat - w_next.reshape(-1, order="F")))
                      / max(1.0, np.max(np.abs(w_next))))
    assert worst_tau <= 1e-12
    assert worst_x <= 1e-12 and worst_w <= 1e-12


def test_pstep_outside_a_funnel_returns_1_with_finite_tau_and_rejects_bad_input(paper, step_lib):
    step_lib.init()
    t = 0.5
    qd = np.array(paper.reference(t)[0]).ravel()
    F1 = np.array(paper.function("funnel_bounds", ["t"], ["F1", "F2"])(t)[0]).ravel()
    rc, tau = step_lib.step(t, qd + 1.5 * F1, np.zeros(2))
    assert rc == 1 and np.all(np.isfinite(tau))
    assert step_lib.margin[0] == pytest.approx(-0.5, abs=1e-12)
    before = step_lib.state.copy()
    assert step_lib.step(t, np.array([np.nan, 0.0]), np.zeros(2))[0] == -2
    assert step_lib.step(math.inf, qd, np.zeros(2))[0] == -2
    np.testing.assert_array_equal(step_lib.state, before)       # unchanged on error


def test_saturation_clips_the_design_torque(paper, tmp_path):
    files = cg.generate(paper, "c", prefix="sat_", rate_hz=1000.0, tau_max=[50.0, 20.0])
    lib = step_library(paper, files)
    sc = paper.scenario
    rc, tau = lib.step(0.0, np.array(sc.q0), np.array(sc.dq0))
    ref = casadi_tau(paper, 0.0, np.array(sc.q0), np.array(sc.dq0), np.zeros(50), np.zeros((51, 2)))[0]
    assert np.all(np.abs(ref) > [50.0, 20.0])               # the paper's start needs more than that
    np.testing.assert_array_equal(tau, np.sign(ref) * [50.0, 20.0])


def test_exponential_euler_keeps_the_reservoir_bounded_where_explicit_euler_diverges(paper):
    """At h = 0.2 s > 2 time_constant / leak explicit Euler on x_esn is unstable; the generated update is not."""
    sc = paper.scenario
    rate = 5.0
    f = step_function(paper, rate)
    ctl = paper.controller()
    t, q, dq = 0.0, np.array(sc.q0), np.array(sc.dq0)
    qd, dqd, ddqd = (np.array(v).ravel() for v in paper.reference(t))
    rng = np.random.default_rng(0)
    x_etd = x_eu = rng.uniform(-1, 1, 50)
    w = np.zeros((51, 2))
    for _ in range(40):
        x_etd = np.array(f(t, q, dq, x_etd, w)[1]).ravel()
        x_eu = x_eu + np.array(ctl(t, q, dq, qd, dqd, ddqd, x_eu, w)[1]).ravel() / rate
    assert np.max(np.abs(x_etd)) <= 1 / sc.esn.leak + 1e-12
    assert np.max(np.abs(x_eu)) > 1e3


@needs_gcc
@pytest.mark.slow
def test_two_prefixed_controllers_link_into_one_strict_program(paper, paper_files, tmp_path):
    arm7 = derive(load_scenario("arm7"))
    arm_files = cg.generate(arm7, "c", prefix="arm7_", rate_hz=1000.0)
    cg.write_output(paper_files, tmp_path)
    cg.write_output({k: v for k, v in arm_files.items() if k.startswith("arm7_controller")}, tmp_path)
    init = lambda v: ", ".join(repr(float(x)) for x in v)  # noqa: E731
    (tmp_path / "both.c").write_text("""
#include <stdio.h>
#include "paper_controller.h"
#include "arm7_controller.h"
int main(void) {
  paper_state a; arm7_state b;
  double qa[PAPER_N_JOINTS] = {@QA@}, dqa[PAPER_N_JOINTS] = {@DQA@}, ta[PAPER_N_JOINTS];
  double qb[ARM7_N_JOINTS] = {@QB@}, dqb[ARM7_N_JOINTS] = {@DQB@}, tb[ARM7_N_JOINTS];
  int i, ra, rb;
  if (paper_init(&a) || arm7_init(&b)) return 2;
  ra = paper_step(&a, 0.0, qa, dqa, ta);
  rb = arm7_step(&b, 0.0, qb, dqb, tb);
  printf("%d %d %d %d\\n", ra, rb, paper_state_size(), arm7_state_size());
  for (i = 0; i < PAPER_N_JOINTS; ++i) printf("%.17g ", ta[i]);
  printf("\\n");
  for (i = 0; i < ARM7_N_JOINTS; ++i) printf("%.17g ", tb[i]);
  printf("\\n");
  return 0;
}
""".replace("@QA@", init(paper.scenario.q0)).replace("@DQA@", init(paper.scenario.dq0))
       .replace("@QB@", init(arm7.scenario.q0)).replace("@DQB@", init(arm7.scenario.dq0)))
    srcs = ["both.c", "paper_controller.c", "arm7_controller.c"]
    # strict flags (ASan/UBSan: test_main_under_asan_ubsan_gives_casadi_torques and `make asan` run the same code)
    for flags, exe in ((list(STRICT_CFLAGS), "both"),):
        proc = subprocess.run([GCC, *flags, "-o", exe, *srcs, "-lm"], cwd=tmp_path, capture_output=True, text=True)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr[:2000]
        run = subprocess.run([f"./{exe}"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert run.returncode == 0 and run.stderr == "", run.stderr
        lines = run.stdout.splitlines()
        assert lines[0].split()[:2] == ["0", "0"]                      # both start inside their funnels
        for design, vals in ((paper, lines[1]), (arm7, lines[2])):
            sc = design.scenario
            N = design.sym["x_esn"].numel()
            x0 = np.asarray(sc.x_esn0, float)
            w0 = np.full(design.sym["w_hat"].shape, sc.w_hat0)
            ref = casadi_tau(design, 0.0, np.array(sc.q0), np.array(sc.dq0), x0, w0)[0]
            got = np.array(vals.split(), dtype=float)
            assert np.max(np.abs(got - ref)) / max(1.0, np.max(np.abs(ref))) <= 1e-12, (N, got, ref)
    for obj, prefix in (("paper_controller.c", "paper_"), ("arm7_controller.c", "arm7_")):
        subprocess.run([GCC, *STRICT_CFLAGS, "-c", "-o", obj + ".o", obj], cwd=tmp_path, check=True)
        nm = subprocess.run(["nm", "-g", "--defined-only", obj + ".o"], cwd=tmp_path, capture_output=True,
                            text=True, check=True)
        names = [line.split()[-1] for line in nm.stdout.splitlines() if line.strip()]
        assert len(names) > 50
        assert [s for s in names if not s.startswith(prefix)] == []


def test_header_has_guards_and_documents_every_argument(paper, paper_files):
    h = paper_files["paper_controller.h"]
    assert h.startswith("#ifndef PAPER_CONTROLLER_H\n#define PAPER_CONTROLLER_H")
    assert h.rstrip().endswith("#endif /* PAPER_CONTROLLER_H */")
    for f in cg.contract_functions(paper):
        for i in range(f.n_in()):
            r, c = f.size_in(i)
            assert re.search(rf"in  {i}: {f.name_in(i)} +{r} x {c} +\[", h), (f.name(), f.name_in(i))
    for arg in ("s    paper_state*", "t    double", "q    const double[2]", "dq   const double[2]", "tau  double[2]"):
        assert arg in h
    assert "int paper_step(paper_state *s, double t, const double *q, const double *dq, double *tau);" in h


@pytest.mark.parametrize("prefix", ["9a", "a-b", "__x", "_X", "a b", ""])
def test_bad_prefix_is_input_error(prefix, tmp_path, capsys):
    assert main(["codegen", "--lang", "c", "--out", str(tmp_path / "o"), "--prefix", prefix]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--prefix" in err[0] and err[0].startswith("symfunnel: error:")
    assert not (tmp_path / "o").exists()


def test_bad_rate_is_input_error(tmp_path, capsys):
    for rate in ("0", "-5", "2e6", "nan"):
        assert main(["codegen", "--lang", "c", "--out", str(tmp_path / "o"), "--rate", rate]) == 2
        assert "--rate" in capsys.readouterr().err


@needs_gcc
def test_documented_control_loop_builds_strictly_against_the_generated_files_alone(paper, tmp_path):
    """The control loop of docs/deployed.md (it was README's), built against the generated files alone."""
    from pathlib import Path
    page = (Path(__file__).parent.parent / "docs" / "deployed.md").read_text()
    section = page.split("## The controller in C", 1)[1]
    code = section.split("```c\n", 1)[1].split("```", 1)[0]
    assert len(code.strip().splitlines()) <= 25
    files = cg.generate(paper, "c", prefix="arm_", rate_hz=2000.0)
    cg.write_output({k: v for k, v in files.items() if k.startswith("arm_controller")}, tmp_path)
    (tmp_path / "loop.c").write_text(code)
    proc = subprocess.run([GCC, *STRICT_CFLAGS, "-o", "loop", "loop.c", "arm_controller.c", "-lm"], cwd=tmp_path,
                          capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    run = subprocess.run(["./loop"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0
    tau = np.array([line.split() for line in run.stdout.splitlines()], dtype=float)
    assert tau.shape == (10, 2) and np.all(np.isfinite(tau))
    # first call: the design's torque at q = dq = 0, t = 0 with the initial controller state
    ref = casadi_tau(paper, 0.0, np.zeros(2), np.zeros(2), np.zeros(50), np.zeros((51, 2)))[0]
    np.testing.assert_allclose(tau[0], ref, rtol=1e-5)        # printed with %g: 6 significant digits

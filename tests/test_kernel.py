"""The generated controller and step as an SX scalar part plus loops (emit/kernel.py): the structure is read off
the design's graph and checked, the loops agree with the SX functions (also for a mutated design and an N = 200
reservoir), a design without that structure keeps the unrolled code, and the vectorisable tanh keeps its stated
error bound against libm (and a broken one does not)."""

from __future__ import annotations

import copy
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from symfunnel.design import derive
from symfunnel.emit import kernel
from symfunnel.emit.c import template
from symfunnel.emit.check import CLibrary, check_output
from symfunnel.emit.files import generate
from symfunnel.emit.step import etd_factors, projection, step_core
from symfunnel.scenario import from_dict, load_scenario


GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc not available")

#: the error bound of the vectorisable tanh against glibc's, as stated in templates/sf_tanh.h
TANH_ULP, TANH_ABS = 2.0, 2.3e-16


def _native() -> tuple[str, ...]:
    """-O3 -march=native where the compiler takes it (the vectorised tanh), else -O2 with the tanh forced."""
    probe = subprocess.run([GCC, "-march=native", "-E", "-x", "c", "-", "-o", "/dev/null"], input="",
                           capture_output=True, text=True)
    return ("-O3", "-march=native") if probe.returncode == 0 else ("-O2", "-DSYMFUNNEL_FAST_TANH")


def _lib(files: dict, base: str, flags: tuple[str, ...]) -> CLibrary:
    from symfunnel.core.ccompile import compile_cached
    src = {base + ".c": files[base + ".c"], base + ".h": files[base + ".h"]}
    return CLibrary(compile_cached(src, [base + ".c"], f"lib{base}.so",
                                   ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-fPIC", "-shared") + flags)
                    .path)


def _step_points(design, k=64, seed=0):
    rng = np.random.default_rng(seed)
    N = design.sym["x_esn"].numel()
    nr = design.sym["w_hat"].shape[0]
    for _ in range(k):
        t = rng.uniform(0, 20)
        qd, dqd, _ = (np.array(v).ravel() for v in design.reference(t))
        yield (t, qd + rng.normal(0, 0.01, design.n), dqd + rng.normal(0, 0.1, design.n), rng.uniform(-1, 1, N),
               rng.normal(0, 3, (nr, design.n)))


def _step_error(design, lib: CLibrary, name: str, rate: float = 2000.0, tau_max=None) -> tuple[float, bool]:
    """Worst relative difference of the compiled step core from the SX one, and whether x_esn_next was bitwise
    equal at every point."""
    f = lib.function(name)
    core = step_core(design, tau_max)
    etd = np.array(etd_factors(design.scenario, rate))
    worst, same_x = 0.0, True
    for t, q, dq, x, W in _step_points(design):
        got = f(t, q, dq, x, W, etd)
        ref = [np.array(v) for v in core(t, q, dq, x, W, etd)]
        for i, (g, r) in enumerate(zip(got, ref)):
            r = r.reshape(g.shape)
            worst = max(worst, float(np.max(np.abs(g - r))) / max(1.0, float(np.max(np.abs(r)))))
            if i == 1:
                same_x &= bool(np.array_equal(g, r))
    return worst, same_x


def test_paper_gets_loops_and_a_small_file(paper_design):
    """The paper's controller and step have the kernel's form; the file shrinks from ~7,800 to ~1,800 lines."""
    files = generate(paper_design, "c", prefix="arm_", rate_hz=2000.0)
    c = files["arm_controller.c"]
    assert "arm_controller_loops" in c and "arm_step_core_loops" in c and "arm_sk_xdot" in c
    assert c.count("\n") < 2500
    assert kernel.step_kernel(paper_design, None, "arm_", projection(paper_design), step_core(paper_design)).c_W == pytest.approx(
        -paper_design.scenario.gamma * paper_design.scenario.sigma, rel=1e-15)


@needs_gcc
@pytest.mark.parametrize("flags", ["libm", "native"])
def test_step_loops_equal_the_sx_step(paper_design, flags):
    """With libm's tanh the reservoir's x_esn_next is the SX graph's value bit for bit (the loops sum in the graph's
    order), tau and W_hat_next agree to rounding; with the vectorised tanh all agree to 1e-12."""
    files = generate(paper_design, "c", prefix="arm_", rate_hz=2000.0)
    fl = ("-O2", "-DSYMFUNNEL_LIBM_TANH") if flags == "libm" else _native()
    err, same_x = _step_error(paper_design, _lib(files, "arm_controller", fl), "arm_step_core")
    assert err <= 1e-14
    if flags == "libm":
        assert same_x


@needs_gcc
def test_w_x_straight_line_and_as_loops_give_the_same_step(paper_design, monkeypatch):
    """The paper's W x (247 nonzeros) is emitted as straight-line code with the weights as constants; forced to the
    loops over the arrays (UNROLL_W_MAX = 0) the file changes and every output of the step is the same double."""
    from symfunnel.emit import step as step_mod
    from symfunnel.family.esn import ESN
    fl = ("-O2", "-DSYMFUNNEL_LIBM_TANH")
    step_mod._RATE_FREE.clear()
    unrolled = generate(paper_design, "c", prefix="arm_", rate_hz=2000.0)
    monkeypatch.setattr(ESN, "UNROLL_W_MAX", 0)
    step_mod._RATE_FREE.clear()
    loops = generate(paper_design, "c", prefix="arm_", rate_hz=2000.0)
    step_mod._RATE_FREE.clear()
    assert "arm_sk_xdot_Wx[" not in unrolled["arm_controller.c"] and "arm_sk_xdot_Wx[" in loops["arm_controller.c"]
    lib_u, lib_l = _lib(unrolled, "arm_controller", fl), _lib(loops, "arm_controller", fl)
    fu, fl_ = lib_u.function("arm_step_core"), lib_l.function("arm_step_core")
    etd = np.array(etd_factors(paper_design.scenario, 2000.0))
    for t, q, dq, x, W in _step_points(paper_design):
        for a, b in zip(fu(t, q, dq, x, W, etd), fl_(t, q, dq, x, W, etd)):
            assert np.array_equal(np.asarray(a), np.asarray(b))


@needs_gcc
def test_a_mutant_design_gets_its_own_loops(paper):
    """The loops come from the graph: for the flip_sigma mutant (W_hat' = Gamma(Phi (mu2 z2)^T + sigma W_hat)) the
    coefficient c flips sign and the generated step matches the mutant's SX step, not the paper's."""
    d = derive(paper, mutant="flip_sigma")
    k = kernel.step_kernel(d, None, "m_", projection(d), step_core(d))
    assert k is not None and k.c_W == pytest.approx(paper.gamma * paper.sigma, rel=1e-15)
    files = generate(d, "c", prefix="m_", rate_hz=2000.0)
    lib = _lib(files, "m_controller", _native())
    assert _step_error(d, lib, "m_step_core")[0] <= 1e-12
    assert _step_error(derive(paper), lib, "m_step_core")[0] > 1e-10      # and it is not the paper's step


def test_without_the_form_the_step_stays_unrolled(paper_design, monkeypatch):
    """A tau that is not affine in W_hat, or a reservoir rate that is not the ESN's, is refused (the SX function is
    generated instead); so is a design without a reservoir."""
    S = paper_design.signals
    W = paper_design.sym["w_hat"]
    bad = dict(S, tau=S["tau"] + W[0, 0] ** 2)
    assert "not affine" in kernel._form(paper_design, bad["tau"], S["w_hat_dot"], ca.SX.zeros(1))
    d = copy.copy(paper_design)
    d.signals = dict(S, x_esn_dot=2 * S["x_esn_dot"])           # not what the ESN's own dynamics give
    assert kernel.step_kernel(d, None, "", projection(d), step_core(d)) is None
    s = paper_design.sym
    names = list(paper_design.inputs)
    wrong = ca.Function("controller", [s[k] for k in names], [S["tau"], 2 * S["x_esn_dot"], S["w_hat_dot"]], names,
                        ["tau", "x_esn_dot", "w_hat_dot"])
    assert kernel.controller_kernel(paper_design, wrong, "controller", "") is None
    assert kernel.controller_kernel(paper_design, paper_design.controller(), "controller", "") is not None
    rbf = derive(load_scenario(str(__import__("pathlib").Path(__file__).parent.parent / "derivations"
                                   / "ppc_log_rbf.toml")))
    assert kernel.step_kernel(rbf, None, "", projection(rbf), step_core(rbf)) is None
    assert "step_core_loops" not in generate(rbf, "c")["symfunnel_controller.c"]


@needs_gcc
@pytest.mark.slow
def test_a_large_reservoir_compiles_small_and_passes_the_check(paper):
    """N = 200 (the unrolled step would be ~40,000 lines): the generated pair stays under 2,500 lines and passes
    `codegen --check` (controller, step core, main.c over the trajectory) at the C threshold."""
    raw = copy.deepcopy(paper.raw)
    raw["esn"]["size"] = 200
    sc = from_dict(raw, file=paper.file, base_dir=__import__("pathlib").Path(paper.file).parent, default_name="n200")
    d = derive(sc)
    files = generate(d, "c")
    assert files["symfunnel_controller.c"].count("\n") < 2500
    report = check_output(d, "c", files, points=200)
    assert report.passed, report.to_json()
    assert "step_core" in report.errors


def _tanh_harness(tmp_path, header: str, flags: tuple[str, ...]) -> list[list[float]]:
    """Worst ulp and absolute error of the header's tanh against libm's over intervals (C harness, array form)."""
    src = r'''
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#define SYMFUNNEL_FAST_TANH
#include "t.h"
static double ulp(double y) { int e; frexp(y, &e); return ldexp(1.0, e - 53); }
static double X[4096], Y[4096];
static void f_arr(int n) { int i; for (i = 0; i < n; ++i) Y[i] = t_tanh(X[i]); }
static void scan(double lo, double hi, long n) {
  double wu = 0, wa = 0; long i = 0;
  while (i <= n) {
    int m = 0, j;
    for (; m < 4096 && i <= n; ++m, ++i) X[m] = lo + (hi - lo) * ((double) i / (double) n);
    f_arr(m);
    for (j = 0; j < m; ++j) {
      double a = tanh(X[j]), b = Y[j], d = fabs(a - b), u = a != 0 ? d / ulp(a) : (b == 0 && signbit(a) == signbit(b) ? 0 : 1e300);
      if (u > wu) wu = u;
      if (d > wa) wa = d;
    }
  }
  printf("%.17g %.17g %.17g %.17g\n", lo, hi, wu, wa);
}
int main(int argc, char **argv) {
  int k;
  for (k = 1; k + 2 < argc; k += 3) scan(atof(argv[k]), atof(argv[k + 1]), atol(argv[k + 2]));
  X[0] = 0.0; X[1] = -0.0; X[2] = INFINITY; X[3] = -INFINITY; X[4] = NAN; X[5] = 1e308; X[6] = 5e-324; X[7] = -5e-324;
  f_arr(8);
  printf("special %d %d %d %d %d %d %d %d\n", Y[0] == 0 && !signbit(Y[0]), Y[1] == 0 && signbit(Y[1]), Y[2] == 1,
         Y[3] == -1, isnan(Y[4]), Y[5] == 1, Y[6] == 5e-324, Y[7] == -5e-324);
  return 0;
}
'''
    (tmp_path / "h.c").write_text(src)
    (tmp_path / "t.h").write_text(header.replace("@P@", "t_"))
    subprocess.run([GCC, "-std=c99", "-Wall", "-Werror", *flags, "-o", "h", "h.c", "-lm"], cwd=tmp_path, check=True)
    args = ["-25", "25", "5000000", "-6", "6", "2000000", "0.6", "0.65", "500000", "-1e-3", "1e-3", "500000",
            "19", "21", "100000"]
    out = subprocess.run(["./h", *args], cwd=tmp_path, capture_output=True, text=True, check=True).stdout
    lines = out.strip().splitlines()
    assert lines[-1] == "special 1 1 1 1 1 1 1 1", lines[-1]
    return [[float(v) for v in ln.split()] for ln in lines[:-1]]


@needs_gcc
@pytest.mark.parametrize("flags", ["scalar", "native"])
def test_fast_tanh_error_bound(tmp_path, flags):
    """At most 2 ulp and 2.3e-16 from glibc's tanh on [-25, 25] (the interval the reservoir sees is inside
    [-6, 6]), scalar and vectorised; +-0, +-inf, NaN, 1e308 and denormals exact."""
    fl = ("-O2",) if flags == "scalar" else _native()
    for lo, hi, ulp, ab in _tanh_harness(tmp_path, template("sf_tanh.h"), fl):
        assert ulp <= TANH_ULP and ab <= TANH_ABS, (lo, hi, ulp, ab)


@needs_gcc
def test_a_broken_tanh_fails_the_bound(tmp_path):
    """The harness can fail: one Pade coefficient of the exponential cut to 8 digits breaks the bound."""
    good = template("sf_tanh.h")
    bad = good.replace("3.02994407707441961300E-2", "3.0299441E-2")
    assert bad != good
    worst = max(ulp for _, _, ulp, _ in _tanh_harness(tmp_path, bad, ("-O2",)))
    assert worst > TANH_ULP


def test_the_reservoir_stays_inside_the_tested_interval(paper_run):
    """The tanh arguments the paper's reservoir sees along its simulated run lie well inside [-6, 6]."""
    esn = paper_run.design.variant.approximator.esn
    cl = paper_run.closed_loop
    r = paper_run.simulation
    parts = cl.unpack(r.x)
    approx = paper_run.design.variant.approximator
    u_fn = ca.Function("u", [paper_run.design.sym[k] for k in paper_run.design.inputs],
                       [approx.inputs(paper_run.design.sym, paper_run.design.signals)])
    qd, dqd, ddqd = (np.array(v) for v in paper_run.design.reference.map(r.t.size)(r.t.reshape(1, -1)))
    args = {"t": r.t.reshape(1, -1), "q": parts["q"].T, "dq": parts["dq"].T, "qd": qd, "dqd": dqd, "ddqd": ddqd,
            "x_esn": parts["x_esn"].T, "w_hat": np.hstack(list(parts["w_hat"]))}
    u = np.array(u_fn.map(r.t.size)(*[args[k] for k in paper_run.design.inputs]))
    z = esn.W_in @ u + esn.W @ parts["x_esn"].T + esn.b[:, None]
    assert np.all(np.isfinite(z)) and np.max(np.abs(z)) < 6.0

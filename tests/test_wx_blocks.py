"""The reservoir's W x in the generated C by blocks of 4 rows x 1 column with AVX's fused multiply-adds
(family/esn.py, `_wx_blocks`): the step built with it agrees with the SX step to 1e-14 and with the scalar rows to
the fused roundings; a block with a perturbed weight or with its lanes in the wrong rows does not; the strict and
unfused builds keep the scalar rows (the graph's doubles)."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from symfunnel.core.ccompile import compile_cached
from symfunnel.emit.check import CLibrary
from symfunnel.emit.files import generate
from symfunnel.emit.step import step_core

GCC = shutil.which("gcc")
STRICT = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-fPIC", "-shared")
BASE = "wx_controller"


def _has_fma4() -> bool:
    """gcc's -march=native here defines __AVX2__ and __FMA__ (what selects the blocks)."""
    if GCC is None:
        return False
    p = subprocess.run([GCC, "-march=native", "-dM", "-E", "-x", "c", "-", "-o", "-"], input="",
                       capture_output=True, text=True)
    return p.returncode == 0 and "#define __AVX2__ 1" in p.stdout and "#define __FMA__ 1" in p.stdout


needs_fma4 = pytest.mark.skipif(not _has_fma4(), reason="no gcc with AVX2 and FMA under -march=native here")


def _files(design) -> dict:
    return generate(design, "c", prefix="wx_", rate_hz=2000.0)


def _step(files: dict, flags: tuple[str, ...]):
    src = {k: files[k] for k in (BASE + ".c", BASE + ".h")}
    return CLibrary(compile_cached(src, [BASE + ".c"], f"lib{BASE}.so", STRICT + flags).path).function("wx_step_core")


def _points(design, k=48, seed=3):
    """States and weights drawn independently of the generator; etd = (1, 1) makes x_esn_next = x + x_esn_dot."""
    rng = np.random.default_rng(seed)
    N, nr = design.sym["x_esn"].numel(), design.sym["w_hat"].shape[0]
    for _ in range(k):
        t = rng.uniform(0, 20)
        qd, dqd, _ = (np.array(v).ravel() for v in design.reference(t))
        yield (t, qd + rng.normal(0, 0.01, design.n), dqd + rng.normal(0, 0.1, design.n), rng.uniform(-1, 1, N),
               rng.normal(0, 3, (nr, design.n)), np.ones(2))


def _worst(design, f) -> float:
    """Worst difference of the compiled x_esn_next (= x + x_esn_dot) from the SX step's, relative to max(1, |.|)."""
    core = step_core(design)
    worst = 0.0
    for args in _points(design):
        got, ref = np.asarray(f(*args)[1]).ravel(), np.asarray(core(*args)[1]).ravel()
        worst = max(worst, float(np.max(np.abs(got - ref))) / max(1.0, float(np.max(np.abs(ref)))))
    return worst


def test_the_blocks_hold_every_nonzero_of_w_once(paper_design):
    """The generated blocks, read back from the C text, rebuild W exactly (row 4g + lane, the broadcast column)."""
    from symfunnel.emit.kernel import _esn_states
    W = np.asarray(_esn_states(paper_design)[0].W)
    c = _files(paper_design)[BASE + ".c"]
    body = c[c.index("/* W x by blocks of 4 rows"):c.index("#else", c.index("/* W x by blocks of 4 rows"))]
    got, j = np.zeros((W.shape[0] + 3) // 4 * 4 * W.shape[1]).reshape(-1, W.shape[1]), None
    n_fma = 0
    for line in body.split(";"):
        m = re.search(r"xj = _mm256_set1_pd\(x\[(\d+)\]\)", line)
        if m:
            j = int(m.group(1))
        m = re.search(r"s(\d+) = _mm256_fmadd_pd\(_mm256_setr_pd\(([^)]*)\), xj, s\1\)", line)
        if m:
            n_fma += 1
            g = int(m.group(1))
            got[4 * g:4 * g + 4, j] += [float(v) for v in m.group(2).split(",")]
    assert np.array_equal(got[:W.shape[0]], W) and not got[W.shape[0]:].any()
    assert n_fma < np.count_nonzero(W)            # paper: 204 blocks for 247 nonzeros


@needs_fma4
def test_fused_blocks_agree_with_the_sx_step_and_broken_blocks_do_not(paper_design):
    files = _files(paper_design)
    assert "#define wx_sk_xdot_FMA4 1" in files[BASE + ".c"]
    native = ("-O3", "-march=native")
    assert _worst(paper_design, _step(files, native)) <= 1e-14
    # the same file with the scalar rows: a different build, the same step to the fused roundings
    fused, scalar = _step(files, native), _step(files, native + ("-DSYMFUNNEL_SCALAR_WX",))
    for args in _points(paper_design, k=8):
        a, b = np.asarray(fused(*args)[1]), np.asarray(scalar(*args)[1])
        assert np.max(np.abs(a - b)) <= 1e-15 * max(1.0, float(np.max(np.abs(b))))
    c = files[BASE + ".c"]
    lines = [m for m in re.finditer(r"_mm256_setr_pd\(([^)]*)\)", c)]
    target = next(m for m in lines if sum(float(v) != 0.0 for v in m.group(1).split(",")) >= 2)
    vals = target.group(1).split(", ")
    perturbed = vals[:]
    k = next(i for i, v in enumerate(vals) if float(v) != 0.0)
    perturbed[k] = repr(float(vals[k]) * (1 + 1e-9))                    # one weight off by 1e-9 relative
    rotated = vals[1:] + vals[:1]                                       # the group's lanes in the wrong rows
    for bad in (perturbed, rotated):
        mutant = dict(files)
        mutant[BASE + ".c"] = c[:target.start(1)] + ", ".join(bad) + c[target.end(1):]
        assert _worst(paper_design, _step(mutant, native)) > 1e-12


@pytest.mark.skipif(GCC is None, reason="gcc not available")
@pytest.mark.parametrize("flags", [("-O2",), ("-O3", "-march=native", "-DSYMFUNNEL_NO_FMA")])
def test_strict_and_unfused_builds_keep_the_scalar_rows(paper_design, flags):
    """Without AVX2 + FMA (plain x86-64 -O2) or with -DSYMFUNNEL_NO_FMA the file compiles the scalar rows: the
    same doubles as the build forced to them, and the SX step to 1e-14."""
    if "-march=native" in flags and not _has_fma4():
        pytest.skip("no -march=native with AVX2 and FMA here")
    files = _files(paper_design)
    f, g = _step(files, flags), _step(files, flags + ("-DSYMFUNNEL_SCALAR_WX",))
    for args in _points(paper_design, k=8):
        for a, b in zip(f(*args), g(*args)):
            assert np.array_equal(np.asarray(a), np.asarray(b))
    assert _worst(paper_design, f) <= 1e-14


def _blocks_of(W: np.ndarray) -> int:
    """Blocks of 4 rows x 1 column of W holding a nonzero, counted from W itself."""
    i, j = np.nonzero(W)
    return len(set(zip(j.tolist(), (i // 4).tolist())))


def test_blocks_only_up_to_their_limit():
    """N = 80 (566 blocks) gets the blocks, N = 110 (1,030, past WX_BLOCKS_MAX = 600: 4x the constants of the
    scalar rows, measured slower there) keeps the scalar rows only."""
    from symfunnel.family.esn import ESN, ESNConfig, WX_BLOCKS_MAX
    for size, blocked in ((80, True), (110, False)):
        esn = ESN(ESNConfig(size=size), 8)
        c = esn.xdot_c("r_xdot")
        assert (_blocks_of(np.asarray(esn.W)) <= WX_BLOCKS_MAX) is blocked
        assert c.count("_mm256_fmadd_pd(") == (_blocks_of(np.asarray(esn.W)) if blocked else 0)
        assert c.count("    s += ") == np.count_nonzero(esn.W)


@needs_fma4
def test_blocks_in_two_passes_agree_with_the_sx_xdot(tmp_path):
    """N = 80: 20 groups of rows in two passes (12 + 8 sums in registers); with libm's tanh the compiled x_dot
    agrees with the SX x_dot (`ESN.xdot_numpy`) to 1e-14 at random states and inputs."""
    import ctypes
    from symfunnel.emit.c import template
    from symfunnel.family.esn import ESN, ESNConfig
    esn = ESN(ESNConfig(size=80, seed=4), 8)
    c = esn.xdot_c("r_xdot", tanh="r_tanh")
    assert c.count("/* rows ") == 2
    src = "\n".join(["#include <math.h>", "#include <stdint.h>", "#include <string.h>",
                     template("sf_tanh.h").replace("@P@", "r_"), c,
                     "void run(const double *x, const double *u, double *out) { r_xdot(x, u, out); }"])
    so = tmp_path / "libr.so"
    (tmp_path / "r.c").write_text(src, encoding="utf-8")
    subprocess.run([GCC, *STRICT, "-O3", "-march=native", "-DSYMFUNNEL_LIBM_TANH", "-o", str(so),
                    str(tmp_path / "r.c"), "-lm"], check=True, capture_output=True)
    run = ctypes.CDLL(str(so)).run
    rng = np.random.default_rng(5)
    P = ctypes.POINTER(ctypes.c_double)
    for _ in range(16):
        x, u, out = rng.uniform(-1, 1, 80), rng.normal(0, 2, 8), np.zeros(80)
        run(x.ctypes.data_as(P), u.ctypes.data_as(P), out.ctypes.data_as(P))
        ref = esn.xdot_numpy(x, u)
        assert np.max(np.abs(out - ref)) <= 1e-14 * max(1.0, float(np.max(np.abs(ref))))

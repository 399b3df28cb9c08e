"""The generated C's vectorisable tanh (templates/sf_tanh.h, one division per lane) against a correctly rounded
reference: numpy's longdouble tanh (64-bit significand), itself checked against mpmath here, at seeded random points
over both branches and at every seam (0.625, the exp's reduction boundaries, the clamp at 20, subnormals, +-0),
fused and unfused; a perturbed coefficient and an inverted branch select fail the same check."""

from __future__ import annotations

import ctypes
import shutil
import subprocess

import mpmath
import numpy as np
import pytest

from symfunnel.emit.c import template

GCC = shutil.which("gcc")
pytestmark = pytest.mark.skipif(GCC is None, reason="gcc not available")

#: the bound stated in templates/sf_tanh.h against the exact tanh
TANH_EXACT_ULP, TANH_EXACT_ABS = 1.8, 2.0e-16

_SRC = r'''
#include <math.h>
#include <stdint.h>
#include <string.h>
#define SYMFUNNEL_FAST_TANH
#include "t.h"
void arr(const double *x, double *y, long n) { long i; for (i = 0; i < n; ++i) y[i] = t_tanh(x[i]); }
'''


def _compiled(tmp_path, header: str, flags: tuple[str, ...], tag: str):
    """The header's tanh over an array, as a numpy function (one shared library per build)."""
    d = tmp_path / tag
    d.mkdir()
    (d / "t.h").write_text(header.replace("@P@", "t_"))
    (d / "a.c").write_text(_SRC)
    subprocess.run([GCC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-fPIC", "-shared", *flags,
                    "-o", "a.so", "a.c", "-lm"], cwd=d, check=True)
    lib = ctypes.CDLL(str(d / "a.so"))

    def f(x):
        x = np.ascontiguousarray(x, dtype=float)
        y = np.empty_like(x)
        lib.arr(x.ctypes.data_as(ctypes.c_void_p), y.ctypes.data_as(ctypes.c_void_p), ctypes.c_long(x.size))
        return y
    return f


def _points(seed: int = 0, k: int = 200_000) -> np.ndarray:
    """Seeded random points over [-25, 25], log-uniform magnitudes down to subnormals, and dense neighbourhoods of
    each seam: the branch switch 0.625, the clamp 20, tanh = 1 from 19.06, and the a where -2a / ln 2 crosses
    k + 1/2 (exp(-2a)'s reduction changes k there), each with its 300 nearest doubles on both sides."""
    rng = np.random.default_rng(seed)
    ln2 = float(mpmath.log(2))
    reduction = [(j + 0.5) * ln2 / 2 for j in range(1, 59)]
    seams = np.array([0.625, 20.0, 19.06, 2.0 ** -1022] + reduction)
    near = list(seams)
    for s in seams:
        lo = hi = s
        for _ in range(300):
            lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)
            near += [lo, hi]
    mags = np.exp(rng.uniform(np.log(5e-324), np.log(25.0), k))
    x = np.concatenate([rng.uniform(-25, 25, k), rng.uniform(0.62, 0.63, k), mags, np.array(near),
                        [0.0, 5e-324, 2.2250738585072009e-308, 1e-300, 1e-8, 0.3, 0.625, 1.0, 19.0615, 20.0, 25.0]])
    return np.concatenate([x, -x])


def _ld_tanh(x: np.ndarray) -> np.ndarray:
    """numpy's longdouble tanh of x, computed in a fresh interpreter: codac and python-flint set the x87 FPU to
    double precision for the rest of a process (measured: the longdouble tanh then errs by 3.3 double ulps), and a
    test worker may have loaded them before this module's tests run."""
    import sys
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        src, dst = f"{d}/x.npy", f"{d}/y.npy"
        np.save(src, np.asarray(x, float))
        subprocess.run([sys.executable, "-c", "import sys, numpy as np; "
                        "np.save(sys.argv[2], np.tanh(np.load(sys.argv[1]).astype(np.longdouble)))", src, dst],
                       check=True)
        return np.load(dst)


def _errors(y: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Worst error in ulps of the reference and worst absolute error, against longdouble tanh."""
    ref = _ld_tanh(x)
    _, e = np.frexp(ref)
    ulp = np.ldexp(np.longdouble(1), np.maximum(e, -1021) - 53)
    err = np.abs(y.astype(np.longdouble) - ref)
    return float(np.max(err / ulp)), float(np.max(err))


def test_the_roundoff_analysis_factor_covers_the_stated_bound():
    """sx.roundoff multiplies u |r| by ROUNDOFF_SAFETY per operation; the C tanh's stated bound in relative terms
    (an ulp of r is at most 2 u |r|) must stay inside it, or that analysis understates the generated code."""
    from symfunnel.sx.roundoff import ROUNDOFF_SAFETY
    assert 2.0 * TANH_EXACT_ULP <= ROUNDOFF_SAFETY


def test_longdouble_reference_is_correctly_rounded_to_double_precision():
    """The reference itself: numpy's longdouble tanh within 0.01 double ulp of mpmath's at 2,000 seeded points."""
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-25, 25, 1000), rng.uniform(0.62, 0.63, 500), np.exp(rng.uniform(-700, 3, 500))])
    mpmath.mp.prec = 120
    worst = 0.0
    for v, ld in zip(x, _ld_tanh(x)):
        hi = float(ld)
        lo = float(ld - np.longdouble(hi))
        exact = mpmath.tanh(mpmath.mpf(float(v)))
        ulp = mpmath.ldexp(1, int(np.frexp(ld)[1]) - 53)
        worst = max(worst, float(abs(mpmath.mpf(hi) + mpmath.mpf(lo) - exact) / ulp))
    assert worst < 0.01


@pytest.mark.parametrize("flags", [("-O2",), ("-O3", "-march=native"), ("-O3", "-march=native", "-DSYMFUNNEL_NO_FMA")],
                         ids=["scalar", "native", "native-unfused"])
def test_tanh_within_its_stated_bound_of_the_exact_tanh(tmp_path, flags):
    """At most 1.8 ulp and 2.0e-16 absolute from the exact tanh at every point and seam; special values exact."""
    if "-march=native" in flags and subprocess.run([GCC, "-march=native", "-E", "-x", "c", "-", "-o", "/dev/null"],
                                                   input="", capture_output=True, text=True).returncode:
        pytest.skip("gcc does not take -march=native here")
    header = template("sf_tanh.h")
    assert "1.8 ulp and 2.0e-16" in header
    f = _compiled(tmp_path, header, flags, "t")
    x = _points()
    ulps, ab = _errors(f(x), x)
    assert ulps <= TANH_EXACT_ULP and ab <= TANH_EXACT_ABS, (ulps, ab)
    special = f(np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e308, 5e-324, -5e-324, -1e-310]))
    assert special[0] == 0 and not np.signbit(special[0]) and special[1] == 0 and np.signbit(special[1])
    assert special[2] == 1 and special[3] == -1 and np.isnan(special[4]) and special[5] == 1
    assert special[6] == 5e-324 and special[7] == -5e-324 and special[8] == -1e-310


@pytest.mark.parametrize("old, new", [
    ("-9.64399179425052238628E-1", "-9.6439918E-1"),          # small branch: a coefficient cut to 8 digits
    ("2.27265548208155028766E-1", "2.2726555E-1"),            # the exp's Pade denominator, cut to 8 digits
    ("m = -(int64_t) (ab < B0625);", "m = -(int64_t) (ab >= B0625);"),   # branch select inverted
    ("n = -2.0 * B;", "n = -2.0 * A;"),                             # the large branch's numerator on the wrong term
], ids=["small-coefficient", "pade-coefficient", "select-inverted", "numerator"])
def test_a_mutated_tanh_fails_the_bound(tmp_path, old, new):
    """The check can fail: each mutant of the header exceeds the stated bound somewhere on the same points."""
    good = template("sf_tanh.h")
    assert good.count(old) == 1
    f = _compiled(tmp_path, good.replace(old, new), ("-O2",), "m")
    x = _points(k=20_000)
    ulps, _ = _errors(f(x), x)
    assert ulps > TANH_EXACT_ULP


@pytest.mark.slow
def test_tanh_bound_over_ten_million_points(tmp_path):
    """The header's measurement: >= 10^7 points (both signs, all seams), native build, the stated bound."""
    if subprocess.run([GCC, "-march=native", "-E", "-x", "c", "-", "-o", "/dev/null"], input="",
                      capture_output=True, text=True).returncode:
        pytest.skip("gcc does not take -march=native here")
    f = _compiled(tmp_path, template("sf_tanh.h"), ("-O3", "-march=native"), "big")
    x = _points(seed=7, k=1_700_000)
    assert x.size >= 10_000_000
    ulps, ab = _errors(f(x), x)
    assert ulps <= TANH_EXACT_ULP and ab <= TANH_EXACT_ABS, (ulps, ab)

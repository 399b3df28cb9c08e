"""Generated code (C and Python) against CasADi: compile flags, sanitizers, cache, determinism, agreement, AD check."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import textwrap

import casadi as ca
import numpy as np
import pytest

from symfunnel import emit as cg
from symfunnel.core import ccompile as build
from symfunnel.emit import check
from symfunnel.emit.c import STRICT_CFLAGS, parse_trajectory_output
from symfunnel.emit.contract import trajectory_inputs
from symfunnel.scenario import load_scenario

from .conftest import private_cache

GCC = shutil.which("gcc")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc not available")
BASE = cg.BASENAME


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A private compile cache for this module (so cache hits and misses are ours)."""
    yield from private_cache(tmp_path_factory)


@pytest.fixture(scope="module")
def design(paper_run):
    return paper_run.design


@pytest.fixture(scope="module")
def c_files(paper_run):
    return paper_run.code("c")


@pytest.fixture(scope="module")
def py_files(paper_run):
    return paper_run.code("python")


@pytest.fixture(scope="module")
def c_dir(c_files, tmp_path_factory):
    out = tmp_path_factory.mktemp("ctl")
    cg.write_output(c_files, out)
    return out


@pytest.fixture(scope="module")
def py_module(py_files, tmp_path_factory):
    out = tmp_path_factory.mktemp("ctlpy")
    cg.write_output(py_files, out)
    return check.load_python_module(out / f"{BASE}.py")


@pytest.fixture(scope="module")
def c_lib(c_files, cache):
    return check.CLibrary(check.c_library(c_files[f"{BASE}.c"], c_files[f"{BASE}.h"], BASE).path)


@pytest.fixture(scope="module")
def points(design):
    return check.sample_points(design, 1000, seed=7)


def casadi_tau(design, inputs):
    return check.casadi_values(design.controller(), inputs)[0][:, 0, :].T        # (k, n)


# --- the contract -------------------------------------------------------------------------------------

def test_manifest_matches_contract(c_files, py_files, design):
    for files, lang in ((c_files, "c"), (py_files, "python")):
        m = json.loads(files["manifest.json"])
        assert m["language"] == lang and m["scenario"] == "paper"
        names = [f["name"] for f in m["functions"]]
        assert names == ["funnels", "errors", "alpha2", "alpha2_dot", "controller"]
        by = {f["name"]: f for f in m["functions"]}
        assert [i["name"] for i in by["alpha2"]["inputs"]] == ["t", "q", "qd", "dqd"]
        assert [i["name"] for i in by["alpha2_dot"]["inputs"]] == ["t", "q", "dq", "qd", "dqd", "ddqd"]
        assert [i["name"] for i in by["controller"]["inputs"]] == list(
            ("t", "q", "dq", "qd", "dqd", "ddqd", "x_esn", "w_hat"))
        assert [o["name"] for o in by["controller"]["outputs"]] == ["tau", "x_esn_dot", "w_hat_dot"]
        assert by["controller"]["inputs"][7]["shape"] == [51, 2]
        assert by["alpha2"]["outputs"][0]["shape"] == [2, 1]
        listed = {f["name"] for f in m["files"]}
        assert listed == set(files) - {"manifest.json"}
        text = files["manifest.json"]
        assert "/tmp" not in text and "/home" not in text and "/work" not in text
        assert not re.search(r"20\d\d-\d\d-\d\d", text)               # no timestamps


def test_python_module_manifest_and_order_agree(py_module, c_files):
    m = json.loads(c_files["manifest.json"])
    # the contract functions in manifest order, then the deployed step's reference and step_core
    assert list(py_module.FUNCTIONS) == [f["name"] for f in m["functions"]] + ["reference", "step_core"]
    for entry, mine in zip(m["functions"], py_module.MANIFEST):
        assert entry["name"] == mine["name"]
        assert entry["inputs"] == mine["inputs"] and entry["outputs"] == mine["outputs"]


def test_regenerating_gives_identical_bytes(c_files, py_files, tmp_path):
    from symfunnel.pipeline import Run
    run2 = Run(load_scenario("paper"))             # fresh SX objects, a fresh simulation
    for lang, files in (("c", c_files), ("python", py_files)):
        again = run2.code(lang)
        assert again == files
        a, b = tmp_path / f"{lang}1", tmp_path / f"{lang}2"
        cg.write_output(files, a)
        cg.write_output(again, b)
        for name in files:
            assert (a / name).read_bytes() == (b / name).read_bytes()


# --- C ------------------------------------------------------------------------------------------------

def test_c_uses_static_memory_and_casadi_api(c_files):
    src, hdr = c_files[f"{BASE}.c"], c_files[f"{BASE}.h"]
    assert not re.search(r"\b(malloc|calloc|realloc|free|alloca)\s*\(", src)
    assert "casadi/mem.h" not in src + hdr and "#include <casadi" not in src + hdr
    for name in ("funnels", "errors", "alpha2", "alpha2_dot", "controller"):
        for suffix in ("", "_work", "_incref", "_decref", "_checkout", "_release", "_n_in", "_n_out",
                       "_sparsity_in", "_sparsity_out", "_name_in"):
            assert re.search(rf"\b{name}{suffix}\(", hdr), name + suffix
        assert f"#define {name}_SZ_W" in hdr
    # CSE: the controller's tape is far smaller than its expression tree
    assert len(src.splitlines()) < 10000


@needs_gcc
def test_strict_gcc_command_is_warning_free(c_dir):
    cmd = [GCC, *STRICT_CFLAGS, "-o", "symfunnel_main", "main.c", f"{BASE}.c", "-lm"]
    assert " ".join(cmd[1:7]) == "-std=c99 -Wall -Wextra -Werror -pedantic -O2"
    proc = subprocess.run(cmd, cwd=c_dir, capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    proc = subprocess.run([GCC, *STRICT_CFLAGS, "-c", "-o", "bench.o", "bench.c"], cwd=c_dir,
                          capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


@needs_gcc
def test_main_under_asan_ubsan_gives_casadi_torques(c_dir, design, c_files, tmp_path):
    exe = tmp_path / "main_asan"
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1", "-g", "-fno-omit-frame-pointer",
             "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    proc = subprocess.run([GCC, *flags, "-o", str(exe), "main.c", f"{BASE}.c", "-lm"], cwd=c_dir,
                          capture_output=True, text=True)
    if proc.returncode != 0 and "asan" in proc.stderr.lower():
        pytest.skip("sanitizer runtime not available")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    run = subprocess.run([str(exe), "trajectory.txt"], cwd=c_dir, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    rows = parse_trajectory_output(run.stdout)
    inputs = trajectory_inputs(design, c_files["trajectory.txt"])
    tau = casadi_tau(design, inputs)
    assert rows.shape == (tau.shape[0], 1 + design.n) and tau.shape[0] == 50
    np.testing.assert_array_equal(rows[:, 0], inputs["t"][0, 0])
    assert np.max(np.abs(rows[:, 1:] - tau) / np.maximum(1, np.abs(tau))) <= 1e-12


@needs_gcc
@pytest.mark.skipif(shutil.which("make") is None, reason="make not available")
def test_makefile_builds_and_runs(c_dir, tmp_path):
    work = tmp_path / "ctl"
    shutil.copytree(c_dir, work)
    proc = subprocess.run(["make", "CC=" + GCC], cwd=work, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "warning" not in proc.stderr.lower()
    run = subprocess.run(["./symfunnel_main", "trajectory.txt"], cwd=work, capture_output=True, text=True)
    assert run.returncode == 0 and len(parse_trajectory_output(run.stdout)) == 50


@needs_gcc
def test_check_c_at_1000_points(design, c_files, cache, points):
    report = cg.check_output(design, "c", c_files, pts=points)
    assert set(report.errors) == {"funnels", "errors", "alpha2", "alpha2_dot", "controller", "step_core"}
    assert report.points == 1000
    assert report.worst <= 1e-12 and report.passed, report.to_json()


@needs_gcc
def test_c_matches_casadi_near_funnel_boundary(design, c_lib):
    """Same libm as CasADi: agreement holds even at 98 % of the funnels, where the controller is ill-conditioned."""
    pts = check.sample_points(design, 1000, seed=3, fill=0.98)
    report = check.check_c(cg.contract_functions(design), c_lib.path, pts)
    assert report.worst <= 1e-12, report.errors


@needs_gcc
def test_compiled_once_and_cached(c_files, cache):
    a = check.c_library(c_files[f"{BASE}.c"], c_files[f"{BASE}.h"], BASE)
    b = check.c_library(c_files[f"{BASE}.c"], c_files[f"{BASE}.h"], BASE)
    assert b.cached and b.path == a.path and b.key == a.key
    assert str(b.path).startswith(str(cache))
    mtime = b.path.stat().st_mtime_ns
    c = check.c_library(c_files[f"{BASE}.c"], c_files[f"{BASE}.h"], BASE)
    assert c.cached and c.path.stat().st_mtime_ns == mtime
    changed = build.compile_cached({"x.c": "int f(void) { return 1; }\n"}, ["x.c"], "libx.so",
                                   build.SHARED_FLAGS)
    changed2 = build.compile_cached({"x.c": "int f(void) { return 2; }\n"}, ["x.c"], "libx.so",
                                    build.SHARED_FLAGS)
    assert changed.key != changed2.key and not changed2.cached


@needs_gcc
def test_compile_errors_are_reported(cache):
    with pytest.raises(RuntimeError, match="compiling"):
        build.compile_cached({"bad.c": "int f(void) { return }\n"}, ["bad.c"], "libbad.so", build.SHARED_FLAGS)
    assert not any(p.name.startswith(".") for p in cache.iterdir())    # no leftover temp dirs


# --- Python and cross-language agreement --------------------------------------------------------------

def test_check_python_at_1000_points(design, py_files, points):
    report = cg.check_output(design, "python", py_files, pts=points)
    assert report.points == 1000
    assert report.worst <= 1e-10 and report.passed, report.to_json()


@needs_gcc
def test_c_and_python_agree(design, c_lib, py_module, points):
    k = 200
    pts = {n: a[:, :, :k] for n, a in points.items()}
    for f in cg.contract_functions(design):
        names = [f.name_in(i) for i in range(f.n_in())]
        got_py = getattr(py_module, f.name())(*[pts[n] for n in names])
        cf = c_lib.function(f.name())
        for j in range(0, k, 7):
            got_c = cf(*[pts[n][:, :, j] for n in names])
            for a, b in zip(got_c, got_py):
                err = check.relative_error(a, b[:, :, j])
                assert err.max() <= 1e-10, (f.name(), j, err)


@pytest.mark.parametrize("lang", ["python", "c"])
def test_alpha2_dot_is_the_derivative_of_alpha2_along_the_flow(design, lang, py_module, request):
    """d/dh alpha2(t + h, q + h dq, qd(t + h), dqd(t + h)) at h = 0 equals alpha2_dot(t, q, dq, qd, dqd, ddqd)."""
    if lang == "c":
        if GCC is None:
            pytest.skip("gcc not available")
        lib = request.getfixturevalue("c_lib")
        a2c, a2dc = lib.function("alpha2"), lib.function("alpha2_dot")

        def alpha2(t, q, qd, dqd):
            return a2c(t, q, qd, dqd)[0]

        def alpha2_dot(*args):
            return a2dc(*args)[0]
    else:
        def alpha2(t, q, qd, dqd):
            return py_module.alpha2(t, q, qd, dqd)[0]

        def alpha2_dot(*args):
            return py_module.alpha2_dot(*args)[0]

    pts = check.sample_points(design, 60, seed=11, fill=0.8)
    ref = design.reference
    worst = 0.0
    for j in range(60):
        t = float(pts["t"][0, 0, j])
        q, dq = pts["q"][:, 0, j], pts["dq"][:, 0, j]
        qd, dqd, ddqd = (np.array(v).ravel() for v in ref(t))
        exact = np.asarray(alpha2_dot(np.array([[t]]), q, dq, qd, dqd, ddqd)).ravel()

        def g(h):
            qd_h, dqd_h, _ = (np.array(v).ravel() for v in ref(t + h))
            return np.asarray(alpha2(np.array([[t + h]]), q + h * dq, qd_h, dqd_h)).ravel()

        # step small against the distance to the funnel boundary, which alpha2 is singular at
        F1, dF1 = (np.array(v).ravel() for v in design.function("F", ["t"], ["F1", "dF1"])(t))
        gap = np.min(F1 - np.abs(q - qd))
        speed = np.max(np.abs(dq - dqd) + np.abs(dF1)) + 1.0
        h = 1e-2 * gap / speed
        # Richardson-extrapolated central differences: error O(h^4)
        d1 = (g(h) - g(-h)) / (2 * h)
        d2 = (g(h / 2) - g(-h / 2)) / h
        fd = (4 * d2 - d1) / 3
        worst = max(worst, float(np.max(np.abs(fd - exact) / np.maximum(1.0, np.abs(exact)))))
    assert worst < 1e-7, worst


# --- numpy alone --------------------------------------------------------------------------------------

BLOCKER = textwrap.dedent("""
    import importlib.abc, sys
    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.split(".")[0] in ("casadi", "sympy", "symfunnel"):
                raise ImportError("blocked: " + name)
            return None
    sys.meta_path.insert(0, Block())
    for m in [m for m in sys.modules if m.split(".")[0] in ("casadi", "sympy", "symfunnel")]:
        del sys.modules[m]
""")


def test_python_module_needs_numpy_only(tmp_path, py_files, design, c_files):
    out = tmp_path / "ctlpy"
    cg.write_output(py_files, out)
    code = BLOCKER + textwrap.dedent(f"""
        import json, runpy, sys
        sys.path.insert(0, {str(out)!r})
        try:
            import casadi
        except ImportError:
            pass
        else:
            raise SystemExit("casadi importable")
        import symfunnel_controller as m
        assert "casadi" not in sys.modules and "sympy" not in sys.modules
        (a,) = m.alpha2([[0.5]], [0.1, 0.2], [0.12, 0.19], [0.2, 0.3])
        print(json.dumps(a.ravel().tolist()))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    got = np.array(json.loads(proc.stdout))
    ref = np.array(design.function("alpha2", ["t", "q", "qd", "dqd"])(0.5, [0.1, 0.2], [0.12, 0.19],
                                                                         [0.2, 0.3])).ravel()
    np.testing.assert_allclose(got, ref, rtol=1e-13)

    # the example runner over the recorded trajectory, with numpy alone, gives CasADi's torques
    run = BLOCKER + "import runpy, sys; sys.argv = ['run_trajectory.py', 'trajectory.txt']; " \
        "runpy.run_path('run_trajectory.py', run_name='__main__')"
    proc = subprocess.run([sys.executable, "-c", run], cwd=out, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = parse_trajectory_output(proc.stdout)
    tau = casadi_tau(design, trajectory_inputs(design, py_files["trajectory.txt"]))
    assert rows.shape == (50, 1 + design.n)
    assert np.max(np.abs(rows[:, 1:] - tau) / np.maximum(1, np.abs(tau))) <= 1e-10


def test_trajectory_stays_in_funnels_and_is_shared(design, c_files, py_files):
    assert c_files["trajectory.txt"] == py_files["trajectory.txt"]
    inp = trajectory_inputs(design, c_files["trajectory.txt"])
    f = design.function("lv", ["t", "q", "dq", "qd", "dqd"], ["e1", "F1", "e2", "F2"])
    e1, F1, e2, F2 = check.casadi_values(f, inp)
    assert np.all(np.abs(e1) < F1) and np.all(np.abs(e2) < F2)
    # reference columns are the scenario's reference at t
    qd = check.casadi_values(ca.Function("r", [design.sym["t"]], [design.reference_t["qd"]], ["t"], ["qd"]),
                             {"t": inp["t"]})[0]
    np.testing.assert_allclose(inp["qd"], qd, rtol=0, atol=1e-15)


def test_relative_error_measure():
    a = np.zeros((2, 1, 3))
    b = a.copy()
    b[0, 0, 1] = 1e-3
    b[1, 0, 2] = 200.0
    a[1, 0, 2] = 200.0 * (1 + 1e-12)
    e = check.relative_error(a, b)
    assert e[0] == 0 and e[1] == pytest.approx(1e-3) and e[2] == pytest.approx(1e-12)
    nan = np.full((1, 1, 1), np.nan)
    assert check.relative_error(nan, nan)[0] == 0
    assert check.relative_error(nan, np.zeros((1, 1, 1)))[0] == np.inf


# --- report and bench ---------------------------------------------------------------------------------

@needs_gcc
def test_codegen_summary_for_the_report(paper_run, cache):
    s = cg.codegen_summary(paper_run.design, paper_run.code_trajectory)
    json.dumps(s, allow_nan=False)
    assert s["points"] >= 1000 and s["controller_operations"] > 1000
    assert [f["name"] for f in s["functions"]] == ["funnels", "errors", "alpha2", "alpha2_dot", "controller"]
    for lang, limit in (("c", 1e-12), ("python", 1e-10)):
        entry = s["languages"][lang]
        assert entry["check"]["passed"] and entry["check"]["worst"] <= limit
        assert all(f["bytes"] > 0 for f in entry["files"])


@needs_gcc
@pytest.mark.slow
def test_bench_area_reports_c_vm_and_python(cache, monkeypatch):
    from symfunnel.bench import codegen as bench
    monkeypatch.setenv("SYMFUNNEL_BENCH_LARGE_N", "60")          # the N = 500 compile's mechanics, at a test's size
    res = {r["id"]: r for r in bench.run(lambda s: None)}
    big = res["codegen.c_compile_n500_s"]
    assert big["unit"] == "CPU s" and big["value"] > 0 and big["baseline_finished"] and big["esn_units"] == 60
    assert big["lines"] < big["baseline_lines"] and big["ratio"] == pytest.approx(big["baseline_value"] / big["value"])
    c = res["codegen.c_controller_ns"]
    assert c["unit"] == "ns" and c["baseline"].startswith("casadi VM") and c["value"] > 0
    assert c["ratio"] == pytest.approx(c["baseline_value"] / c["value"])
    assert c["operations"] == res["codegen.controller_ops"]["value"] > 1000
    assert c["value"] < c["baseline_value"]                    # compiled C beats the VM called from Python
    assert c["unrolled_c_ns"] > 0 and "-O" in c["flags"]
    assert res["codegen.python_controller_ns"]["value"] > 0
    g = res["codegen.rate_search_generate_s"]                 # paired in the same run; the figures, not a target
    assert g["unit"] == "CPU s" and g["value"] > 0 and g["baseline_value"] > 0 and len(g["rates"]) == 7
    assert g["ratio"] == pytest.approx(g["baseline_value"] / g["value"])

"""The deployed controller as an FMI 2.0 Co-Simulation FMU (issue 41), checked by a real client (FMPy): validation,
the closed loop against our own sampled loop, refused communication steps, FMU state, a build from sources/ alone."""

from __future__ import annotations

import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

fmpy = pytest.importorskip("fmpy")
from fmpy.fmi1 import FMICallException  # noqa: E402
from fmpy.validation import validate_fmu  # noqa: E402

from symfunnel.core.ccompile import SHARED_FLAGS, compile_cached  # noqa: E402
from symfunnel.deployed.fmu import FmuController, check_fmu  # noqa: E402
from symfunnel.deployed.loop import StepLibrary, simulate_sampled  # noqa: E402
from symfunnel.design import derive  # noqa: E402
from symfunnel.emit.files import generate  # noqa: E402
from symfunnel.emit.fmu import build_fmu, fmu_platform, fmu_sources  # noqa: E402
from symfunnel.emit.step import step_states  # noqa: E402
from symfunnel.scenario import load_scenario  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
GCC = shutil.which("gcc")
pytestmark = pytest.mark.skipif(GCC is None, reason="gcc not available")

#: the scenarios of the family the FMU is built for: the two shipped robots, one without an approximator, RBF + log
SCENARIOS = {"paper": "paper", "arm7": "arm7", "none": str(REPO / "tests" / "data" / "certify_none.toml"),
             "rbf": str(REPO / "derivations" / "ppc_log_rbf.toml")}
RATE = 2000.0


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """{key: (scenario, design, FmuSources, path of the .fmu)} at a rate and FMI version, built on first use."""
    cache = {}

    def get(key: str, rate: float = RATE, fmi: str = "2"):
        if (key, rate, fmi) not in cache:
            sc = load_scenario(SCENARIOS[key])
            design = derive(sc)
            src = fmu_sources(design, rate, fmi=fmi)
            path = tmp_path_factory.mktemp(f"fmu{fmi}_{key}") / f"{src.identifier}.fmu"
            path.write_bytes(build_fmu(src))
            cache[key, rate, fmi] = (sc, design, src, path)
        return cache[key, rate, fmi]
    return get


def exported_functions(fmi: str) -> set[str]:
    """The functions the standard's header declares (FMI2_Export / FMI3_Export)."""
    import re
    text = (REPO / "symfunnel" / "emit" / "templates" / f"fmi{fmi}Functions.h").read_text()
    return set(re.findall(rf"FMI{fmi}_Export\s+fmi{fmi}\w+TYPE\s+(fmi{fmi}\w+);", text))


def c_step(design, rate):
    """The generated C step (same generator, prefix 'ref_') compiled on its own and wrapped as StepLibrary, sized
    by `step_states` (so that a design without a reservoir or weights works too)."""
    files = generate(design, "c", prefix="ref_", rate_hz=rate)
    lib = compile_cached({"s.c": files["ref_controller.c"], "ref_controller.h": files["ref_controller.h"]},
                         ["s.c"], "libref_step.so", SHARED_FLAGS)
    x, w = step_states(design)
    return StepLibrary(lib.path, "ref_", design.n, int(x.numel()), int(w.numel()))


@pytest.mark.parametrize("fmi", ["2", "3"])
@pytest.mark.parametrize("key", list(SCENARIOS))
def test_fmpy_validates_loads_and_steps_the_fmu_of_every_family_member(built, key, fmi):
    sc, design, src, path = built(key, fmi=fmi)
    assert validate_fmu(str(path)) == []
    md = fmpy.read_model_description(str(path))
    assert md.fmiVersion == f"{fmi}.0" and md.coSimulation is not None and md.modelExchange is None
    assert md.coSimulation.modelIdentifier == src.identifier and md.guid == src.guid
    assert md.coSimulation.canGetAndSetFMUstate and md.coSimulation.canSerializeFMUstate
    assert float(md.defaultExperiment.stepSize) == 1.0 / RATE
    n = design.n
    by = {v.name: v for v in md.modelVariables}
    for i in range(1, n + 1):
        for name in (f"q[{i}]", f"dq[{i}]"):
            assert by[name].causality == "input" and by[name].variability == "discrete"
        assert by[f"tau[{i}]"].causality == "output" and by[f"tau[{i}]"].unit in ("N.m", "N")
    outputs = [v for v in md.modelVariables if v.causality == "output"]
    assert len(outputs) == 4 * n + 1 and by["status"].type == ("Integer" if fmi == "2" else "Int32")
    assert [u.variable for u in md.outputs] == outputs          # ModelStructure: one Unknown / Output per output
    for v in md.modelVariables:
        assert v.description and (v.type in ("Integer", "Int32") or v.unit), v.name
    assert not [v for v in md.modelVariables if v.causality == "parameter"]   # the step takes no design numbers
    if fmi == "3":
        assert float(md.coSimulation.fixedInternalStepSize) == 1.0 / RATE and not md.coSimulation.hasEventMode
        assert by["time"].causality == "independent" and by["time"].unit == "s"     # no clocks: none declared
        assert not [v for v in md.modelVariables if v.type == "Clock"]
        assert md.buildConfigurations[0].sourceFileSets[0].sourceFiles == list(src.compile_files)
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
    assert f"binaries/{fmu_platform(fmi)}/{src.identifier}.so" in names
    assert {f"sources/{f}" for f in src.sources} <= names and "modelDescription.xml" in names
    # one source: the FMU compiles the generated step C as codegen --lang c writes it (with the FMU's prefix)
    step = generate(design, "c", prefix=src.identifier + "_", rate_hz=RATE)
    assert src.sources[src.identifier + "_controller.c"] == step[src.identifier + "_controller.c"]
    with FmuController(path) as ctl:
        ctl.init()
        rc, tau = ctl.step(0.0, sc.q0, sc.dq0)
        assert rc == 0 and np.all(np.isfinite(tau)) and tau.shape == (n,)


@pytest.mark.parametrize("fmi", ["2", "3"])
@pytest.mark.parametrize("key", list(SCENARIOS))
def test_the_fmu_gives_the_c_steps_torque_bit_for_bit_along_a_closed_loop_run(built, key, fmi):
    """The FMU (stepped by FMPy) closes our sampled loop; the compiled C step, fed the same measurements, gives the
    same torque to the last bit (works for every family member, the loop's own C step included or not)."""
    sc, design, src, path = built(key, fmi=fmi)
    with FmuController(path) as ctl:
        run = simulate_sampled(sc, design, rate_hz=RATE, t_final=1.0, controller=ctl)
    assert run.status == "ok" and run.tau.shape == (int(RATE), design.n)
    lib = c_step(design, RATE)
    lib.init()
    h = 1.0 / RATE                      # the loop's sample times are k * h (not k / RATE: another double)
    tau = np.array([lib.step(k * h, run.q[k], run.dq[k])[1] for k in range(run.tau.shape[0])])
    assert np.array_equal(tau, run.tau)


# arm7 through FMI 2 only: FMI 3's path is the paper rows', and arm7's FMI 3 binary gives the C step's torque bit for
# bit along a 1 s loop (the test above); a second 10,000-step 7-joint run cost about 12 s of the suite's CPU
@pytest.mark.parametrize("key, fmi", [("paper", "2"), ("paper", "3"), pytest.param("arm7", "2", marks=pytest.mark.slow)])
def test_fmpy_driven_loop_reproduces_our_sampled_loop_over_ten_thousand_steps(built, key, fmi):
    sc, design, src, path = built(key, fmi=fmi)
    report = check_fmu(path, sc, design, RATE)
    assert report.samples >= 10_000 and report.samples == report.samples_reference
    assert report.status == report.status_reference == "ok"
    assert report.max_rel_tau <= 1e-9 and report.max_abs_tau == 0.0 and report.max_rel_state == 0.0
    assert report.problems == [] and report.passed


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_at_a_rate_too_low_the_fmu_loop_breaches_exactly_where_ours_does(built, fmi):
    sc, design, src, path = built("paper", 1000.0, fmi)
    report = check_fmu(path, sc, design, 1000.0)
    assert report.status_reference == "breach" and report.status == "breach"
    assert report.breach["time"] == report.breach_reference["time"]
    assert report.same_breach and report.max_abs_tau == 0.0 and report.passed


@pytest.mark.parametrize("key", ["none", "rbf"])
def test_check_on_designs_without_reservoir_or_weights(built, key):
    """A design without an ESN (no approximator; an RBF network, no reservoir): our own sampled loop runs its C step
    (the step library sizes its state from the step API) and the FMU, stepped by FMPy, reproduces it."""
    sc, design, src, path = built(key)
    report = check_fmu(path, sc, design, RATE, t_final=0.5)
    assert report.status_reference != "failed", report.error
    assert report.passed and report.samples == report.samples_reference == 1000 and report.max_abs_tau == 0.0


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_a_communication_step_not_a_multiple_of_the_period_is_refused_with_a_logged_message(built, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    h = 1.0 / RATE
    with FmuController(path) as ctl:
        ctl.init()
        ctl.set_inputs([0.01, -0.02], [0.0, 0.0])
        with pytest.raises(FMICallException, match=f"fmi{fmi}DoStep failed with status 3"):
            ctl.do_step(0.0, 1.5 * h)
        status, category, message = ctl.log[-1]
        assert status == 3 and category == "logStatusError"
        assert "not a whole number of controller periods" in message and "0.0005" in message
        # refused without effect: the FMU steps on from the same state; a multiple of the period is accepted
        ctl.do_step(0.0, 3 * h)
        tau3 = ctl.outputs()[1]
        ctl.init()
        for k in range(3):
            rc, tau = ctl.step(k * h, [0.01, -0.02], [0.0, 0.0])
        assert np.array_equal(tau, tau3)


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_a_non_finite_input_is_a_logged_error_and_the_instance_recovers_by_state_or_reset(built, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    h = 1.0 / RATE
    with FmuController(path) as ctl:
        ctl.init()
        ctl.step(0.0, [0.01, 0.0], [0.0, 0.0])
        state = ctl.get_state()
        good = ctl.step(h, [0.012, 0.0], [0.1, 0.0])
        ctl.set_state(state)
        rc, tau = ctl.step(h, [float("nan"), 0.0], [0.0, 0.0])
        assert rc == -3 and "non-finite q or dq" in ctl.error and ctl.log[-1][0] == 3
        with pytest.raises(FMICallException):       # the instance is in its error state: no further step
            ctl.do_step(2 * h, h)
        ctl.set_state(state)                          # back to the state before the failed step
        again = ctl.step(h, [0.012, 0.0], [0.1, 0.0])
        ctl.free_state(state)
        assert again[0] == good[0] and np.array_equal(again[1], good[1])
        ctl.init()                                    # and fmi*Reset brings it back to the start
        assert ctl.step(0.0, [0.01, 0.0], [0.0, 0.0])[0] == 0


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_fmu_state_get_set_and_serialize_round_trip(built, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    h = 1.0 / RATE
    rng = np.random.default_rng(0)
    qs = rng.normal(0, 0.02, (200, 2))
    with FmuController(path) as ctl:
        ctl.init()
        for k in range(100):
            ctl.step(k * h, qs[k], -qs[k])
        state = ctl.get_state()
        blob = ctl.serialize(state)
        first = [ctl.step(k * h, qs[k], -qs[k]) for k in range(100, 200)]
        ctl.set_state(state)
        again = [ctl.step(k * h, qs[k], -qs[k]) for k in range(100, 200)]
        ctl.free_state(state)
        assert all(a[0] == b[0] and np.array_equal(a[1], b[1]) for a, b in zip(first, again))
        restored = ctl.deserialize(blob)
        ctl.set_state(restored)
        third = [ctl.step(k * h, qs[k], -qs[k]) for k in range(100, 200)]
        ctl.free_state(restored)
        assert all(np.array_equal(a[1], b[1]) for a, b in zip(first, third))
        with pytest.raises(FMICallException):
            ctl.deserialize(blob[:-1])
        assert "not a serialized state" in ctl.log[-1][2]
        # a state of another FMU (another rate: another GUID, the same size) is refused too
        with FmuController(built("paper", 2 * RATE, fmi)[3]) as other:
            other.init()
            s2 = other.get_state()
            foreign = other.serialize(s2)
            other.free_state(s2)
        assert len(foreign) == len(blob) and foreign != blob
        with pytest.raises(FMICallException):
            ctl.deserialize(foreign)
        assert "GUID" in ctl.log[-1][2] or "token" in ctl.log[-1][2]


def test_instantiate_checks_the_guid_and_refuses_model_exchange(built):
    sc, design, src, path = built("paper")
    from fmpy.fmi2 import FMU2Model, FMU2Slave
    d = fmpy.extract(str(path))
    try:
        bad = FMU2Slave(guid="{00000000-0000-0000-0000-000000000000}", unzipDirectory=d,
                        modelIdentifier=src.identifier, instanceName="x")
        with pytest.raises(Exception, match="Failed to instantiate"):
            bad.instantiate()
        bad.freeLibrary()
        me = FMU2Model(guid=src.guid, unzipDirectory=d, modelIdentifier=src.identifier, instanceName="x")
        with pytest.raises(Exception, match="Failed to instantiate"):
            me.instantiate()
        me.freeLibrary()
    finally:
        shutil.rmtree(d, ignore_errors=True)


def test_fmi3_instantiate_checks_the_token_and_refuses_model_exchange(built):
    sc, design, src, path = built("paper", fmi="3")
    from fmpy.fmi3 import FMU3Model, FMU3Slave
    d = fmpy.extract(str(path))
    try:
        bad = FMU3Slave(guid="{00000000-0000-0000-0000-000000000000}", unzipDirectory=d,
                        modelIdentifier=src.identifier, instanceName="x")
        with pytest.raises(Exception, match="Failed to instantiate"):
            bad.instantiate(logMessage=lambda *a: None)
        bad.freeLibrary()
        me = FMU3Model(guid=src.guid, unzipDirectory=d, modelIdentifier=src.identifier, instanceName="x")
        with pytest.raises(Exception, match="Failed to instantiate"):
            me.instantiate(logMessage=lambda *a: None)
        me.freeLibrary()
    finally:
        shutil.rmtree(d, ignore_errors=True)


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_the_sources_alone_build_with_gcc_into_an_fmu_that_gives_identical_results(built, tmp_path, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    d = Path(fmpy.extract(str(path), unzipdir=str(tmp_path / "fmu")))
    so = d / "binaries" / fmu_platform(fmi) / f"{src.identifier}.so"
    so.unlink()
    build = tmp_path / "build"
    shutil.copytree(d / "sources", build)
    if fmi == "3":        # the files to compile, as a build tool reads them from buildDescription.xml
        md = fmpy.read_model_description(str(d))
        files = md.buildConfigurations[0].sourceFileSets[0].sourceFiles
    else:                 # FMI 2: modelDescription's SourceFiles
        import xml.etree.ElementTree as ET
        files = [f.get("name") for f in ET.parse(d / "modelDescription.xml").getroot().iter("File")]
    assert files == list(src.compile_files)
    cmd = [GCC, "-std=c99", "-O2", "-shared", "-fPIC", "-fvisibility=hidden", "-o", str(so),
           *[str(build / f) for f in files], "-lm"]
    subprocess.run(cmd, check=True, capture_output=True, cwd=build)
    rebuilt = tmp_path / "rebuilt.fmu"
    with zipfile.ZipFile(rebuilt, "w") as zf:
        for p in sorted(d.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(d).as_posix())
    assert validate_fmu(str(rebuilt)) == []
    runs = []
    for fmu in (path, rebuilt):
        with FmuController(fmu) as ctl:
            runs.append(simulate_sampled(sc, design, rate_hz=RATE, t_final=1.0, controller=ctl))
    assert np.array_equal(runs[0].tau, runs[1].tau) and np.array_equal(runs[0].q, runs[1].q)


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_the_shipped_library_exports_every_fmi_function_and_nothing_else(built, tmp_path, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    with zipfile.ZipFile(path) as zf:
        data = zf.read(f"binaries/{fmu_platform(fmi)}/{src.identifier}.so")
    so = tmp_path / "probe.so"
    so.write_bytes(data)
    exported = subprocess.run(["nm", "-D", "--defined-only", str(so)], capture_output=True, text=True).stdout
    funcs = {line.split()[-1] for line in exported.splitlines() if " T " in line}
    assert funcs == exported_functions(fmi) and len(funcs) == (44 if fmi == "2" else 75)


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_generation_is_deterministic(built, fmi):
    sc, design, src, path = built("paper", fmi=fmi)
    again = fmu_sources(design, RATE, fmi=fmi)
    assert again.guid == src.guid and again.sources == src.sources
    assert build_fmu(again) == path.read_bytes()
    other = fmu_sources(design, 2 * RATE, fmi=fmi)
    assert other.guid != src.guid


# ---- the command line: symfunnel codegen --lang fmu ---------------------------------------------------------------

def test_cli_writes_only_the_fmu_and_its_check_passes(tmp_path, capsys):
    import json

    from symfunnel.cli import main
    out = tmp_path / "out"
    assert main(["codegen", "paper", "--lang", "fmu", "--rate", "2000", "--out", str(out), "--check", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["file"] == "paper.fmu" and data["fmi_version"] == "2.0" and data["rate_hz"] == 2000.0
    check = data["check"]
    assert check["passed"] and check["validation_problems"] == [] and check["samples"] == 40000
    assert check["max_abs_tau_difference"] == 0.0 and check["status"] == check["status_reference"] == "ok"
    assert sorted(p.name for p in out.iterdir()) == ["paper.fmu"]
    assert validate_fmu(str(out / "paper.fmu")) == []
    # written again over its own file: no --force needed; a file of the user's is kept without --force
    assert main(["codegen", "paper", "--lang", "fmu", "--rate", "2000", "--out", str(out), "-q"]) == 0
    assert "wrote" in capsys.readouterr().out
    (out / "paper.fmu").write_bytes(b"the user's own file")
    assert main(["codegen", "paper", "--lang", "fmu", "--rate", "2000", "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--force" in err and "paper.fmu" in err
    assert (out / "paper.fmu").read_bytes() == b"the user's own file"
    assert main(["codegen", "paper", "--lang", "fmu", "--rate", "2000", "--out", str(out), "--force", "-q"]) == 0
    assert validate_fmu(str(out / "paper.fmu")) == []
    assert main(["codegen", "paper", "--lang", "fmu", "--fmi", "3", "--rate", "2000", "--out", str(out), "-q"]) == 0
    assert "FMI 3.0 Co-Simulation" in capsys.readouterr().out
    assert validate_fmu(str(out / "paper.fmu")) == [] and fmpy.read_model_description(
        str(out / "paper.fmu")).fmiVersion == "3.0"


@pytest.mark.parametrize("args, option, words", [
    (["--lang", "fmu"], "--rate", "missing"),
    (["--lang", "fmu", "--rate", "0"], "--rate", ""),
    (["--lang", "fmu", "--rate", "1000", "--fmi", "4"], "--fmi", "'4'"),
    (["--lang", "fmu", "--rate", "1000", "--fmi", "2.5"], "--fmi", "'2.5'"),
    (["--lang", "c", "--fmi", "2"], "--fmi", "--lang fmu"),
    (["--lang", "fmu", "--rate", "1000", "--prefix", "p_"], "--prefix", "--lang fmu"),
])
def test_cli_bad_input_is_one_line_naming_the_option_and_writes_nothing(tmp_path, capsys, args, option, words):
    from symfunnel.cli import main
    out = tmp_path / "out"
    assert main(["codegen", "paper", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("symfunnel: error:") and option in err and words in err
    assert not out.exists()


def test_cli_check_without_fmpy_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    import sys

    from symfunnel.cli import main
    monkeypatch.setitem(sys.modules, "fmpy", None)
    out = tmp_path / "out"
    assert main(["codegen", "paper", "--lang", "fmu", "--rate", "1000", "--out", str(out), "--check"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--check" in err and "symfunnel[fmu]" in err
    assert not out.exists()


def test_python_api_exports_and_checks_the_fmu(tmp_path):
    import symfunnel
    from symfunnel.core.errors import InputError
    res = symfunnel.codegen("paper", "fmu", tmp_path / "o", rate_hz=2000.0, check=True)
    assert res.path == tmp_path / "o" / "paper.fmu" and res.check.passed and res.check.samples == 40000
    assert res.to_json("paper", tmp_path / "o")["check"]["max_abs_tau_difference"] == 0.0
    with pytest.raises(InputError, match="rate_hz"):
        symfunnel.codegen("paper", "fmu", tmp_path / "p")
    with pytest.raises(InputError, match="fmi"):
        symfunnel.codegen("paper", "c", fmi="2")
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("fmi", ["2", "3"])
def test_the_fmpy_lines_of_docs_fmu_run_as_printed(built, capsys, fmi):
    import re
    sc, design, src, path = built("paper", fmi=fmi)
    text = (REPO / "docs" / "fmu.md").read_text(encoding="utf-8")
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len(block.strip().splitlines()) == 3
    scope = {}
    exec(compile(block.replace("ctl/paper.fmu", str(path)), "docs/fmu.md", "exec"), scope)
    res = scope["res"]
    assert len(res) == 21 and res["tau[1]"][0] == 0.0 and res["tau[1]"][1] != 0.0 and set(res["status"]) == {0}


@pytest.mark.slow
def test_the_check_covers_the_implementation_section_and_a_mujoco_scenario(write_scenario):
    """Saturation, one sample of delay, seeded measurement noise and an encoder: the FMU-driven loop equals the C
    step's bit for bit (the loop applies delay, noise and quantisation around either); a scenario whose plant engine
    is MuJoCo is checked on symfunnel's plant (the check is about the controller)."""
    import tempfile
    text = (REPO / "derivations" / "paper_2dof.toml").read_text()
    assert "[implementation]" not in text
    text += ("\n[implementation]\nrate_hz = 2000.0\ndelay_samples = 1\ntau_max = 600.0\nnoise_q = 1e-4\n"
             "noise_dq = 1e-3\nencoder_resolution = 1e-5\nseed = 3\n")
    sc = load_scenario(write_scenario(text))
    design = derive(sc)
    src = fmu_sources(design, 2000.0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "paper.fmu"
        path.write_bytes(build_fmu(src))
        report = check_fmu(path, sc, design, 2000.0, t_final=2.0)
    # with the delay the loop leaves a funnel after about 1 s: both runs, at the same instant, with the same torques
    assert report.passed and report.samples == report.samples_reference >= 1000 and report.max_abs_tau == 0.0
    assert report.status == report.status_reference and report.same_breach
    heavy = load_scenario(REPO / "derivations" / "arm7_mujoco_heavy.toml")
    assert heavy.plant.engine == "mujoco"
    d2 = derive(heavy)
    src2 = fmu_sources(d2, 2000.0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "arm7.fmu"
        path.write_bytes(build_fmu(src2))
        report = check_fmu(path, heavy, d2, 2000.0, t_final=0.5)
    assert report.passed and report.samples == 1000 and report.max_abs_tau == 0.0

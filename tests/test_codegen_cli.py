"""`symfunnel codegen`: the command line of item 4 (exit codes, output directory, --check)."""

from __future__ import annotations

import json
import shutil

import pytest

from symfunnel.cli import main

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None and shutil.which("cc") is None,
                               reason="no C compiler")


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path_factory.getbasetemp() / "cli-cache"))


@needs_gcc
def test_c_check_passes_and_second_run_reuses_the_cache(tmp_path, capsys):
    out = tmp_path / "ctl"
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(out), "--check", "-q"]) == 0
    text = capsys.readouterr().out
    assert "worst relative error" in text and "PASS" in text
    for name in ("symfunnel_controller.c", "symfunnel_controller.h", "main.c", "Makefile", "trajectory.txt",
                 "manifest.json"):
        assert (out / name).is_file()
    from symfunnel.core.ccompile import cache_dir
    before = sorted(p.name for p in cache_dir().iterdir())
    mtimes = {p: p.stat().st_mtime_ns for p in cache_dir().rglob("*") if p.is_file()}
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(out), "--check", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["check"]["passed"] and data["check"]["worst"] <= 1e-12 and data["check"]["points"] >= 1000
    assert sorted(p.name for p in cache_dir().iterdir()) == before
    assert {p: p.stat().st_mtime_ns for p in cache_dir().rglob("*") if p.is_file()} == mtimes


def test_python_check_passes(tmp_path, capsys):
    out = tmp_path / "ctlpy"
    assert main(["codegen", "paper", "--lang", "python", "--out", str(out), "--check", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["language"] == "python" and data["check"]["passed"]
    assert data["check"]["worst"] <= 1e-10
    assert set(data["check"]["errors"]) == {"funnels", "errors", "alpha2", "alpha2_dot", "controller"}
    assert (out / "symfunnel_controller.py").is_file() and (out / "manifest.json").is_file()


def test_check_fails_with_exit_1_above_threshold(tmp_path, monkeypatch, capsys):
    from symfunnel.emit import check
    monkeypatch.setitem(check.THRESHOLDS, "python", 0.0)
    assert main(["codegen", "--lang", "python", "--out", str(tmp_path / "o"), "--check"]) == 1
    assert "FAIL" in capsys.readouterr().out


def test_bad_lang_is_an_argparse_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["codegen", "--lang", "fortran", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_out_pointing_at_a_file_is_input_error(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("keep me")
    assert main(["codegen", "--lang", "python", "--out", str(f)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("symfunnel: error:") and "--out" in err and "not a directory" in err
    assert f.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_too_few_points_is_input_error(tmp_path, capsys):
    assert main(["codegen", "--lang", "python", "--out", str(tmp_path / "o"), "--check", "--points", "10"]) == 2
    assert "--points" in capsys.readouterr().err


def test_unknown_scenario_is_input_error(tmp_path, capsys):
    assert main(["codegen", str(tmp_path / "missing.toml"), "--lang", "c", "--out", str(tmp_path / "o")]) == 2


def test_existing_directory_is_updated_and_failures_leave_nothing_half_written(tmp_path, monkeypatch):
    from symfunnel import emit as cg
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["codegen", "--lang", "python", "--out", str(out), "-q"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "symfunnel_controller.py").is_file()

    # a failure while writing leaves neither the target nor temporary directories behind
    target = tmp_path / "new"
    with pytest.raises(TypeError):
        cg.write_output({"a.txt": "fine", "b.txt": None}, target)
    assert not target.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]


def test_generated_python_matches_casadi_at_the_funnel_edge(paper_run):
    """Near the boundary the controller amplifies last-bit differences (z = e/(F - |e|)); the generated Python
    evaluates exp like libm, so it still matches CasADi to round-off at |e| = 0.999 F."""
    from symfunnel.emit import check_output
    files = paper_run.code("python")
    report = check_output(paper_run.design, "python", files, points=2000, fill=0.999)
    assert report.worst <= 1e-13


@pytest.mark.parametrize("signalled", [False, True])
def test_a_check_stopped_by_a_signal_writes_nothing_a_failing_one_writes_for_reading(tmp_path, monkeypatch, capsys,
                                                                                   signalled):
    """A RuntimeError out of the check is a failed check (the files are written to read, exit 1) unless it is a
    SIGTERM that a C call turned into one (CasADi's "... KeyboardInterrupt"): then the command stops with 143 and
    writes nothing. Found by the twenty-SIGTERM test: exit 143, and the output there."""
    import signal

    from symfunnel.core import lifecycle
    from symfunnel.emit import check

    def failing(*a, **k):
        if signalled:
            lifecycle._pending.append(int(signal.SIGTERM))       # what the handler records before CasADi throws
            raise RuntimeError("Error in Function::call for 'f' [MXFunction] at .../casadi: KeyboardInterrupt")
        raise RuntimeError("gcc: error: main.c: no such file")
    monkeypatch.setattr(check, "check_output", failing)
    out = tmp_path / "o"
    code = main(["codegen", "--lang", "python", "--out", str(out), "--check", "-q"])
    err = capsys.readouterr().err
    if signalled:
        assert code == 143 and not out.exists() and "terminated by signal 15" in err
        assert sorted(p.name for p in tmp_path.iterdir()) == []
    else:
        assert code == 1 and (out / "symfunnel_controller.py").is_file() and "no such file" in err


def test_the_reports_code_check_stops_at_a_signal_a_c_call_turned_into_an_error(paper_run, monkeypatch):
    """codegen_summary shows why a language could not be checked (the report's code section), except a signal
    that surfaced as a RuntimeError: that stops the report (Terminated), instead of a section saying
    'KeyboardInterrupt' and a report committed after the signal."""
    import signal

    from symfunnel.core import lifecycle
    from symfunnel.emit import check

    def failing(*a, **k):
        raise RuntimeError("gcc: error: main.c: no such file")
    monkeypatch.setattr(check, "check_output", failing)
    s = check.codegen_summary(paper_run.design, paper_run.code_trajectory)
    assert s["languages"]["c"]["check"] is None and "no such file" in s["languages"]["c"]["error"]

    def signalled(*a, **k):
        lifecycle._pending.append(int(signal.SIGTERM))
        raise RuntimeError("Error in Function::call for 'f' [MXFunction]: KeyboardInterrupt")
    monkeypatch.setattr(check, "check_output", signalled)
    try:
        with pytest.raises(lifecycle.Terminated):
            check.codegen_summary(paper_run.design, paper_run.code_trajectory)
    finally:
        lifecycle._pending.clear()


"""Bad options and outputs fail before the work (exit 2); huge URDFs; default report names; SIGTERM clean-up."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from symfunnel.cli import main
from symfunnel.core.errors import InputError
from tests.conftest import PAPER


def one_error_line(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("symfunnel: error: "), err   # no progress line: nothing ran
    for n in needles:
        assert n in err[0], err[0]


@pytest.mark.parametrize("argv, needles", [
    (["codegen", "--lang", "python", "--out", "OUT", "--seed", "-1"], ["--seed", "-1"]),
    (["codegen", "--lang", "python", "--out", "OUT", "--points", "100000000"], ["--points", "100000"]),
    (["verify", "--samples", "1000000000"], ["--samples", "1000000"]),
    (["report", "--samples", "1000000000"], ["--samples"]),
    (["verify", "--samples", "0"], ["--samples"]),
])
def test_option_caps_exit_2(tmp_path, capsys, argv, needles):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    assert main(argv) == 2
    one_error_line(capsys, *needles)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("cmd", ["report", "simulate"])
def test_out_directory_fails_before_the_work(tmp_path, capsys, cmd):
    d = tmp_path / "d.npz" if cmd == "simulate" else tmp_path / "d.html"
    d.mkdir()
    assert main([cmd, "--out", str(d)]) == 2
    one_error_line(capsys, str(d), "is a directory")


@pytest.mark.parametrize("cmd", ["report", "simulate"])
def test_out_under_a_file_or_device_fails_before_the_work(tmp_path, capsys, cmd):
    f = tmp_path / "file"
    f.write_text("")
    name = "x.npz" if cmd == "simulate" else "x.html"
    assert main([cmd, "--out", str(f / name)]) == 2
    one_error_line(capsys, "Not a directory")


@pytest.mark.parametrize("target", ["dir", "under_file"])
def test_latex_output_is_checked_first(tmp_path, capsys, target):
    f = tmp_path / "file"
    f.write_text("")
    path = tmp_path if target == "dir" else f / "x.tex"
    assert main(["derive", "--latex", str(path)]) == 2
    one_error_line(capsys, "--latex")


def test_device_as_out_is_refused():
    from symfunnel.core.outputs import check_output_file
    with pytest.raises(InputError, match="not a regular file"):
        check_output_file("/dev/null")


def test_read_only_out_directory(read_only_dir, capsys):
    for cmd, name in (("report", "r.html"), ("simulate", "s.npz")):
        assert main([cmd, "--out", str(read_only_dir / name)]) == 2
        one_error_line(capsys, "cannot be written")


def test_check_output_file_accepts_new_nested_paths(tmp_path):
    from symfunnel.core.outputs import check_output_file
    assert check_output_file(tmp_path / "a" / "b" / "r.html") == tmp_path / "a" / "b" / "r.html"
    assert not (tmp_path / "a").exists()            # the check creates nothing


def _chain_urdf(n_links: int, movable_every: int) -> str:
    parts = ['<robot name="chain">']
    for i in range(n_links):
        parts.append(f'<link name="l{i}"><inertial><mass value="0.1"/><origin xyz="0 0 0.05"/>'
                     '<inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>')
    for i in range(1, n_links):
        movable = i % movable_every == 0
        kind = "revolute" if movable else "fixed"
        limit = '<limit lower="-1" upper="1" effort="10" velocity="1"/><axis xyz="0 1 0"/>' if movable else ""
        parts.append(f'<joint name="j{i}" type="{kind}"><parent link="l{i - 1}"/><child link="l{i}"/>'
                     f'<origin xyz="0 0 0.1"/>{limit}</joint>')
    parts.append("</robot>")
    return "\n".join(parts)


def test_a_1000_link_chain_loads_without_recursion(tmp_path):
    """1000 links, one joint movable: the fixed chain is merged iteratively (was RecursionError, exit 3)."""
    from symfunnel.model.urdf import build_urdf
    (tmp_path / "c.urdf").write_text(_chain_urdf(1000, 500))
    m = build_urdf({"type": "urdf", "path": "c.urdf"}, file="s.toml", base_dir=tmp_path)
    assert m.n == 1
    # M is the inertia about joint 500's axis (y) of links 500..999, stacked 0.1 m apart with their COM 0.05 m
    # above their origin: an independent sum by the parallel-axis theorem
    import casadi as ca
    import numpy as np
    M = float(ca.Function("M", [m.q], [m.M])(0.3))
    z = 0.1 * np.arange(500) + 0.05
    assert M == pytest.approx(np.sum(0.1 * z ** 2 + 1e-4), rel=1e-12)


def test_a_1000_joint_chain_is_refused_clearly(tmp_path, capsys):
    (tmp_path / "c.urdf").write_text(_chain_urdf(1000, 1))
    s = tmp_path / "s.toml"
    s.write_text('[model]\ntype = "urdf"\npath = "c.urdf"\n[reference]\nq = "0"\n[initial]\nq = 0.0\n')
    assert main(["derive", str(s)]) == 2
    one_error_line(capsys, "c.urdf", "more than 50 movable joints")


def test_default_report_name_of_a_copied_builtin(tmp_path):
    from symfunnel.reporting import default_path
    from symfunnel.scenario import load_scenario
    copy = tmp_path / "my_copy.toml"
    copy.write_text(PAPER.read_text())
    sc = load_scenario(copy)
    assert sc.name == "paper"                                   # the copy keeps its name ...
    assert default_path(sc) == Path("reports") / "my_copy.html"   # ... but not the built-in's report
    assert default_path(load_scenario("paper")) == Path("reports") / "paper.html"


def test_sigterm_during_an_atomic_write_leaves_no_temporary_file(tmp_path):
    prog = textwrap.dedent(f"""
        import time
        from symfunnel.core import lifecycle
        from symfunnel.core.io import atomic_path
        lifecycle.install()
        try:
            with atomic_path({str(tmp_path / "out.html")!r}) as tmp:
                tmp.write_text("half")
                print("ready", flush=True)
                time.sleep(60)
        except lifecycle.Terminated:
            raise SystemExit(143)
        """)
    p = subprocess.Popen([sys.executable, "-c", prog], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    p.send_signal(signal.SIGTERM)
    assert p.wait(timeout=30) == 143
    assert list(tmp_path.iterdir()) == []


def test_sigterm_stops_the_cli_with_one_line(tmp_path):
    p = subprocess.Popen([sys.executable, "-m", "symfunnel.cli", "report", "--out", str(tmp_path / "r.html"),
                          "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines() == [f"symfunnel: terminated by signal {int(signal.SIGTERM)}"]
    assert list(tmp_path.iterdir()) == []


def test_sigterm_inside_the_integrator_is_not_an_integrator_failure(tmp_path):
    """CasADi turns a signal during CVODES into RuntimeError('... KeyboardInterrupt'); the CLI still stops with 143."""
    p = subprocess.Popen([sys.executable, "-m", "symfunnel", "simulate", "--t-final", "5000", "--out",
                          str(tmp_path / "r.npz")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in p.stderr:
        if "simulating the closed loop" in line:
            break
    time.sleep(1.0)                           # inside the integration by now (5000 s of simulated time)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert list(tmp_path.iterdir()) == []


def test_main_collects_garbage_at_its_own_thresholds_and_gives_the_callers_back(monkeypatch):
    """A command runs at symfunnel.cli.GC_THRESHOLDS; a caller of main() (the Python API, a test) gets its own
    thresholds back, also when the command fails."""
    import gc

    import symfunnel.cli as cli
    seen = []

    def command(argv, deadline, lifecycle):
        seen.append(gc.get_threshold())
        if argv == ["fail"]:
            raise RuntimeError("boom")
        return 0
    monkeypatch.setattr(cli, "_run", command)
    before = gc.get_threshold()
    try:
        gc.set_threshold(1234, 5, 6)
        assert cli.main(["ok"]) == 0
        assert gc.get_threshold() == (1234, 5, 6)
        with pytest.raises(RuntimeError):
            cli.main(["fail"])
        assert gc.get_threshold() == (1234, 5, 6)
    finally:
        gc.set_threshold(*before)
    assert seen == [cli.GC_THRESHOLDS] * 2 and cli.GC_THRESHOLDS[0] > 700

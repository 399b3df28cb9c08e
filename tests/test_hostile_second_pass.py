"""Inputs that crashed or were silently accepted in the second hostile pass: each is one line and exit 2 now
(issue 21, rows 8-11, 14, 18-22)."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from symfunnel.cli import main
from tests.conftest import PAPER

ROOT = Path(__file__).resolve().parents[1]


def one_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("symfunnel: error: "), err
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


def _variant(tmp_path, old: str, new: str, name="v.toml") -> Path:
    text = PAPER.read_text()
    assert old in text, old
    p = tmp_path / name
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize("ref, needle", [
    ('"0.1*sin(t)/(t - t)"', "reference.q"),
    ('"log(0 - 1)"', "reference.q"),
])
def test_a_reference_that_is_not_finite_is_refused_at_load(tmp_path, capsys, ref, needle):
    """Row 8: exit 3 (TypeError in a format string) on main."""
    text = PAPER.read_text()
    start = text.index("[reference]")
    line = text.index("\nq = ", start) + 1
    end = text.index("\n", line)
    p = tmp_path / "r.toml"
    p.write_text(text[:line] + f"q = {ref}" + text[end:])
    assert main(["derive", str(p), "-q"]) == 2
    one_error(capsys, needle, "finite")


def test_a_funnel_of_1e200_is_refused_at_load(tmp_path, capsys):
    p = _variant(tmp_path, "[funnel.e1]\n", "[funnel.e1]\nphi0 = 1e200\n") if "phi0" not in \
        PAPER.read_text().split("[funnel.e1]")[1].split("[")[0] else None
    if p is None:
        text = PAPER.read_text()
        sec = text.index("[funnel.e1]")
        i = text.index("phi0", sec)
        j = text.index("\n", i)
        p = tmp_path / "f.toml"
        p.write_text(text[:i] + "phi0 = [1e200, 1e200]" + text[j:])
    assert main(["derive", str(p), "-q"]) == 2
    one_error(capsys, "funnel.e1", "at most 1e+08")


@pytest.mark.parametrize("argv, key", [
    (["derive", "--wall-limit", "1e300"], "--wall-limit"),
    (["simulate", "--wall-limit", "1e300"], "--wall-limit"),
    (["tune", "--wall-limit", "1e300"], "--wall-limit"),
])
def test_huge_limits_exit_2(capsys, argv, key):
    """Row 9: OverflowError (exit 3) on main."""
    assert main([*argv, "-q"]) == 2
    one_error(capsys, key, "at most 604800")


@pytest.mark.parametrize("key, value", [("wall_limit", "1e300"), ("sympy_timeout", "1e300")])
def test_huge_limits_in_the_scenario_exit_2(tmp_path, capsys, key, value):
    section = "[simulation]" if key == "wall_limit" else "[audit]"
    text = PAPER.read_text()
    p = tmp_path / "l.toml"
    p.write_text(text.replace(section + "\n", f"{section}\n{key} = {value}\n", 1) if section in text
                 else text + f"\n{section}\n{key} = {value}\n")
    assert main(["derive", str(p), "-q"]) == 2
    one_error(capsys, key)


def test_an_infinite_compile_timeout_exits_2(monkeypatch):
    from symfunnel.core.ccompile import compile_timeout
    from symfunnel.core.errors import InputError
    monkeypatch.setenv("SYMFUNNEL_COMPILE_TIMEOUT", "inf")
    with pytest.raises(InputError, match="SYMFUNNEL_COMPILE_TIMEOUT"):
        compile_timeout()


@pytest.mark.parametrize("rate", ["1e-300", "0.1", "1"])
def test_rates_too_low_for_the_plant_are_refused_with_the_lowest_usable_rate(capsys, rate):
    """Rows 6 and 10: exit 3 (1e-300), a hang of minutes (0.1 Hz), gcc on a 6.4 MB plant step (1 Hz) on main."""
    assert main(["simulate", "--rate", rate, "-q"]) == 2
    line = one_error(capsys, "RK4 plant steps", "a rate of at least")
    from symfunnel.deployed.loop import MAX_PLANT_SUBSTEPS, min_rate_hz
    from symfunnel.scenario import load_scenario
    lowest = min_rate_hz(load_scenario("paper"))
    assert f"{lowest:.6g} Hz" in line
    # the bound is the plant's: at that rate the plant step needs exactly MAX_PLANT_SUBSTEPS RK4 steps
    from symfunnel.deployed.loop import plant_substeps
    assert plant_substeps(load_scenario("paper"), 1.0 / (lowest * 1.0001)) == MAX_PLANT_SUBSTEPS


def test_writing_under_a_file_size_limit_is_one_line_and_leaves_nothing(tmp_path):
    """Row 11: EFBIG/ENOSPC came out as exit 3 after the work on main."""
    out = tmp_path / "s.npz"

    def small():
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    env = dict(os.environ, SYMFUNNEL_NO_JIT="1")
    r = subprocess.run([sys.executable, "-m", "symfunnel", "simulate", "--t-final", "2", "--out", str(out), "-q"],
                       capture_output=True, text=True, timeout=600, preexec_fn=small, env=env)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(out) in lines[0] and "cannot be written" in lines[0], lines
    assert list(tmp_path.iterdir()) == []


def test_staged_writes_are_all_or_nothing(tmp_path):
    """Row 18: `report --figures DIR` stopped by its limit left 14 of 24 figures ('nothing was written')."""
    from symfunnel.core.io import atomic_write, staged
    with pytest.raises(RuntimeError):
        with staged():
            for i in range(5):
                atomic_write(tmp_path / f"f{i}.png", b"x" * 10)
            raise RuntimeError("the limit")
    assert list(tmp_path.iterdir()) == []
    with staged():
        for i in range(3):
            atomic_write(tmp_path / f"g{i}.png", b"y")
        assert list(tmp_path.iterdir()) == []                # nothing before the block ends
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g0.png", "g1.png", "g2.png"]


#: `report`, its wall-clock limit made to expire (by the real deadline machinery) once the simulation figures are staged
_REPORT_LIMIT_HOOK = """
import sys, time
from symfunnel import cli
from symfunnel.core import deadline, io
import symfunnel.reporting.sections as S
real = S.tuning_section                 # the section after the simulation's figures
def hooked(*a, **k):
    sys.stderr.write("staged %d\\n" % sum(len(b) for b in io._staging))
    for d in deadline._stack:
        d.expiry = time.monotonic()
    deadline.check("a hooked report section")
    return real(*a, **k)
S.tuning_section = hooked
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_report_figures_stopped_by_the_limit_leave_nothing(tmp_path):
    """The limit reached after the figures were staged: exit 1 with the limit's line, no figure and no report."""
    figs = tmp_path / "figs"
    r = subprocess.run([sys.executable, "-c", _REPORT_LIMIT_HOOK, "report", "--figures", str(figs), "--out",
                        str(tmp_path / "r.html"), "--wall-limit", "600", "--t-final", "1", "--samples", "200",
                        "--no-codegen", "--no-mutants", "--no-deployed", "-q"], capture_output=True, text=True,
                       timeout=600, cwd=tmp_path)
    staged = [int(line.split()[1]) for line in r.stderr.splitlines() if line.startswith("staged ")]
    assert staged and staged[0] >= 4, r.stderr[-600:]          # PNG and PDF of at least two figures were held back
    assert r.returncode == 1 and "wall-clock limit of 600 s reached while a hooked report section" in r.stderr
    assert list(figs.iterdir()) == [] and not (tmp_path / "r.html").exists()
    assert not [f for f in tmp_path.rglob("*") if f.name.endswith(".tmp")]


def test_init_escapes_joint_names_so_the_output_loads_as_written(tmp_path):
    """Row 14: a joint name holding an encoded newline escaped the comment and injected keys."""
    from tests.test_signals import _chain_urdf
    text = _chain_urdf(2).replace('name="j1"', 'name="j1&#10;description = &quot;injected&quot;&#10;deviations = []"')
    text = text.replace('name="j2"', 'name="j2&#13;&#10;[x]&#x2028;&quot;"')
    (tmp_path / "r.urdf").write_text(text)
    out = tmp_path / "s.toml"
    assert main(["init", "--urdf", str(tmp_path / "r.urdf"), "--out", str(out), "-q"]) == 0
    doc = tomllib.loads(out.read_text())
    assert "description" not in doc and "deviations" not in doc and "x" not in doc
    assert main(["derive", str(out), "-q"]) == 0


def test_codegen_refuses_to_overwrite_the_users_files(tmp_path, capsys):
    """Row 19: the user's Makefile and main.c were overwritten silently."""
    d = tmp_path / "ctl"
    d.mkdir()
    (d / "Makefile").write_text("# mine\n")
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(d), "-q"]) == 2
    one_error(capsys, "Makefile", "--force")
    assert (d / "Makefile").read_text() == "# mine\n" and sorted(p.name for p in d.iterdir()) == ["Makefile"]
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(d), "-q", "--force"]) == 0
    capsys.readouterr()
    assert (d / "Makefile").read_text() != "# mine\n"
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(d), "-q"]) == 0       # our own files: fine
    capsys.readouterr()
    (d / "main.c").write_text((d / "main.c").read_text() + "/* edited */\n")
    assert main(["codegen", "--lang", "c", "--rate", "2000", "--out", str(d), "-q"]) == 2        # changed since: the user's now
    one_error(capsys, "main.c")


def test_python_codegen_refuses_c_only_options(tmp_path, capsys):
    """Row 21: `--lang python --rate 1000 --prefix x_` ignored both options."""
    assert main(["codegen", "--lang", "python", "--rate", "1000", "--prefix", "x_", "--out",
                 str(tmp_path / "p"), "-q"]) == 2
    one_error(capsys, "--lang c")
    assert not (tmp_path / "p").exists()


def test_a_cache_entry_copied_over_another_is_rebuilt(tmp_path):
    """Row 20: another entry's .so and record copied over a cache entry were accepted (the other controller)."""
    import shutil
    import warnings

    from symfunnel.core.ccompile import SHARED_FLAGS, compile_cached
    a = compile_cached({"f.c": "double f(double x){return x + 1.0;}\n"}, ["f.c"], "libf.so", SHARED_FLAGS,
                       cache=tmp_path)
    b = compile_cached({"f.c": "double f(double x){return x + 2.0;}\n"}, ["f.c"], "libf.so", SHARED_FLAGS,
                       cache=tmp_path)
    for name in os.listdir(b.path.parent):
        shutil.copy(b.path.parent / name, a.path.parent / name)           # b's library and record in a's place
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again = compile_cached({"f.c": "double f(double x){return x + 1.0;}\n"}, ["f.c"], "libf.so",
                               SHARED_FLAGS, cache=tmp_path)
    assert not again.cached and any("another key" in str(w.message) for w in caught)
    import ctypes
    lib = ctypes.CDLL(str(again.path))
    lib.f.restype, lib.f.argtypes = ctypes.c_double, [ctypes.c_double]
    assert lib.f(1.0) == 2.0                                             # a's code: 1 + 1


@pytest.mark.parametrize("coordinate", ["return", "class", "while"])
def test_keywords_as_coordinates_are_refused(write_scenario, capsys, coordinate):
    from tests.conftest import MINIMAL_2LINK
    text = MINIMAL_2LINK.replace('coordinates = ["q1", "q2"]', f'coordinates = ["{coordinate}", "q2"]')
    text = text.replace("cos(q2)", "cos(q2)").format(C="")
    assert main(["derive", str(write_scenario(text)), "-q"]) == 2
    one_error(capsys, "model.coordinates[0]", "keyword")


def test_an_invisible_expect_reason_is_refused(tmp_path, capsys):
    """Row 21: a breaching design passed the gate on the reason "\\u200b"."""
    text = PAPER.read_text()
    i = text.index("[[expect]]")
    j = text.index("reason = ", i)
    k = text.index("\n", j)
    p = tmp_path / "e.toml"
    p.write_text(text[:j] + 'reason = "\\u200b\\u2060 "' + text[k:])
    assert main(["derive", str(p), "-q"]) == 2
    one_error(capsys, "reason")


def test_duplicate_keys_in_a_point_file_are_refused(tmp_path, capsys):
    pt = tmp_path / "p.json"
    pt.write_text('{"t": 0.5, "t": 0.7, "q": [0.15, 0.14], "dq": [-0.15, 0.5]}')
    assert main(["derive", "--eval", str(pt), "-q"]) == 2
    one_error(capsys, "'t' twice")


def test_an_infinite_urdf_effort_is_refused(tmp_path, capsys):
    from tests.test_signals import _chain_urdf
    (tmp_path / "r.urdf").write_text(_chain_urdf(2).replace('effort="10"', 'effort="inf"', 1))
    s = tmp_path / "s.toml"
    assert main(["init", "--urdf", str(tmp_path / "r.urdf"), "--out", str(s), "-q"]) == 0
    s.write_text(s.read_text() + '\n[implementation]\nrate_hz = 1000.0\ntau_max = "urdf"\n')
    assert main(["derive", str(s), "-q"]) == 2
    one_error(capsys, "effort", "finite")


@pytest.mark.parametrize("value, bad", [("a\\u0000b\\nc", ["\x00", "\n"]), ("x" * 30000, [])])
def test_messages_are_one_clean_bounded_line(tmp_path, capsys, value, bad):
    """Row 22: raw NUL, newlines or 30 kB of input in messages; 'is a array'."""
    text = PAPER.read_text().replace('name = "paper"', f'name = "{value}"', 1)
    p = tmp_path / "n.toml"
    p.write_text(text)
    assert main(["derive", str(p), "-q"]) == 2
    line = one_error(capsys)
    assert len(line) < 700 and not any(b in line for b in bad)


def test_type_names_take_their_article(write_scenario, capsys):
    from tests.conftest import MINIMAL_2LINK
    text = MINIMAL_2LINK.format(C="").replace("[initial]\nq = [0.0, 0.2]", "[initial]\nq = [0.0, 0.2]\n"
                                              "dq = {a = 1}")
    assert main(["derive", str(write_scenario(text)), "-q"]) == 2
    line = one_error(capsys)
    assert " a array" not in line and " a integer" not in line

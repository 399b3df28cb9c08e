"""The Python API: one function per command, results with to_json(), errors raised instead of exit codes."""

from __future__ import annotations

import json

import pytest

import symfunnel as sf
from symfunnel.core.errors import CheckFailed, InputError


@pytest.mark.slow
def test_one_function_per_command_with_json_results(tmp_path):
    v = sf.verify("paper", t_final=1.0, samples=500)
    out = json.loads(json.dumps(v.to_json()))
    assert out["status"] == "pass" and {c["id"] for c in out["checks"]} >= {"design.identity.vdot", "claim.eq26"}
    assert "<table>" in v._repr_html_() and "gate" in v._repr_html_()
    s = sf.simulate("paper", t_final=0.5)
    assert s.to_json()["status"] == "ok" and "simulation" in s._repr_html_()
    a = sf.audit("paper")
    assert {c["id"] for c in a.to_json()["checks"]} >= {"model.M_symmetric", "claim.eq37"}
    c = sf.codegen("paper", "python", tmp_path / "py", check=True, points=1000, t_final=0.5)
    assert c.check.passed and (tmp_path / "py" / "manifest.json").exists() and c.to_json()["language"] == "python"
    # the call and its result are what is tested here: the sections a report can leave out are left out (the
    # deployed section's rate search and its C compiles are tested in test_report.py)
    r = sf.report("paper", tmp_path / "r.html", codegen=False, mutants=False, deployed=False, t_final=0.5,
                  samples=200)
    assert r.path.exists() and r.to_json()["path"].endswith("r.html")
    m = sf.verify("paper", t_final=1.0, samples=500, mutants=True)
    assert m.status == "pass" and m.mutation_score >= 0.9


def test_errors_are_raised_not_exit_codes(write_scenario):
    with pytest.raises(InputError):
        sf.verify("no-such-scenario")
    text = (sf.load_scenario("paper").path).read_text(encoding="utf-8")
    bad = write_scenario(text.replace('name = "eq26"\nexpect = "fail"', 'name = "eq26"', 1))
    assert sf.verify(bad, t_final=0.5, samples=200).status == "fail"
    with pytest.raises(CheckFailed, match="claim.eq26"):
        sf.verify(bad, t_final=0.5, samples=200, strict=True)


def test_python_m_symfunnel_runs_the_cli():
    import subprocess
    import sys
    p = subprocess.run([sys.executable, "-m", "symfunnel", "derive", "--json"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0 and "alpha2_dot" in json.loads(p.stdout)["signals"]

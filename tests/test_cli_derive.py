"""`symfunnel derive`: the JSON contract, --eval against finite differences, --latex, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from symfunnel.cli import main


def test_derive_json_contract(capsys):
    assert main(["derive", "--json"]) == 0
    sig = json.loads(capsys.readouterr().out)["signals"]
    for name in ("M", "C", "G", "e1", "z1", "alpha2", "alpha2_dot", "e2", "z2", "tau", "F1", "F2"):
        assert set(sig[name]) == {"ops", "free", "shape"}
    assert sig["alpha2"]["shape"] == [2, 1]
    assert not any(s in ("dq1", "dq2") for s in sig["alpha2"]["free"])
    assert "dq1" in sig["alpha2_dot"]["free"]


def test_derive_eval_agrees_with_finite_differences(tmp_path, capsys):
    """derive --eval alpha2_dot equals central differences of derive --eval alpha2 along the flow."""
    t, q, dq = 0.8, np.array([0.2, 0.21]), np.array([0.25, 0.18])
    h = 1e-5
    pts = [{"t": t + s, "q": (q + s * dq).tolist(), "dq": dq.tolist()} for s in (-2 * h, -h, 0.0, h, 2 * h)]
    f = tmp_path / "p.json"
    f.write_text(json.dumps(pts))
    assert main(["derive", "--eval", str(f), "--json"]) == 0
    vals = json.loads(capsys.readouterr().out)["values"]
    a = [np.array(v["alpha2"]) for v in vals]
    fd = (8 * (a[3] - a[1]) - (a[4] - a[0])) / (12 * h)
    np.testing.assert_allclose(fd, vals[2]["alpha2_dot"], rtol=1e-7)
    for k in ("M", "C", "G", "e1", "z1", "e2"):
        assert vals[2][k] is not None


def test_eval_inside_both_funnels_gives_tau(tmp_path, capsys):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"t": 0.8, "q": [0.2, 0.21], "dq": [0.0, 0.0]}))
    main(["derive", "--eval", str(f), "--json"])
    alpha2 = json.loads(capsys.readouterr().out)["values"]["alpha2"]
    f.write_text(json.dumps({"t": 0.8, "q": [0.2, 0.21], "dq": alpha2}))
    main(["derive", "--eval", str(f), "--json"])
    v = json.loads(capsys.readouterr().out)["values"]
    assert v["e2"] == pytest.approx([0.0, 0.0], abs=1e-12)
    for k in ("z2", "tau", "v", "w_hat_dot"):
        assert v[k] is not None


def test_eval_outside_funnel_is_null_with_warning(tmp_path):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"t": 3.0, "q": [1.0, 0.0], "dq": [0.0, 0.0]}))
    r = subprocess.run([sys.executable, "-m", "symfunnel.cli", "derive", "--eval", str(f), "--json"],
                       capture_output=True, text=True)
    assert r.returncode == 0
    v = json.loads(r.stdout)["values"]
    assert v["z1"] is None and v["alpha2"] is None and v["e1"] is not None
    assert "warning" in r.stderr and "funnel e1" in r.stderr


@pytest.mark.parametrize("content, needle", [
    ('{"t": 0, "q": [0, 0]}', "dq"),
    ('{"t": 0, "q": [0, 0, 0], "dq": [0, 0]}', "q"),
    ('{"t": 0, "q": [0, 0], "dq": [0, 0], "dqq": 1}', "did you mean 'dq'"),
    ('{"t": "now", "q": [0, 0], "dq": [0, 0]}', "t"),
    ('[1, 2', "not valid JSON"),
    ('[]', "empty"),
])
def test_bad_point_files_exit_2(tmp_path, content, needle):
    f = tmp_path / "p.json"
    f.write_text(content)
    r = subprocess.run([sys.executable, "-m", "symfunnel.cli", "derive", "--eval", str(f)],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert needle in r.stderr and str(f) in r.stderr and "Traceback" not in r.stderr


def test_derive_from_any_directory_and_latex(tmp_path):
    out = tmp_path / "signals.tex"
    r = subprocess.run([sys.executable, "-m", "symfunnel.cli", "derive", "--latex", str(out)],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    tex = out.read_text()
    assert r"\alpha_2 =" in tex and "cos" in tex
    assert "alpha2_dot" in r.stdout


def test_unknown_scenario_exit_2():
    r = subprocess.run([sys.executable, "-m", "symfunnel.cli", "derive", "papr"], capture_output=True, text=True)
    assert r.returncode == 2 and "did you mean 'paper'" in r.stderr

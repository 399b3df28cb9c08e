"""Hostile input files: special files, oversized files, unusable numbers and mistyped point files end in exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.core.errors import InputError
from tests.conftest import PAPER


def run_cli(*args, timeout=120, cwd=None):
    return subprocess.run([sys.executable, "-m", "symfunnel.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def assert_one_line(r, *needles):
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("symfunnel: error: "), r.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@pytest.mark.parametrize("where", ["scenario", "eval"])
def test_fifo_is_refused_without_hanging(tmp_path, where):
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    args = ["derive", str(fifo)] if where == "scenario" else ["derive", "--eval", str(fifo)]
    assert_one_line(run_cli(*args, timeout=60), str(fifo), "FIFO")


def test_device_and_directory_are_refused(tmp_path):
    assert_one_line(run_cli("derive", "/dev/zero", timeout=60), "/dev/zero", "not a regular file")
    assert_one_line(run_cli("derive", "--eval", str(tmp_path), timeout=60), str(tmp_path), "directory")


def test_oversized_file_is_refused_before_reading(tmp_path):
    from symfunnel.core.inputs import MAX_INPUT_BYTES, read_input
    big = tmp_path / "big.toml"
    with open(big, "wb") as fh:                 # sparse: costs no disk
        fh.truncate(MAX_INPUT_BYTES + 1)
    with pytest.raises(InputError, match="larger than the limit"):
        read_input(big, expected="x")
    small = tmp_path / "small"
    small.write_bytes(b"x" * 100)
    assert read_input(small, expected="x", limit=100) == b"x" * 100
    with pytest.raises(InputError, match="limit of 99 bytes"):
        read_input(small, expected="x", limit=99)


def _variant(tmp_path, value: str):
    text = PAPER.read_text().replace("k1 = 5.0", f"k1 = {value}", 1)
    assert f"k1 = {value}" in text
    p = tmp_path / "v.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("value, needle", [
    ("1" * 5001, "5001 digits"),
    ("1e309", "overflows"),
    ("-1e309", "overflows"),
    ("1e-400", "underflows"),
    ("1e-310", "underflows"),              # subnormal: not zero, but its precision is gone
    ("1" * 400, "400 digits"),             # fits Python's int but not a double
])
def test_unusable_toml_numbers_exit_2(tmp_path, capsys, value, needle):
    p = _variant(tmp_path, value)
    assert main(["derive", str(p)]) == 2
    err = capsys.readouterr().err
    assert needle in err and str(p) in err and len(err.strip().splitlines()) == 1


def test_toml_integer_notations_are_exact_integers(tmp_path):
    """Decision (docs/scenario.md): TOML integers in any notation are accepted where a number is meant."""
    from symfunnel.scenario import load_scenario
    assert load_scenario(_variant(tmp_path, "0x10")).k1 == [16.0, 16.0]
    assert load_scenario(_variant(tmp_path, "1_000")).k1 == [1000.0, 1000.0]


def test_float_literal_boundaries():
    from symfunnel.core.inputs import float_literal
    assert float_literal("2.2250738585072014e-308", file=None) == sys.float_info.min
    assert float_literal("0.0", file=None) == 0.0 and float_literal("-0e5", file=None) == 0.0
    assert float_literal("1.7976931348623157e308", file=None) == sys.float_info.max
    for bad in ("2e-308", "1.8e308", "5e-324", "0.5e-400"):
        with pytest.raises(InputError):
            float_literal(bad, file=None)


@pytest.mark.parametrize("point, key, what", [
    ({"t": 0, "q": ["0.1", 0], "dq": [0, 0]}, "q[0]", "string"),
    ({"t": 0, "q": [True, 0], "dq": [0, 0]}, "q[0]", "boolean"),
    ({"t": 0, "q": [[0.1], [0]], "dq": [0, 0]}, "q[0]", "array"),
    ({"t": 0, "q": [0, 0], "dq": [0, 0], "w_hat": "x"}, "w_hat", "string"),
    ({"t": [0], "q": [0, 0], "dq": None}, "dq", "null"),
    ({"t": 0, "q": [0, 0], "dq": [0, 0], "w_hat": [[0.0] * 2] * 50}, "w_hat", "shape"),
])
def test_mistyped_point_files_exit_2(tmp_path, capsys, point, key, what):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(point))
    assert main(["derive", "--eval", str(f)]) == 2
    err = capsys.readouterr().err
    assert f"key '{key}'" in err and what in err and str(f) in err, err


@pytest.mark.parametrize("text, needle", [
    ('{"t": 0, "q": [0, %s], "dq": [0, 0]}' % ("1" * 5001), "5001 digits"),
    ('{"t": 0, "q": [0, 1e309], "dq": [0, 0]}', "overflows"),
    ('{"t": 0, "q": [0, 1e-400], "dq": [0, 0]}', "underflows"),
    ('{"t": 0, "q": [0, NaN], "dq": [0, 0]}', "NaN"),
])
def test_unusable_json_numbers_exit_2(tmp_path, capsys, text, needle):
    f = tmp_path / "p.json"
    f.write_text(text)
    assert main(["derive", "--eval", str(f)]) == 2
    err = capsys.readouterr().err
    assert needle in err and str(f) in err


def test_point_values_are_read_exactly(paper_design):
    """The strict reader keeps the values: w_hat as a scalar, rows or a flat column-major list agree."""
    from symfunnel.design import point_inputs
    d = paper_design
    N1, n = d.sym["w_hat"].shape
    W = np.arange(N1 * n, dtype=float).reshape(N1, n) / 100
    base = {"t": 0.1, "q": [0.0, 0.1], "dq": [0.0, 0.0]}
    rows = point_inputs(d, {**base, "w_hat": W.tolist()})["w_hat"]
    flat = point_inputs(d, {**base, "w_hat": W.ravel(order="F").tolist()})["w_hat"]
    np.testing.assert_array_equal(rows, W)
    np.testing.assert_array_equal(flat, W)
    np.testing.assert_array_equal(point_inputs(d, {**base, "w_hat": 0.5})["w_hat"], np.full((N1, n), 0.5))


def test_api_errors_name_no_file_and_warnings_use_the_warnings_module(paper_design):
    from symfunnel.design import evaluate
    with pytest.raises(InputError) as ei:
        evaluate(paper_design, {"t": 0, "q": ["0.1", 0], "dq": [0, 0]})
    assert ei.value.file is None and "POINT" not in str(ei.value) and "q[0]" in str(ei.value)
    with pytest.warns(UserWarning, match="outside funnel e1 at joint 1"):
        out = evaluate(paper_design, {"t": 0.5, "q": [0.4, 0.2], "dq": [0.0, 0.0]})
    assert out["z1"] is None


def test_cli_prints_a_warning_as_one_line(tmp_path):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({"t": 3.0, "q": [1.0, 0.0], "dq": [0.0, 0.0]}))
    r = run_cli("derive", "--eval", str(f), "--json")
    assert r.returncode == 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("symfunnel: warning: point outside funnel e1"), r.stderr


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@pytest.mark.parametrize("kind", ["fifo", "directory", "device"])
def test_urdf_that_is_not_a_regular_file(tmp_path, kind):
    target = {"fifo": "r.urdf", "directory": "r.urdf", "device": "/dev/zero"}[kind]
    if kind == "fifo":
        os.mkfifo(tmp_path / target)
    elif kind == "directory":
        (tmp_path / target).mkdir()
    s = tmp_path / "s.toml"
    s.write_text(f'[model]\ntype = "urdf"\npath = "{target}"\n[reference]\nq = "0"\n[initial]\nq = 0.0\n')
    what = {"fifo": "FIFO", "directory": "is a directory", "device": "character device"}[kind]
    assert_one_line(run_cli("derive", str(s), timeout=60), what, "expected a URDF file")

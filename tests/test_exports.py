"""`simulate --out` by suffix (.npz, .csv, .mat) and the sweep's results.csv: each read back with numpy / scipy and
compared with the npz (or the parquet) array by array, units included."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.io

from symfunnel.cli import main


def _read_csv(path):
    """(names, units, data) of a trajectory CSV, read as its header says (genfromtxt with skip_header)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    skip = int(head[0].split()[1])
    assert skip == len(head) + 1                      # the comment lines and the names row
    names = lines[skip - 1].split(",")
    units = next(ln for ln in head if ln.startswith("# units: "))[len("# units: "):].split(",")
    data = np.genfromtxt(path, delimiter=",", skip_header=skip)
    return names, units, np.atleast_2d(data)


def _columns(names, data, key, shape):
    """The CSV columns of one array, in its shape (time first)."""
    if len(shape) == 1:
        return data[:, names.index(key)]
    idx = [i for i, nm in enumerate(names) if nm.startswith(key + "[")]
    return data[:, idx].reshape((data.shape[0],) + tuple(shape[1:]))


@pytest.fixture(scope="module")
def continuous(tmp_path_factory):
    d = tmp_path_factory.mktemp("cont")
    for suffix in ("npz", "csv", "mat"):
        assert main(["simulate", "paper", "--t-final", "0.3", "-q", "--out", str(d / f"run.{suffix}")]) == 0
    return d


def test_csv_holds_the_npz_arrays_with_units(continuous):
    npz = np.load(continuous / "run.npz")
    names, units, data = _read_csv(continuous / "run.csv")
    assert names[0] == "t" and units[0] == "s"
    assert len(units) == len(names) == data.shape[1]
    u = dict(zip(names, units))
    assert u["q[1]"] == "rad" and u["dq[2]"] == "rad/s" and u["tau[1]"] == "N m" and u["m1[1]"] == "1"
    compared = 0
    for key in npz.files:
        a = npz[key]
        if a.ndim == 0 or a.dtype.kind != "f" or a.shape[0] != npz["t"].size:
            continue
        got = _columns(names, data, key, a.shape)
        # repr() of a float reads back exactly
        np.testing.assert_array_equal(got, a, err_msg=key)
        compared += 1
    assert compared >= 20
    left = next(ln for ln in (continuous / "run.csv").read_text().splitlines() if "not in this file" in ln)
    assert "W_star" in left                         # the array without a time axis is named, not dropped silently


def test_mat_holds_the_npz_arrays_by_name_with_units(continuous):
    npz = np.load(continuous / "run.npz")
    mat = scipy.io.loadmat(continuous / "run.mat", squeeze_me=True)
    for key in npz.files:
        a = npz[key]
        if a.dtype.kind in "US":
            assert str(mat[key]) == str(a), key
            continue
        np.testing.assert_array_equal(np.asarray(mat[key], float).reshape(a.shape), a, err_msg=key)
    units = mat["units"]
    assert str(units["t"]) == "s" and str(units["q"]) == "rad, rad" and str(units["tau"]) == "N m, N m"
    assert "tracking error" in str(mat["description"]["e1"])


def test_sampled_loop_csv_and_mat(tmp_path):
    """The sampled loop's held torque has one row less: the CSV leaves its last row empty (NaN)."""
    for suffix in ("npz", "csv", "mat"):
        assert main(["simulate", "paper", "--t-final", "0.1", "--rate", "1000", "-q", "--out",
                     str(tmp_path / f"s.{suffix}")]) == 0
    npz = np.load(tmp_path / "s.npz")
    names, units, data = _read_csv(tmp_path / "s.csv")
    assert data.shape[0] == npz["t"].size == npz["tau"].shape[0] + 1
    np.testing.assert_array_equal(_columns(names, data, "tau", (1, 2))[:-1], npz["tau"])
    assert np.isnan(_columns(names, data, "tau", (1, 2))[-1]).all()
    np.testing.assert_array_equal(_columns(names, data, "q", (1, 2)), npz["q"])
    np.testing.assert_array_equal(_columns(names, data, "e1", (1, 2)), npz["e1"])
    mat = scipy.io.loadmat(tmp_path / "s.mat")
    for key in ("t", "q", "dq", "tau", "margins", "e1"):
        np.testing.assert_array_equal(np.asarray(mat[key]).reshape(npz[key].shape), npz[key])


def test_bad_suffix_is_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "run.txt"
    assert main(["simulate", "paper", "--t-final", "0.1", "-q", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and ".csv" in err[0] and ".mat" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_api_simulate_out_by_suffix(tmp_path):
    import symfunnel as sf
    res = sf.simulate("paper", t_final=0.1, out=tmp_path / "a.mat")
    mat = scipy.io.loadmat(tmp_path / "a.mat", squeeze_me=True)
    np.testing.assert_array_equal(mat["t"], res.t)
    np.testing.assert_array_equal(mat["tau"], res.signals["tau"])
    from symfunnel.core.errors import InputError
    with pytest.raises(InputError, match="out"):
        sf.simulate("paper", t_final=0.1, out=tmp_path / "a.xlsx")


def test_sweep_writes_results_csv_equal_to_the_parquet(tmp_path):
    import pyarrow.parquet as pq

    from symfunnel.core.toml_write import dumps
    from symfunnel.scenario import load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["uncertainty"] = [{"key": "plant.mass_scale", "dist": "uniform", "low": 0.8, "high": 1.2}]
    raw["sweep"] = {"runs": 3, "design": "sobol", "seed": 1, "t_final": 0.2}
    f = tmp_path / "c.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    out = tmp_path / "sw"
    assert main(["sweep", str(f), "--out", str(out), "--workers", "1", "-q"]) in (0, 1)
    table = pq.read_table(str(out / "results.parquet")).to_pydict()
    lines = (out / "results.csv").read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("#") and lines[1].startswith("# units: ")
    names = lines[2].split(",")
    units = dict(zip(names, lines[1][len("# units: "):].split(",")))
    assert units["max_abs_tau"] == "N m" and units["t_end"] == "s" and units["min_margin_e1"] == "1"
    assert names == list(table)
    rows = [ln.split(",") for ln in lines[3:]]
    assert len(rows) == 3
    for i, r in enumerate(rows):
        for c, cell in zip(names, r):
            v = table[c][i]
            if c == "status":
                assert cell == v
            elif isinstance(v, float) and np.isnan(v):
                assert cell == ""
            else:
                assert float(cell) == v, c

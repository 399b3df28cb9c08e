"""[[uncertainty]] / [sweep] sections: bad input (one line, exit 2, nothing written) and the designs of experiments."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.scenario import DATA_DIR, from_dict, load_scenario
from symfunnel.core.toml_write import dumps
from symfunnel.scenario.uncertainty import Uncertainty, design_points

MASS = {"key": "plant.mass_scale", "dist": "uniform", "low": 0.8, "high": 1.2}


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def _with(paper, uncs, sweep=None):
    raw = copy.deepcopy(paper.raw)
    raw["uncertainty"] = uncs
    if sweep is not None:
        raw["sweep"] = sweep
    return raw


def _cli_error(paper, tmp_path, capsys, uncs, sweep=None, extra=()):
    f = tmp_path / "campaign.toml"
    f.write_text(dumps(_with(paper, uncs, sweep)), encoding="utf-8")
    out = tmp_path / "out"
    code = main(["sweep", str(f), "--out", str(out), "-q", *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    lines = err.splitlines()
    assert lines[0].startswith("symfunnel: error: ") and not out.exists()
    if len(lines) > 1:                       # one line, or one line and the example it announces
        assert lines[0].endswith("append to the file:)") or lines[0].endswith("append to the copy:)")
        import tomllib
        doc = tomllib.loads("\n".join(x[4:] for x in lines[1:]))
        assert all(x.startswith("    ") for x in lines[1:]) and doc["uncertainty"][0]["key"] == "plant.mass_scale"
    return err


@pytest.mark.parametrize("uncs,sweep,needle", [
    ([dict(MASS, dsit="uniform")], None, "did you mean 'dist'"),
    ([{"key": "plant.mass_scal", "dist": "uniform", "low": 0.8, "high": 1.2}], None,
     "did you mean 'plant.mass_scale'"),
    ([{"key": "controller.k1", "dist": "uniform", "low": 1.0, "high": 2.0}], None, "controller sees"),
    ([{"key": "model.parameters.m4", "dist": "uniform", "low": 1.0, "high": 2.0}], None,
     "did you mean 'plant.parameters.m4'"),
    ([dict(MASS, low=1.2, high=1.2)], None, "low < high"),
    ([{"key": "plant.coulomb", "dist": "normal", "mean": 6.0, "std": 0.0}], None, "uncertainty[0].std"),
    ([{"key": "plant.coulomb", "dist": "normal", "mean": 6.0, "std": -1.0}], None, "uncertainty[0].std"),
    ([{"key": "plant.coulomb", "dist": "choice", "values": []}], None, "uncertainty[0].values"),
    ([dict(MASS, std=1.0)], None, "unknown key for dist = 'uniform'"),
    ([MASS], {"runs": 0}, "sweep.runs"),
    ([MASS], {"runs": 10 ** 7 + 1}, "sweep.runs"),
    ([MASS], {"design": "sobel"}, "sweep.design"),
    ([dict(MASS, per_joint=True)], None, "per_joint"),
    ([dict(MASS, low=0.0)], None, "values > 0"),
    ([{"key": "plant.dead_zone.b_l", "dist": "uniform", "low": -1.0, "high": 0.5}], None, "values < 0"),
    ([{"key": "plant.coulomb", "dist": "normal", "mean": 1.0, "std": 1.0}], None, "mean - 5 std"),
    ([MASS, MASS], None, "given twice"),
])
def test_bad_campaign_is_one_line_exit_2(paper, tmp_path, capsys, uncs, sweep, needle):
    err = _cli_error(paper, tmp_path, capsys, uncs, sweep)
    assert needle in err
    assert "campaign.toml" in err


def test_bad_runs_option_and_missing_uncertainty(paper, tmp_path, capsys):
    assert "--runs" in _cli_error(paper, tmp_path, capsys, [MASS], extra=["--runs", "0"])
    assert "--runs" in _cli_error(paper, tmp_path, capsys, [MASS], extra=["--runs", str(10 ** 7 + 1)])
    assert "[[uncertainty]]" in _cli_error(paper, tmp_path, capsys, [], {"runs": 4})


def test_dead_zone_branch_checked_at_the_extreme_breakpoints(paper):
    """A branch written with the nominal breakpoint's number is only 0 there: varying b_r must be refused."""
    from symfunnel.core.errors import InputError
    raw = _with(paper, [{"key": "plant.dead_zone.b_r", "dist": "uniform", "low": 0.5, "high": 2.0}])
    raw["plant"]["dead_zone"]["right"] = "1.1*(u - 1.0)"
    with pytest.raises(InputError, match="extreme breakpoints"):
        from_dict(raw, file="x.toml", base_dir=DATA_DIR)
    raw["plant"]["dead_zone"]["right"] = "1.1*(u - b_r)"
    assert from_dict(raw, file="x.toml", base_dir=DATA_DIR).campaign is not None


def test_unreachable_scheduler_exits_2_naming_it(paper, tmp_path, capsys):
    import time
    t0 = time.monotonic()
    err = _cli_error(paper, tmp_path, capsys, [MASS], {"runs": 2, "t_final": 0.1},
                     extra=["--scheduler", "tcp://127.0.0.1:9"])
    assert time.monotonic() - t0 < 15
    assert "tcp://127.0.0.1:9" in err and "--scheduler" in err


# --- designs of experiments ------------------------------------------------------------------------------

@pytest.mark.parametrize("design", ["sobol", "lhs", "random"])
def test_each_run_reproduces_alone(design):
    all_ = design_points(design, 3, 7, np.arange(64), 64)
    for i in (0, 1, 17, 63):
        assert np.array_equal(design_points(design, 3, 7, [i], 64)[0], all_[i])
    scattered = [40, 3, 4, 5, 62]
    assert np.array_equal(design_points(design, 3, 7, scattered, 64), all_[scattered])
    assert not np.array_equal(design_points(design, 3, 8, np.arange(64), 64), all_)
    assert ((all_ >= 0) & (all_ < 1)).all()


def test_sobol_is_the_whole_scrambled_sequence_indexed():
    from scipy.stats import qmc
    ref = qmc.Sobol(4, scramble=True, seed=11).random(128)
    assert np.array_equal(design_points("sobol", 4, 11, np.arange(128), 128), ref)


def test_lhs_stratifies_every_coordinate():
    u = design_points("lhs", 3, 5, np.arange(50), 50)
    for j in range(3):
        assert sorted(np.floor(u[:, j] * 50).astype(int)) == list(range(50))


def test_distributions_map_design_points():
    u = design_points("sobol", 1, 0, np.arange(4096), 4096)[:, 0]
    uni = Uncertainty("plant.mass_scale", "uniform", {"low": 0.8, "high": 1.2}, False, ["x"]).transform(u)
    assert uni.min() >= 0.8 and uni.max() < 1.2 and abs(uni.mean() - 1.0) < 1e-3
    nor = Uncertainty("plant.coulomb", "normal", {"mean": 6.0, "std": 0.5}, False, ["x"]).transform(u)
    assert abs(nor.mean() - 6.0) < 5e-3 and abs(nor.std() - 0.5) < 5e-3
    assert np.abs(nor - 6.0).max() <= 5 * 0.5 + 1e-12
    cho = Uncertainty("plant.coulomb", "choice", {"values": [1.0, 2.0, 5.0]}, False, ["x"]).transform(u)
    counts = np.array([np.sum(cho == v) for v in (1.0, 2.0, 5.0)])
    assert counts.sum() == u.size and np.all(np.abs(counts / u.size - 1 / 3) < 0.01)


def test_per_joint_columns_and_values(paper):
    raw = _with(paper, [MASS, {"key": "plant.viscous", "dist": "uniform", "low": 10.0, "high": 20.0,
                               "per_joint": True}], {"runs": 16, "seed": 2})
    c = from_dict(raw, file="x.toml", base_dir=DATA_DIR).campaign
    assert c.columns == ["plant.mass_scale", "plant.viscous[1]", "plant.viscous[2]"]
    v = c.values(range(16))
    assert v.shape == (16, 3) and not np.allclose(v[:, 1], v[:, 2])
    assert math.isclose(float(np.min(v[:, 1:])), 10.0, abs_tol=1.0) and float(np.max(v[:, 1:])) < 20.0


def test_dead_zone_key_needs_a_dead_zone(paper):
    from symfunnel.core.errors import InputError
    raw = _with(paper, [{"key": "plant.dead_zone.left_scale", "dist": "uniform", "low": 0.5, "high": 1.5}])
    del raw["plant"]["dead_zone"]
    with pytest.raises(InputError, match="has no dead zone"):
        from_dict(raw, file="x.toml", base_dir=DATA_DIR)


def test_bad_workers_and_out_file(paper, tmp_path, capsys):
    assert "--workers" in _cli_error(paper, tmp_path, capsys, [MASS], {"runs": 2}, extra=["--workers", "0"])
    f = tmp_path / "campaign.toml"
    f.write_text(dumps(_with(paper, [MASS], {"runs": 2})), encoding="utf-8")
    target = tmp_path / "a-file"
    target.write_text("x")
    assert main(["sweep", str(f), "--out", str(target), "-q"]) == 2
    err = capsys.readouterr().err
    assert "a-file" in err and "a directory" in err and target.read_text() == "x"


def test_toml_writer_round_trips_through_tomllib(paper):
    """What worst.toml is written with loads back (tomllib) to the same document, floats to the last digit."""
    import tomllib
    doc = copy.deepcopy(paper.raw)
    doc["odd keys"] = {"a.b": 1, "ü": "quote \" backslash \\ tab \t newline \n del \x7f é", "x": [1.0 / 3, -0.0, 1e300]}
    doc["nested"] = [{"k": 1, "sub": {"v": [[1, 2], [3]]}}, {"k": 2, "flag": False, "inf": float("inf")}]
    assert tomllib.loads(dumps(doc)) == doc

"""The rate searches' build of the step API (deployed.rate_step): the shipped C text with the period's weights set
at run time, compiled once for every rate of a search. Its runs must be the shipped build's bit for bit at each rate,
its text the shipped text but for the rate's own lines, and a search must compile the step API once."""

from __future__ import annotations

import difflib

import numpy as np
import pytest

from symfunnel.deployed.loop import simulate_sampled
from symfunnel.deployed.rate_step import RateStep, search_sources, search_step
from symfunnel.emit.files import generate
from symfunnel.emit.step import etd_factors, step_settings

T = 0.6           # a short horizon: a few hundred periods of the paper's 2-joint loop


def _arrays(res):
    return {k: getattr(res, k) for k in ("t", "q", "dq", "tau", "margins", "between_margins", "e1")}


@pytest.mark.parametrize("rate", [400.0, 1733.3])
def test_the_search_build_runs_the_shipped_build_bit_for_bit(paper, paper_design, rate):
    shipped = simulate_sampled(paper, paper_design, rate_hz=rate, t_final=T)
    # another rate's step of the same build first: the weights are one global of the library, set per instance
    other = search_step(paper_design, 3 * rate, None)
    searched = simulate_sampled(paper, paper_design, rate_hz=rate, t_final=T, search_build=True)
    simulate_sampled(paper, paper_design, rate_hz=3 * rate, t_final=T, controller=other)
    again = simulate_sampled(paper, paper_design, rate_hz=rate, t_final=T, search_build=True)
    assert shipped.tau.shape[0] == int(T * rate + 1e-9)
    for name, a in _arrays(shipped).items():
        for run in (searched, again):
            np.testing.assert_array_equal(getattr(run, name), a, err_msg=name)    # NaN where NaN, else equal bits
    assert (searched.status, searched.breach) == (shipped.status, shipped.breach)


def test_the_weights_decide_the_run_so_the_comparison_above_can_fail(paper, paper_design):
    """The same build at 400 Hz with the weights of 1200 Hz: another x_esn / W_hat update, another torque."""
    wrong = search_step(paper_design, 1200.0, None)
    wrong.etd = etd_factors(paper, 1200.0)
    right = simulate_sampled(paper, paper_design, rate_hz=400.0, t_final=T, search_build=True)
    bad = simulate_sampled(paper, paper_design, rate_hz=400.0, t_final=T, controller=wrong)
    assert not np.array_equal(right.tau, bad.tau)
    assert isinstance(wrong, RateStep) and wrong.etd != etd_factors(paper, 400.0)


def test_the_search_text_is_the_shipped_text_but_for_the_rates_lines(paper_design):
    rate_hz, tau_max = step_settings(paper_design)           # the scenario's, else the defaults: what ships
    src = search_sources(paper_design, tau_max)
    files = generate(paper_design, "c", rate_hz=rate_hz, tau_max=tau_max)
    hdr = next(k for k in src if k.endswith(".h"))
    base = hdr[:-2]
    assert files[base + ".c"] == src["core.c"] + src["shipped_api.c"]          # the shipped text, split
    rate = repr(float(rate_hz))
    for shipped, searched in ((src["shipped_api.c"], src["api.c"]), (files[hdr], src[hdr])):
        diff = [d for d in difflib.ndiff(shipped.splitlines(), searched.splitlines()) if d[:2] in ("- ", "+ ")]
        removed = [d[2:] for d in diff if d.startswith("- ")]
        added = [d[2:] for d in diff if d.startswith("+ ")]
        assert removed and len(removed) == len(added)
        # every changed line of the shipped text carries the rate or its weights; the search's reads 0.0 there
        phi = [repr(v) for v in etd_factors(paper_design.scenario, rate_hz)]
        assert all(rate in line or all(p in line for p in phi) for line in removed), removed
        assert all(rate not in line for line in added), added
    etd = [line for line in src["api.c"].splitlines() if "etd_[2] =" in line]
    assert etd == ["double symfunnel_etd_[2] = {0.0, 0.0};"]


def test_a_rate_search_compiles_the_step_api_once_and_finds_what_the_per_rate_build_finds(paper, paper_design):
    """From an empty compile cache each (bench.rate_search.cold_search): the previous search linked the step API
    once per rate tried; the search build links it once, and every rate, status and margin is the same."""
    from symfunnel.bench.rate_search import cold_search
    _, old_runs, old = cold_search(paper, paper_design, search_build=False, t_final=T)
    _, new_runs, new = cold_search(paper, paper_design, search_build=True, t_final=T)
    api = [[c for c in runs if "api.c" in c] for runs in (old_runs, new_runs)]
    assert len(new["tried"]) >= 4 and new["min_rate_hz"] is not None
    assert len(api[0]) == len(old["tried"]) and len(api[1]) == 1
    assert len(new_runs) == len(old_runs) - len(old["tried"]) + 1        # nothing else compiled more or less
    assert new == old                                                     # every number of every rate tried


def test_a_removed_compile_cache_is_built_again(paper, paper_design, tmp_path, monkeypatch):
    """The process keeps its search builds' paths; one whose cache directory is gone is compiled again."""
    import shutil

    from symfunnel.deployed import rate_step
    monkeypatch.setattr(rate_step, "_BUILT", [])
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path / "a"))
    first = search_step(paper_design, 500.0, None)
    assert str(first.lib._name).startswith(str(tmp_path / "a"))
    shutil.rmtree(tmp_path / "a")
    monkeypatch.setenv("SYMFUNNEL_CACHE", str(tmp_path / "b"))
    again = search_step(paper_design, 500.0, None)
    assert str(again.lib._name).startswith(str(tmp_path / "b")) and len(rate_step._BUILT) == 1
    res = simulate_sampled(paper, paper_design, rate_hz=500.0, t_final=0.1, controller=again)
    assert res.tau.shape[0] == 50 and np.all(np.isfinite(res.tau))


def test_on_the_physics_engine_the_search_build_runs_the_shipped_build_bit_for_bit(tmp_path):
    """The same comparison with MuJoCo as the plant (deployed.engine drives the step through its raw pointers)."""
    pytest.importorskip("mujoco")
    from symfunnel.cli import main
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    out = tmp_path / "s.toml"
    assert main(["init", "--out", str(out), "--force", "-q"]) == 0         # the 2-link planar arm of `init`
    sc = load_scenario(out)
    design = derive(sc)
    for rate in (300.0, 900.0):
        shipped = simulate_sampled(sc, design, rate_hz=rate, t_final=0.3, engine="mujoco")
        searched = simulate_sampled(sc, design, rate_hz=rate, t_final=0.3, engine="mujoco", search_build=True)
        assert shipped.stats["engine"] == "mujoco" and shipped.tau.shape[0] == int(0.3 * rate + 1e-9)
        for name, a in _arrays(shipped).items():
            np.testing.assert_array_equal(getattr(searched, name), a, err_msg=name)


def test_a_saturated_step_searched_is_the_shipped_one_bit_for_bit(tmp_path):
    """With [implementation] tau_max the step core clamps the torque: the search build runs the shipped build's
    numbers; another limit is another build."""
    from symfunnel.design import derive
    from symfunnel.scenario import load_scenario
    from tests.test_sampled import paper_with
    sc = load_scenario(paper_with(tmp_path, "rate_hz = 2000.0\ntau_max = [400.0, 1000.0]"))
    design = derive(sc)
    shipped = simulate_sampled(sc, design, rate_hz=1500.0, t_final=T)
    searched = simulate_sampled(sc, design, rate_hz=1500.0, t_final=T, search_build=True)
    assert np.max(np.abs(shipped.tau[:, 0])) == 400.0                  # the limit is reached: the clamp matters
    for name, a in _arrays(shipped).items():
        np.testing.assert_array_equal(getattr(searched, name), a, err_msg=name)
    mine = search_step(design, 1500.0, [400.0, 1000.0]).lib._name
    assert search_step(design, 1500.0, [500.0, 1000.0]).lib._name != mine
    assert search_step(design, 1500.0, None).lib._name == mine          # None: the scenario's, as `generate` reads it

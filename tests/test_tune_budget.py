"""The derivative-free search ends on an evaluation count (by default `DERIVATIVE_FREE_EVALUATIONS`), never on a
timing: the same scenario gives the same tuned file under any wall-clock limit that is not reached; a search the
limit does end is reported as such and marked timing-dependent."""

from __future__ import annotations

import copy
import json
import shutil

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.core.toml_write import dumps
from symfunnel.scenario import load_scenario

needs_gcc = pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not available")


def sampled_paper(tmp_path, t_final: float = 0.5):
    """The paper deployed at 1 kHz with |tau| <= 200 N m (the derivative-free path), short horizon, two parameters."""
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = t_final
    raw["implementation"] = {"rate_hz": 1000.0, "tau_max": 200.0}
    raw["tune"] = {"objective": "peak_torque", "parameters": ["controller.k2", "funnel.e2.phi_inf"]}
    return _write(tmp_path, raw)


def _write(tmp_path, raw: dict):
    p = tmp_path / "s.toml"
    p.write_text(dumps(raw), encoding="utf-8")
    return p


@needs_gcc
@pytest.mark.slow
def test_the_default_budget_ends_the_search_and_two_limits_write_the_same_file(tmp_path, capsys, monkeypatch):
    from symfunnel.synthesis import search
    monkeypatch.setattr(search, "DERIVATIVE_FREE_EVALUATIONS", 7)     # the default budget, made cheap
    src = sampled_paper(tmp_path)
    outs, results = [], []
    for i, limit in enumerate(("90", "400")):                          # both far above what 7 evaluations need
        out = tmp_path / f"tuned{i}.toml"
        code = main(["tune", str(src), "--out", str(out), "--json", "-q", "--wall-limit", limit])
        res = json.loads(capsys.readouterr().out)
        assert code in (0, 1), res
        outs.append(out.read_bytes())
        results.append(res)
    for res in results:
        assert res["method"].startswith("derivative-free"), res["method"]
        assert res["evaluations"] == 7 and res["ended_by"] == "evaluations" and res["timing_dependent"] is False
        assert any("after 7 evaluations" in n and "default budget" in n for n in res["notes"]), res["notes"]
        assert not any("timing-dependent" in n for n in res["notes"])
    assert outs[0] == outs[1]
    assert results[0]["changes"] == results[1]["changes"] and results[0]["changes"]   # the search moved the design


@needs_gcc
def test_a_search_the_wall_limit_ends_says_so_and_is_marked_timing_dependent(tmp_path, capsys, monkeypatch):
    from symfunnel.synthesis import search
    # a tiny limit for the search (its share of --wall-limit): the first new candidate is past it; the command's
    # whole limit stays ample, so what ends the search is the limit, not an error of the command
    monkeypatch.setattr(search, "SEARCH_SHARE", 1e-9)
    src = sampled_paper(tmp_path, t_final=0.3)
    code = main(["tune", str(src), "--json", "-q", "--wall-limit", "120"])
    res = json.loads(capsys.readouterr().out)
    assert code in (0, 1)
    assert res["evaluations"] == 1 and res["ended_by"] == "wall-limit" and res["timing_dependent"] is True
    assert any("wall-clock limit" in n for n in res["notes"])
    code = main(["tune", str(src), "-q", "--wall-limit", "120"])       # the text output says it too
    text = capsys.readouterr().out
    assert "search stopped at the wall-clock limit" in text and "timing-dependent" in text
    # the same scenario with an evaluation count: not timing-dependent
    monkeypatch.setattr(search, "SEARCH_SHARE", 0.8)
    code = main(["tune", str(src), "--json", "-q", "--max-evals", "2", "--wall-limit", "120"])
    res = json.loads(capsys.readouterr().out)
    assert res["evaluations"] == 2 and res["ended_by"] == "evaluations" and res["timing_dependent"] is False


def test_an_ipopt_pass_its_wall_time_ended_marks_the_result_timing_dependent(tmp_path, capsys, monkeypatch):
    from symfunnel.synthesis import gradient as G, search
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = 0.3
    raw.pop("implementation", None)
    raw["tune"] = {"tau_max": 200.0, "parameters": ["controller.k2"]}

    def timed_out(self, z0, **kw):         # IPOPT's answer when its max_wall_time ended the pass (a timing)
        return {"z": np.asarray(z0, float), "status": "Maximum_WallTime_Exceeded", "success": False,
                "iterations": 3, "f": 1.0, "coarse": None}
    monkeypatch.setattr(G.GradientProblem, "solve", timed_out)
    sc = load_scenario(_write(tmp_path, raw))
    r = search.tune(sc, max_evaluations=2, gate=False, method="gradient", wall_limit=120.0)
    assert r.method.startswith("gradient")          # (the stand-in runs in IPOPT's forked child)
    assert r.timing_dependent is True and r.ended_by == "evaluations"
    assert any("IPOPT's pass of start 1" in n and "timing-dependent" in n for n in r.notes), r.notes


@needs_gcc
def test_verify_gate_ended_by_the_wall_limit_marks_the_result_timing_dependent(tmp_path, monkeypatch):
    from symfunnel.core import deadline as DL
    from symfunnel.synthesis import search

    def gate_past_the_limit(scenario, progress=None):      # the gate interrupted by the command's limit
        raise DL.WallLimitReached(120.0, "verify's gate", 120.0)
    monkeypatch.setattr(search, "verify_gate", gate_past_the_limit)
    r = search.tune(load_scenario(sampled_paper(tmp_path)), max_evaluations=12, wall_limit=120.0)
    assert r.ended_by == "evaluations"                        # the search itself ended on its count
    assert r.gate["status"] == "not completed" and r.status == "infeasible"
    assert r.timing_dependent is True and any("ended verify's gate" in n for n in r.notes), r.notes

"""tune says which parameter ended at a bound of [tune.bounds] (`synthesis.active`): on the log scale of the search,
within AT_BOUND of either end; the JSON carries the list and the notes say it in words."""

from __future__ import annotations

import math

from symfunnel.synthesis.active import AT_BOUND, at_bounds
from symfunnel.synthesis.candidates import Variable
from symfunnel.synthesis.search import TuneResult


def _var(key="controller.k1", lo=0.1, hi=100.0, base=(5.0, 5.0)):
    return Variable(key, None, lo, hi, list(base), [1.0, 1.0])


def test_values_at_and_near_the_bounds():
    v = _var()
    span = math.log(1000.0)
    inside = 0.1 * math.exp(0.5 * AT_BOUND * span)       # half the tolerance above the lower bound
    outside = 0.1 * math.exp(2.0 * AT_BOUND * span)      # twice the tolerance: not at the bound
    got = at_bounds([v, v, v, v, v], [0.1, 100.0, 5.0, inside, outside])
    assert [(e["bound"], e["value"]) for e in got] == [("lower", 0.1), ("upper", 100.0), ("lower", inside)]
    assert got[0] == {"key": "controller.k1", "value": 0.1, "bound": "lower", "bound_value": 0.1, "before": 5.0}
    # one joint's coordinate is named with its joint
    w = Variable("controller.k2", 1, 0.5, 50.0, [10.0, 20.0], [])
    assert at_bounds([w], [50.0])[0]["key"] == "controller.k2[2]" and at_bounds([w], [50.0])[0]["before"] == 20.0


def test_json_has_the_active_bounds():
    r = TuneResult(status="ok", method="m", why="w", objective={}, changes=[], binding=[], wall_s=0.0,
                   evaluations=0, constraints={}, samples=0, confidence=None, gate={}, tuned_raw={}, notes=[],
                   at_bounds=at_bounds([_var()], [0.1]))
    assert r.to_json()["at_bounds"][0]["bound"] == "lower"


def test_degradations_flag_tracking_and_chattering_beyond_twice():
    from symfunnel.synthesis.active import degradations
    before = {"e1_rms_after_transient": 1e-4, "chattering": 10.0}
    assert degradations(before, {"e1_rms_after_transient": 1.9e-4, "chattering": 19.0}) == []
    notes = degradations(before, {"e1_rms_after_transient": 2.6e-2, "chattering": 25.0})
    assert len(notes) == 2 and "grew 260x" in notes[0] and "tracking" in notes[0] and "grew 2.5x" in notes[1]
    assert degradations({"chattering": 0.0}, {"chattering": 5.0}) == []      # no ratio to an idle torque


def test_report_tuning_rows_show_the_margin_tune_ranks_by_labelled(tmp_path):
    """The report's original/tuned table: the post-transient margin (tune's measure, labelled so) beside the
    whole-run one, and the e1 RMS and chattering; each against numpy on the two runs' own signals."""
    import copy

    import numpy as np

    from symfunnel.core.toml_write import dumps
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting.sections import tuning_section
    from symfunnel.reporting.text import fmt
    from symfunnel.scenario import load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = 1.0
    raw["controller"]["k2"] = 4.0
    raw["deviations"] = list(raw.get("deviations") or []) + [
        {"key": "controller.k2", "paper": "", "value": "10.0 -> 4.0", "reason": "symfunnel tune (ok): test"}]
    f = tmp_path / "tuned.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    run = Run(load_scenario(f), RunOptions(t_final=1.0))
    sec = tuning_section(run, lambda s: None)
    rows = {k.split(" (")[0]: (a, b) for k, a, b in sec["rows"]}
    sim = run.simulation
    ts = sim.margins()["settle_time"]
    keep = sim.t >= ts - 1e-12
    assert rows["min margin e1 after the transient"][1] == fmt(float(np.min(sim.signals["m1"][keep])))
    assert rows["min margin e2, whole run"][1] == fmt(float(np.min(sim.signals["m2"])))
    e1 = sim.signals["e1"][keep]
    rms = np.sqrt(np.sum(0.5 * (e1[1:] ** 2 + e1[:-1] ** 2) * np.diff(sim.t[keep])[:, None], axis=0)
                  / (sim.t[keep][-1] - sim.t[keep][0]))
    assert rows["e1 RMS after the transient [rad]"][1] == fmt(float(np.max(rms)))
    assert "as in tune's table" in next(k for k, _, _ in sec["rows"] if k.startswith("min margin e1 after"))


def test_tracking_constraint_against_an_independent_run(tmp_path):
    """[tune] tracking = 2: a candidate's constraint is 1 - rms / (2 rms0), rms its nominal e1 RMS after the
    transient (max over joints) and rms0 the user's design's; both recomputed with numpy from plain runs."""
    import copy

    import numpy as np
    import pytest

    from symfunnel.core.toml_write import dumps
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.scenario import load_scenario
    from symfunnel.synthesis.search import Evaluator, _with_tracking, variables
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["simulation"]["t_final"] = 2.0
    raw["tune"] = {"parameters": ["controller.k1"], "objective": "peak_torque", "tracking": 2.0}
    f = tmp_path / "t.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    sc = load_scenario(f)
    ev = Evaluator(sc, sc.tune)
    vars_ = variables(sc, sc.tune)
    before = _with_tracking(ev, sc.tune, ev.evaluate(vars_, [5.0]), lambda s: None)
    assert before.constraints["tracking"] == pytest.approx(0.5)
    c = ev.evaluate(vars_, [0.1])

    def rms(k1):
        r = copy.deepcopy(raw)
        r["controller"]["k1"] = k1
        g = tmp_path / f"k{k1}.toml"
        g.write_text(dumps(r), encoding="utf-8")
        sim = Run(load_scenario(g), RunOptions(t_final=2.0)).simulation
        keep = sim.t >= sim.margins()["settle_time"] - 1e-12
        t, e = sim.t[keep], sim.signals["e1"][keep]
        ise = np.sum(0.5 * (e[1:] ** 2 + e[:-1] ** 2) * np.diff(t)[:, None], axis=0)
        return float(np.max(np.sqrt(ise / (t[-1] - t[0]))))
    r0, r1 = rms(5.0), rms(0.1)
    assert ev.tracking_ref == pytest.approx(r0, rel=1e-9)
    assert c.constraints["tracking"] == pytest.approx(1 - r1 / (2 * r0), rel=1e-9)
    assert r1 > 2 * r0 and not c.feasible          # k1 = 0.1 tracks far worse: the constraint rejects it


def test_tracking_below_one_is_bad_input(tmp_path, capsys):
    import copy

    from symfunnel.cli import main
    from symfunnel.core.toml_write import dumps
    from symfunnel.scenario import load_scenario
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["tune"] = {"tracking": 0.5}
    f = tmp_path / "t.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    assert main(["tune", str(f), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tune.tracking" in err[0]

"""The run loop in C (simulation/crun.py, csrc/cvodes_loop.c) against the Python loop it transcribes: the same run
bit for bit -- times, states, every logged signal, the extremes between output points, the integrator's counts, the
breach -- on the paper, arm7, a URDF robot, a funnel that dips between output points and a breach; and the C loop
really ran the chunks (a run handing every chunk back to Python would pass the comparison vacuously)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.simulation import crun
from symfunnel.simulation.run import simulate

from .conftest import PAPER, REPO

#: a funnel e1 that dips for about a millisecond between output points 0.50 and 0.51 (test_between_points' dip)
DIP_F1 = "0.18*exp(-2*t) + 0.01 - 0.06*exp(-((t - 0.5025)/0.0005)^2)"


def _paper_variant(tmp_path, name: str, edits: dict[str, str]):
    text = PAPER.read_text()
    for old, new in edits.items():
        text, k = re.subn(old, new, text)
        assert k == 1, old
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return load_scenario(p)


def _dip(tmp_path, depth: float):
    return _paper_variant(tmp_path, f"dip{depth}", {
        r"\[funnel\.e1\]\nphi0 = 0\.18\nphi_inf = 0\.01\na = 2\.0":
            f'[funnel.e1]\nF = "{DIP_F1.replace("0.06", repr(depth))}"',
        r"\[initial\]\nq = \[0\.0, 0\.0\]\ndq = \[0\.0, 0\.0\]": "[initial]\nq = [0.0, 0.0]\ndq = [0.3, 0.3]"})


def _scenario(which: str, tmp_path):
    if which == "urdf":
        s = tmp_path / "robot.toml"
        assert main(["init", "--urdf", str(REPO / "tests" / "data" / "branched.urdf"), "--out", str(s), "-q"]) == 0
        return load_scenario(s), 1.0
    if which == "dip":
        return _dip(tmp_path, 0.06), 0.6
    if which in ("paper", "arm7"):
        return load_scenario(which), {"paper": 2.0, "arm7": 0.3}[which]
    text = (REPO / "derivations" / "sim_breach.toml").read_text()
    if which == "breach":                      # at t = 0.017 s, in the first chunk
        return load_scenario(REPO / "derivations" / "sim_breach.toml"), 0.5
    # the disturbance switched on around t = 1 s, the friction lowered: the breach ends the run at t = 1.07 s
    late = 'disturbance = ["60*sin(3*t)/(1 + exp(-40*(t - 1)))", "0"]'
    for old, new in (('disturbance = ["60*sin(3*t)", "0"]', late),
                     ("coulomb = 6.0", "coulomb = 0.0"), ("viscous = 15.0", "viscous = 1.0")):
        assert old in text
        text = text.replace(old, new)
    p = tmp_path / "late_breach.toml"
    p.write_text(text)
    return load_scenario(p), 1.5


def _both(sc, tf, monkeypatch):
    """The run with the C loop (and the return codes of its calls) and with the Python loop."""
    d = derive(sc)
    calls = []
    advance = crun.CLoop.advance

    def spy(self, **kw):
        a = advance(self, **kw)
        calls.append((a.rc, a.t.size))
        return a
    monkeypatch.setattr(crun.CLoop, "advance", spy)
    monkeypatch.setattr(crun, "RUN_IN_C", True)
    a = simulate(sc, d, t_final=tf)
    monkeypatch.setattr(crun, "RUN_IN_C", False)
    n_calls = len(calls)
    b = simulate(sc, d, t_final=tf)
    assert len(calls) == n_calls                 # the Python loop did not call it
    return a, b, calls


def _assert_same(a, b):
    assert (a.status, a.message, a.breach) == (b.status, b.message, b.breach)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.x, b.x, equal_nan=True)
    assert a.signals.keys() == b.signals.keys()
    for k in b.signals:
        assert np.array_equal(a.signals[k], b.signals[k], equal_nan=True), k
    for k in ("steps", "rhs_evaluations", "jacobian_evaluations", "error_test_failures", "between", "event_counts",
              "cvodes_backend"):
        assert json.dumps(a.stats[k], sort_keys=True) == json.dumps(b.stats[k], sort_keys=True), k


@pytest.mark.parametrize("which", ["paper", pytest.param("arm7", marks=pytest.mark.slow), "urdf", "dip",
                                   "late_breach", "breach"])
def test_the_c_loop_is_the_python_loop_bit_for_bit(which, tmp_path, monkeypatch):
    sc, tf = _scenario(which, tmp_path)
    a, b, calls = _both(sc, tf, monkeypatch)
    assert calls, "the C loop was not used"
    kept = sum(n for _, n in calls)
    if which != "breach":
        assert kept >= 25, calls                 # at least the first chunk came from C
    if which in ("paper", "arm7", "urdf", "dip"):
        assert a.status == "ok" and calls[-1][0] == crun.DONE and kept == a.t.size - 1, calls
    if which == "dip":
        assert a.stats["between"]["refined_steps"] > 0
    if which in ("late_breach", "breach"):
        assert a.status == "breach" and calls[-1][0] == crun.HANDOVER, calls
    _assert_same(a, b)


def test_a_history_too_large_to_keep_is_integrated_again_in_c(monkeypatch):
    """A chunk whose kept steps pass HISTORY_BYTES is integrated again on its dense grid (runner.py's fallback), in
    C as in Python: the same run, and no chunk handed back (arm7's 20 s run has such a chunk at t = 11.25 s)."""
    from symfunnel.simulation import sundials
    monkeypatch.setattr(sundials, "HISTORY_BYTES", 2e5)
    a, b, calls = _both(load_scenario("paper"), 1.0, monkeypatch)
    assert a.ok and [rc for rc, _ in calls] == [crun.DONE], calls
    _assert_same(a, b)


def test_the_comparison_sees_a_changed_run(tmp_path, monkeypatch):
    """Not vacuous: a C loop refining on another number of points gives another run."""
    sc, tf = _scenario("dip", tmp_path)
    d = derive(sc)
    a = simulate(sc, d, t_final=tf)
    monkeypatch.setattr(crun, "REFINE_POINTS", 128)
    b = simulate(sc, d, t_final=tf)
    assert a.stats["between"]["refined_steps"] == b.stats["between"]["refined_steps"] > 0
    assert a.stats["between"]["points"] != b.stats["between"]["points"]


def test_env_selects_the_python_loop(tmp_path, monkeypatch):
    sc, tf = load_scenario("paper"), 0.3
    d = derive(sc)
    called = []
    monkeypatch.setattr(crun.CLoop, "advance", lambda self, **kw: called.append(1) or (_ for _ in ()).throw(
        AssertionError("C loop used")))
    monkeypatch.setenv("SYMFUNNEL_RUN_LOOP", "python")
    r = simulate(sc, d, t_final=tf)
    assert r.ok and not called


@pytest.mark.parametrize("which", ["paper", "dip"])
def test_samples_written_in_place_or_copied_into_time_order_give_the_python_loops_run(which, tmp_path, monkeypatch):
    """The C loop's two placements of the samples between output points (straight into their rows in time order,
    the default, and the previous buffer-then-copy kept as the bench's baseline) are each the Python loop's run."""
    sc, tf = _scenario(which, tmp_path)
    monkeypatch.setattr(crun, "SAMPLES_IN_PLACE", False)
    copied, py, calls = _both(sc, tf, monkeypatch)
    assert calls and copied.ok
    _assert_same(copied, py)
    monkeypatch.setattr(crun, "SAMPLES_IN_PLACE", True)
    placed, _, calls = _both(sc, tf, monkeypatch)
    assert calls and [rc for rc, _ in calls][-1] == crun.DONE
    _assert_same(placed, py)

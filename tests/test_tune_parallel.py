"""tune's IPOPT starts run side by side (issue 43): `worker.start_killable` starts forked calls at once and collects
them in order; `search._gradient_search` judges the starts' results in the starts' order whatever order they end in,
and stops the starts it does not collect."""

from __future__ import annotations

import os
import time
from types import SimpleNamespace

import numpy as np
import pytest

from symfunnel.core.worker import run_killable, start_killable


def _timed_call(sleep_s: float, value):
    """(start, end, value, pid): when the call ran and in which process."""
    t0 = time.monotonic()
    time.sleep(sleep_s)
    return time.monotonic(), t0, value, os.getpid()


def test_started_calls_overlap_and_come_back_in_order():
    jobs = [start_killable(_timed_call, 0.6, k) for k in range(3)]
    out = [j.result(wall_limit=30.0) for j in jobs]
    assert [o[2] for o in out] == [0, 1, 2]
    assert len({o[3] for o in out} | {os.getpid()}) == 4          # three children, none of them this process
    ends, starts = [o[0] for o in out], [o[1] for o in out]
    # each call began before the first one ended: they ran side by side, not one after the other (which
    # run_killable, waiting for each call before the next, gives: its second call starts after the first ends)
    assert max(starts) < min(ends)
    seq = [run_killable(_timed_call, 0.2, k) for k in range(2)]
    assert seq[1][1] >= seq[0][0]


def test_killed_call_leaves_no_child_and_errors_come_back():
    slow = start_killable(time.sleep, 60)
    bad = start_killable(lambda: 1 / 0)
    pid = slow.pid
    slow.kill()
    with pytest.raises(ChildProcessError):                      # reaped: no child of that id any more
        os.waitpid(pid, os.WNOHANG)
    with pytest.raises(ZeroDivisionError):
        bad.result(wall_limit=30.0)
    slow.kill()                                                  # a second kill is a no-op


class _FakeProblem:
    """A stand-in for `gradient.GradientProblem`: `solve` returns z0 / 2 after a delay that is longest for the first
    start, so the starts end in the reverse of their order."""

    d, ng, nplants, K = 2, 4, 1, 3

    def __init__(self, delays):
        self.delays = delays

    def solve(self, z0, *, objective, ref, wall_s, progress=None):
        k = int(round(float(z0[1]) * 1000)) % len(self.delays)     # which start this is (encoded in z0, below)
        time.sleep(self.delays[k])
        return {"z": np.asarray(z0) / 2, "status": "ok", "iterations": 1, "f": 0.0, "coarse": None,
                "ended": time.monotonic()}


def _search(monkeypatch, delays, max_evaluations=None):
    from symfunnel.synthesis import search
    starts = [np.array([0.5, 0.0]), np.array([0.25, 0.001]), np.array([0.75, 0.002])]
    monkeypatch.setattr("symfunnel.core.sobol.sobol", lambda d, n, skip: [s.copy() for s in starts[1:1 + n]])
    monkeypatch.setattr(search, "GRADIENT_SOBOL_STARTS", len(starts) - 1)
    judged = []
    ev = SimpleNamespace(count=0)

    def f(z, final=False):
        judged.append(np.asarray(z).copy())
        ev.count += 1
        return 0.0
    spec = SimpleNamespace(objective="peak_torque")
    vars_ = [None, None]
    lines: list[str] = []
    try:
        search._gradient_search(_FakeProblem(delays), vars_, ev, starts[0].copy(), f, {}, lines.append, spec,
                                deadline=time.perf_counter() + 60.0, max_evaluations=max_evaluations)
    except search._OutOfTime as exc:
        lines.append(f"out of time: {exc}")
    return starts, judged, lines


def test_gradient_search_judges_the_starts_in_order_whatever_order_they_end_in(monkeypatch):
    starts, judged, lines = _search(monkeypatch, delays=[0.8, 0.4, 0.0])
    assert [list(z) for z in judged] == [list(s / 2) for s in starts]
    assert any("3 starts side by side" in s for s in lines)


def test_gradient_search_stops_at_the_evaluation_cap_and_kills_the_rest(monkeypatch):
    import symfunnel.core.lifecycle as lc
    before = set(lc._children)              # what earlier tests of this worker left registered is not this test's
    starts, judged, lines = _search(monkeypatch, delays=[0.0, 30.0, 30.0], max_evaluations=1)
    assert [list(z) for z in judged] == [list(starts[0] / 2)]
    assert any("after 1 evaluations" in s for s in lines)
    assert set(lc._children) <= before                          # the two uncollected starts were killed and reaped


def test_sequential_starts_the_bench_baseline_judge_the_same(monkeypatch):
    """$SYMFUNNEL_TUNE_STARTS=sequential (bench `tune.paper_side_by_side_wall_s`'s baseline): one start after the
    other, the same results judged in the same order."""
    monkeypatch.setenv("SYMFUNNEL_TUNE_STARTS", "sequential")
    starts, judged, lines = _search(monkeypatch, delays=[0.2, 0.1, 0.0])
    assert [list(z) for z in judged] == [list(s / 2) for s in starts]
    assert any("3 starts one after the other" in s for s in lines)


def test_a_start_that_fails_to_launch_stops_the_ones_already_started(monkeypatch):
    """The third start failing as it is launched (a signal, the command's limit, fork failing) kills and reaps the
    two started before it instead of leaving them running and registered."""
    import symfunnel.core.lifecycle as lc
    import symfunnel.core.worker as worker
    started = []

    def launching(fn, *args, **kwargs):
        if len(started) == 2:
            raise OSError("fork failed")
        job = start_killable(fn, *args, **kwargs)
        started.append(job.pid)
        return job
    monkeypatch.setattr(worker, "start_killable", launching)
    before = set(lc._children)
    with pytest.raises(OSError, match="fork failed"):
        _search(monkeypatch, delays=[30.0, 30.0, 30.0])
    assert len(started) == 2
    for pid in started:
        with pytest.raises(ChildProcessError):                  # reaped: no child of that id any more
            os.waitpid(pid, os.WNOHANG)
    assert set(lc._children) <= before

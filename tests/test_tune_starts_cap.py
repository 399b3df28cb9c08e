"""tune's IPOPT starts launched side by side only as far as the evaluations left can judge them (issue 43): each
start's result costs one evaluation (none when it repeats a design already judged), so with `--max-evals 2` (the
user's design plus one) the second and third starts' IPOPT runs were killed unheard; they are now not launched.
The harness (a stand-in problem whose `solve` halves z0) is tests/test_tune_parallel.py's."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from tests.test_tune_parallel import _FakeProblem, _search


def _counting(monkeypatch) -> list:
    """Count the forked starts (`worker.start_killable`, imported by the search at call time)."""
    import symfunnel.core.worker as worker
    real = worker.start_killable
    launched = []

    def counted(fn, *args, **kwargs):
        launched.append(np.asarray(args[0]).copy())
        return real(fn, *args, **kwargs)
    monkeypatch.setattr(worker, "start_killable", counted)
    return launched


def test_a_start_the_evaluation_cap_cannot_judge_is_not_launched(monkeypatch):
    launched = _counting(monkeypatch)
    starts, judged, lines = _search(monkeypatch, delays=[0.0, 0.0, 0.0], max_evaluations=1)
    assert [list(z) for z in judged] == [list(starts[0] / 2)]          # the same result as before
    assert any("after 1 evaluations" in s for s in lines)
    assert len(launched) == 1                                           # was 3: two IPOPT runs killed unheard
    assert any("1 at once" in s for s in lines)
    # without a cap all three run side by side, as before
    launched.clear()
    starts, judged, lines = _search(monkeypatch, delays=[0.2, 0.1, 0.0])
    assert len(launched) == 3 and [list(z) for z in judged] == [list(s / 2) for s in starts]


def test_a_start_whose_result_was_already_judged_lets_the_next_one_run(monkeypatch):
    """A result that repeats a judged design costs no evaluation (`f` returns its score from `seen`): the cap then
    reaches one start further, which is launched when its turn comes and judged as before."""
    from symfunnel.synthesis import search
    launched = _counting(monkeypatch)
    starts = [np.array([0.5, 0.0]), np.array([0.25, 0.001]), np.array([0.75, 0.002])]
    monkeypatch.setattr("symfunnel.core.sobol.sobol", lambda d, n, skip: [s.copy() for s in starts[1:1 + n]])
    monkeypatch.setattr(search, "GRADIENT_SOBOL_STARTS", 2)
    judged, seen = [], set()
    ev = SimpleNamespace(count=0)

    def f(z, final=False):
        judged.append(np.asarray(z).copy())
        key = round(float(z[0]), 10)
        if key not in seen and len(judged) > 1:          # the first result is a design judged before: free
            ev.count += 1
        seen.add(key)
        return 0.0
    lines: list[str] = []
    try:
        search._gradient_search(_FakeProblem([0.0, 0.0, 0.0]), [None, None], ev, starts[0].copy(), f, {},
                                lines.append, SimpleNamespace(objective="peak_torque"),
                                deadline=time.perf_counter() + 60.0, max_evaluations=1)
    except search._OutOfTime as exc:
        lines.append(str(exc))
    assert [list(z) for z in judged] == [list(starts[0] / 2), list(starts[1] / 2)]
    assert len(launched) == 2 and [list(z) for z in launched] == [list(starts[0]), list(starts[1])]


def test_no_start_is_launched_when_the_cap_is_already_spent(monkeypatch):
    from symfunnel.synthesis import search
    launched = _counting(monkeypatch)
    monkeypatch.setattr("symfunnel.core.sobol.sobol", lambda d, n, skip: [np.array([0.25, 0.001])] * n)
    ev = SimpleNamespace(count=2)
    lines: list[str] = []
    try:
        search._gradient_search(_FakeProblem([0.0]), [None, None], ev, np.array([0.5, 0.0]), lambda z, final=False: 0.0,
                                {}, lines.append, SimpleNamespace(objective="peak_torque"),
                                deadline=time.perf_counter() + 60.0, max_evaluations=2)
    except search._OutOfTime as exc:
        lines.append(str(exc))
    assert launched == [] and "after 2 evaluations" in lines[-1]

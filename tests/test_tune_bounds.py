"""tune says which parameter ended at a bound of [tune.bounds] (`synthesis.active`): on the log scale of the search,
within AT_BOUND of either end; the JSON carries the list and the notes say it in words."""

from __future__ import annotations

import math

from symfunnel.synthesis.active import AT_BOUND, at_bounds
from symfunnel.synthesis.search import TuneResult, Variable


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

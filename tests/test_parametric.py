"""The closed loop compiled once with the plant's uncertain quantities as parameters p (and x0 as the initial state)."""

from __future__ import annotations

import numpy as np
import pytest

from symfunnel.scenario import load_scenario
from symfunnel.simulate import simulate

# The paper run's summary, recorded before the plant's quantities became parameters of the compiled loop
# (commit e9d59c2, values compiled into the code): parameterising must not change what `simulate` gives.
PINNED_PAPER = {"min_margin_e1": [0.9796013764050912, 0.9683783515271457],
                "min_margin_e2": [0.26829268292682934, 0.26829268292682934],
                "max_abs_tau": [501.5964766017037, 165.62490465631925]}


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def test_paper_run_unchanged_by_parameterisation(paper):
    s = simulate(paper).summary()
    assert s["status"] == "ok"
    for k, v in PINNED_PAPER.items():
        assert s[k] == pytest.approx(v, rel=1e-6), k

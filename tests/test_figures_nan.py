"""Row 22 of issue 21: "All-NaN slice encountered" on every report of a scenario without a printed decay claim --
the falsification figure took the worst margin of bins that held NaN only (the claim's rhs is NaN throughout)."""

from __future__ import annotations

import warnings

import numpy as np

from symfunnel.reporting.figures import falsification


def _fz(rhs_paper):
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0, 10, 400))
    V_dot = -rng.uniform(0.1, 1.0, 400)
    rhs = V_dot + 0.05                                   # the corrected inequality holds everywhere
    return {"arrays": {"t": t, "V_dot": V_dot, "rhs": rhs, "rhs_paper": rhs_paper(V_dot)}, "t_range": (0.0, 10.0),
            "samples": 400}


def test_a_scenario_without_a_printed_claim_draws_no_series_for_it_and_warns_nothing():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        svg = falsification(_fz(lambda v: np.full_like(v, np.nan)))
    assert "Theorem 1 as printed" not in svg and "0 of 400 violate" in svg


def test_nan_samples_are_left_out_of_the_counts_not_counted_as_holding():
    def some_nan(V_dot):
        r = V_dot - 0.05                                 # violated everywhere ...
        r[:100] = np.nan                                 # ... except where it is undefined
        return r
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        svg = falsification(_fz(some_nan), claim="Theorem 1")
    assert "printed claim Theorem 1: 300 of 300 violate" in svg

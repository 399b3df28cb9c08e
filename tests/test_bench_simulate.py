"""bench.simulate.against_previous: this path and the previous one run in fresh processes and integrate the same
trajectory (the same CVODES step counts: the changes they compare are copies and heap settings, not arithmetic)."""

from symfunnel.bench.simulate import against_previous


def test_against_previous_runs_both_paths_on_the_same_trajectory():
    r = against_previous("paper", 1.0, perturbations=(0.0, 1e-11), rounds=1)
    assert len(r["this"]) == len(r["previous"]) == 2
    assert r["steps_this"] == r["steps_previous"] and min(r["steps_this"]) > 50
    assert all(c > 0 for c in r["this"] + r["previous"]) and r["paired_ratio"] > 0

"""`between.refine_peaks`: each joint's largest |tau| refined on its output step, a step integrated once however many
joints peak in it, and the run's figures those of refining it once per joint (the path before)."""

from __future__ import annotations

import numpy as np

import symfunnel.simulation.between as between_mod
from symfunnel.simulation.closedloop import build_closed_loop
from symfunnel.simulation.run import simulate


def _per_joint(result, runner, comp, between) -> None:
    """The reference: every (joint, step) pair integrated on its own, as refine_peaks did before."""
    t, X, h = result.t, result.x, runner.h
    tau = np.abs(result.signals["tau"])
    for j in range(between.n):
        i = int(np.nanargmax(np.where(np.isfinite(tau[:, j]), tau[:, j], -np.inf)))
        best, tb = float(tau[i, j]), float(t[i])
        if np.isfinite(between.tau[j]) and between.tau[j] > best:
            best, tb = float(between.tau[j]), float(between.t_tau[j])
        k = int(np.searchsorted(t, tb, side="left"))
        for a in sorted({max(k - 1, 0), min(k, t.size - 2)}):
            if t[a + 1] - t[a] < 0.5 * h or t[a + 1] - t[a] > 1.5 * h:
                continue
            r = between_mod.refine(runner, comp, between.n, float(t[a]), X[a], float(t[a + 1] - t[a]))
            if r is not None:
                between.update(r[0], r[2], 0)


def test_joints_peaking_in_one_step_share_its_refinement_and_the_run_is_unchanged(paper, paper_design,
                                                                                  monkeypatch):
    cl = build_closed_loop(paper, paper_design)
    calls = []
    real = between_mod.refine

    def counting(runner, comp, n, t_a, x_a, h):
        calls.append((t_a, h, x_a.tobytes()))
        return real(runner, comp, n, t_a, x_a, h)
    monkeypatch.setattr(between_mod, "refine", counting)
    new = simulate(paper, paper_design, t_final=0.3, closed_loop=cl, fixed_chunks=True)
    # every refine call left after the C loop is refine_peaks' (the run stays in C): one per distinct step
    assert len(calls) == len(set(calls)) >= 1
    # the paper's joints both peak in the first output step (the initial error is largest): one integration there
    tau = np.abs(new.signals["tau"])
    assert new.t[int(np.argmax(tau[:, 0]))] <= new.t[1] and new.t[int(np.argmax(tau[:, 1]))] <= new.t[1]
    assert len(calls) == 1 and calls[0][0] == 0.0
    monkeypatch.setattr(between_mod, "refine_peaks", _per_joint)
    import symfunnel.simulation.run as run_mod
    monkeypatch.setattr(run_mod, "refine_peaks", _per_joint)
    calls.clear()
    old = simulate(paper, paper_design, t_final=0.3, closed_loop=cl, fixed_chunks=True)
    assert len(calls) == 2                      # the reference integrates the shared step once per joint
    assert old.stats["between"] == new.stats["between"]       # every extreme, time and count, exactly
    assert old.message == new.message
    for key in ("tau", "m1", "m2"):
        assert old.extreme(key) == new.extreme(key)
    np.testing.assert_array_equal(old.x, new.x)

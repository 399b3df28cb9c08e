"""The engineer's metrics (`simulation.metrics`): each against a synthetic signal whose answer is known in closed form,
and `simulate --json`'s block against a numpy computation on the run's own npz (continuous and sampled loop)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from symfunnel.cli import main
from symfunnel.simulation.metrics import SETTLING_BAND, joint_metrics, metric_units


def _one(t, e1, tau, ts=0.0, held=False):
    return joint_metrics(t, np.asarray(e1).reshape(-1, 1), np.asarray(tau).reshape(-1, 1), ts, held=held)[0]


def test_rms_and_max_after_the_transient_of_a_sine():
    """e1 = 0.3 sin(2 pi t) over 8 whole periods after t_s = 2 (a 1 rad step before): RMS 0.3/sqrt 2, max 0.3."""
    t = np.linspace(0.0, 10.0, 20001)
    e1 = np.where(t < 2.0, 1.0, 0.3 * np.sin(2 * np.pi * t))
    m = _one(t, e1, np.zeros_like(t), ts=2.0)
    assert m["e1_rms_after_transient"] == pytest.approx(0.3 / math.sqrt(2), rel=1e-6)
    assert m["e1_max_after_transient"] == pytest.approx(0.3, rel=1e-6)
    # the whole run's RMS would count the step: the transient is left out
    assert m["e1_rms_after_transient"] < 0.3


def test_overshoot_and_settling_time_of_a_piecewise_linear_error():
    """e1 from 1 down to -0.25 at t = 1, back to 0.1 at t = 2 and to 0 at t = 3: overshoot 0.25; |e1| enters the
    2 % band (0.02 of the peak 1) at t = 2.8 on the last segment and stays."""
    t = np.linspace(0.0, 5.0, 5001)
    e1 = np.interp(t, [0, 1, 2, 3, 5], [1.0, -0.25, 0.1, 0.0, 0.0])
    m = _one(t, e1, np.zeros_like(t))
    assert m["overshoot"] == pytest.approx(0.25, abs=1e-12)
    assert m["settling_band"] == pytest.approx(SETTLING_BAND * 1.0)
    assert abs(m["settling_time"] - 2.8) <= 1e-3 + 1e-12
    # starting on the reference, the first excursion sets the direction: down to -0.5, then 0.2 past zero
    e1 = np.interp(t, [0, 1, 2, 3, 5], [0.0, -0.5, 0.2, 0.0, 0.0])
    assert _one(t, e1, np.zeros_like(t))["overshoot"] == pytest.approx(0.2, abs=1e-12)
    # a monotone decay has no overshoot; one that ends outside its band has not settled
    assert _one(t, np.exp(-t), np.zeros_like(t))["overshoot"] == 0.0
    assert _one(t, 1.0 + 0.0 * t, np.zeros_like(t))["settling_time"] is None
    # exp(-t) enters the band 0.02 at t = ln 50
    assert abs(_one(t, np.exp(-t), np.zeros_like(t))["settling_time"] - math.log(50.0)) <= 1e-3


def test_energy_and_chattering_of_a_sine_torque():
    """tau = 2 sin(2 pi 3 t) over 2 s: integral of tau^2 = 4 (2 s)/2 = 4; total variation 4 x amplitude per period,
    3 periods per s: 24 N m/s; peaks 2."""
    t = np.linspace(0.0, 2.0, 40001)
    tau = 2.0 * np.sin(2 * np.pi * 3.0 * t)
    m = _one(t, np.zeros_like(t), tau)
    assert m["control_energy"] == pytest.approx(4.0, rel=1e-6)
    assert m["chattering"] == pytest.approx(24.0, rel=1e-6)
    assert m["peak_tau"] == pytest.approx(2.0, rel=1e-6)
    assert m["peak_tau_after_t0"] == pytest.approx(2.0, rel=1e-6)


def test_an_initial_spike_counts_in_the_peak_only():
    """A 100 N m spike at t = 0 decaying linearly to 0 at t = 0.1, then 3 sin(2 pi 5 (t - 0.1)) for 2 s: peak 100,
    peak after the decay 3, chattering over the 10 periods after it 4 x 3 x 5 = 60 N m/s."""
    t = np.linspace(0.0, 2.1, 21001)
    tau = np.where(t <= 0.1, 100.0 * (1 - t / 0.1), 3.0 * np.sin(2 * np.pi * 5.0 * (t - 0.1)))
    m = _one(t, np.zeros_like(t), tau)
    assert m["peak_tau"] == pytest.approx(100.0)
    assert m["peak_tau_after_t0"] == pytest.approx(3.0, rel=1e-6)
    assert m["chattering"] == pytest.approx(60.0, rel=1e-4)


def test_held_torque_energy_and_jumps_are_exact():
    """A torque held over K periods of h, alternating +-1.5: energy 1.5^2 K h, K - 1 jumps of 3 over K h."""
    K, h = 400, 1e-3
    t = np.arange(K + 1) * h
    tau = 1.5 * (-1.0) ** np.arange(K)
    m = _one(t, np.zeros_like(t), tau, held=True)
    assert m["control_energy"] == pytest.approx(1.5 ** 2 * K * h, rel=1e-12)
    assert m["chattering"] == pytest.approx(3.0 * (K - 1) / (K * h), rel=1e-12)


def test_units_follow_the_joint_type():
    u = metric_units(["revolute", "prismatic"], 2)
    assert u["e1_rms_after_transient"] == ["rad", "m"]
    assert u["peak_tau"] == ["N m", "N"]
    assert u["settling_time"] == ["s", "s"]
    assert u["chattering"] == ["N m/s", "N/s"]
    assert u["control_energy"] == ["N^2 m^2 s", "N^2 s"]


def _trapz(y, x):
    from scipy.integrate import trapezoid
    return float(trapezoid(y, x))


def _run(argv, capsys):
    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr().out
    return code, out


def test_simulate_json_metrics_match_numpy_on_the_npz(tmp_path, capsys):
    """The continuous loop's block, recomputed from its npz (e1, tau on the output grid) with scipy and numpy."""
    npz = tmp_path / "run.npz"
    code, out = _run(["simulate", "paper", "--t-final", "1", "--json", "-q", "--out", str(npz)], capsys)
    assert code == 0
    s = json.loads(out)
    met = s["metrics"]
    assert met["units"]["e1_rms_after_transient"] == ["rad", "rad"]
    assert met["units"]["peak_tau"] == ["N m", "N m"]
    d = np.load(npz)
    t, e1, tau = d["t"], d["e1"], d["tau"]
    ts = s["settle_time"]
    k = t >= ts
    for j, m in enumerate(met["per_joint"]):
        rms = math.sqrt(_trapz(e1[k, j] ** 2, t[k]) / (t[k][-1] - t[k][0]))
        assert m["e1_rms_after_transient"] == pytest.approx(rms, rel=1e-12)
        assert m["e1_max_after_transient"] == pytest.approx(np.abs(e1[k, j]).max(), rel=1e-12)
        assert m["peak_tau"] == pytest.approx(np.abs(tau[:, j]).max(), rel=1e-12)
        assert m["peak_tau"] == pytest.approx(s["max_abs_tau"][j], rel=1e-6)
        assert m["control_energy"] == pytest.approx(_trapz(tau[:, j] ** 2, t), rel=1e-12)
        # the paper's torque is largest at t = 0; after its decay it is far smaller
        assert np.argmax(np.abs(tau[:, j])) == 0
        assert m["peak_tau_after_t0"] < 0.5 * m["peak_tau"]


def test_sampled_json_metrics_use_the_error_at_the_samples(tmp_path, capsys):
    """The sampled loop's e1 (in its npz) is q - qd at the samples: equal to the continuous run's q - qd where
    the grids meet (the loops differ, so a loose tolerance), and its block matches numpy on the held torque."""
    npz, cnpz = tmp_path / "s.npz", tmp_path / "c.npz"
    code, out = _run(["simulate", "paper", "--t-final", "0.5", "--rate", "2000", "--json", "-q", "--out",
                      str(npz)], capsys)
    assert code == 0
    s = json.loads(out)
    assert main(["simulate", "paper", "--t-final", "0.5", "-q", "--out", str(cnpz)]) == 0
    d, c = np.load(npz), np.load(cnpz)
    t, tau, e1 = d["t"], d["tau"], d["e1"]
    # qd from the continuous run's log; its grid (5 ms) is every 10th sample
    idx = np.searchsorted(t, c["t"] - 1e-12)
    assert np.allclose(t[idx], c["t"], atol=1e-12)
    assert np.allclose(e1[idx], d["q"][idx] - c["qd"], atol=1e-12)
    h = 1.0 / 2000
    for j, m in enumerate(s["metrics"]["per_joint"]):
        assert m["control_energy"] == pytest.approx(float(np.sum(tau[:, j] ** 2) * h), rel=1e-9)
        assert m["peak_tau"] == pytest.approx(np.abs(tau[:, j]).max(), rel=1e-12)
        assert m["e1_max_after_transient"] == pytest.approx(
            np.abs(e1[t >= s["metrics"]["settle_time"], j]).max(), rel=1e-12)


def test_text_table_carries_units(capsys):
    code, out = _run(["simulate", "paper", "--t-final", "0.5", "-q"], capsys)
    assert code == 0
    assert "max |tau| commanded [N m]" in out
    assert "chattering (total variation of tau per s) [N m/s]" in out
    assert "e1 RMS after the transient" in out and "[rad]" in out
    # f_true = ddq_plant - ddq_nom (simulation.closedloop): an acceleration
    assert "RMS f_true (scale) [rad/s^2]" in out and "RMS ESN error |W^T Phi - f_true| [rad/s^2]" in out


def test_bounded_tau_detail_carries_its_unit(paper_run):
    from symfunnel.checks.verify import check_bounded
    c = check_bounded(paper_run.simulation, paper_run.design, None)[0]
    assert c.id == "bounded.tau"
    peak = c.evidence["max_abs"]
    assert f"max |tau| = {peak:.4g} N m at t = " in c.detail


def test_report_metrics_table_has_units_and_the_json_numbers():
    """The report's table: one unit column when the joints share it, each cell its own unit where they differ."""
    from symfunnel.reporting.sections import metrics_table
    from symfunnel.reporting.text import fmt
    from symfunnel.simulation.metrics import metrics_block
    t = np.linspace(0.0, 1.0, 101)
    e1 = np.column_stack([np.exp(-5 * t), 0.5 * np.exp(-5 * t)])
    tau = np.column_stack([np.cos(t), 2 * np.cos(t)])
    block = metrics_block(t, e1, tau, 0.5, ["revolute", "prismatic"], n=2)
    tab = metrics_table(block)
    assert tab["joints"] == ["joint 1", "joint 2"]
    rows = {name.split(" (")[0]: (unit, cells) for name, unit, cells in tab["rows"]}
    unit, cells = rows["peak |tau|"]
    assert unit == "per joint" and cells == [f"{fmt(1.0)} N m", f"{fmt(2.0)} N"]
    unit, cells = rows["settling time of e1"]
    assert unit == "s" and cells == [fmt(block["per_joint"][0]["settling_time"]),
                                     fmt(block["per_joint"][1]["settling_time"])]
    # exp(-5 t) enters 2 % of its peak at ln(50)/5
    assert abs(block["per_joint"][0]["settling_time"] - math.log(50) / 5) <= 0.01

"""What a user reads: counts in the right number, one sign for a missing number, a run that reached its horizon
said so, grid values without binary noise, and a top-level --help that names the gate and the exit codes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from symfunnel.checks.gate import counts_line
from symfunnel.checks.result import CheckResult
from symfunnel.cli import main
from symfunnel.core.text import MISSING, reached


def _checks(**n) -> list[CheckResult]:
    return [CheckResult(f"c.{s}{i}", s, "") for s, k in n.items() for i in range(k)]


@pytest.mark.parametrize("warn, word", [(0, "0 warnings"), (1, "1 warning,"), (2, "2 warnings")])
def test_counts_line_says_warning_in_the_right_number(warn, word):
    line = counts_line(_checks(**{"pass": 3, "warn": warn, "skip": 1}))
    assert word in line and line.startswith("3 passed, 0 failed (0 expected), ")
    assert "1 warnings" not in line


def test_rate_shows_a_missing_margin_the_same_way_in_its_progress_and_its_table(capsys):
    """On paper (0.5 s) the search tries 62.5 Hz, whose run leaves a funnel before the transient ends: it has no
    margin after the transient, shown as MISSING in both places, never as -inf or nan."""
    assert main(["rate", "paper", "--t-final", "0.5"]) == 0
    cap = capsys.readouterr()
    progress = [line for line in cap.err.splitlines() if "rate 62.5 Hz" in line]
    table = [line for line in cap.out.splitlines() if line.strip().startswith("62.5 Hz")]
    assert len(progress) == 1 and len(table) == 1, (cap.err, cap.out)
    assert f"after the transient {MISSING} " in progress[0] and "breach" in progress[0]
    assert f"after the transient {MISSING:>10} " in table[0]
    for text in (cap.err, cap.out):
        assert "-inf" not in text and "nan" not in text and " - " not in text


def test_a_run_that_ends_within_one_sample_of_the_horizon_reached_it():
    import symfunnel as sf
    # 3512.5 Hz does not divide 0.5 s: the last sample is at floor(1756.25) / 3512.5 = 0.49993 s
    r = sf.simulate("paper", t_final=0.5, rate_hz=3512.5)
    assert r.t[-1] == pytest.approx(1756 / 3512.5) and r.t[-1] < 0.5
    assert r.message == "reached the horizon t = 0.5 s inside both funnels"
    assert reached(4.99829, 5.0, 1 / 500.0) == "reached the horizon t = 5 s"
    assert reached(3.2, 5.0, 0.01) == "reached t = 3.2 s"         # stopped early: the time it stopped


@pytest.mark.parametrize("T", [0.3, 1.7, 5.0, 20.0])
def test_settle_time_is_the_grid_value_without_binary_noise(T):
    """The settle time is a point k T / (N - 1) of the settle grid: the same point as linspace's (within one ulp),
    printed with no more digits than the grid value has (5.975, not 5.9750000000000005)."""
    import symfunnel as sf
    from symfunnel.simulation.margins import SETTLE_GRID, settle_time
    sc = sf.load_scenario("paper")
    ts, _ = settle_time(sf.derive(sc), T)
    grid = np.linspace(0.0, T, SETTLE_GRID)
    k = int(np.argmin(np.abs(grid - ts)))
    assert abs(grid[k] - ts) <= np.spacing(ts) and 0 < ts < T
    assert ts == T * k / (SETTLE_GRID - 1) and len(repr(ts)) <= 12, repr(ts)


def test_simulate_json_settle_time_is_short(capsys):
    assert main(["simulate", "paper", "--t-final", "0.3", "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(repr(out["metrics"]["settle_time"])) <= 12


def test_top_level_help_names_the_gate_and_the_exit_codes(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "`symfunnel verify SCENARIO` is the gate" in out
    assert "exit codes:" in out
    for code, words in (("0", "success"), ("1", "a check failed"), ("2", "bad input"), ("3", "internal error"),
                        ("130", "interrupted")):
        assert any(line.split()[:1] == [code] and words in line for line in out.splitlines()), (code, out)


def test_simulate_events_line_is_words_not_a_dict(capsys):
    """The events row: the total, then each counter in words; the counters sum to the total (from the JSON)."""
    assert main(["simulate", "paper", "--t-final", "1", "--json", "-q"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert main(["simulate", "paper", "--t-final", "1", "-q"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.strip().startswith("events"))
    assert "{" not in line and "_" not in line, line
    assert sum(s["event_counts"].values()) == s["events"] > 0
    import re
    assert re.search(r"grid\)\s+(\d+): ", line).group(1) == str(s["events"])
    c = s["event_counts"]
    assert f"e1 zero crossings {c['e1_zero_crossings']}" in line
    assert f"dead-zone transitions {c['dead_zone_transitions']}" in line


def test_figure_legends_name_the_printed_claim_by_its_name():
    """The Lyapunov figures' legends say 'printed claim theorem1', never the Claim object or its check id."""
    from symfunnel.checks.verify import decay_claim
    from symfunnel.pipeline import Run, RunOptions
    from symfunnel.reporting import figures as FIG
    from symfunnel.scenario import load_scenario
    sc = load_scenario("paper")
    claim = decay_claim(sc)
    assert claim is not None
    r = Run(sc, RunOptions(t_final=0.5, samples=50))
    svg = FIG.lyapunov_bound(r.lyapunov, r.simulation, claim) + FIG.lyapunov_decay(r.lyapunov, r.simulation, claim)
    assert f"printed claim {claim.name}" in svg
    assert "Claim(" not in svg and f"claim.{claim.name}" not in svg


def test_verify_says_an_initial_state_outside_its_funnel_in_words(write_scenario, capsys):
    """paper with F1(0) = 0.18 below |e1(0)|: verify's run line and its progress say so in words, never the JSON's
    status value `initial_outside` (which --json keeps)."""
    from symfunnel.scenario import DATA_DIR
    text = (DATA_DIR / "paper_2dof.toml").read_text(encoding="utf-8").replace("phi0 = 0.4 ", "phi0 = 0.18 ", 1)
    p = write_scenario(text)
    main(["verify", str(p), "--t-final", "0.5", "--samples", "100"])
    cap = capsys.readouterr()
    assert "continuous-time run: the initial state is outside a funnel: " in cap.out
    assert "simulation: the initial state is outside a funnel (" in cap.err
    assert "initial_outside" not in cap.out + cap.err
    main(["verify", str(p), "--t-final", "0.5", "--samples", "100", "--json", "-q"])
    assert json.loads(capsys.readouterr().out)["verdicts"]["continuous"]["status"] == "initial_outside"

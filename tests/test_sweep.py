"""`symfunnel sweep`: identical rows whatever runs them, kill + --resume, Parquet, Clopper-Pearson, worst.toml replay."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pyarrow.parquet as pq
import pytest

from symfunnel.design import derive
from symfunnel.scenario import load_scenario
from symfunnel.campaigns.campaign import make_job, run_chunk, sweep
from symfunnel.campaigns.statistics import clopper_pearson
from symfunnel.core.toml_write import dumps

# |q0| beyond F1(0) = 0.19 starts outside the funnel (a breach at t = 0): a breach region known in advance
UNCS = [{"key": "initial.q", "dist": "uniform", "low": -0.3, "high": 0.3},
        {"key": "plant.mass_scale", "dist": "uniform", "low": 0.7, "high": 1.4},
        {"key": "plant.dead_zone.b_r", "dist": "uniform", "low": 0.5, "high": 2.0, "per_joint": True}]


def _campaign_file(tmp_path, runs=10, t_final=0.4, design="sobol", q0=0.3):
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["uncertainty"] = copy.deepcopy(UNCS)
    raw["uncertainty"][0].update(low=-q0, high=q0)
    raw["sweep"] = {"runs": runs, "design": design, "seed": 4, "t_final": t_final}
    f = tmp_path / "campaign.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    return f


def _rows(path):
    return pq.read_table(str(path)).to_pylist()


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.keys() == y.keys()
        for k in x:
            assert x[k] == y[k] or (isinstance(x[k], float) and np.isnan(x[k]) and np.isnan(y[k])), (k, x, y)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The campaign's rows computed in this process, chunk by chunk, without any pool."""
    tmp = tmp_path_factory.mktemp("ref")
    sc = load_scenario(_campaign_file(tmp))
    job = make_job(sc)
    return sc, job, run_chunk(job, range(5)) + run_chunk(job, [9, 8, 7, 6, 5])[::-1]


def test_rows_identical_for_any_workers_and_parquet_reads_back(reference, tmp_path):
    sc, job, ref = reference
    r1 = sweep(sc, workers=1, out=tmp_path / "w1", chunk_size=3)
    r2 = sweep(sc, workers=2, out=tmp_path / "w2", chunk_size=1)
    t = pq.read_table(str(tmp_path / "w2" / "results.parquet"))
    assert t.column_names == ["run", "initial.q", "plant.mass_scale", "plant.dead_zone.b_r[1]",
                              "plant.dead_zone.b_r[2]", "status", "t_end", "min_margin_e1", "min_margin_e2",
                              "max_abs_tau", "min_margin_e1_after_transient", "min_margin_e2_after_transient",
                              "settle_time", "e1_rms_after_transient", "peak_tau_after_t0", "control_energy",
                              "chattering"]
    assert str(t.schema.field("run").type) == "int64" and str(t.schema.field("status").type) == "string"
    _same(_rows(tmp_path / "w1" / "results.parquet"), ref)
    _same(t.to_pylist(), ref)
    assert r1.summary["workers"] == 1 and r2.summary["workers"] == 2
    assert not (tmp_path / "w2" / ".results.parts").exists()
    # an initial error outside F1(0) is a breach at t = 0 with margin 1 - |q0|/F1(0) (e1(0) = q0 as q_d(0) = 0);
    # inside, e2(0) = -alpha2(0) may still leave F2(0), so only the implication is theory
    F1_0 = 0.18 + 0.01
    assert {r["status"] for r in ref} == {"ok", "breach"}
    for row in ref:
        outside = abs(row["initial.q"]) >= F1_0
        assert row["status"] == "breach" or not outside, row
        if outside:
            assert row["t_end"] == 0.0 and row["min_margin_e1"] == pytest.approx(1 - abs(row["initial.q"]) / F1_0)


def test_summary_and_worst_scenario_replays(reference, tmp_path):
    from symfunnel.simulation import simulate
    sc, job, ref = reference
    out = tmp_path / "s"
    res = sweep(sc, workers=1, out=out)
    s = json.loads((out / "summary.json").read_text())
    for k in ("runs", "breaches", "breach_probability", "ci95", "worst_run", "runs_per_second", "workers"):
        assert k in s
    assert s == res.to_json()
    breaches = sum(r["status"] == "breach" for r in ref)
    assert s["runs"] == 10 and s["breaches"] == breaches and s["breach_probability"] == breaches / 10
    # the worst run is the one with the lowest margin after the transient (a breach counts wherever it is)
    # (a run that breached before the settle time has no post-transient samples of the other funnel: NaN there)
    m = np.fmin([r["min_margin_e1_after_transient"] for r in ref], [r["min_margin_e2_after_transient"] for r in ref])
    assert s["worst_run"] == ref[int(np.nanargmin(m))]["run"]
    for r, mr in zip(ref, m):
        if r["status"] == "breach":
            assert mr <= 0.0
    # worst.toml: a complete scenario that simulate replays to the worst run's margins
    w = load_scenario(out / "worst.toml")
    assert w.campaign is None
    r = simulate(w, derive(w), t_final=None).summary()
    row = ref[s["worst_run"]]
    assert r["status"] in ("breach", "initial_outside") if row["status"] == "breach" else r["status"] == row["status"]
    assert min(r["min_margin_e1"]) == pytest.approx(row["min_margin_e1"], abs=1e-12)
    # a run that stays inside: its replay through a written scenario gives the same row, to the last digit
    ok = next(x for x in ref if x["status"] == "ok")
    from symfunnel.campaigns.campaign import worst_scenario
    (tmp_path / "ok.toml").write_text(worst_scenario(job, sc.campaign, ok["run"], sc.n))
    r = simulate(*_sd(load_scenario(tmp_path / "ok.toml"))).summary()
    assert r["status"] == "ok" and r["t_end"] == ok["t_end"]
    assert min(r["min_margin_e1"]) == ok["min_margin_e1"] and min(r["min_margin_e2"]) == ok["min_margin_e2"]
    assert max(r["max_abs_tau"]) == ok["max_abs_tau"]


def test_clopper_pearson_against_binomial_tails():
    """The interval's ends solve P(X >= k | lo) = 2.5% and P(X <= k | hi) = 2.5% (scipy.stats.binom)."""
    from scipy.stats import binom
    for k, n in ((0, 10), (3, 10), (10, 10), (17, 1000), (1, 2)):
        lo, hi = clopper_pearson(k, n)
        assert 0 <= lo <= k / n <= hi <= 1
        if k > 0:
            assert binom.sf(k - 1, n, lo) == pytest.approx(0.025, rel=1e-6)
        else:
            assert lo == 0
        if k < n:
            assert binom.cdf(k, n, hi) == pytest.approx(0.025, rel=1e-6)
        else:
            assert hi == 1
    assert clopper_pearson(0, 10)[1] == pytest.approx(1 - 0.025 ** (1 / 10), rel=1e-12)


@pytest.mark.slow
def test_killed_sweep_resumes_without_duplicates(tmp_path):
    # runs that stay inside (small initial errors) and last 2 s each, so that the kill lands mid-campaign
    f = _campaign_file(tmp_path, runs=10, t_final=2.0, q0=0.005)
    sc = load_scenario(f)
    ref = run_chunk(make_job(sc), range(10))
    assert {r["status"] for r in ref} == {"ok"}
    out = tmp_path / "k"
    cmd = [sys.executable, "-m", "symfunnel.cli", "sweep", str(f), "--out", str(out), "--workers", "1", "-q"]
    # a one-run probe, then batches of at most the remaining runs over 2 x workers: several parts reach the disk
    # before the kill
    p = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            parts = list((out / ".results.parts").glob("*.parquet")) if (out / ".results.parts").is_dir() else []
            if len(parts) >= 2 or (out / "results.parquet").exists() or p.poll() is not None:
                break
            time.sleep(0.05)
        os.killpg(p.pid, signal.SIGKILL)
    finally:
        p.wait(timeout=30)
    assert p.returncode != 0, "the sweep finished before it could be killed"
    assert not (out / "summary.json").exists()
    from symfunnel.campaigns.campaign import ResultStore
    before = ResultStore(out, sc.campaign.columns).done()
    assert 0 < len(before) < 10
    r = subprocess.run(cmd + ["--resume", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = _rows(out / "results.parquet")
    assert [x["run"] for x in rows] == list(range(10))
    _same(rows, ref)


def test_resume_refuses_another_campaign(reference, tmp_path):
    from symfunnel.core.errors import InputError
    sc, job, ref = reference
    out = tmp_path / "r"
    sweep(sc, workers=1, out=out, runs=2)
    with pytest.raises(InputError, match="different campaign"):
        sweep(sc, workers=1, out=out, runs=3, resume=True)
    assert sweep(sc, workers=1, out=out, runs=2, resume=True).summary["runs"] == 2


def test_report_sweep_section(reference, tmp_path, capsys):
    """report --sweep DIR: a self-contained page with the three figures; the breach region's axes are the
    quantities that decide breaches (here the initial position, which alone sets e1(0))."""
    from symfunnel.cli import main
    from symfunnel.reporting.html import no_network_references
    from symfunnel.reporting.sweep import correlation_ratio, load_sweep, strongest_pair
    sc, job, ref = reference
    out = tmp_path / "rep"
    sweep(sc, workers=2, out=out, runs=40)
    assert main(["report", "--sweep", str(out)]) == 0
    page = (out / "sweep.html").read_text()
    assert page.count("<svg") == 3 and not no_network_references(page)
    assert "Clopper-Pearson" in page
    _, cols = load_sweep(out)
    assert strongest_pair(cols)[0] == "initial.q"
    # eta^2 against an independent case: y = x^2 on symmetric x is fully explained, unrelated noise is not
    x = np.linspace(-1, 1, 400)
    assert correlation_ratio(x, x ** 2, bins=20) > 0.95
    assert correlation_ratio(x, np.random.default_rng(0).normal(size=400)) < 0.1
    assert main(["report", "--sweep", str(tmp_path / "nothing")]) == 2
    assert not (tmp_path / "nothing").exists()


def test_cli_json_is_summary_and_progress_shows_rate(tmp_path, capsys):
    from symfunnel.cli import main
    f = _campaign_file(tmp_path, runs=4, t_final=0.2)
    out = tmp_path / "cli"
    assert main(["sweep", str(f), "--out", str(out), "--workers", "1", "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out) == json.loads((out / "summary.json").read_text())
    assert "runs/s" in cap.err and "s left" in cap.err and "compiled once" in cap.err


def _cl(sc):
    from symfunnel.simulation.closedloop import build_closed_loop
    return build_closed_loop(sc, derive(sc))


def _sd(sc):
    return sc, derive(sc)


def test_campaign_caps_the_cvodes_step_at_half_the_output_step(tmp_path):
    """A campaign integrates with simulation.max_step = dt/2 unless the scenario sets it (0 keeps CVODES free); the
    cap is written into worst.toml, so a replay integrates exactly as the run did."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib

    from symfunnel.campaigns.campaign import MAX_STEP_OF_DT, worst_scenario
    sc = load_scenario(_campaign_file(tmp_path, runs=2))
    job = make_job(sc)
    assert MAX_STEP_OF_DT == 0.5
    assert job.raw["simulation"]["max_step"] == 0.5 * sc.simulation.dt and "max_step" not in sc.raw["simulation"]
    replay = tomllib.loads(worst_scenario(job, sc.campaign, 1, sc.n))
    assert replay["simulation"]["max_step"] == 0.5 * sc.simulation.dt
    for given in (0.0, 0.003):
        raw = copy.deepcopy(sc.raw)
        raw["simulation"]["max_step"] = given
        (tmp_path / "given.toml").write_text(dumps(raw), encoding="utf-8")
        assert make_job(load_scenario(tmp_path / "given.toml")).raw["simulation"]["max_step"] == given


def test_values_sent_with_a_chunk_are_the_ones_its_worker_would_draw(tmp_path):
    """`sweep` sends each chunk's drawn values with it (the workers need no scipy.stats): the rows are the same as
    when the worker draws them itself, and values that do not fit the chunk are refused."""
    f = _campaign_file(tmp_path, runs=8, t_final=0.2, q0=0.005)
    sc = load_scenario(f)
    job = make_job(sc)
    ids = [5, 2, 7]
    sent = run_chunk(job, ids, sc.campaign.values(ids, job.runs))
    assert json.dumps(sent, sort_keys=True) == json.dumps(run_chunk(job, ids), sort_keys=True)   # NaN-safe
    assert [r["run"] for r in sent] == ids and len({r["plant.mass_scale"] for r in sent}) == 3
    with pytest.raises(ValueError, match="2 rows of values for 3 runs"):
        run_chunk(job, ids, sc.campaign.values(ids[:2], job.runs))

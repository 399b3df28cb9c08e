"""The sweep's sensitivity ranking (`campaigns.sensitivity`): a synthetic campaign where one quantity drives the
margin by construction and another does nothing, against scipy's spearmanr and the asymptotic interval; the sweep
page (histograms over their data, no breach region without breaches) and its refusal of another scenario's
campaign."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from scipy.stats import spearmanr

from symfunnel.campaigns.sensitivity import sensitivity, spearman
from symfunnel.cli import main


def _campaign(N=400, noise=0.0, seed=3):
    """Results columns of a synthetic campaign: margin = 0.9 - 0.5 x (+ noise), peak torque = 10 + 5 z; w is drawn
    like them and enters nothing."""
    rng = np.random.default_rng(seed)
    x, z, w = rng.uniform(size=(3, N))
    m = 0.9 - 0.5 * x + noise * rng.standard_normal(N)
    return {"run": np.arange(N), "x": x, "z": z, "w": w, "status": np.array(["ok"] * N, dtype=object),
            "min_margin_e1": m, "min_margin_e2": np.full(N, 0.95), "min_margin_e1_after_transient": m,
            "min_margin_e2_after_transient": np.full(N, 0.95), "max_abs_tau": 10 + 5 * z}


def _entries(s, target):
    return [e for e in s if e["target"] == target]


def _eta2_adjusted(x, y, bins=10):
    """The bias-adjusted correlation ratio of y's ranks over x's quantile bins, written out plainly."""
    from scipy.stats import rankdata
    r = rankdata(y)
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    lab = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, bins - 1)
    between = sum(np.sum(lab == b) * (r[lab == b].mean() - r.mean()) ** 2 for b in range(bins))
    eta = between / np.sum((r - r.mean()) ** 2)
    return eta - (bins - 1) * (1 - eta) / (len(r) - bins)


def test_the_driving_quantity_ranks_first_and_the_idle_one_is_not_shown_to_matter():
    cols = _campaign(noise=0.05)
    s = sensitivity(cols, ["w", "x", "z"])
    margin = _entries(s, "min_margin_after_transient")
    assert [e["key"] for e in margin][0] == "x" and margin[0]["rank"] == 1
    y = np.fmin(cols["min_margin_e1"], 0.95)
    for e in margin:
        assert e["spearman"] == pytest.approx(spearmanr(cols[e["key"]], y).statistic, abs=1e-12)   # scipy's
        assert e["index"] == pytest.approx(_eta2_adjusted(cols[e["key"]], y), abs=1e-12)
    x, w = margin[0], next(e for e in margin if e["key"] == "w")
    assert x["index"] > 0.8 and x["ci95"][0] > 0.7 and x["spearman_ci95"][1] < 0      # drives it, downwards
    assert w["ci95"][0] <= 0 and abs(w["index"]) < 0.05                              # does nothing
    # the percentile interval of an idle quantity's rho is about the asymptotic +-1.96 sqrt(1.06/(N-3)) wide
    half = (w["spearman_ci95"][1] - w["spearman_ci95"][0]) / 2
    assert 0.6 < half / (1.96 * math.sqrt(1.06 / (400 - 3))) < 1.5
    tau = _entries(s, "max_abs_tau")
    assert tau[0]["key"] == "z" and tau[0]["spearman"] == pytest.approx(1.0) and tau[0]["ci95"][0] > 0.95


def test_an_effect_through_the_magnitude_is_found_where_rank_correlation_sees_none():
    """margin = 1 - |x| on symmetric x (an initial error of either sign): rho ~ 0, the first-order index ~ 0.9."""
    rng = np.random.default_rng(5)
    N = 400
    x, w = rng.uniform(-1, 1, size=(2, N))
    m = 1 - np.abs(x) + 0.05 * rng.standard_normal(N)
    cols = {"x": x, "w": w, "status": np.array(["ok"] * N, dtype=object), "min_margin_e1": m,
            "min_margin_e2": np.full(N, 2.0), "max_abs_tau": np.ones(N)}
    e = _entries(sensitivity(cols, ["w", "x"]), "min_margin_after_transient")
    assert e[0]["key"] == "x" and e[0]["index"] > 0.8 and e[0]["ci95"][0] > 0.7
    assert abs(e[0]["spearman"]) < 0.15 and e[0]["spearman_ci95"][0] < 0 < e[0]["spearman_ci95"][1]
    assert e[1]["ci95"][0] <= 0


def test_exact_monotone_effect_and_no_spread():
    """A perfectly monotone effect: rho = -1; the index is the share of the ranks' variance between 10 bins of 40
    consecutive ranks: 1 - (40^2 - 1)/(400^2 - 1), then adjusted by -(10 - 1)(1 - eta^2)/(400 - 10)."""
    cols = _campaign()
    s = sensitivity(cols, ["x", "w"])
    e = _entries(s, "min_margin_after_transient")[0]
    assert e["key"] == "x" and e["spearman"] == pytest.approx(-1.0)
    assert e["spearman_ci95"] == pytest.approx([-1.0, -1.0])
    eta = 1 - (40 ** 2 - 1) / (400 ** 2 - 1)
    assert e["index"] == pytest.approx(eta - 9 * (1 - eta) / 390, abs=1e-12)
    # a column without spread has no index and ranks last
    cols["c"] = np.full(400, 2.0)
    s = _entries(sensitivity(cols, ["c", "x"]), "min_margin")
    assert s[-1]["key"] == "c" and s[-1]["index"] is None and s[-1]["ci95"] is None
    # failed runs do not count
    cols["status"][:100] = "failed"
    cols["min_margin_e1_after_transient"][:100] = 50.0
    e = _entries(sensitivity(cols, ["x"]), "min_margin_after_transient")[0]
    assert e["runs"] == 300 and e["spearman"] == pytest.approx(-1.0)


def test_large_campaigns_bootstrap_a_subset_centred_on_the_whole():
    rng = np.random.default_rng(0)
    x = rng.uniform(size=3000)
    y = x + rng.standard_normal(3000)
    rho, ci, how = spearman(x, y)
    assert "subset of 2000 runs" in how
    assert rho == pytest.approx(spearmanr(x, y).statistic, abs=1e-12) and ci[0] < rho < ci[1]
    # the interval is about as wide as the asymptotic one of 2000 runs (wider than that of 3000)
    half = (ci[1] - ci[0]) / 2
    se = math.sqrt(1.06 / 1997) * (1 - rho ** 2)
    assert 0.7 < half / (1.96 * se) < 1.4


def test_histogram_range_shows_the_data_not_the_outliers():
    from symfunnel.reporting.sweep import histogram_range
    a = np.concatenate([np.linspace(0.95, 0.97, 99), [-1.0]])
    lo, hi, outside = histogram_range(a)
    assert 0.9 < lo < 0.96 and hi == pytest.approx(np.quantile(a, 0.99)) and outside >= 1
    lo, hi, outside = histogram_range(np.full(10, 0.5))
    assert lo < 0.5 < hi and hi - lo < 0.01 and outside == 0
    assert histogram_range(np.array([0.1, 0.9])) == (0.1, 0.9, 0)


@pytest.fixture(scope="module")
def paper_campaign(tmp_path_factory):
    from symfunnel.core.toml_write import dumps
    from symfunnel.scenario import load_scenario
    d = tmp_path_factory.mktemp("sens")
    raw = copy.deepcopy(load_scenario("paper").raw)
    raw["uncertainty"] = [{"key": "plant.mass_scale", "dist": "uniform", "low": 0.8, "high": 1.2},
                          {"key": "plant.viscous", "dist": "uniform", "low": 0.0, "high": 1.0}]
    raw["sweep"] = {"runs": 8, "design": "sobol", "seed": 2, "t_final": 0.3}
    f = d / "c.toml"
    f.write_text(dumps(raw), encoding="utf-8")
    out = d / "sw"
    assert main(["sweep", str(f), "--out", str(out), "--workers", "1", "-q"]) == 0
    return out


def test_summary_has_the_ranking_and_the_page_shows_it(paper_campaign, capsys):
    s = json.loads((paper_campaign / "summary.json").read_text())
    sens = s["sensitivity"]
    assert {(e["key"], e["target"]) for e in sens} == {(k, t) for k in ("plant.mass_scale", "plant.viscous")
                                                       for t in ("min_margin_after_transient", "min_margin",
                                                                 "max_abs_tau")}
    for t in ("min_margin_after_transient", "max_abs_tau"):
        es = _entries(sens, t)
        assert [e["rank"] for e in es] == [1, 2]
        idx = [e["index"] if e["index"] is not None else -1 for e in es]
        assert idx == sorted(idx, reverse=True)
    assert s["units"]["max_abs_tau"] == "N m"
    # the runs' metrics columns are results, not uncertain quantities
    from symfunnel.reporting.sweep import load_sweep, parameters
    assert parameters(load_sweep(paper_campaign)[1]) == ["plant.mass_scale", "plant.viscous"]
    capsys.readouterr()
    assert main(["report", "--sweep", str(paper_campaign), "-q"]) == 0
    page = (paper_campaign / "sweep.html").read_text()
    assert "id='sensitivity'" in page and "plant.mass_scale" in page
    assert s["breaches"] == 0 and page.count("<svg") == 2 and "no breach region" in page
    assert "peak |tau| [N m]" in page


def test_report_of_another_scenario_refuses_the_campaign(paper_campaign, capsys):
    capsys.readouterr()
    assert main(["report", "arm7", "--sweep", str(paper_campaign), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "summary.json" in err[0] and "'paper'" in err[0] and "arm7" in err[0]
    assert main(["report", "paper", "--sweep", str(paper_campaign), "--out", str(paper_campaign / "p.html"),
                 "-q"]) == 0


def test_fewer_than_four_runs_have_no_index():
    cols = _campaign(N=3)
    s = sensitivity(cols, ["x"])
    assert [e["index"] for e in s] == [None] * 3 and s[0]["method"] == "fewer than 4 runs"

"""Which uncertain quantity drives the worst margin and the peak torque: a campaign's sensitivity ranking.

For each uncertain column x and each target y (TARGETS: the run's margin after the transient, its whole-run margin,
its peak |tau|), the index is Spearman's rank correlation rho(x, y) over the decided runs (status ok or breach, y
finite), with a 95 % interval: the percentile interval of BOOTSTRAP resamples of the runs (a fixed seed: the same
campaign gives the same interval), or, beyond BOOTSTRAP_MAX_RUNS runs, Fisher's z interval with the standard error
sqrt(1.06 / (N - 3)) of a rank correlation. Rank correlation sees monotone effects of any shape and is not moved by
a few deep breaches (margins down to -1e3); a quantity whose interval contains 0 is not shown to matter.
The entries are ranked per target by |index| (a column or target without spread has index null, last).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["TARGETS", "sensitivity", "spearman", "BOOTSTRAP"]

#: (target name in summary.json, how it is read from the results columns)
TARGETS = ("min_margin_after_transient", "min_margin", "max_abs_tau")
#: bootstrap resamples of the runs
BOOTSTRAP = 1000
#: above this many runs the interval is Fisher's z (the bootstrap ranks BOOTSTRAP x runs values per pair: 0.1 s
#: at 1000 runs; at 10^5 runs the interval is narrower than the index's last shown digit anyway)
BOOTSTRAP_MAX_RUNS = 2000
#: resamples ranked at once (bounds the memory: CHUNK x runs values)
CHUNK = 250
SEED = 20240


def _ranks(a: np.ndarray) -> np.ndarray:
    from scipy.stats import rankdata
    return rankdata(a, axis=-1)


def _pearson_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Pearson's r of each row pair of x and y (…, N); NaN where a row has no spread."""
    xc = x - x.mean(axis=-1, keepdims=True)
    yc = y - y.mean(axis=-1, keepdims=True)
    den = np.sqrt((xc * xc).sum(axis=-1) * (yc * yc).sum(axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (xc * yc).sum(axis=-1) / np.where(den > 0, den, 1.0), np.nan)


def spearman(x, y) -> tuple[float | None, list[float] | None, str]:
    """(rho, [lo, hi] at 95 %, how the interval was found) of the pairs with both values finite; None without
    spread or with fewer than 4 pairs."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    N = x.size
    if N < 4 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return None, None, "no spread" if N >= 4 else "fewer than 4 runs"
    rho = float(_pearson_rows(_ranks(x), _ranks(y)))
    if N > BOOTSTRAP_MAX_RUNS:
        z, se = math.atanh(max(min(rho, 1 - 1e-15), -1 + 1e-15)), math.sqrt(1.06 / (N - 3))
        return rho, [math.tanh(z - 1.959964 * se), math.tanh(z + 1.959964 * se)], "fisher_z"
    rng = np.random.default_rng(SEED)
    parts = []
    for _ in range(BOOTSTRAP // CHUNK):
        idx = rng.integers(0, N, size=(CHUNK, N))
        parts.append(_pearson_rows(_ranks(x[idx]), _ranks(y[idx])))
    r = np.concatenate(parts)
    r = r[np.isfinite(r)]
    if r.size < BOOTSTRAP // 2:
        return rho, None, "bootstrap (too few resamples with spread)"
    lo, hi = np.quantile(r, [0.025, 0.975])
    return rho, [float(lo), float(hi)], f"bootstrap ({BOOTSTRAP} resamples, percentile)"


def target_values(cols: dict, target: str) -> np.ndarray:
    """A target per run from the results columns (the margins: the smaller of e1's and e2's)."""
    if target == "max_abs_tau":
        return np.asarray(cols["max_abs_tau"], float)
    if target == "min_margin":
        return np.fmin(np.asarray(cols["min_margin_e1"], float), np.asarray(cols["min_margin_e2"], float))
    e1 = cols.get("min_margin_e1_after_transient", cols["min_margin_e1"])
    e2 = cols.get("min_margin_e2_after_transient", cols["min_margin_e2"])
    return np.fmin(np.asarray(e1, float), np.asarray(e2, float))


def sensitivity(cols: dict, columns: list[str]) -> list[dict]:
    """The ranking: per target, one entry per uncertain column {"key", "target", "index", "ci95", "method",
    "runs"}, by decreasing |index| (null last)."""
    status = np.asarray(cols["status"], dtype=object)
    decided = (status == "ok") | (status == "breach")
    out = []
    for target in TARGETS:
        y = np.where(decided, target_values(cols, target), np.nan)
        entries = []
        for key in columns:
            x = np.asarray(cols[key], float)
            rho, ci, how = spearman(x, y)
            entries.append({"key": key, "target": target, "index": rho, "ci95": ci, "method": how,
                            "runs": int(np.sum(np.isfinite(x) & np.isfinite(y)))})
        entries.sort(key=lambda e: -abs(e["index"]) if e["index"] is not None else 1.0)
        for k, e in enumerate(entries):
            e["rank"] = k + 1
        out += entries
    return out

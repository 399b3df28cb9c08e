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


def _unit_rows(a: np.ndarray) -> np.ndarray:
    """Each row (last axis) centred and scaled to unit norm (NaN for a row without spread): Pearson's r of two rows
    is then their dot product."""
    c = a - a.mean(axis=-1, keepdims=True)
    nrm = np.sqrt((c * c).sum(axis=-1, keepdims=True))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(nrm > 0, c / np.where(nrm > 0, nrm, 1.0), np.nan)


def spearman(x, y) -> tuple[float | None, list[float] | None, str]:
    """(rho, [lo, hi] at 95 %, how the interval was found) of the pairs with both values finite; None without
    spread or with fewer than 4 pairs."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    return _indices(x[ok][None, :], y[ok][None, :])[0][0]


def _indices(X: np.ndarray, Y: np.ndarray) -> list[list[tuple]]:
    """spearman of every row of X (columns, N) with every row of Y (targets, N), all values finite; the bootstrap
    resamples are shared (one draw of runs for all pairs: each column and each target is ranked once per chunk)."""
    k, N = X.shape
    m = Y.shape[0]
    out = [[(None, None, "fewer than 4 runs")] * m for _ in range(k)]
    if N < 4:
        return out
    rho = _pearson_rows(_ranks(X)[:, None, :], _ranks(Y)[None, :, :])          # (k, m)
    spread = (np.ptp(X, axis=1) > 0)[:, None] & (np.ptp(Y, axis=1) > 0)[None, :]
    boot = None
    if N <= BOOTSTRAP_MAX_RUNS and spread.any():
        rng = np.random.default_rng(SEED)
        parts = []
        for _ in range(BOOTSTRAP // CHUNK):
            idx = rng.integers(0, N, size=(CHUNK, N))
            rx = _unit_rows(_ranks(X[:, idx]))           # (k, CHUNK, N), each resample's ranks standardised
            ry = _unit_rows(_ranks(Y[:, idx]))           # (m, CHUNK, N)
            parts.append(np.einsum("icn,jcn->ijc", rx, ry))                      # (k, m, CHUNK)
        boot = np.concatenate(parts, axis=-1)
    for i in range(k):
        for j in range(m):
            if not spread[i, j]:
                out[i][j] = (None, None, "no spread")
                continue
            r = float(rho[i, j])
            if boot is None:
                z, se = math.atanh(max(min(r, 1 - 1e-15), -1 + 1e-15)), math.sqrt(1.06 / (N - 3))
                out[i][j] = (r, [math.tanh(z - 1.959964 * se), math.tanh(z + 1.959964 * se)], "fisher_z")
                continue
            b = boot[i, j]
            b = b[np.isfinite(b)]
            if b.size < BOOTSTRAP // 2:
                out[i][j] = (r, None, "bootstrap (too few resamples with spread)")
                continue
            lo, hi = np.quantile(b, [0.025, 0.975])
            out[i][j] = (r, [float(lo), float(hi)], f"bootstrap ({BOOTSTRAP} resamples, percentile)")
    return out


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
    if not columns:
        return []
    decided = (status == "ok") | (status == "breach")
    X = np.array([np.asarray(cols[key], float) for key in columns], dtype=float).reshape(len(columns), status.size)
    Ys = {t: np.where(decided, target_values(cols, t), np.nan) for t in TARGETS}
    # the targets with the same runs (finite, decided) share one bootstrap draw
    groups: dict[bytes, list[str]] = {}
    for t, y in Ys.items():
        groups.setdefault(np.isfinite(y).tobytes(), []).append(t)
    res = {}
    for ts in groups.values():
        ok = np.isfinite(Ys[ts[0]]) & np.all(np.isfinite(X), axis=0)
        got = _indices(X[:, ok], np.array([Ys[t][ok] for t in ts]))
        for j, t in enumerate(ts):
            for i, key in enumerate(columns):
                res[(key, t)] = (*got[i][j], int(ok.sum()))
    out = []
    for target in TARGETS:
        entries = []
        for key in columns:
            rho, ci, how, runs = res[(key, target)]
            entries.append({"key": key, "target": target, "index": rho, "ci95": ci, "method": how, "runs": runs})
        entries.sort(key=lambda e: -abs(e["index"]) if e["index"] is not None else 1.0)
        for k, e in enumerate(entries):
            e["rank"] = k + 1
        out += entries
    return out

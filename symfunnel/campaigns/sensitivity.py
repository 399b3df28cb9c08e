"""Which uncertain quantity drives the worst margin and the peak torque: a campaign's sensitivity ranking.

For each uncertain column x and each target y (TARGETS: the run's margin after the transient, its whole-run margin,
its peak |tau|), over the decided runs (status ok or breach, y finite), on the ranks of y (a few deep breaches, with
margins down to -1e3, do not decide alone):

- ``index``: the first-order index of x, the share of the variance of y's ranks that x alone explains, whatever the
  shape of the effect (a margin that depends on |x| included): the correlation ratio eta^2 of y's ranks over BINS
  quantile bins of x, bias-adjusted, eps^2 = eta^2 - (k - 1)(1 - eta^2)/(N - k) (about 0 for an idle x, it can be
  slightly negative). ``ci95``: the basic bootstrap interval [2 S - q97.5, 2 S - q2.5] of BOOTSTRAP resamples of
  the runs (it corrects the estimator's own bootstrap bias: duplicated runs share their bin); a quantity whose
  interval reaches down to 0 is not shown to matter.
- ``spearman``: Spearman's rank correlation (the direction of a monotone effect) with ``spearman_ci95``, the
  percentile bootstrap interval of the same resamples.

Beyond BOOTSTRAP_MAX_RUNS runs the resamples are drawn from a fixed subset of that many runs (intervals somewhat
wider than the whole campaign's, centred on its estimates). The resamples use a fixed seed (the same campaign gives
the same intervals) and are shared by every column and target. The entries are ranked per target by the index (no spread: null, last).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["TARGETS", "sensitivity", "spearman", "first_order", "BOOTSTRAP", "BINS"]

#: (target name in summary.json, how it is read from the results columns)
TARGETS = ("min_margin_after_transient", "min_margin", "max_abs_tau")
#: bootstrap resamples of the runs
BOOTSTRAP = 1000
#: above this many runs the bootstrap resamples a fixed subset of this many (it ranks BOOTSTRAP x runs values per
#: column and target: 0.8 s for 2 columns and 3 targets at 1000 runs)
BOOTSTRAP_MAX_RUNS = 2000
#: resamples ranked at once (bounds the memory: CHUNK x runs values)
CHUNK = 250
SEED = 20240
#: the most quantile bins of x for the first-order index (at least 10 runs per bin, at least 2 bins)
BINS = 10


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


def bins_of(x: np.ndarray) -> tuple[np.ndarray, int]:
    """(bin label per run, number of bins): quantile bins of x, BINS at most and at least 10 runs per bin."""
    kb = int(max(2, min(BINS, x.size // 10)))
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, kb + 1)))
    lab = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    return lab, max(len(edges) - 1, 1)


def _eps2(lab: np.ndarray, yu: np.ndarray, kb: int) -> np.ndarray:
    """The bias-adjusted correlation ratio of standardised ranks yu (..., N; centred, unit norm: their total sum of
    squares is 1) over the bin labels lab (broadcast to yu)."""
    N = yu.shape[-1]
    lab = np.broadcast_to(lab, yu.shape)
    eta = np.zeros(yu.shape[:-1])
    used = np.zeros(yu.shape[:-1])
    for b in range(kb):
        m = lab == b
        c = m.sum(axis=-1)
        sb = np.where(m, yu, 0.0).sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            eta += np.where(c > 0, sb * sb / np.where(c > 0, c, 1), 0.0)
        used += c > 0
    return eta - (used - 1) * (1 - eta) / np.maximum(N - used, 1)


def first_order(x, y) -> float | None:
    """The first-order index (see the module doc) of x for y, both finite; None without spread."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 4 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return None
    lab, kb = bins_of(x)
    return float(_eps2(lab, _unit_rows(_ranks(y)), kb))


def spearman(x, y) -> tuple[float | None, list[float] | None, str]:
    """(rho, [lo, hi] at 95 %, how the interval was found) of the pairs with both values finite; None without
    spread or with fewer than 4 pairs."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    return _indices(x[ok][None, :], y[ok][None, :])[0][0][:3]


def _indices(X: np.ndarray, Y: np.ndarray) -> list[list[tuple]]:
    """spearman of every row of X (columns, N) with every row of Y (targets, N), all values finite; the bootstrap
    resamples are shared (one draw of runs for all pairs: each column and each target is ranked once per chunk)."""
    k, N = X.shape
    m = Y.shape[0]
    out = [[(None, None, "fewer than 4 runs", None, None)] * m for _ in range(k)]
    if N < 4:
        return out
    rho = _pearson_rows(_ranks(X)[:, None, :], _ranks(Y)[None, :, :])          # (k, m)
    spread = (np.ptp(X, axis=1) > 0)[:, None] & (np.ptp(Y, axis=1) > 0)[None, :]
    binned = [bins_of(X[i]) for i in range(k)]
    yu = _unit_rows(_ranks(Y))
    s1 = np.array([[float(_eps2(binned[i][0], yu[j], binned[i][1])) for j in range(m)] for i in range(k)])
    boot = boot1 = None
    rng = np.random.default_rng(SEED)
    # beyond BOOTSTRAP_MAX_RUNS runs the resamples are drawn from a fixed subset of that many (wider intervals,
    # centred on the whole campaign's estimates): the bootstrap's memory and time stay bounded
    pool = np.arange(N) if N <= BOOTSTRAP_MAX_RUNS else np.sort(rng.choice(N, BOOTSTRAP_MAX_RUNS, replace=False))
    P = pool.size
    if pool.size < N:
        yp = _unit_rows(_ranks(Y[:, pool]))
        rho_ref = _pearson_rows(_ranks(X[:, pool])[:, None, :], _ranks(Y[:, pool])[None, :, :])
        s1_ref = np.array([[float(_eps2(binned[i][0][pool], yp[j], binned[i][1])) for j in range(m)]
                           for i in range(k)])
    else:
        rho_ref, s1_ref = rho, s1
    if spread.any():
        parts, parts1 = [], []
        for _ in range(BOOTSTRAP // CHUNK):
            idx = pool[rng.integers(0, P, size=(CHUNK, P))]
            rx = _unit_rows(_ranks(X[:, idx]))           # (k, CHUNK, N), each resample's ranks standardised
            ry = _unit_rows(_ranks(Y[:, idx]))           # (m, CHUNK, N)
            parts.append(np.einsum("icn,jcn->ijc", rx, ry))                      # (k, m, CHUNK)
            # the first-order index: the runs keep the bins of their x (duplicates share theirs)
            parts1.append(np.array([_eps2(binned[i][0][idx][None], ry, binned[i][1]) for i in range(k)]))
        boot = np.concatenate(parts, axis=-1)
        boot1 = np.concatenate(parts1, axis=-1)
    for i in range(k):
        for j in range(m):
            if not spread[i, j]:
                out[i][j] = (None, None, "no spread", None, None)
                continue
            r, e = float(rho[i, j]), float(s1[i, j])
            b, b1 = boot[i, j], boot1[i, j]
            good = np.isfinite(b) & np.isfinite(b1)
            if good.sum() < BOOTSTRAP // 2:
                out[i][j] = (r, None, "bootstrap (too few resamples with spread)", e, None)
                continue
            # rho: the percentile interval, moved with the estimate when drawn from a subset; the index: the basic
            # interval [2 S - q97.5, 2 S - q2.5] about its reference (S itself without a subset)
            lo, hi = np.quantile(b[good], [0.025, 0.975]) + (r - float(rho_ref[i, j]))
            q1, q9 = np.quantile(b1[good], [0.025, 0.975])
            e0 = float(s1_ref[i, j])
            how = (f"bootstrap ({BOOTSTRAP} resamples" + (f" of a fixed subset of {P} runs" if P < N else "")
                   + "): basic interval of the index, percentile interval of rho")
            out[i][j] = (r, [float(lo), float(hi)], how, e, [float(e + e0 - q9), float(e + e0 - q1)])
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
    """The ranking: per target, one entry per uncertain column {"key", "target", "index", "ci95", "spearman",
    "spearman_ci95", "method", "runs", "rank"}, by decreasing index (null last)."""
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
            rho, ci, how, s1, ci1, runs = res[(key, target)]
            entries.append({"key": key, "target": target, "index": s1, "ci95": ci1, "spearman": rho,
                            "spearman_ci95": ci, "method": how, "runs": runs})
        entries.sort(key=lambda e: -e["index"] if e["index"] is not None else math.inf)
        for k, e in enumerate(entries):
            e["rank"] = k + 1
        out += entries
    return out

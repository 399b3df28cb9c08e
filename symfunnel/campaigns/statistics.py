"""A campaign's statistics from its results table: the breach probability with its exact (Clopper-Pearson)
interval, the worst run, and the quantiles of the margins, the torque and the metrics.
"""

from __future__ import annotations

import numpy as np

from ..simulation.metrics import CAMPAIGN_METRICS

__all__ = ["clopper_pearson", "summarize"]


def clopper_pearson(k: int, n: int, level: float = 0.95) -> list[float]:
    """Exact (Clopper-Pearson) confidence interval of a binomial proportion k/n."""
    from scipy.stats import beta
    if n <= 0:
        return [0.0, 1.0]
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return [lo, hi]


def _finite(v) -> float | None:
    return float(v) if np.isfinite(v) else None


def _quantiles(a: np.ndarray) -> dict:
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {}
    qs = np.quantile(a, [0.0, 0.01, 0.05, 0.5, 0.95, 0.99, 1.0])
    return dict(zip(["min", "p01", "p05", "median", "p95", "p99", "max"], (float(x) for x in qs)),
                mean=float(np.mean(a)))


def summarize(table, columns: list[str]) -> dict:
    """The campaign's figures from its results table (contract keys first)."""
    d = table.to_pydict()
    status = np.array(d["status"], dtype=object)
    whole = np.fmin(np.array(d["min_margin_e1"], float), np.array(d["min_margin_e2"], float))
    p1 = np.array(d.get("min_margin_e1_after_transient", d["min_margin_e1"]), float)
    p2 = np.array(d.get("min_margin_e2_after_transient", d["min_margin_e2"]), float)
    post = np.fmin(p1, p2)         # runs are ranked by the margin after the transient (the whole run's: ties)
    m = np.where(np.isfinite(post), post, whole)    # a run that ended before its settle time: by its whole run's
    runs = len(status)
    breaches = int(np.sum(status == "breach"))
    failed = int(np.sum(status == "failed"))
    decided = runs - failed
    worst = None
    if np.isfinite(m).any():
        # lowest post-transient margin; ties go to the lower sum of the two, then the lower whole-run margin
        total = p1 + p2
        order = np.lexsort((np.nan_to_num(whole, nan=np.inf), np.nan_to_num(total, nan=np.inf),
                            np.nan_to_num(m, nan=np.inf)))
        i = int(order[0])
        worst = {"run": int(d["run"][i]), "status": str(status[i]), "min_margin": float(whole[i]),
                 "min_margin_after_transient": _finite(post[i]),
                 "min_margin_e1_after_transient": _finite(p1[i]), "min_margin_e2_after_transient": _finite(p2[i]),
                 "settle_time": float(d["settle_time"][i]) if "settle_time" in d else None,
                 "min_margin_e1": float(d["min_margin_e1"][i]), "min_margin_e2": float(d["min_margin_e2"][i]),
                 "max_abs_tau": float(d["max_abs_tau"][i]), "values": {c: float(d[c][i]) for c in columns}}
    return {"runs": runs, "breaches": breaches,
            "breach_probability": breaches / decided if decided else None,
            "ci95": clopper_pearson(breaches, decided),
            "worst_run": worst["run"] if worst else None,
            "failed": failed, "worst": worst,
            "min_margin": _quantiles(whole), "min_margin_after_transient": _quantiles(post),
            "min_margin_e1_after_transient": _quantiles(p1), "min_margin_e2_after_transient": _quantiles(p2),
            "max_abs_tau": _quantiles(np.array(d["max_abs_tau"], float)),
            "metrics": {k: _quantiles(np.array(d[k], float)) for k in CAMPAIGN_METRICS if k in d}}

"""The report's robustness-campaign section: figures and figures-with-text from a sweep directory.

    from symfunnel.reporting.sweep import load_sweep, sweep_section, write_sweep_page
    section = sweep_section("reports/paper-sweep")     # dict: summary, table rows, SVG figures

`write_sweep_page` writes the section alone as a self-contained HTML file (`symfunnel report --sweep DIR`); the full
report can embed `sweep_section(...)` the same way as its other sections.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..simulation.metrics import CAMPAIGN_METRICS
from .figures import _plt, _with_rc

STATUS_COLORS = {"ok": "C0", "breach": "crimson", "failed": "0.5"}
FIXED = ("run", "status", "t_end", "min_margin_e1", "min_margin_e2", "max_abs_tau", "min_margin_e1_after_transient",
         "min_margin_e2_after_transient", "settle_time")
#: the results columns that are neither FIXED (present in every version) nor uncertain: the runs' metrics
METRIC_COLUMNS = CAMPAIGN_METRICS


def load_sweep(directory) -> tuple[dict, dict]:
    """(summary.json, results.parquet as column -> numpy array) of a sweep directory; InputError if incomplete."""
    d = Path(directory)
    summary_path, results = d / "summary.json", d / "results.parquet"
    for p in (summary_path, results):
        if not p.is_file():
            raise InputError("is missing", file=str(p), key="--sweep",
                             expected="a directory written by `symfunnel sweep` (summary.json, results.parquet)")
    from ..core.inputs import loads_json, read_text
    summary = loads_json(read_text(summary_path, expected="summary.json written by `symfunnel sweep`"),
                         file=str(summary_path), expected="summary.json written by `symfunnel sweep`")
    _check_summary(summary, str(summary_path))
    try:
        import pyarrow.parquet as pq
        table = pq.read_table(str(results)).to_pydict()
        cols = {k: np.asarray(v, dtype=object if k == "status" else float) for k, v in table.items()}
    except Exception as exc:  # noqa: BLE001 - a damaged file is bad input, not a crash
        raise InputError(f"cannot be read ({type(exc).__name__})", file=str(results), key="--sweep",
                         expected="results.parquet written by `symfunnel sweep`") from None
    missing = [k for k in FIXED if k not in cols]
    if missing:
        raise InputError(f"has no column '{missing[0]}'", file=str(results), key="--sweep",
                         expected="results.parquet written by `symfunnel sweep`")
    if len(cols["run"]) != summary["runs"]:
        raise InputError(f"has {len(cols['run'])} rows, its summary.json says {summary['runs']} runs",
                         file=str(results), key="--sweep", expected="the results and summary of one sweep")
    return summary, cols


def _check_summary(s, file: str) -> None:
    """The keys of summary.json the section reads, with their types (InputError naming the file and key)."""
    def bad(key, expected):
        raise InputError("is missing" if not isinstance(s, dict) or key not in s else f"is {s[key]!r}"[:80],
                         file=file, key=key, expected=expected)

    def number(x):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)

    if not isinstance(s, dict):
        raise InputError("is not a JSON object", file=file, key="--sweep", expected="summary.json of a sweep")
    for key in ("runs", "breaches"):
        if not (isinstance(s.get(key), int) and not isinstance(s.get(key), bool) and s[key] >= 0):
            bad(key, "an integer >= 0")
    p = s.get("breach_probability")
    if p is not None and not (number(p) and 0 <= p <= 1):
        bad("breach_probability", "a probability or null")
    ci = s.get("ci95")
    if not (isinstance(ci, list) and len(ci) == 2 and all(number(x) for x in ci)):
        bad("ci95", "[low, high]")
    w = s.get("worst_run")
    if w is not None and not (isinstance(w, int) and not isinstance(w, bool)):
        bad("worst_run", "a run number or null")


def parameters(cols: dict) -> list[str]:
    """The uncertain columns of a results table."""
    return [k for k in cols if k not in FIXED and k not in METRIC_COLUMNS]


def _post(cols: dict, key: str) -> np.ndarray:
    """A funnel's post-transient margin column (a results table of an older version: the whole run's)."""
    return cols.get(f"min_margin_{key}_after_transient", cols[f"min_margin_{key}"])


def min_margin(cols: dict) -> np.ndarray:
    """Per run, the smaller of the two funnels' minimum margins after the transient (<= 0: breach)."""
    return np.fmin(_post(cols, "e1"), _post(cols, "e2"))


def histogram_range(a: np.ndarray) -> tuple[float, float, int]:
    """(lo, hi, runs outside) of a histogram that shows its data: the values' own range, or, when a few outliers
    (deep breaches) would squeeze the rest into one bin, the 1st..99th percentile range; a single value gets a
    narrow range around it (a visible bar, not a sliver at the edge of [value - 0.5, value + 0.5])."""
    lo, hi = float(np.min(a)), float(np.max(a))
    if hi > lo and a.size >= 20:
        p1, p99 = (float(v) for v in np.quantile(a, [0.01, 0.99]))
        if p99 > p1 and (p99 - p1) < 0.2 * (hi - lo):
            return p1, p99, int(np.sum((a < p1) | (a > p99)))
    if hi == lo:
        w = max(abs(lo) * 1e-3, 1e-12)
        return lo - w, hi + w, 0
    return lo, hi, 0


@_with_rc
def margin_histograms(cols: dict, tau_unit: str = "N m") -> str:
    """Histograms of the minimum margins of e1 and e2 and of the peak torque over the runs, each over its data's
    own range (the breach line at 0 where it falls inside it)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(9.0, 2.6), constrained_layout=True)
    post = {"e1": _post(cols, "e1"), "e2": _post(cols, "e2"), "max_abs_tau": cols["max_abs_tau"]}
    for ax, key, title in ((axes[0], "e1", "min margin e1 after the transient"),
                           (axes[1], "e2", "min margin e2 after the transient"),
                           (axes[2], "max_abs_tau", f"peak |tau| [{tau_unit}]")):
        a = post[key][np.isfinite(post[key])]
        label = "1 - |e|/F [1]" if key != "max_abs_tau" else f"max over joints and time [{tau_unit}]"
        if a.size:
            lo, hi, outside = histogram_range(a)
            ax.hist(a, bins=min(40, max(5, a.size // 5)), range=(lo, hi),
                    color="C0" if key != "max_abs_tau" else "C2")
            ax.set_xlim(lo - 0.02 * (hi - lo), hi + 0.02 * (hi - lo))
            if key != "max_abs_tau":
                if lo <= 0.0 <= hi:
                    ax.axvline(0.0, color="crimson", lw=1, ls="--")
                elif lo > 0:
                    label += "; breach (0) left of the range"
            if outside:
                label += f"; {outside} runs outside"
        else:
            ax.text(0.5, 0.5, "no finite value", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(label, fontsize=8)
    axes[0].set_ylabel("runs")
    fig.suptitle("Distributions over the campaign (breach: margin <= 0)", fontsize=10)
    return fig


@_with_rc
def margin_vs_parameters(cols: dict) -> str:
    """The minimum margin of each run against each uncertain parameter, coloured by status."""
    plt = _plt()
    ps = parameters(cols)
    k = max(1, len(ps))
    ncol = min(3, k)
    nrow = int(np.ceil(k / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.0 * ncol, 2.4 * nrow), squeeze=False, sharey=True,
                             constrained_layout=True)
    m = min_margin(cols)
    for i, p in enumerate(ps):
        ax = axes[i // ncol][i % ncol]
        for st, c in STATUS_COLORS.items():
            sel = cols["status"] == st
            if sel.any():
                ax.scatter(cols[p][sel], m[sel], s=6, color=c, label=st)
        ax.axhline(0.0, color="crimson", lw=0.8, ls="--")
        if np.nanmin(m, initial=0.0) < -1.0:
            ax.set_yscale("symlog", linthresh=1.0)      # deep breaches reach -1e3; keep [0, 1] readable
        ax.set_xlabel(p, fontsize=8)
    for j in range(len(ps), nrow * ncol):
        axes[j // ncol][j % ncol].set_visible(False)
    axes[0][0].set_ylabel("min margin after the transient")
    axes[0][0].legend(fontsize=7, loc="best")
    fig.suptitle("Minimum funnel margin after the transient against each uncertain quantity", fontsize=10)
    return fig


def correlation_ratio(x: np.ndarray, y: np.ndarray, bins: int = 10) -> float:
    """eta^2: the share of y's variance explained by x's quantile bins (catches non-monotone effects, e.g. |x|)."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 4 or np.ptp(x) == 0 or np.var(y) == 0:
        return 0.0
    k = int(max(2, min(bins, x.size // 4)))
    edges = np.unique(np.quantile(x, np.linspace(0, 1, k + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    between = sum(np.sum(idx == b) * (np.mean(y[idx == b]) - np.mean(y)) ** 2 for b in np.unique(idx))
    return float(between / (x.size * np.var(y)))


def strongest_pair(cols: dict) -> list[str]:
    """The (up to) two uncertain columns that explain most of the minimum margin's variance (correlation ratio).

    The margin enters by its ranks: deep breaches give margins of -1e3 that would otherwise decide alone.
    """
    from scipy.stats import rankdata
    ps = parameters(cols)
    m = min_margin(cols)
    m = np.where(np.isfinite(m), rankdata(np.nan_to_num(m, nan=0.0)), np.nan)
    scores = [correlation_ratio(cols[p], m) for p in ps]
    order = np.argsort(scores, kind="stable")[::-1]
    return [ps[i] for i in order[:2]]


@_with_rc
def breach_region(cols: dict) -> str:
    """Runs in the plane of the two quantities that matter most, breaches marked: where the funnel breaks."""
    plt = _plt()
    pair = strongest_pair(cols)
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    if len(pair) == 1:
        x, y = cols[pair[0]], min_margin(cols)
        ax.set_xlabel(pair[0])
        ax.set_ylabel("min margin after the transient")
    else:
        x, y = cols[pair[0]], cols[pair[1]]
        ax.set_xlabel(pair[0])
        ax.set_ylabel(pair[1])
    for st, c in STATUS_COLORS.items():
        sel = cols["status"] == st
        if sel.any():
            ax.scatter(x[sel], y[sel], s=10 if st == "ok" else 18, color=c, marker="o" if st == "ok" else "x",
                       label=f"{st} ({int(sel.sum())})")
    ax.legend(fontsize=7, loc="best")
    ax.set_title("Breach region", fontsize=10)
    return fig


def sweep_section(directory) -> dict:
    """The campaign's summary, its worst run, the sensitivity ranking and the figures (SVG), for a report template;
    the breach-region figure only when the campaign has breaches."""
    summary, cols = load_sweep(directory)
    tau_unit = ((summary.get("units") or {}).get("max_abs_tau")) or "N m"
    figs = {"histograms": margin_histograms(cols, tau_unit), "margin_vs_parameters": margin_vs_parameters(cols)}
    if np.any(cols["status"] == "breach"):
        figs["breach_region"] = breach_region(cols)
    return {"available": True, "directory": str(directory), "summary": summary,
            "parameters": parameters(cols), "figures": figs}


#: how the sweep page names the sensitivity targets
TARGET_NAMES = {"min_margin_after_transient": "min margin after the transient", "min_margin":
                "min margin over the whole run", "max_abs_tau": "peak |tau|"}


def sensitivity_rows(summary: dict) -> list[tuple[str, ...]]:
    """The ranking of summary.json as table rows: target, rank, quantity, first-order index with its 95 % interval,
    Spearman rho (the direction), whether the campaign shows that it matters (interval above 0)."""
    rows = []
    for e in summary.get("sensitivity") or []:
        ci, idx, rho = e.get("ci95"), e.get("index"), e.get("spearman")
        matters = ci is not None and ci[0] > 0
        rows.append((TARGET_NAMES.get(e["target"], e["target"]), str(e.get("rank", "")), e["key"],
                     "-" if idx is None else f"{idx:.3f}",
                     "-" if ci is None else f"[{ci[0]:+.3f}, {ci[1]:+.3f}]",
                     "-" if rho is None else f"{rho:+.3f}",
                     "yes" if matters else "not shown (interval reaches 0)" if ci is not None else "-"))
    return rows


def render_section(sec: dict) -> str:
    """The section as an HTML fragment (figures inline)."""
    s = sec["summary"]
    e = html.escape
    lo, hi = s["ci95"]
    p = s.get("breach_probability")
    rows = [("runs", s["runs"]), ("breaches", s["breaches"]), ("failed runs", s.get("failed", "-")),
            ("breach probability", "-" if p is None else f"{p:.4g}"),
            ("95% interval (Clopper-Pearson)", f"[{lo:.4g}, {hi:.4g}]"),
            ("design / seed", f"{s.get('design', '-')} / {s.get('seed', '-')}"),
            ("horizon per run", f"{s.get('t_final', '-')} s"),
            ("worst run", s.get("worst_run")),
            ("throughput", f"{s.get('runs_per_second') or 0:.3g} runs/s on {s.get('workers')} workers")]
    w = s.get("worst") or {}
    if w:
        rows.append(("worst run's values", ", ".join(f"{k} = {v:.6g}" for k, v in w.get("values", {}).items())))
        pt = w.get("min_margin_after_transient")
        rows.append(("worst run's min margin after the transient / whole run",
                     f"{'-' if pt is None else format(pt, '.4g')} / {w.get('min_margin'):.4g} ({w.get('status')}); "
                     "replay: symfunnel simulate worst.toml"))
    for key, label in (("min_margin_after_transient", "min margin after the transient"),
                       ("min_margin", "min margin over the whole run")):
        q = s.get(key) or {}
        if q:
            rows.append((f"{label}: p01 / median / p99", f"{q['p01']:.5g} / {q['median']:.5g} / {q['p99']:.5g}"))
    table = "".join(f"<tr><th>{e(str(k))}</th><td>{e(str(v))}</td></tr>" for k, v in rows)
    sens = sensitivity_rows(s)
    sens_html = ""
    if sens:
        head = ("target", "rank", "uncertain quantity", "first-order index", "95 % interval (bootstrap)",
                "Spearman \u03c1 (direction)", "matters")
        sens_html = ("<h3>What matters</h3><p>The first-order index of each uncertain quantity: the share of the "
                     "variance of the runs' margin (or peak torque) ranks that the quantity alone explains, whatever "
                     "the shape of its effect; ranked by it per target, over the decided runs. Spearman's \u03c1 "
                     "gives the direction of a monotone effect. A quantity whose interval reaches 0 is not shown to "
                     "matter by this campaign.</p><table id='sensitivity'><tr>"
                     + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>"
                     + "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in sens)
                     + "</table>")
    f = sec["figures"]
    figs = "".join(f"<figure>{f[k]}</figure>" for k in ("histograms", "margin_vs_parameters", "breach_region")
                   if k in f)
    if "breach_region" not in f:
        figs += "<p>No run breached a funnel: no breach region to draw.</p>"
    return (f"<section id='sweep'><h2>Robustness campaign</h2><table>{table}</table>{sens_html}{figs}</section>")


def check_campaign_of(directory, scenario_name: str) -> None:
    """InputError (one line) when the sweep directory holds another scenario's campaign than `scenario_name`."""
    summary_path = Path(directory) / "summary.json"
    if not summary_path.is_file():
        return                              # load_sweep says what is missing
    from ..core.inputs import loads_json, read_text
    s = loads_json(read_text(summary_path, expected="summary.json written by `symfunnel sweep`"),
                   file=str(summary_path), expected="summary.json written by `symfunnel sweep`")
    name = s.get("scenario") if isinstance(s, dict) else None
    if name is not None and name != scenario_name:
        raise InputError(f"is '{name}': the campaign of another scenario", file=str(summary_path), key="scenario",
                         expected=f"a sweep of '{scenario_name}' (or no scenario argument)")


def write_sweep_page(directory, out=None, scenario_name: str | None = None) -> Path:
    """Write the section as a self-contained HTML page (default DIR/sweep.html), atomically; returns its path.
    With `scenario_name`, refuse (InputError) a directory holding another scenario's campaign."""
    from ..core.io import atomic_write
    if scenario_name is not None:
        check_campaign_of(directory, scenario_name)
    sec = sweep_section(directory)
    title = html.escape(f"symfunnel sweep: {sec['summary'].get('scenario', '')}")
    page = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{title}</title><style>"
            "body{font-family:sans-serif;max-width:60em;margin:1em auto}th{text-align:left;padding-right:1em}"
            "svg{max-width:100%;height:auto}</style></head><body>"
            f"<h1>{title}</h1>{render_section(sec)}</body></html>")
    path = Path(out) if out is not None else Path(directory) / "sweep.html"
    atomic_write(path, page)
    return path

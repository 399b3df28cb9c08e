"""The report's figures: matplotlib rendered to inline SVG text (deterministic, no external fonts or references),
and on request also written as PNG and PDF files (`export`)."""

from __future__ import annotations

import io
import re

import numpy as np

MAX_POINTS = 1000          # per line; longer series are decimated (the min/max envelope is kept)

_RC = {
    "svg.hashsalt": "symfunnel",       # deterministic ids
    "svg.fonttype": "none",            # text stays text; the font is a family name, never a file or URL
    "font.family": "sans-serif",
    "font.size": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "lines.linewidth": 1.2,
    "figure.dpi": 100,
}


def _plt():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def to_svg(fig) -> str:
    """A figure as inline SVG markup: no XML prolog, no DOCTYPE, no metadata block (which holds URLs)."""
    plt = _plt()
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches=_tight_bbox(fig), metadata={"Date": None, "Creator": None})
    plt.close(fig)
    s = buf.getvalue()
    s = re.sub(r"<\?xml[^>]*\?>\s*", "", s)
    s = re.sub(r"<!DOCTYPE[^>]*>\s*", "", s, flags=re.S)
    s = re.sub(r"<metadata>.*?</metadata>\s*", "", s, flags=re.S)
    s = re.sub(r"<!--.*?-->\s*", "", s, flags=re.S)
    # width/height in pt -> keep the aspect, let CSS scale it
    s = re.sub(r'(<svg[^>]*?)\swidth="[^"]*"\s+height="[^"]*"', r"\1", s, count=1)
    return s.strip()


def _tight_bbox(fig):
    """What savefig's bbox_inches="tight" crops to (the artists' extents in inches, padded by savefig.pad_inches),
    measured on an Agg renderer without drawing: "tight" itself draws the whole figure once more to find it, 44 %
    of an arm7 figure's SVG time. A figure with a layout engine (laid out at draw time) keeps "tight"."""
    import matplotlib as mpl
    if fig.get_layout_engine() is not None:
        return "tight"
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    return fig.get_tightbbox(canvas.get_renderer()).padded(mpl.rcParams["savefig.pad_inches"])


def _decimate(t: np.ndarray, *ys: np.ndarray):
    """Thin a series to about MAX_POINTS, keeping each bucket's min and max (spikes stay visible)."""
    T = len(t)
    if T <= MAX_POINTS:
        return (t, *ys)
    k = int(np.ceil(T / (MAX_POINTS / 2)))
    idx = []
    for s in range(0, T, k):
        e = min(T, s + k)
        idx.append(s)
        for y in ys:
            yy = np.asarray(y)[s:e]
            if yy.ndim > 1:
                yy = yy.reshape(len(yy), -1)[:, 0]
            if np.isfinite(yy).any():
                idx.append(s + int(np.nanargmin(yy)))
                idx.append(s + int(np.nanargmax(yy)))
    idx.append(T - 1)
    idx = np.unique(idx)
    return (t[idx], *[np.asarray(y)[idx] for y in ys])


def _joint_axes(n: int, title: str, height: float = 1.9):
    plt = _plt()
    with plt.rc_context(_RC):
        fig, axes = plt.subplots(n, 1, figsize=(8.0, max(2.2, height * n)), sharex=True, squeeze=False)
    fig.suptitle(title, fontsize=10)
    return fig, [a[0] for a in axes]


def _mark_end(ax, res):
    if res.status != "ok" and res.t.size:
        ax.axvline(res.t[-1], color="crimson", ls=":", lw=1)


def _legend_outside(ax, fontsize: int = 8):
    """The legend beside the axes (right of the plot area), never over the curves."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=fontsize, frameon=False)


def export(fig, directory, stem: str) -> list:
    """Write a figure as STEM.png (150 dpi) and STEM.pdf into directory, each atomically; returns the paths."""
    from pathlib import Path

    from ..core.io import atomic_write
    out = []
    # "symfunnel" as the writer marks the files as ours (core.outputs.MARKS): a later run may replace them
    for fmt, meta in (("png", {"Software": "symfunnel"}), ("pdf", {"Creator": "symfunnel", "Producer": None,
                                                                  "CreationDate": None})):
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=150, bbox_inches=_tight_bbox(fig), metadata=meta)
        out.append(atomic_write(Path(directory) / f"{stem}.{fmt}", buf.getvalue()))
    return out


def _with_rc(fn):
    """fn builds a Figure; the public function returns it as SVG text (and with export=(DIR, STEM) also writes
    PNG and PDF); fn.figure(...) returns the Figure itself (the caller closes it)."""
    def wrapped(*a, export_to=None, **k):
        plt = _plt()
        with plt.rc_context(_RC):
            fig = fn(*a, **k)
            if export_to is not None:
                export(fig, *export_to)
            return to_svg(fig)

    def figure(*a, **k):
        plt = _plt()
        with plt.rc_context(_RC):
            return fn(*a, **k)
    wrapped.__name__ = fn.__name__
    wrapped.__doc__ = fn.__doc__
    wrapped.figure = figure
    return wrapped


@_with_rc
def tracking(res, n: int, units=None) -> str:
    """Joint positions against the reference."""
    fig, axes = _joint_axes(n, "Joint tracking: q_i(t) against the reference q_d,i(t)")
    for j, ax in enumerate(axes):
        t, q, qd = _decimate(res.t, res.signals["q"][:, j], res.signals["qd"][:, j])
        ax.plot(t, qd, "k--", lw=1, label="reference q_d")
        ax.plot(t, q, color="C0", label="q")
        ax.set_ylabel(f"joint {j + 1} [{units[j]['e1'] if units else 'rad'}]")
        _mark_end(ax, res)
    _legend_outside(axes[0], fontsize=8)
    axes[-1].set_xlabel("t [s]")
    return fig


@_with_rc
def funnel(res, n: int, key: str, units=None) -> str:
    """e_i inside +-F_i."""
    Fk = "F" + key[1]
    fig, axes = _joint_axes(n, f"Funnel {key}: {key}(t) inside \u00b1{Fk}(t)")
    for j, ax in enumerate(axes):
        t, e, F = _decimate(res.t, res.signals[key][:, j], res.signals[Fk][:, j])
        ax.fill_between(t, -F, F, color="C2", alpha=0.15, lw=0, label=f"\u00b1{Fk}")
        ax.plot(t, F, color="C2", lw=0.8)
        ax.plot(t, -F, color="C2", lw=0.8)
        ax.plot(t, e, color="C0", label=key)
        ax.set_ylabel(f"joint {j + 1} [{units[j][key] if units else ('rad' if key == 'e1' else 'rad/s')}]")
        _mark_end(ax, res)
        b = res.breach or {}
        if b.get("funnel") == key and b.get("joint") == j + 1:
            ax.plot([b["time"]], [np.sign(e[-1] if len(e) else 1) * b["boundary"]], "x", color="crimson", ms=9,
                    label="breach")
    _legend_outside(axes[0], fontsize=8)
    axes[-1].set_xlabel("t [s]")
    return fig


@_with_rc
def z_signals(res, n: int) -> str:
    """The transformed errors z1, z2."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(8.0, 4.0), sharex=True)
    fig.suptitle("Transformed errors z_1 = e_1/(F_1 - |e_1|) and z_2 = e_2/(F_2 - |e_2|)", fontsize=10)
    for ax, key in zip(axes, ("z1", "z2")):
        for j in range(n):
            t, z = _decimate(res.t, res.signals[key][:, j])
            ax.plot(t, z, label=f"joint {j + 1}")
        ax.set_ylabel(key)
        _mark_end(ax, res)
    _legend_outside(axes[0], fontsize=8)
    axes[-1].set_xlabel("t [s]")
    return fig


@_with_rc
def torque(res, n: int, dead_zone=None, units=None) -> str:
    """Commanded torque against the torque the dead zone lets through."""
    fig, axes = _joint_axes(n, "Torque: commanded \u03c4 against applied D(\u03c4) through the unknown dead zone")
    for j, ax in enumerate(axes):
        t, tau, ta = _decimate(res.t, res.signals["tau"][:, j], res.signals["tau_applied"][:, j])
        ax.plot(t, tau, color="C0", label="commanded \u03c4")
        ax.plot(t, ta, color="C3", lw=1, alpha=0.8, label="applied D(\u03c4)")
        if dead_zone is not None:
            ax.axhspan(dead_zone.b_l[j], dead_zone.b_r[j], color="0.5", alpha=0.15, lw=0, label="dead band")
        ax.set_ylabel(f"joint {j + 1} [{units[j]['tau'] if units else 'N m'}]")
        both = np.concatenate([np.ravel(tau), np.ravel(ta)])
        both = both[np.isfinite(both)]
        if both.size:
            lo, hi = float(both.min()), float(both.max())
            pad = 0.08 * (hi - lo + 1e-9)
            ax.set_ylim(lo - pad, hi + pad)          # the whole range: the peak is never clipped
            typical = float(np.percentile(np.abs(both), 95))
            if typical > 0 and max(abs(lo), abs(hi)) > 10 * typical:
                # a short peak would flatten the rest: linear up to the typical size, logarithmic beyond
                ax.set_yscale("symlog", linthresh=typical)
                ax.set_ylim(lo - pad, hi + pad)
        _mark_end(ax, res)
    _legend_outside(axes[0], fontsize=8)
    axes[-1].set_xlabel("t [s]  (y range: all values; symmetric-log beyond the typical size when a peak "
                        "dwarfs it)")
    return fig


@_with_rc
def esn_estimate(res, n: int, W_star_fit=None) -> str:
    """The ESN's estimate W_hat^T Phi against the true unknown term f_true."""
    fig, axes = _joint_axes(n, "Unknown term: the ESN's estimate \u0174\u1d40\u03a6 against the true f_true")
    for j, ax in enumerate(axes):
        t, f, w = _decimate(res.t, res.signals["f_true"][:, j], res.signals["w_phi"][:, j])
        ax.plot(t, f, color="k", lw=1, label="f_true (plant, unknown to the controller)")
        ax.plot(t, w, color="C1", lw=1, alpha=0.9, label="\u0174\u1d40\u03a6 (ESN estimate)")
        if W_star_fit is not None:
            tt, ws = _decimate(res.t, W_star_fit[:, j])
            ax.plot(tt, ws, color="C4", lw=0.8, ls="--", label="W*\u1d40\u03a6 (fitted ideal weight)")
        ax.set_ylabel(f"joint {j + 1} [rad/s\u00b2]")
        if len(f):
            lo, hi = np.nanpercentile(np.concatenate([f, w]), [1, 99])
            pad = 0.3 * (hi - lo + 1e-9)
            ax.set_ylim(lo - pad, hi + pad)
        _mark_end(ax, res)
    _legend_outside(axes[0], fontsize=7)
    axes[-1].set_xlabel("t [s]")
    return fig


@_with_rc
def weights(res, W_star=None) -> str:
    """||W_hat(t)||_F (and ||W*||_F)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.0, 2.6))
    W = np.asarray(res.signals["w_hat"]).reshape(len(res.t), -1)
    t, nrm = _decimate(res.t, np.linalg.norm(W, axis=1))
    ax.plot(t, nrm, color="C0", label="\u2016\u0174(t)\u2016_F")
    if W_star is not None:
        ax.axhline(np.linalg.norm(W_star), color="C4", ls="--", lw=1, label="\u2016W*\u2016_F (fitted)")
    ax.set_title("Adaptive weights: \u2016\u0174(t)\u2016_F", fontsize=10)
    ax.set_xlabel("t [s]")
    _legend_outside(ax, fontsize=8)
    _mark_end(ax, res)
    return fig


def _claim_name(claim) -> str:
    """A printed claim as a legend names it: the scenario's name of it ('theorem1'), never the object or its id."""
    name = getattr(claim, "name", claim)
    return str(name).removeprefix("claim.")


@_with_rc
def lyapunov_bound(L, res, claim: str | None = None) -> str:
    """V(t) with the integrated bound (and a printed decay claim's, when the scenario has one)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.0, 3.2))
    t, V, B, Bp = _decimate(L.t, L.V, L.bound, L.bound_paper)
    ax.semilogy(t, V, color="C0", lw=1.5, label="V(t) (exact, with fitted W*)")
    ax.semilogy(t, B, color="C2", ls="--",
                label=f"corrected bound, \u03c1 = {L.rho_const:.3g}, \u03b4 = {L.delta_max:.3g}")
    if claim and np.isfinite(L.rho_paper_const) and np.isfinite(L.delta_paper_const) and np.isfinite(Bp).any():
        ax.semilogy(t, Bp, color="C3", ls=":", label=f"bound of the printed claim {_claim_name(claim)}, \u03c1 = "
                    f"{L.rho_paper_const:.3g}, \u03b4 = {L.delta_paper_const:.3g}")
    ax.set_title("Lyapunov function V(t) and V(0)e^(-\u03c1t) + (\u03b4/\u03c1)(1 - e^(-\u03c1t))", fontsize=10)
    ax.set_xlabel("t [s]")
    _legend_outside(ax, fontsize=8)
    _mark_end(ax, res)
    return fig


@_with_rc
def lyapunov_decay(L, res, claim: str | None = None) -> str:
    """V_dot (exact, by AD) against -rho V + delta (and a printed decay claim's, with its violations marked)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.0, 3.4))
    rc, rp = L.rhs("corrected"), L.rhs("paper")
    t, Vd, RC, RP = _decimate(L.t, L.V_dot, rc, rp)
    ax.plot(t, RC, color="C2", lw=1, label="-\u03c1V + \u03b4 (corrected, eq. 8)")
    printed = bool(claim) and np.isfinite(rp).any()
    if printed:
        ax.plot(t, RP, color="C3", lw=1, ls=":", label=f"-\u03c1V + \u03b4 (printed claim {_claim_name(claim)})")
    ax.plot(t, Vd, color="C0", lw=1, label="dV/dt (exact, AD along the flow)")
    bad = np.isfinite(L.V_dot) & np.isfinite(rp) & (L.V_dot > np.where(np.isfinite(rp), rp, np.inf))
    if printed and bad.any():
        ax.plot(L.t[bad], L.V_dot[bad], "x", color="crimson", ms=6, label=f"printed claim {_claim_name(claim)} violated")
    bad_c = np.isfinite(L.V_dot) & (L.V_dot > rc)
    if bad_c.any():
        ax.plot(L.t[bad_c], L.V_dot[bad_c], "o", mfc="none", color="crimson", ms=7,
                label="corrected claim violated")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_title("Decay claim dV/dt \u2264 -\u03c1V + \u03b4 along the trajectory", fontsize=10)
    ax.set_xlabel("t [s]")
    _legend_outside(ax, fontsize=8)
    _mark_end(ax, res)
    return fig


@_with_rc
def falsification(fz, bins: int = 40, claim: str | None = None) -> str:
    """Sampled states binned by t: fraction violating the decay inequality, and the worst relative margin per bin."""
    plt = _plt()
    a = fz["arrays"]
    t = np.asarray(a["t"])
    lo, hi = fz["t_range"]
    edges = np.linspace(lo, hi, bins + 1)
    idx = np.clip(np.digitize(t, edges) - 1, 0, bins - 1)
    mids = 0.5 * (edges[1:] + edges[:-1])
    fig, axes = plt.subplots(2, 1, figsize=(8.0, 4.4), sharex=True)
    versions = [("rhs", "corrected (eq. 8)", "C2")]
    if claim and np.isfinite(np.asarray(a["rhs_paper"], float)).any():
        versions.insert(0, ("rhs_paper", f"printed claim {_claim_name(claim)}", "C3"))
    for key, label, color in versions:
        m = np.asarray(a[key], float) - np.asarray(a["V_dot"], float)
        with np.errstate(invalid="ignore"):
            rel = m / np.maximum(np.abs(a[key]) + np.abs(a["V_dot"]), 1e-300)
        ok = np.isfinite(rel)
        if not ok.any():        # no such inequality in this scenario (no printed decay claim: NaN throughout)
            continue
        cells = [(idx == k) & ok for k in range(bins)]
        frac = np.array([np.mean(rel[c] < 0) if c.any() else np.nan for c in cells])
        worst = np.array([np.min(rel[c]) if c.any() else np.nan for c in cells])
        nv = int(np.sum(rel[ok] < 0))
        axes[0].step(mids, 100 * frac, where="mid", color=color, label=f"{label}: {nv} of {int(ok.sum())} violate")
        axes[1].step(mids, worst, where="mid", color=color, label=label)
    axes[0].set_ylabel("violating [%]")
    _legend_outside(axes[0], fontsize=8)
    axes[1].axhline(0, color="k", lw=0.8)
    axes[1].set_ylabel("worst relative margin")
    axes[1].set_xlabel("t of the sampled state [s] (bins)")
    fig.suptitle(f"Falsification (sampled, not a proof): {fz['samples']} Sobol states inside the funnels; "
                 "relative margin = (rhs - dV/dt)/(|rhs| + |dV/dt|)", fontsize=9)
    return fig


@_with_rc
def reservoir(res, leak: float) -> str:
    """Envelope of the reservoir state against its invariant box."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.0, 2.4))
    x = np.asarray(res.signals["x_esn"]).reshape(len(res.t), -1)
    t, mx, mn = _decimate(res.t, np.max(x, axis=1), np.min(x, axis=1))
    ax.fill_between(t, mn, mx, color="C0", alpha=0.3, lw=0, label="range of x_esn over the units")
    ax.axhline(1 / leak, color="k", ls="--", lw=0.8, label="invariant box \u00b11/leak")
    ax.axhline(-1 / leak, color="k", ls="--", lw=0.8)
    ax.set_title("Echo-state reservoir x_esn(t)", fontsize=10)
    ax.set_xlabel("t [s]")
    _legend_outside(ax, fontsize=8)
    _mark_end(ax, res)
    return fig


@_with_rc
def funnel_margin(res, n: int) -> str:
    """|e1|/F1 and |e2|/F2 on a log scale: containment (< 1) stays visible however small the funnel gets."""
    fig, axes = _joint_axes(n, "Containment at every scale: |e_i(t)|/F_i(t) (log scale; inside the funnel iff < 1)")
    for j, ax in enumerate(axes):
        for key, color in (("e1", "C0"), ("e2", "C1")):
            Fk = "F" + key[1]
            r = np.abs(np.asarray(res.signals[key])[:, j]) / np.asarray(res.signals[Fk])[:, j]
            t, rr = _decimate(res.t, r)
            ax.semilogy(t, np.maximum(rr, 1e-12), color=color, label=f"|{key}|/{Fk}")
        ax.axhline(1.0, color="crimson", lw=1, ls="--", label="funnel boundary")
        lo = ax.get_ylim()[0]
        ax.set_ylim(max(lo, 1e-8), 2.0)
        ax.set_ylabel(f"joint {j + 1}")
        _mark_end(ax, res)
    _legend_outside(axes[0], fontsize=8)
    axes[-1].set_xlabel("t [s]")
    return fig


@_with_rc
def tune_comparison(original, tuned, tau_max=None) -> str:
    """Original against tuned design: the largest |tau_i| over the joints and the smallest margins of e1 and e2."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(7.0, 4.6), sharex=True)
    for res, label, ls in ((original, "original", "--"), (tuned, "tuned", "-")):
        t = np.asarray(res.t)
        if t.size < 2:
            continue
        tau = np.max(np.abs(np.asarray(res.signals["tau"]).reshape(t.size, -1)), axis=1)
        m1 = np.min(np.asarray(res.signals["m1"]).reshape(t.size, -1), axis=1)
        m2 = np.min(np.asarray(res.signals["m2"]).reshape(t.size, -1), axis=1)
        tt, tau, m1, m2 = _decimate(t, tau, m1, m2)
        axes[0].plot(tt, tau, ls, color="C0" if label == "tuned" else "C3", label=f"{label}: max_i |tau_i|")
        axes[1].plot(tt, m1, ls, color="C0" if label == "tuned" else "C3", label=f"{label}: min_i margin e1")
        axes[1].plot(tt, m2, ls, color="C2" if label == "tuned" else "C1", label=f"{label}: min_i margin e2")
    if tau_max is not None:
        axes[0].axhline(float(np.min(tau_max)), color="crimson", lw=1, ls=":", label="torque limit")
    axes[0].set_ylabel("|tau| [N m]")
    axes[0].set_yscale("symlog", linthresh=1.0)
    axes[1].set_ylabel("1 - |e|/F")
    axes[1].set_xlabel("t [s]")
    axes[0].set_title("Original (dashed) against tuned (solid) design")
    _legend_outside(axes[0], fontsize=7)
    _legend_outside(axes[1], fontsize=7)
    return fig


@_with_rc
def rate_bracket(marks) -> str:
    """The deployed controller's rates on one log-frequency axis: marks [(label, Hz)] (f_sim, f_proven, f_theory;
    the ones that exist), each a vertical line with its value."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.0, 1.9))
    vals = [float(v) for _, v in marks]
    for i, (label, v) in enumerate(marks):
        ax.axvline(v, color=f"C{i}", lw=2, label=f"{label}: {v:.6g} Hz")
        ax.plot([v], [0.5], "o", color=f"C{i}")
    if vals:
        lo, hi = min(vals), max(vals)
        ax.set_xlim(lo / 3.0, hi * 3.0)
    ax.set_xscale("log")
    ax.set_yticks([])
    ax.set_ylim(0, 1)
    ax.set_xlabel("sample rate [Hz]")
    ax.set_title("Sample rates of the deployed controller")
    _legend_outside(ax, fontsize=8)
    return fig

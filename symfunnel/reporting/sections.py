"""One function per section of the report, each turning the Run's stages into the plain data its template block shows."""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np

from ..core.names import compress_names, joint_units, unit_label
from . import figures as FIG
from . import formula as FM
from .mathml import (
    DOT,
    FORMULA_MAX_CHARS,
    FORMULA_MAX_OPS,
    WIDTH_CLAIM,
    WIDTH_PAGE,
    WIDTH_SIGNAL,
    claim_sympy,
    formula_html,
    mathml_body,
    matrix_html,
    noise_note,
    signal_sympy,
    symbol_mathml,
)
from .text import flatten, fmt, where_text


def versions() -> list[tuple[str, str]]:
    """Software versions of this run."""
    from importlib import metadata

    from ..core.version import __version__
    out = [("symfunnel", __version__), ("Python", sys.version.split()[0]), ("platform", platform.platform())]
    for mod, dist in (("casadi", "casadi"), ("numpy", "numpy"), ("scipy", "scipy"), ("sympy", "sympy"),
                      ("matplotlib", "matplotlib"), ("jinja2", "Jinja2")):
        try:
            out.append((mod, metadata.version(dist)))
        except metadata.PackageNotFoundError:
            out.append((mod, "not available"))
    return out


# --- sections --------------------------------------------------------------------------------------

def funnel_text(shape, n: int) -> str:
    """A funnel as text: one formula, or one per joint when they differ."""
    texts = [shape.text(i) for i in range(n)]
    return texts[0] if len(set(texts)) == 1 else "; ".join(f"joint {i + 1}: {t}" for i, t in enumerate(texts))


def scenario_section(sc) -> dict:
    """The scenario and (when it lists them) its deviations from its source."""
    f1, f2 = sc.funnels["e1"], sc.funnels["e2"]
    pl = sc.plant
    params = [
        ("joints n", sc.n), ("model", f"{sc.model.kind}, C {sc.model.C_source}"),
        ("model parameters", ", ".join(f"{k} = {v:g}" for k, v in zip(sc.model.p_names, sc.model.p_values)) or "—"),
        ("reference q_d(t)", ", ".join(e.text for e in sc.reference)),
        ("initial q(0), dq(0)", f"{fmt(sc.q0)}, {fmt(sc.dq0)}"),
        ("funnel F1(t)", funnel_text(f1, sc.n)),
        ("funnel F2(t)", funnel_text(f2, sc.n)),
        ("gains k1, k2", f"{fmt(sc.k1)}, {fmt(sc.k2)}"),
        ("adaptation gamma, sigma, W_hat(0)", f"{sc.gamma:g}, {sc.sigma:g}, {sc.w_hat0:g}"),
        ("design", f"{sc.design.variant}, transformation {sc.design.transform}, approximator "
                   f"{sc.design.approximator}"),
        *([("ESN", f"N = {sc.esn.size}, leak {sc.esn.leak:g}, time constant {sc.esn.time_constant:g} s, spectral "
                   f"radius {sc.esn.spectral_radius:g}, sparsity {sc.esn.sparsity:g}, seed {sc.esn.seed}, inputs "
                   f"{', '.join(sc.esn.inputs)}")] if sc.design.approximator == "esn" else []),
        ("plant (unknown to the controller)",
         f"viscous {fmt(pl.viscous)}, Coulomb {fmt(pl.coulomb)}, disturbance "
         f"{', '.join(e.text for e in pl.disturbance)}, mass scale {pl.mass_scale:g}"
         + (f", dead zone b_l = {fmt(pl.dead_zone.b_l)}, b_r = {fmt(pl.dead_zone.b_r)}, left {pl.dead_zone.left.text},"
            f" right {pl.dead_zone.right.text}" if pl.dead_zone else ", no dead zone")),
        ("simulation", f"t_final {sc.simulation.t_final:g} s, output step {sc.simulation.dt:g} s, "
                       f"{sc.simulation.integrator}, rtol {sc.simulation.rtol:g}, atol {sc.simulation.atol:g}, "
                       f"smoothing width {sc.simulation.smoothing_width:g}"),
    ]
    return {"name": sc.name, "title": sc.title, "source": sc.source, "description": sc.description,
            "file": sc.file, "file_shown": file_shown(sc), "params": params, "deviations": sc.deviations,
            "origin": "the source" if sc.source else "the scenario"}


def file_shown(sc) -> str:
    """Where the scenario came from, as the header shows it: 'built-in: NAME' for a scenario shipped with symfunnel
    (its install path says nothing to a reader), else the file's path."""
    from ..scenario import BUILTIN, DATA_DIR
    try:
        p = Path(sc.file).resolve()
    except (TypeError, OSError):
        return str(sc.file)
    for name, fname in BUILTIN.items():
        if p == (DATA_DIR / fname).resolve():
            return f"built-in: {name}"
    return str(sc.file)


def model_section(sc, audit_results) -> dict:
    """M, C, G as MathML (parameters kept symbolic) and the audit's model/funnel/design checks."""
    from ..sx.tosympy import sx_to_sympy
    m = sc.model
    eqs = []
    ins = [m.q, m.dq] + ([m.p] if m.p.numel() else [])
    for name in ("M", "C", "G"):
        X = getattr(m, name)
        try:
            f = ca.Function("f", ins, [X])
            if f.n_instructions() > 2000:
                raise ValueError("large")
            mat, dropped = FM.present(sx_to_sympy(X, ins))
            mm = matrix_html(name, mat)
            if mm is None or len(mm) > 6 * FORMULA_MAX_CHARS:
                raise ValueError("large")
            eqs.append({"name": name, "mathml": mm, "ops": None, "note": noise_note(dropped)})
        except Exception:  # noqa: BLE001 - a large model is shown by its size
            from ..design import count_ops
            eqs.append({"name": name, "mathml": None, "ops": count_ops(ca.Function("f", ins, [X]))})
    checks = [check_row(c) for c in audit_results if not c.id.startswith("claim.")]
    return {"equations": eqs, "checks": checks}


def check_row(c) -> dict:
    """A check as every table of the report shows it: the verdict against the declaration (label and style, as
    in the overview and in `symfunnel verify`), margin, where, detail, method and the declared reason."""
    from ..checks.gate import verdict
    label, css = verdict(c)
    return {"id": c.id, "status": c.status, "expected": c.expected, "label": label, "css": css, "detail": c.detail,
            "method": c.method, "margin": fmt(c.margin), "where": where_text(c.where), "reason": c.reason,
            "row": {"finding": "finding-row", "fail": "fail-row"}.get(css, "")}


SIGNAL_ORDER = ("F1", "dF1", "e1", "de1", "zeta1", "z1", "mu1", "alpha2", "alpha2_dot", "z1_dot", "e2", "zeta2", "z2",
                "mu2", "Phi", "v", "tau", "ddq", "de2", "z2_dot", "w_hat_dot", "x_esn_dot")


def derivation_section(design, audit_results, progress) -> dict:
    """Each signal: formula where small (joint 1 shown), size in operations without and with CSE; alpha2_dot panel."""
    import sympy

    from ..core.names import SIGNALS
    from ..design import count_ops
    rows = []
    for k in SIGNAL_ORDER:
        if k not in design.signals:
            continue
        e = design.signals[k]
        inputs = design.inputs_of(k)
        syms = [design.sym[x] for x in inputs]
        raw = count_ops(ca.Function("raw", syms, [e]))
        cse = design.ops(k)
        row = {"name": k, "sym": symbol_mathml(k), "desc": SIGNALS.get(k, ("", 0))[0],
               "shape": f"{e.shape[0]}\u00d7{e.shape[1]}", "ops_raw": raw, "ops_cse": cse,
               "free": compress_names(design.free_symbols(k)), "mathml": None, "note": ""}
        # one entry (joint 1) is shown whatever n is: its size, not the vector's, decides
        if k in ("alpha2", "alpha2_dot"):
            row["note"] = "entry of joint 1 below (The exact \u03b1\u0307\u2082)"
        elif k not in ("Phi",) and count_ops(ca.Function("e1", syms, [e[0]])) <= 4 * FORMULA_MAX_OPS:
            try:
                s = signal_sympy(design, k, 0)
                if sympy.count_ops(s) <= FORMULA_MAX_OPS:
                    mm = formula_html(symbol_mathml(k), s, WIDTH_SIGNAL)
                    if mm is not None and len(mm) <= FORMULA_MAX_CHARS:
                        row["mathml"] = mm
                        row["note"] = "entry of joint 1 (the other joints alike)" if e.numel() > 1 else ""
            except Exception as exc:  # noqa: BLE001
                row["note"] = f"not converted ({type(exc).__name__})"
        if row["mathml"] is None and not row["note"]:
            row["note"] = "too large to read as a formula: size only"
        rows.append(row)
    progress("derivation: the exact alpha2_dot")
    # the exact derivative (cse form), laid out to the page; the printed claims are the claims table, once
    panel = {"alpha2": None, "alpha2_dot": None, "alpha2_dot_cse": [], "ops": design.ops("alpha2_dot")}
    try:
        a2 = signal_sympy(design, "alpha2", 0)
        panel["alpha2"] = panel_formula("<msub><mi>&#945;</mi><mn>2,1</mn></msub>", a2)
        a2d, _ = FM.present(signal_sympy(design, "alpha2_dot", 0))
        taken = {str(x) for x in a2d.free_symbols}
        xs = (sympy.Symbol(f"x{i}") for i in range(10 ** 6) if f"x{i}" not in taken)
        repl, (red,) = sympy.cse(a2d, symbols=xs)
        # the key result first (its top-level structure), then the subexpressions it uses
        panel["alpha2_dot"] = panel_formula(f"<msub><mover><mi>&#945;</mi>{DOT}</mover><mn>2,1</mn></msub>", red)
        panel["alpha2_dot_cse"] = [panel_formula(mathml_body(s), v) for s, v in repl]
        panel["alpha2_dot_ops_joint1"] = int(sympy.count_ops(a2d))
    except Exception as exc:  # noqa: BLE001
        panel["error"] = f"{type(exc).__name__}: {exc}"
    claims = claims_rows(design, audit_results)
    return {"signals": rows, "alpha2": panel, "claims": claims}


def panel_formula(lhs: str, expr) -> str:
    """A formula of the exact alpha2_dot laid out to the page (never dropped: it is the key result)."""
    h = formula_html(lhs, expr, WIDTH_PAGE, max_lines=10 ** 6)
    if h is None:
        raise ValueError("too large to lay out")
    return h


def claims_rows(design, audit_results) -> list[dict]:
    """Each printed claim: its formula as printed (MathML), the exact signal's name, the audit verdict."""
    by_id = {c.id: c for c in audit_results}
    out = []
    for cl in design.scenario.claims:
        r = by_id.get(f"claim.{cl.name}")
        row = {"name": cl.name, "source": cl.source, "description": cl.description, "signal": cl.signal,
               "kind": cl.kind, "mathml": None, "text": "", "check": check_row(r) if r is not None else None}
        if cl.kind == "funnel":
            row["text"] = f"F(t) = {funnel_text(cl.spec, design.n)} for {cl.funnel}"
            row["signal"] = f"funnel {cl.funnel}"
        elif cl.kind == "decay":
            row["text"] = f"dV/dt <= -rho V + delta with rho = {cl.rho.text}, delta = {cl.delta.text}"
            row["signal"] = "V_dot"
        elif cl.kind == "inequality":
            row["text"] = f"{cl.lhs.text} <= {cl.rhs.text}"
            row["signal"] = "inequality"
        else:
            row["text"] = cl.expression.text
            try:
                s = claim_sympy(cl)
                row["mathml"] = formula_html(symbol_mathml(cl.signal), s, WIDTH_CLAIM)
            except Exception:  # noqa: BLE001 - shown as text
                row["mathml"] = None
        out.append(row)
    return out


PAPER_TITLE = "Adaptive Predefined Performance Neural Control for Robotic Manipulators with Unknown Dead Zone"


# report figure -> the figure of the paper's Section 4 it corresponds to (number, the paper's caption)
PAPER_FIGURES = {"tracking": (6, "Output tracking"), "esn": (7, "Friction compensation"),
                 "torque": (8, "Control signals")}


def cites_paper(sc) -> bool:
    """Whether a scenario's `source` is the paper whose Section 4 figures the report's figures correspond to."""
    return bool(sc.source) and PAPER_TITLE.lower() in sc.source.lower()


def figure_caption(fid: str, caption: str, sc) -> str:
    """A figure's caption, with the figure of the paper it reproduces when the scenario's source is that paper."""
    if fid in PAPER_FIGURES and cites_paper(sc):
        num, title = PAPER_FIGURES[fid]
        verb = "Reproduces" if sc.name == "paper" else "Corresponds to"
        return f"{caption}. {verb} Figure {num} (\u201c{title}\u201d) of the source."
    return f"{caption}."


def simulation_section(v, progress, figures_dir=None) -> dict:
    """Summary of the run and its figures (SVG; also PNG and PDF files in figures_dir when given)."""
    res = v.result
    sc = v.scenario
    n = v.design.n
    L = v.lyapunov
    figs = []
    units = joint_units(sc.model.joint_types, n)
    claim = decay_claim(sc)

    def add(fid, caption, fn, *args):
        stem = f"fig{len(figs) + 1:02d}-{fid}"
        svg = fn(*args, export_to=(figures_dir, stem) if figures_dir is not None else None)
        figs.append((fid, figure_caption(fid, caption, sc), svg))

    if res.t.size >= 2:
        progress("figures: tracking, funnels, z, torque")
        add("tracking", "Joint tracking against the reference", FIG.tracking, res, n, units)
        add("funnel-e1", "e1 inside \u00b1F1", FIG.funnel, res, n, "e1", units)
        add("funnel-margin", "|e|/F on a log scale: containment in both funnels at every scale",
            FIG.funnel_margin, res, n)
        add("funnel-e2", "e2 inside \u00b1F2", FIG.funnel, res, n, "e2", units)
        add("z", "Transformed errors z1, z2", FIG.z_signals, res, n)
        add("torque", "Commanded against applied torque" + (" through the dead zone" if sc.plant.dead_zone else ""),
            FIG.torque, res, n, sc.plant.dead_zone, units)
        progress("figures: ESN, weights, Lyapunov")
        fit = None
        if L is not None and v.design.n_regressor:
            from ..checks.lyapunov import regressor_values
            fit = regressor_values(v.closed_loop, res.x) @ L.W_star
        if v.design.n_regressor:
            add("esn", "The approximator's estimate against the true unknown term", FIG.esn_estimate, res, n, fit)
            add("weights", "\u2016\u0174\u2016_F", FIG.weights, res, L.W_star if L is not None else None)
        if "x_esn" in res.signals:
            add("reservoir", "Reservoir state", FIG.reservoir, res, sc.esn.leak)
        if L is not None and np.isfinite(L.V).sum() >= 2:
            add("lyapunov-bound", "V(t) with its bound", FIG.lyapunov_bound, L, res, claim)
            add("lyapunov-decay", "dV/dt against -\u03c1V + \u03b4", FIG.lyapunov_decay, L, res, claim)
    if v.falsification is not None:
        add("falsification", "Falsification over sampled states", FIG.falsification, v.falsification, 40, claim)
    summ = res.summary()
    from ..simulation.hints import status_text
    stats = [("status", status_text(res.status)), ("message", res.message),
             ("simulated", f"{summ.get('t_end', 0):g} of {summ.get('t_final') or 0:g} s, {summ.get('points')} output points"),
             ("integrator", f"{summ.get('integrator')} ({summ.get('code')} code), steps {summ.get('steps')}, "
                            f"rhs evaluations {summ.get('rhs_evaluations')}"),
             ("non-smooth terms", summ.get("non_smooth_treatment")),
             ("wall time", f"{fmt(summ.get('wall_time'))} s (real-time factor {fmt(summ.get('realtime_factor'))})"),
             ("min margin 1 - |e|/F of e1 / e2 per joint, whole run",
              f"{fmt(summ.get('min_margin_e1'))} / {fmt(summ.get('min_margin_e2'))}"),
             (f"min margin of e1 / e2 per joint after the transient (t \u2265 {fmt(summ.get('settle_time'))} s, "
              f"{summ.get('settle_source', '')})",
              f"{fmt(summ.get('min_margin_e1_after_transient'))} / {fmt(summ.get('min_margin_e2_after_transient'))} "
              f"(at t = {fmt(summ.get('t_min_margin_e1_after_transient'))} / "
              f"{fmt(summ.get('t_min_margin_e2_after_transient'))} s)"),
             (f"max |tau| / |D(tau)| per joint [{unit_label(units, 'tau')}]",
              f"{fmt(summ.get('max_abs_tau'))} / {fmt(summ.get('max_abs_tau_applied'))}"),
             (f"rms ESN error / rms f_true [{unit_label(units, 'e1')}/s\u00b2]",
              f"{fmt(summ.get('rms_esn_error'))} / {fmt(summ.get('rms_f_true'))}")]
    return {"figures": figs, "stats": stats, "status": res.status, "breach": res.breach,
            "metrics": metrics_table(summ.get("metrics"))}


#: the report's names of the metrics (`simulation.metrics`, docs/metrics.md)
METRIC_NAMES = {"e1_rms_after_transient": "e1 RMS after the transient", "e1_max_after_transient":
                "max |e1| after the transient", "overshoot": "overshoot of e1", "settling_time": "settling time of e1",
                "peak_tau": "peak |tau| (whole run)", "peak_tau_after_t0": "peak |tau| after the initial decay",
                "control_energy": "control energy \u222b tau\u00b2 dt",
                "chattering": "chattering (total variation of tau per s)"}


def metrics_table(block: dict | None) -> dict | None:
    """The metrics block of a summary as a table: one row per metric with its unit, one column per joint (a cell
    carries its own unit where the joints' differ)."""
    if not block or not block.get("per_joint"):
        return None
    per, units = block["per_joint"], block.get("units") or {}
    rows = []
    for key, name in METRIC_NAMES.items():
        us = units.get(key) or [""] * len(per)
        same = len(set(us)) == 1
        if key == "settling_time":
            name += f" (band {100 * block.get('settling_band_fraction', 0.02):g} % of max |e1|)"
        if key.endswith("after_transient"):
            name += f" (t \u2265 {fmt(block.get('settle_time'))} s)"
        cells = [fmt(m.get(key)) + ("" if same or m.get(key) is None else f" {u}") for m, u in zip(per, us)]
        rows.append((name, us[0] if same else "per joint", cells))
    return {"joints": [f"joint {j + 1}" for j in range(len(per))], "rows": rows}


def decay_claim(sc) -> str | None:
    """The id of the scenario's printed decay claim (whose rho, delta the Lyapunov stage evaluates), if any."""
    c = next((c for c in sc.claims if c.kind == "decay"), None)
    return f"claim.{c.name}" if c is not None else None


def verification_section(v, shown=()) -> dict:
    """verify's own checks (those not already in the audit's and the claims' tables: `shown`), W* and rho/delta,
    falsification summary; the counts are over every check, as `symfunnel verify` prints them."""
    from ..checks.gate import counts, counts_line
    shown = set(shown)
    rows = [check_row(c) for c in v.checks if c.id not in shown]
    L = v.lyapunov
    info = None
    claim = decay_claim(v.scenario)
    if L is not None:
        wi = L.w_star_info
        info = [("W* (estimated; not given by the source)" if v.scenario.source else "W* (estimated)",
                 wi.get("method", "")),
                ("||W*||_F", fmt(wi.get("norm"))),
                ("rms eps = f_true - W*^T Phi (rms f_true)", f"{fmt(wi.get('rms_residual'))} ({fmt(wi.get('rms_f_true'))})"),
                ("plain least squares, for comparison", f"||W||_F = {fmt(wi.get('plain_ls_norm'))}, rms residual "
                 f"{fmt(wi.get('plain_ls_rms_residual'))}, condition number {fmt(wi.get('plain_ls_condition'))}"),
                ("corrected: constant rho (min over trajectory) / constant lower bound",
                 f"{fmt(L.rho_const)} / {fmt(L.rho_const_lower)}"),
                ("corrected: delta_max (max over trajectory), ultimate bound delta/rho",
                 f"{fmt(L.delta_max)}, {fmt(L.delta_max / L.rho_const if L.rho_const else None)}"),
                *([(f"printed decay claim {claim}: rho (min over trajectory), delta (max over trajectory)",
                    f"{fmt(L.rho_paper_const)}, {fmt(L.delta_paper_const)}")]
                  if claim and np.isfinite(L.rho_paper_const) else [])]
    fz = None
    if v.falsification is not None:
        f = v.falsification
        fz = {"samples": f["samples"], "fill": f["fill"], "w_scale": fmt(f["w_scale"]), "t_range": f["t_range"],
              "rows": [{"which": w, "violations": f[w]["violations"], "evaluated": f[w]["evaluated"],
                        "fraction": f"{f[w]['fraction']:.2%}", "worst": fmt(f[w]["worst_margin"]),
                        "where": where_text(f[w]["where"])} for w in ("paper", "corrected")
                       if f[w]["evaluated"] and (w == "corrected" or claim)]}
        for r in fz["rows"]:
            r["which"] = f"printed claim {claim}" if r["which"] == "paper" else "corrected (docs/derivation.md)"
    return {"rows": rows, "info": info, "falsification": fz, "counts": counts(v.checks),
            "counts_line": counts_line(v.checks), "claim": claim, "shown": len(shown & {c.id for c in v.checks})}


def implementation_section(run, progress) -> dict:
    """The deployed controller: minimum rate with every tried rate, what sets it (re-computed for variations),
    the sampled torque (stairs) over the continuous one, and the peak torque beside the actuator limits."""
    from ..deployed.rate import margin_rate_figure
    from ..deployed.summary import torque_figure
    from .deployed import fmu_entry, rate_bracket
    progress("deployed controller: minimum sample rate, design help, sampled run")
    try:
        data = run.implementation
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
    r = data["min_rate"]
    figs = [("margin-rate", "Minimum funnel margin against the sample rate (every rate the search tried)",
             FIG.to_svg(margin_rate_figure(r)))]
    res = (data.get("run") or {}).get("result")
    if res is not None:
        figs.append(("torque-sampled", f"Sampled torque (held, {res.rate_hz:g} Hz) over the continuous-time "
                     "controller's, first 0.5 s", FIG.to_svg(torque_figure(res, run.simulation, t_max=0.5,
                                                       units=joint_units(run.scenario.model.joint_types,
                                                                         run.scenario.n)))))
    bracket = rate_bracket(run, r, progress=progress)
    if bracket.get("figure") and bracket["figure"][2]:
        figs.append(bracket["figure"])
    sens = data.get("sensitivity") or {}
    rows = [{"key": v["key"], "factor": fmt(v["factor"]), "before": fmt(v["before"]), "after": fmt(v["after"]),
             "rate": fmt(v["min_rate_hz"]), "ratio": fmt(v["ratio"])} for v in sens.get("variations", [])]
    return {"available": True, "min_rate": fmt(r["min_rate_hz"]), "margin": fmt(r["margin"]),
            "rate_reason": r.get("reason"),
            "tried": [(fmt(d["rate_hz"]), d["status"], fmt(d.get("min_margin_after_transient", d["min_margin"])))
                      for d in r["tried"]],
            "tau_unit": unit_label(joint_units(run.scenario.model.joint_types, run.scenario.n), "tau"),
            "variations": rows, "gain": fmt(sens.get("inner_loop_gain")),
            "rate": fmt(res.rate_hz) if res is not None else None,
            "status": (data.get("run") or {}).get("status"), "peak_tau": fmt(data.get("peak_tau")),
            "tau_max": fmt(data.get("tau_max")), "effort": fmt(data.get("effort_limits")),
            "declared": run.scenario.implementation is not None, "figures": figs,
            "fmu": fmu_entry(run, res.rate_hz if res is not None else None), "bracket": bracket}


def tuning_section(run, progress, figures_dir=None) -> dict:
    """Original against tuned design side by side, when the scenario carries `symfunnel tune`'s `[[deviations]]`
    records (the original is those records undone): torque, margins, minimum rate, breach probability, a figure."""
    from ..synthesis.records import compare_designs, tune_records
    sc = run.scenario
    if not tune_records(sc.raw):
        return {"available": False}
    progress("tuning: the original design against the tuned one")
    try:
        cmp_ = compare_designs(sc, tuned_run=run, t_final=run.options.t_final, progress=progress)
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"available": True, "error": f"{type(exc).__name__}: {exc}"}
    o, t = cmp_["original"], cmp_["tuned"]
    units = joint_units(sc.model.joint_types, sc.n)
    tu, eu = unit_label(units, "tau"), unit_label(units, "e1")

    def post(side, key):                 # the margin tune's table shows: the minimum after the transient
        vals = [v for v in side["simulation"].margins()[f"min_margin_{key}_after_transient"] if v is not None]
        return fmt(min(vals)) if vals else None

    def metric(side, key):               # docs/metrics.md, the largest over the joints
        vals = [m[key] for m in side["simulation"].metrics()["per_joint"] if m.get(key) is not None]
        return fmt(max(vals)) if vals else None

    ts = fmt(t["simulation"].margins()["settle_time"])
    rows = [("status of the continuous-time run", o["status"], t["status"]),
            (f"peak |tau| [{tu}]", fmt(o["peak_torque"]), fmt(t["peak_torque"])),
            (f"min margin e1 after the transient (t \u2265 {ts} s; as in tune's table)", post(o, "e1"), post(t, "e1")),
            (f"min margin e2 after the transient (t \u2265 {ts} s; as in tune's table)", post(o, "e2"), post(t, "e2")),
            ("min margin e1, whole run", fmt(o["min_margin_e1"]), fmt(t["min_margin_e1"])),
            ("min margin e2, whole run", fmt(o["min_margin_e2"]), fmt(t["min_margin_e2"])),
            (f"e1 RMS after the transient [{eu}] (largest joint)", metric(o, "e1_rms_after_transient"),
             metric(t, "e1_rms_after_transient")),
            (f"chattering [{tu}/s] (largest joint)", metric(o, "chattering"), metric(t, "chattering"))]
    if "min_rate_hz" in t:
        rows.append(("minimum sample rate [Hz]", fmt(o["min_rate_hz"]), fmt(t["min_rate_hz"])))
    if "breach_probability" in t:
        def bp(side):
            lo, hi = side["breach_ci95"] or (None, None)
            return f"{fmt(side['breach_probability'])} (95 % CI [{fmt(lo)}, {fmt(hi)}], {side['runs']} runs)"
        rows.append(("breach probability", bp(o), bp(t)))
    impl = sc.implementation
    tau_max = impl.tau_max if impl is not None else (sc.tune.tau_max if sc.tune is not None else None)
    stem = "fig-tune-comparison"
    svg = FIG.tune_comparison(o["simulation"], t["simulation"], tau_max,
                              export_to=(figures_dir, stem) if figures_dir is not None else None)
    changes = [(c["name"], fmt(c["before"]), fmt(c["after"])) for c in cmp_["changes"]]
    return {"available": True, "rows": rows, "changes": changes,
            "figures": [("tune-comparison", figure_caption("tune-comparison", "Original (dashed) against tuned "
                                                           "(solid): largest |tau| and smallest funnel margins",
                                                           sc), svg)]}


def codegen_section(run, progress) -> dict:
    """The code-generation summary of a Run: both languages generated, compiled/imported and cross-checked."""
    from ..emit.check import codegen_summary
    progress("code generation: C and Python, compiled/imported and cross-checked")
    t0 = time.perf_counter()
    try:
        s = codegen_summary(run.design, run.code_trajectory)
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"available": False, "reason": f"code generation failed: {type(exc).__name__}: {exc}"}
    out = {"available": True, "seconds": time.perf_counter() - t0, "functions": s.get("functions", []),
           "controller_operations": s.get("controller_operations"), "points": s.get("points"), "languages": [],
           "timings": flatten(s.get("timings")) if s.get("timings") else [],
           "timings_error": s.get("timings_error")}
    for lang, e in (s.get("languages") or {}).items():
        chk = e.get("check") or {}
        out["languages"].append({
            "lang": lang, "files": e.get("files", []), "error": e.get("error"),
            "passed": chk.get("passed"), "worst": fmt(chk.get("worst")), "threshold": fmt(chk.get("threshold")),
            "errors": [(k, fmt(v)) for k, v in (chk.get("errors") or {}).items()] +
                      [(k, fmt(v)) for k, v in (chk.get("extra") or {}).items()],
        })
    return out


def run_hints(run) -> list[str]:
    """What to do after the continuous-time run left a funnel (the sampled run's hint is in its verdict line)."""
    res = run.simulation
    b = res.breach or {}
    return [b["hint"]] if b.get("hint") and res.status != "ok" else []

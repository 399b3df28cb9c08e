"""The self-contained HTML report: everything symfunnel knows about one scenario, in one file that opens offline.

    from symfunnel.reporting import build_report
    path = build_report(load_scenario("paper"))          # reports/paper.html

Figures are inline SVG (matplotlib; optionally also PNG and PDF files), equations MathML (sympy's presentation printer), CSS inline; there are no
scripts and no network references. The file is written atomically.
"""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path

__all__ = ["build_report", "render_report", "default_path"]


def default_path(scenario) -> Path:
    """reports/<SCENARIO>.html: a built-in's name, else the scenario file's stem (so a copy of a built-in that
    keeps its `name` does not overwrite the built-in's report); relative to the working directory."""
    from ..scenario import is_builtin
    stem = scenario.name if is_builtin(scenario.path) else Path(scenario.path).stem
    return Path("reports") / f"{stem or scenario.name}.html"


def render_report(run, *, codegen: bool = True, mutants: bool = True, deployed: bool = True,
                  figures_dir=None) -> str:
    """The report of a pipeline Run as HTML text (its stages are computed here if they were not yet); with
    figures_dir, every figure is also written there as PNG and PDF."""
    from . import html as H
    from . import sections as S
    say = run.progress or (lambda s: None)
    t_all = time.perf_counter()
    scenario, design = run.scenario, run.design
    audit_results = run.audit
    verification = run.verification
    timings = [(f"stage: {k}", v) for k, v in run.timings.items()]
    t0 = time.perf_counter()
    say("report: scenario, model and derivation sections")
    ctx = {
        "scenario": S.scenario_section(scenario),
        "model": S.model_section(scenario, audit_results),
        "derivation": S.derivation_section(design, verification.checks, say),
    }
    timings.append(("report: formulas (SX -> sympy -> MathML)", time.perf_counter() - t0))
    t0 = time.perf_counter()
    ctx["simulation"] = S.simulation_section(verification, say, figures_dir=figures_dir)
    timings.append(("report: figures (matplotlib -> SVG)", time.perf_counter() - t0))
    from .certify import certify_section
    ctx["certify"] = certify_section(run, say)
    # each check once: the certificates have their own table
    shown = [c.id for c in audit_results] + [r["id"] for r in ctx["certify"].get("rows", [])]
    ctx["verification"] = S.verification_section(verification, shown=shown)
    t0 = time.perf_counter()
    ctx["tuning"] = S.tuning_section(run, say, figures_dir=figures_dir)
    if ctx["tuning"]["available"]:
        timings.append(("tuning: original against tuned", time.perf_counter() - t0))
    for key, wanted, section, label, reason in (
            ("deployed", deployed, S.implementation_section, "deployed controller (rate search, design help)",
             "left out of this report (deployed=False)"),
            ("codegen", codegen, S.codegen_section, "code generation and cross-check",
             "code generation was skipped for this report (codegen=False)")):
        if not wanted:
            ctx[key] = {"available": False, "reason": reason}
            continue
        t0 = time.perf_counter()
        ctx[key] = section(run, say)
        timings.append((label, time.perf_counter() - t0))
    from ..checks.gate import counts_line, outcome_hint, verdict
    from .engine import engine_section
    ctx["engine"] = engine_section(run, say) if deployed else {"available": False, "reason": "deployed=False"}
    checks = verification.checks
    guarantee = next((c for c in checks if c.id == "lyapunov.guarantee"), None)
    g_label, g_css = verdict(guarantee) if guarantee else ("SKIP", "skip")
    vd = verification.verdicts()
    unexpected = []
    for c in verification.unexpected:
        row = S.check_row(c)
        row["hint"] = outcome_hint(scenario, c)
        unexpected.append(row)
    ctx["overview"] = {
        "gate": verification.status, "unexpected": unexpected, "counts_line": counts_line(checks),
        "findings": [c for c in checks if c.expected == "fail" and c.status == "fail"],
        "guarantee": {"status": guarantee.status if guarantee else "skip", "label": g_label, "css": g_css,
                      "detail": guarantee.detail if guarantee else "not evaluated"},
        "mutation": None,
        "sim_status": vd["continuous"]["status"], "sim_message": vd["continuous"]["message"],
        "sampled": vd["sampled"], "hints": S.run_hints(run),
    }
    ctx["omitted"] = [f"{k}: {ctx[k]['reason']}" for k in ("deployed", "codegen") if not ctx[k]["available"]]
    if mutants:
        t0 = time.perf_counter()
        say("mutation testing: the design's seeded errors through the same gate")
        m = run.mutation
        ctx["overview"]["mutation"] = {
            "score": f"{m['score']:.2f}", "killed": m["killed"], "equivalent": m["equivalent"],
            "nonequivalent": m["total"] - m["equivalent"],
            "survived": [r["id"] for r in m["mutants"] if not r["killed"] and not r["equivalent"]]}
        timings.append(("mutation testing", time.perf_counter() - t0))
    timings.append(("report total (after the stages)", time.perf_counter() - t_all))
    ctx["timings"] = [(k, f"{v:.2f} s") for k, v in timings]
    ctx["versions"] = S.versions()
    ctx["generated"] = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    say("rendering HTML")
    return H.render(ctx)


def build_report(run, out=None, *, codegen: bool = True, mutants: bool = True, deployed: bool = True,
                 figures_dir=None) -> Path:
    """Write the report of a Run (default reports/<name>.html) atomically; returns the path. With figures_dir,
    every figure also goes there as figNN-ID.png and figNN-ID.pdf (each written atomically)."""
    from ..core.io import atomic_write
    text = render_report(run, codegen=codegen, mutants=mutants, deployed=deployed, figures_dir=figures_dir)
    path = Path(out) if out is not None else default_path(run.scenario)
    atomic_write(path, text)
    return path

"""The self-contained HTML report: everything symfunnel knows about one scenario, in one file that opens offline.

    from symfunnel.report import build_report
    path = build_report(load_scenario("paper"))          # reports/paper.html

Figures are inline SVG (matplotlib), equations MathML (sympy's presentation printer), CSS inline; there are no
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


def render_report(scenario, *, design=None, verification=None, t_final=None, samples: int = 10000,
                  codegen: bool = True, progress=None) -> tuple[str, object]:
    """The report as HTML text, and the Verification it rests on (computed here unless given)."""
    from ..checks.audit import audit
    from ..checks.verify import verify
    from ..design import derive
    from . import html as H
    say = progress or (lambda s: None)
    timings = []
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    if design is None:
        say("deriving the design")
        design = derive(scenario)
    timings.append(("derive (one SX derivation)", time.perf_counter() - t0))
    t0 = time.perf_counter()
    say("audit: model properties and printed claims")
    audit_results = audit(scenario, design, progress=say)
    timings.append(("audit", time.perf_counter() - t0))
    if verification is None:
        t0 = time.perf_counter()
        verification = verify(scenario, design, t_final=t_final, samples=samples, progress=say)
        for k, v in verification.timings.items():
            if k != "derive":
                timings.append((f"verify: {k}", v))
    t0 = time.perf_counter()
    say("report: scenario, model and derivation sections")
    ctx = {
        "scenario": H.scenario_section(scenario),
        "model": H.model_section(scenario, audit_results),
        "derivation": H.derivation_section(design, audit_results, say),
    }
    timings.append(("report: formulas (SX -> sympy -> MathML)", time.perf_counter() - t0))
    t0 = time.perf_counter()
    ctx["simulation"] = H.simulation_section(verification, say)
    timings.append(("report: figures (matplotlib -> SVG)", time.perf_counter() - t0))
    ctx["verification"] = H.verification_section(verification)
    if codegen:
        t0 = time.perf_counter()
        ctx["codegen"] = H.codegen_section(scenario, design, say)
        timings.append(("code generation summary", time.perf_counter() - t0))
    else:
        ctx["codegen"] = {"available": False, "reason": "code generation was skipped for this report (codegen=False)"}
    audit_fail = [c for c in audit_results if c.status == "fail"]
    ctx["overview"] = {
        "verify_failed": [c.id for c in verification.checks if c.status == "fail"],
        "audit_failed": [c.id for c in audit_fail],
        "sim_status": verification.result.status, "sim_message": verification.result.message,
    }
    timings.append(("total", time.perf_counter() - t_all))
    ctx["timings"] = [(k, f"{v:.2f} s") for k, v in timings]
    ctx["versions"] = H.versions()
    ctx["generated"] = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    say("rendering HTML")
    return H.render(ctx), verification


def build_report(scenario, out=None, *, design=None, t_final=None, samples: int = 10000, codegen: bool = True,
                 progress=None) -> Path:
    """Write the report of a scenario (default reports/<name>.html) atomically; returns the path."""
    from ..io import atomic_write
    text, _ = render_report(scenario, design=design, t_final=t_final, samples=samples, codegen=codegen,
                            progress=progress)
    path = Path(out) if out is not None else default_path(scenario)
    atomic_write(path, text)
    return path

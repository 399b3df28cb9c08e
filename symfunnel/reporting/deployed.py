"""The deployed section's additions: the FMU of the deployed controller listed beside the C files (built by the
emitter at the section's rate, cached by core.ccompile, never embedded), and the rate bracket -- simulated, proven
(certify.sampled, the whole bracket under a small wall-clock budget) and the sampled-data theory's bound -- on one log-frequency axis."""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET

from .text import fmt

__all__ = ["fmu_entry", "rate_bracket", "BRACKET_WALL_LIMIT"]

#: seconds the report gives the whole bracket (set, one-period map, proof, theory bound, the sampled run at f_proven):
#: the proof's search stops at a share of it; a step still running at its end leaves the bracket undecided
BRACKET_WALL_LIMIT = 10.0
#: what the budget covers, as the report says it
COVERED = "set, one-period map, proof, theory bound"


def fmu_entry(run, rate_hz: float | None, fmi: str = "2") -> dict:
    """The FMU `codegen --lang fmu --fmi FMI --rate RATE` would write, described for the report: file name, FMI
    version, size, model identifier, variable count, GUID and a one-line FMPy snippet ({"error": why} when no rate
    or the build fails). The binary is built (cached by its sources) but not embedded."""
    if rate_hz is None:
        return {"error": "no sampled run, so no rate to build the FMU at"}
    from ..emit.fmu import build_fmu, fmu_sources
    t0 = time.perf_counter()
    try:
        src = fmu_sources(run.design, rate_hz, fmi=fmi)
        data = build_fmu(src)
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"error": f"{type(exc).__name__}: {exc}"}
    root = ET.fromstring(src.model_description)
    file = f"{src.identifier}.fmu"
    return {"file": file, "fmi_version": root.get("fmiVersion"), "bytes": len(data), "guid": src.guid,
            "model_identifier": src.identifier, "variables": len(root.find("ModelVariables")),
            "rate": fmt(src.rate_hz), "seconds": time.perf_counter() - t0,
            "command": f"symfunnel codegen {_scenario_arg(run.scenario)} --lang fmu --fmi {fmi} --rate {src.rate_hz:g} "
                       f"--out DIR",
            "snippet": f'import fmpy; res = fmpy.simulate_fmu("{file}", stop_time={10.0 / src.rate_hz:g}, '
                       f'output=["tau[1]", "status"])'}


def rate_bracket(run, r: dict, *, wall_limit: float | None = None, progress=None) -> dict:
    """`rate --certify`'s bracket for the report (same margin and horizon as the section's rate search `r`, the
    same S: certify.containment's when proven, else the default margins) with the whole bracket limited to
    `wall_limit` seconds (`sampled_bracket(budget_owner=...)`): the three rates, the certificate's status and detail,
    a sentence saying what is proven on which set and what the budget covered, and the figure."""
    from ..certificates.sampled import DEFAULT_SET_MARGIN
    from ..certificates.sampled_rate import sampled_bracket, simulated_w_hat_range
    from . import figures as FIG
    wall_limit = BRACKET_WALL_LIMIT if wall_limit is None else wall_limit
    f_sim = r.get("min_rate_hz")
    hz = (lambda v: "-" if v is None else f"{v:.6g}")      # the rates as `rate --certify` prints them
    # the certificates the report already computed (not computed here when it did not): their containment is
    # reused when it is for the same problem (sampled_rate.reuse_containment)
    prior = getattr(run.__dict__.get("certification"), "context", None)
    try:
        b = sampled_bracket(run.scenario, run.design, t_final=run.t_final, margin=r["margin"],
                            set_margin=None, f_sim=f_sim, wall_limit=wall_limit, progress=progress,
                            w_hat_range=simulated_w_hat_range(run.design, run.closed_loop, run.simulation),
                            prior=prior, budget_owner="the report's")
    except Exception as exc:  # noqa: BLE001 - the report says why, instead of failing as a whole
        return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
    c = b["certificate"]
    f_proven, f_theory = b["proven_rate_hz"], b["theory_rate_hz"]
    region = c.get("region") or {}
    m = region.get("margin") or {}
    T = (region.get("t") or [0.0, run.t_final])[1]
    where = (f"the set S of sampled states with |e1| \u2264 (1 \u2212 {m.get('e1', DEFAULT_SET_MARGIN[0]):g}) F1 and "
             f"|e2| \u2264 (1 \u2212 {m.get('e2', DEFAULT_SET_MARGIN[1]):g}) F2, every parameter of the scenario's "
             f"box, t in [0, {T:g}] s")
    tried = c.get("tried") or []
    out = c.get("budget_ran_out")
    cut = out is not None or any(t.get("reason") == "seconds" for t in tried) or \
        "budget ran out" in str((c.get("theory") or {}).get("reason"))
    budget = f" The report gives the bracket {wall_limit:g} s ({COVERED})" + (
        ", which ran out; `symfunnel rate --certify` without --wall-limit runs it to its box budget." if cut else ".")
    th = c.get("theory") or {}
    theory_is = (f"f_theory = {hz(f_theory)} Hz is the sampled-data theory's reach-time bound with rigorous constants"
                 if f_theory is not None else
                 f"f_theory, the sampled-data theory's reach-time bound, is {th.get('reason') or 'not computed'}")
    if out is not None:
        sentence = (f"No rate is proven: the report's {wall_limit:g} s ran out while {out}, so certify.sampled is "
                    f"undecided and the figure shows f_sim only. f_sim = {hz(f_sim)} Hz is a statement about the "
                    f"simulated runs only.{budget}")
    elif c["status"] == "proven":
        lo = c.get("not_proven_below_hz")
        sentence = (f"Proven: at every rate ≥ f_proven = {hz(f_proven)} Hz (certify.sampled; not proven at "
                    f"{hz(lo)} Hz) one period from any state of {where} keeps both funnels with margin "
                    f"{r['margin']:g} and returns to S, and the initial state is in S. f_sim = {hz(f_sim)} Hz is a "
                    f"statement about the simulated runs only; {theory_is} on the same set.{budget}")
    else:
        sentence = (f"No rate is proven: certify.sampled is {c['status']} ({c['detail']}), so the figure shows "
                    f"f_sim and f_theory only. f_sim = {hz(f_sim)} Hz is a statement about the simulated runs; "
                    f"{theory_is} on {where}.{budget}")
    marks = [("f_sim (simulated)", f_sim), ("f_proven (certify.sampled)", f_proven), ("f_theory (theory bound)",
                                                                                     f_theory)]
    shown = [(k, v) for k, v in marks if v is not None]
    svg = FIG.rate_bracket(shown) if shown else None
    return {"available": True, "status": c["status"], "detail": c["detail"], "sim": hz(f_sim),
            "proven": hz(f_proven), "theory": hz(f_theory), "theory_reason": th.get("reason"),
            "ratio": fmt(b["ratio"]), "sentence": sentence, "seconds": c.get("seconds"),
            "figure": ("rate-bracket", "The simulated, proven and theory rates on one log-frequency axis", svg)}


def _scenario_arg(scenario) -> str:
    """How the command line names the scenario: a built-in's name, else its file."""
    from ..scenario import is_builtin
    return scenario.name if is_builtin(scenario.path) else str(scenario.path)

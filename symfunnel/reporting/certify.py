"""The report's certificates: one row per certificate (what is proven, refuted or undecided, with its numbers and
counterexample) and the overview's three lines."""

from __future__ import annotations

import numpy as np

from ..checks.gate import verdict
from .text import detail_html, fmt

_SUMMARY = {"certify.input_gain": "input gain sym(M_p^-1 D M) > 0", "certify.bounds": "bounds of mu2, tau (and eps)",
            "certify.invariance": "forward invariance of the funnels (Lyapunov level set)",
            "certify.containment": "the funnels kept with a margin (Nagumo on the faces)"}


def _short(x) -> str:
    """A counterexample or region value as short text (long arrays are summarised)."""
    if isinstance(x, dict):
        return ", ".join(f"{k} = {_short(v)}" for k, v in x.items() if v is not None and v != {} and v != [])
    if isinstance(x, (list, tuple)):
        a = np.asarray(x, dtype=object)
        if a.size > 8:
            try:
                f = np.asarray(x, dtype=float)
                return f"{list(f.shape)} values in [{fmt(float(np.min(f)))}, {fmt(float(np.max(f)))}]"
            except (TypeError, ValueError):
                return f"{a.size} values"
        return "[" + ", ".join(_short(v) for v in x) + "]"
    return fmt(x)


def certify_section(run, progress=None) -> dict:
    """The certificates of the Run (its `certification` stage, as verify's gate saw it)."""
    v = run.verification
    cert = getattr(v, "certification", None)
    if cert is None:
        return {"available": False, "reason": "certificates were not computed for this report"}
    checks = {c.id: c for c in v.checks}
    rows, lines = [], {"proven": [], "refuted": [], "undecided": []}
    for c in cert.certificates:
        ck = checks.get(c.id)
        rows.append({"id": c.id, "status": c.status, "badge": {"proven": "pass", "refuted": "fail",
                                                              "undecided": "warn"}[c.status],
                     "lower": fmt(c.lower), "upper": fmt(c.upper), "boxes": c.boxes,
                     "seconds": f"{c.seconds:.1f}", "fraction": f"{c.undecided_fraction:.3g}",
                     "detail": c.detail, "brief": _brief(c.detail, 200), "method": c.method,
                     "region": _short(c.region),
                     "counterexample": _short(c.counterexample) if c.counterexample else "",
                     "expected": ck.expected if ck else "pass", "reason": ck.reason if ck else "",
                     # the gate's verdict label, as every other table of the report shows it
                     **dict(zip(("label", "css"), verdict(ck) if ck else (c.status.upper(), "skip")))})
        lines[c.status].append(f"{_SUMMARY.get(c.id, c.id)} ({c.id})")
    overview = {k: "; ".join(v) if v else "nothing" for k, v in lines.items()}
    return {"available": True, "rows": rows, "overview": overview, "seconds": f"{cert.seconds:.1f}",
            "guarantees": guarantees(cert, checks, v.checks)}


def _brief(text: str, limit: int = 160) -> str:
    """The first clause of a certificate's or check's detail (the rest is shown on request)."""
    text = str(text)
    cut = len(text)
    for sep in ("; ", " (", " -- ", ": "):
        k = text.find(sep, 40)
        if 0 <= k < cut:
            cut = k
    cut = min(cut, limit)
    return text if cut >= len(text) else text[:cut].rstrip(" ,;:") + " ..."


def guarantees(cert, checks: dict, all_checks) -> dict:
    """What the report opens with: what is proven for this design (the funnels kept with a margin, the torque
    bound on the proven set, the input gain), what is refuted and by what, and what is open -- one line each (its
    first clause; the whole detail, counterexample included, in a collapsed block), from the certificates and
    verify's failed checks (a failure of the simulated run is a refutation too; a declared finding says so)."""
    proven, refuted, open_ = [], [], []
    first = ("certify.containment", "certify.bounds", "certify.input_gain")      # the guarantee, then its numbers
    for c in sorted(cert.certificates, key=lambda c: first.index(c.id) if c.id in first else len(first)):
        ck = checks.get(c.id)
        name = f"{_SUMMARY.get(c.id, c.id)} ({c.id})"
        if c.status == "refuted":
            by = f" -- at {_short(c.counterexample)}" if c.counterexample else ""
            if ck is not None and ck.status == "warn":
                open_.append((f"{name}: refuted as an argument, not as a property of the design", c.detail))
            else:
                declared = " (declared in the scenario)" if ck is not None and ck.expected == "fail" else ""
                refuted.append((f"{name}{declared}: {_brief(c.detail)}", f"{c.detail}{by}"))
        elif c.status == "undecided":
            open_.append((f"{name}: undecided -- {_brief(c.detail)}", c.detail))
        elif ck is not None and ck.status == "warn":
            open_.append((f"{name}: holds only on a stand-in region, not on a set the loop is shown to stay in",
                          c.detail))
        elif c.id == "certify.containment":
            mg = c.extra.get("margin", {})
            proven.append((f"the funnels are kept: |e1| <= (1 - {fmt(mg.get('e1'))}) F1 and |e2| <= "
                           f"(1 - {fmt(mg.get('e2'))}) F2 for every plant of the parameter box "
                           f"(horizon {c.extra.get('horizon')})", c.detail))
        elif c.id == "certify.bounds":
            proven.append((f"on the proven set: max |tau| <= {fmt(c.upper)} (attained {fmt(c.lower)})", c.detail))
        else:
            proven.append((f"{name}: {_brief(c.detail)}", c.detail))
    for ck in all_checks:
        if ck.status == "fail" and not ck.id.startswith(("certify.", "claim.")):
            declared = " (declared in the scenario)" if ck.expected == "fail" else ""
            refuted.append((f"{ck.id}{declared}: {_brief(ck.detail)}", f"{ck.method or 'check'}: {ck.detail}"))
    # a check's detail may hold sympy matrices: shown as tables, as everywhere else in the report
    return {k: [{"head": detail_html(h), "detail": detail_html(d) if d and d != h else ""} for h, d in v]
            for k, v in (("proven", proven), ("refuted", refuted), ("open", open_))}

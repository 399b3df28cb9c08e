"""The report's certificates: one row per certificate (what is proven, refuted or undecided, with its numbers and
counterexample) and the overview's three lines."""

from __future__ import annotations

import numpy as np

from ..checks.gate import verdict
from .text import fmt

_SUMMARY = {"certify.input_gain": "input gain sym(M_p^-1 D M) > 0", "certify.bounds": "bounds of mu2, tau (and eps)",
            "certify.invariance": "forward invariance of the funnels (barrier closure)"}


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
                     "detail": c.detail, "method": c.method, "region": _short(c.region),
                     "counterexample": _short(c.counterexample) if c.counterexample else "",
                     "expected": ck.expected if ck else "pass", "reason": ck.reason if ck else "",
                     # the gate's verdict label, as every other table of the report shows it
                     **dict(zip(("label", "css"), verdict(ck) if ck else (c.status.upper(), "skip")))})
        lines[c.status].append(f"{_SUMMARY.get(c.id, c.id)} ({c.id})")
    overview = {k: "; ".join(v) if v else "nothing" for k, v in lines.items()}
    return {"available": True, "rows": rows, "overview": overview, "seconds": f"{cert.seconds:.1f}"}

"""The gate: what the scenario declares about each check's outcome, and whether the outcomes match.

A check is expected to pass unless its claim says `expect = "fail"` or an `[[expect]]` entry declares it, with a
reason. The gate fails exactly on an unexpected outcome (a failure expected to pass, or a pass expected to fail);
`warn` (an informative finding) and `skip` never fail it.
"""

from __future__ import annotations

from .audit import CheckResult


def apply_expectations(scenario, checks: list[CheckResult]) -> list[CheckResult]:
    """Set `expected` (and `reason`) on every check from the scenario's declarations; returns the same list."""
    declared = {f"claim.{c.name}": (c.expect, c.description or c.source) for c in scenario.claims}
    declared.update({e.check: (e.status, e.reason) for e in scenario.expectations})
    for c in checks:
        status, reason = declared.get(c.id, ("pass", ""))
        c.expected = status
        c.reason = reason if status == "fail" else ""
    return checks


def gate_status(checks: list[CheckResult]) -> str:
    """'pass' when every outcome is as declared, else 'fail'."""
    return "fail" if any(c.unexpected for c in checks) else "pass"


#: how an outcome is shown wherever it appears (verify's lines, the report's badges): (label, style class)
VERDICTS = {
    ("fail", "fail"): ("FINDING (expected)", "finding"),
    ("fail", "pass"): ("FAIL (unexpected)", "fail"),
    ("pass", "fail"): ("PASS (unexpected)", "fail"),
    ("pass", "pass"): ("PASS", "pass"),
}


def verdict(c: CheckResult) -> tuple[str, str]:
    """The one label and style class of a check's outcome against its declaration (FINDING (expected), FAIL
    (unexpected), PASS (unexpected), PASS, WARN, SKIP)."""
    if c.status in ("warn", "skip"):
        return c.status.upper(), c.status
    return VERDICTS.get((c.status, c.expected), (c.status.upper(), c.status))


def counts(checks: list[CheckResult]) -> dict:
    """The outcome counts verify prints (and the report and `verify --json` show): passed, failed, of the failures
    those expected, warnings, skipped, unexpected."""
    out = {s: sum(c.status == s for c in checks) for s in ("pass", "fail", "warn", "skip")}
    out["expected_fail"] = sum(c.status == "fail" and c.expected == "fail" for c in checks)
    out["unexpected"] = sum(c.unexpected for c in checks)
    return out


def counts_line(checks: list[CheckResult]) -> str:
    """'19 passed, 13 failed (13 expected), 1 warning, 0 skipped': verify's count line, also in the report."""
    from ..core.text import plural
    k = counts(checks)
    return (f"{k['pass']} passed, {k['fail']} failed ({k['expected_fail']} expected), {plural(k['warn'], 'warning')}, "
            f"{k['skip']} skipped")


#: the scenario keys a printed claim's signal depends on (what a user changes that makes a printed equation stale)
_SIGNAL_KEYS = {
    "F1": "funnel.e1", "dF1": "funnel.e1", "e1": "funnel.e1", "z1": "funnel.e1", "zeta1": "funnel.e1",
    "mu1": "funnel.e1", "z1_dot": "funnel.e1", "F2": "funnel.e2", "dF2": "funnel.e2", "z2": "funnel.e2",
    "zeta2": "funnel.e2", "mu2": "funnel.e2", "z2_dot": "funnel.e2", "alpha2": "controller.k1 or funnel.e1",
    "alpha2_dot": "controller.k1 or funnel.e1", "e2": "controller.k1 or funnel.e1",
    "tau": "controller or the funnels", "w_hat_dot": "adaptation", "x_esn_dot": "esn",
}


def outcome_hint(scenario, c: CheckResult) -> str:
    """What to do about an unexpected outcome, in one sentence: for a printed claim that no longer matches (it is
    the scenario's printed equation, which a changed design leaves behind) remove it or declare its failure; for a
    declared failure that now passes, remove the declaration."""
    if not c.unexpected:
        return ""
    if c.id.startswith("claim."):
        name = c.id[len("claim."):]
        cl = next((x for x in scenario.claims if x.name == name), None)
        if cl is None:
            return ""
        what = f"printed {cl.source}" if cl.source else "printed claim"
        if c.status == "pass":
            return (f"{c.id} is the scenario's {what} and now holds: remove its expect = \"fail\" "
                    f"(the [[claims]] entry named {name!r})")
        keys = (f"funnel.{cl.funnel}" if cl.kind == "funnel" else "the design" if cl.kind in ("decay", "inequality")
                else _SIGNAL_KEYS.get(cl.signal, "the design"))
        return (f"{c.id} is the scenario's {what} (signal {cl.signal or cl.kind}); after changing {keys}, remove "
                f"the [[claims]] entry named {name!r} or declare expect = \"fail\" with the reason in its description")
    if c.status == "pass" and c.expected == "fail":
        return (f"{c.id} passes now: remove the [[expect]] entry with check = {c.id!r} (its failure was declared)")
    return ""

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

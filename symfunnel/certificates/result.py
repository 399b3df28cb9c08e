"""One certificate's outcome in the contract's form, and the whole certification of a scenario.

    {"id", "status": "proven" | "refuted" | "undecided", "lower", "upper", "counterexample", "region", "boxes",
     "undecided_fraction", "seconds", "detail", ...extra keys}

A certificate enters verify's gate as a check: proven -> pass, refuted -> fail (the counterexample as `where`),
undecided -> warn (what is left in `detail`). One fact, one severity -- two certificates are findings about an
argument rather than guarantees of the design, and are shown as `warn` unless the scenario declares them:

- `certify.invariance` refuted says the *Lyapunov level-set argument* is vacuous for this design (like
  `lyapunov.guarantee`), not that the design breaches its funnels: warn, unless an `[[expect]]` entry names
  `certify.invariance` (status "pass": the scenario requires the argument to close, so a refutation fails the gate;
  status "fail": a declared finding, shown as FINDING (expected)).
- `certify.bounds` proven on a stand-in region (`region.kind == "stand_in"`: a region the closed loop is not shown
  to stay in) is information about that region, never a PASS: warn.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..checks.audit import CheckResult
from ..core.io import json_safe

#: certificate status -> the check status verify shows for it
CHECK_STATUS = {"proven": "pass", "refuted": "fail", "undecided": "warn"}
STATUSES = tuple(CHECK_STATUS)


@dataclass
class Certificate:
    """A proof over a region (or its refutation, or what is left undecided), with its numbers."""

    id: str
    status: str
    detail: str
    lower: float | None = None
    upper: float | None = None
    counterexample: dict | None = None
    region: dict = field(default_factory=dict)
    boxes: int = 0
    undecided_fraction: float = 0.0
    seconds: float = 0.0
    method: str = ""
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.status not in CHECK_STATUS:
            raise ValueError(f"certificate status {self.status!r} (expected one of {', '.join(CHECK_STATUS)})")

    def to_json(self) -> dict:
        """The contract's dict (extra keys after the fixed ones)."""
        out = {"id": self.id, "status": self.status, "lower": self.lower, "upper": self.upper,
               "counterexample": self.counterexample, "region": self.region, "boxes": int(self.boxes),
               "undecided_fraction": float(self.undecided_fraction), "seconds": float(self.seconds),
               "detail": self.detail, "method": self.method}
        out.update(self.extra)
        return json_safe(out)

    def to_check(self) -> CheckResult:
        """The certificate as one of verify's checks."""
        margin = None
        if self.id == "certify.input_gain":
            margin = self.lower if self.status == "proven" else self.upper
        ev = {k: v for k, v in self.to_json().items() if k not in ("id", "status", "detail", "method")}
        return CheckResult(self.id, CHECK_STATUS[self.status], f"{self.status}: {self.detail}",
                           method=self.method or "interval branch and bound", margin=margin,
                           where=self.counterexample, evidence=ev)


#: certificates whose refutation is a finding about an argument (warn), unless the scenario declares them
FINDING_WHEN_REFUTED = ("certify.invariance",)


def finding_policy(cert: Certificate, check: CheckResult, declared: set[str]) -> CheckResult:
    """One fact, one severity: a refuted `certify.invariance` (the Lyapunov level-set argument is vacuous) is a
    warning unless the scenario declares it in `[[expect]]`; a bound on a stand-in region is a warning, never a
    pass. Returns the check (changed in place)."""
    if cert.id in FINDING_WHEN_REFUTED and cert.status == "refuted" and cert.id not in declared:
        check.status = "warn"
        check.detail = ("finding about the Lyapunov level-set argument, not a breach of the design (declare "
                        f"[[expect]] check = \"{cert.id}\" to require it): " + check.detail)
    kind = cert.region.get("kind") if isinstance(cert.region, dict) else None
    if cert.id == "certify.bounds" and cert.status == "proven" and kind == "stand_in":
        check.status = "warn"
        check.detail = ("information, not a guarantee: enclosures on a stand-in region the closed loop is not "
                        "shown to stay in: " + check.detail)
    return check


@dataclass
class Certification:
    """Every certificate computed for one scenario (the `certify` stage of the pipeline)."""

    scenario: str
    certificates: list[Certificate]
    seconds: float = 0.0
    wall_limit: float | None = None
    #: the problem.Context they were computed in (not serialised): what a later certificate may reuse them for
    context: object = field(default=None, repr=False, compare=False)

    def checks(self, scenario=None) -> list[CheckResult]:
        """The certificates as checks (findings about an argument demoted to warn unless the scenario declares
        them), with the scenario's expectations applied when it is given."""
        declared = {e.check for e in scenario.expectations} if scenario is not None else set()
        out = [finding_policy(c, c.to_check(), declared) for c in self.certificates]
        if scenario is not None:
            from ..checks.gate import apply_expectations
            apply_expectations(scenario, out)
        return out

    def status(self, scenario) -> str:
        """'fail' when an outcome is not the one the scenario declares (a refutation expected to be proven...)."""
        return "fail" if any(c.unexpected for c in self.checks(scenario)) else "pass"

    def to_json(self, scenario=None) -> dict:
        """{"scenario", "status", "certificates": [...], "seconds"}; status by the scenario's expectations."""
        out = {"scenario": self.scenario, "certificates": [c.to_json() for c in self.certificates],
               "seconds": self.seconds, "wall_limit": self.wall_limit}
        if scenario is not None:
            checks = self.checks(scenario)
            out["status"] = "fail" if any(c.unexpected for c in checks) else "pass"
            out["unexpected"] = [c.id for c in checks if c.unexpected]
            for cj, ck in zip(out["certificates"], checks):
                cj["expected"] = ck.expected
                cj["check"] = ck.status         # the status verify shows (findings and stand-in bounds: warn)
                if ck.reason:
                    cj["reason"] = ck.reason
        return json_safe({"scenario": out.pop("scenario"), **({"status": out.pop("status")} if "status" in out
                                                                 else {}), **out})

    def by_id(self, cid: str) -> Certificate | None:
        """The certificate with this id, if computed."""
        return next((c for c in self.certificates if c.id == cid), None)

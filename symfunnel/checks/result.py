"""The result of one check: its id, status, detail, how it was decided, the evidence and the declared outcome."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class CheckResult:
    """One check: id, pass/fail/warn/skip, a one-line detail, how it was decided, and the evidence.

    `expected` is the outcome the scenario declares (pass unless a claim's `expect` or an `[[expect]]` entry says
    fail, with `reason`); the check is *unexpected* -- it fails the gate -- when it fails while expected to pass or
    passes while expected to fail. warn and skip never fail the gate.
    """

    id: str
    status: str
    detail: str
    method: str = ""
    margin: float | None = None
    where: dict | None = None
    evidence: dict = field(default_factory=dict)
    expected: str = "pass"
    reason: str = ""
    #: a claim's verdict: "proven", "refuted" or "not proven" (a sampled agreement is never a proof)
    verdict: str = ""
    value: float | None = None           # the check's measured quantity where it has one (e.g. an agreement error)

    @property
    def unexpected(self) -> bool:
        """True when this outcome fails the gate."""
        return self.status in ("pass", "fail") and self.status != self.expected

    def to_json(self) -> dict:
        """The JSON form of `audit --json` (id, status, expected, detail, plus method, margin, where, evidence)."""
        out = {"id": self.id, "status": self.status, "expected": self.expected, "detail": self.detail,
               "method": self.method}
        if self.reason:
            out["reason"] = self.reason
        if self.verdict:
            out["verdict"] = self.verdict
        if self.margin is not None:
            out["margin"] = self.margin
        if self.value is not None:
            out["value"] = self.value
        if self.where is not None:
            out["where"] = self.where
        if self.evidence:
            out["evidence"] = self.evidence
        return out

"""One certificate's outcome in the contract's form, and the whole certification of a scenario.

    {"id", "status": "proven" | "refuted" | "undecided", "lower", "upper", "counterexample", "region", "boxes",
     "undecided_fraction", "seconds", "detail", ...extra keys}

A certificate enters verify's gate as a check: proven -> pass, refuted -> fail (the counterexample as `where`),
undecided -> warn (what is left in `detail`).
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


@dataclass
class Certification:
    """Every certificate computed for one scenario (the `certify` stage of the pipeline)."""

    scenario: str
    certificates: list[Certificate]
    seconds: float = 0.0
    wall_limit: float | None = None

    def checks(self, scenario=None) -> list[CheckResult]:
        """The certificates as checks, with the scenario's expectations applied when it is given."""
        out = [c.to_check() for c in self.certificates]
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
                if ck.reason:
                    cj["reason"] = ck.reason
        return json_safe({"scenario": out.pop("scenario"), **({"status": out.pop("status")} if "status" in out
                                                                 else {}), **out})

    def by_id(self, cid: str) -> Certificate | None:
        """The certificate with this id, if computed."""
        return next((c for c in self.certificates if c.id == cid), None)

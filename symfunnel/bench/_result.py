"""One bench result in the contract's form `{"id", "value", "unit", "baseline", "baseline_value", "ratio"}`."""

from __future__ import annotations


def result(id: str, value: float, unit: str, baseline: str | None = None, baseline_value: float | None = None,
           ratio: float | None = None, **extra) -> dict:
    """One bench result in the contract's form (extra keys are allowed and ignored by consumers)."""
    out = {"id": id, "value": float(value), "unit": unit, "baseline": baseline,
           "baseline_value": None if baseline_value is None else float(baseline_value),
           "ratio": None if ratio is None else float(ratio)}
    out.update(extra)
    return out

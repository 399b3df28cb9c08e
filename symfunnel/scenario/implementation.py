"""The `[implementation]` scenario section: how the controller is deployed (sample rate, delay, saturation, noise).

Absent, the controller is the continuous-time one, as before. Present, `symfunnel.deployed.loop` simulates the sampled
loop around the generated C step function, and verify adds the implementation checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from ..core import validate as V
from ..core.errors import InputError

KEYS = ["rate_hz", "delay_samples", "tau_max", "noise_q", "noise_dq", "encoder_resolution", "seed"]
MAX_RATE_HZ = 1e6


@dataclass(frozen=True)
class ImplementationSpec:
    """A deployed controller: sample rate with zero-order hold, delay, torque limit per joint, noise, quantisation."""

    rate_hz: float = 1000.0
    delay_samples: int = 0
    tau_max: tuple[float, ...] | None = None
    noise_q: float = 0.0
    noise_dq: float = 0.0
    encoder_resolution: float = 0.0
    seed: int = 0

    def with_rate(self, rate_hz: float) -> "ImplementationSpec":
        """The same implementation at another rate."""
        return replace(self, rate_hz=float(rate_hz))


def check_rate(value: Any, *, file: str, key: str) -> float:
    """A sample rate in (0, 1e6] Hz, else InputError naming the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0 < value <= MAX_RATE_HZ:
        raise InputError(f"is {value!r}", file=file, key=key, expected=f"a sample rate in (0, {MAX_RATE_HZ:g}] Hz")
    return float(value)


def parse_implementation(table: Any, *, n: int, file: str, raw_model: dict, base_dir: Path) -> ImplementationSpec:
    """Validate `[implementation]` (see docs/scenario.md); `tau_max = "urdf"` reads the URDF's effort limits."""
    p = "implementation"
    V.check_keys(table, KEYS, file=file, prefix=p)
    rate = check_rate(table.get("rate_hz", ImplementationSpec.rate_hz), file=file, key=p + ".rate_hz")
    delay = V.get_int(table, "delay_samples", 0, file=file, prefix=p, minimum=0, maximum=1)
    tau_max = parse_tau_max(table, p, n=n, file=file, raw_model=raw_model, base_dir=base_dir)
    noise_q = V.get_float(table, "noise_q", 0.0, file=file, prefix=p, minimum=0)
    noise_dq = V.get_float(table, "noise_dq", 0.0, file=file, prefix=p, minimum=0)
    res = V.get_float(table, "encoder_resolution", 0.0, file=file, prefix=p, minimum=0)
    seed = V.get_int(table, "seed", 0, file=file, prefix=p, minimum=0, maximum=2**63 - 1)
    return ImplementationSpec(rate, delay, tau_max, noise_q, noise_dq, res, seed)


def parse_tau_max(table: dict, prefix: str, *, n: int, file: str, raw_model: dict,
                  base_dir: Path) -> tuple[float, ...] | None:
    """A `tau_max` key of a table (None when absent): a number > 0, one per joint, or "urdf" (the effort limits)."""
    if "tau_max" not in table:
        return None
    v = table["tau_max"]
    if v == "urdf":
        return _urdf_limits(raw_model, n, file, base_dir, prefix + ".tau_max")
    if isinstance(v, str):
        raise InputError(f"is '{v}'", file=file, key=prefix + ".tau_max",
                         expected='a number > 0, one per joint, or "urdf"')
    return tuple(V.per_joint(table, "tau_max", n, file=file, prefix=prefix, minimum=0, strict_min=True))


def _urdf_limits(raw_model: dict, n: int, file: str, base_dir: Path, key: str) -> tuple[float, ...]:
    if not isinstance(raw_model, dict) or raw_model.get("type") != "urdf":
        raise InputError('is "urdf" but the model is not a URDF', file=file, key=key,
                         expected="a number or one per joint (effort limits come only from a URDF model)")
    from ..model.urdf import effort_limits
    limits = effort_limits(Path(base_dir) / raw_model["path"])
    missing = [i + 1 for i, v in enumerate(limits) if v is None or not v > 0]
    if missing:
        raise InputError(f'is "urdf" but joint(s) {missing} of the URDF have no positive effort limit', file=file,
                         key=key, expected="a URDF with <limit effort> > 0 on every movable joint, or numbers")
    return tuple(float(v) for v in limits)


def implementation_of(scenario, rate_hz: float | None = None) -> ImplementationSpec | None:
    """The scenario's implementation, at `rate_hz` when given (a default implementation when it has none)."""
    impl = getattr(scenario, "implementation", None)
    if rate_hz is None:
        return impl
    rate = check_rate(rate_hz, file=scenario.file, key="--rate")
    return (impl or ImplementationSpec()).with_rate(rate)

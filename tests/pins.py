"""The registry of pinning cases: for each check id, the tests where it must fail and where, near its boundary, it
must pass (`tests/test_check_pins.py::test_every_check_id_has_a_failing_and_a_near_boundary_passing_case`)."""

from __future__ import annotations

from collections import defaultdict

#: check id -> {"fail": [test names], "pass": [test names]}
PINS: dict[str, dict[str, list[str]]] = defaultdict(lambda: {"fail": [], "pass": []})


def pins(check_id: str, *kinds: str):
    """Register the decorated test as a case of `check_id` where it must fail and/or pass ("fail", "pass")."""
    assert kinds and set(kinds) <= {"fail", "pass"}, kinds

    def mark(fn):
        for k in kinds:
            PINS[check_id][k].append(f"{fn.__module__}::{fn.__name__}")
        return fn
    return mark

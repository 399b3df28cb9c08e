"""Proofs on SX with sympy under a time limit: the symbolic half of the audit, usable from any layer."""

from __future__ import annotations

import sys
import types

import casadi as ca

_UNITS = "sympy.physics.units"


class _Timeout(Exception):
    pass


def simplify(expr):
    """sympy.simplify(expr) without importing sympy.physics.units (0.1-0.5 CPU-s per process).

    simplify imports that package only to ask whether expr holds unit quantities, which expressions converted from
    CasADi never do: while the call runs (and the package is not loaded yet), a placeholder module whose Quantity
    nothing is an instance of answers that question; it is removed afterwards, so a later import gets the real one.
    This also keeps a time limit from interrupting that import half-way."""
    import sympy
    if _UNITS in sys.modules:
        return sympy.simplify(expr)
    stub = types.ModuleType(_UNITS, "placeholder while symfunnel.sx.proof.simplify runs")
    stub.Quantity = type("Quantity", (), {})
    sys.modules[_UNITS] = stub
    try:
        return sympy.simplify(expr)
    finally:
        if sys.modules.get(_UNITS) is stub:
            del sys.modules[_UNITS]


def time_limit(seconds: float):
    """Raise _Timeout inside the block after `seconds` (main thread only; elsewhere no limit is applied).

    Nested in a command's wall-clock limit (`symfunnel.core.deadline`): whichever expires first stops the block, and the
    command's own limit is never swallowed as this one's _Timeout."""
    from ..core.deadline import limit
    return limit(seconds if seconds > 0 else None, on_expiry=_Timeout)


def sympy_is_zero(expr: ca.SX, inputs: list[ca.SX], timeout: float, max_ops: int = 3000):
    """True if sympy proves every entry of `expr` identically zero, False if it simplifies to nonzero, None if undecided.

    The returned second value is the simplified sympy matrix (or None).
    """
    import sympy

    from .tosympy import sx_to_sympy
    f = ca.Function("f", inputs, [expr])
    if f.n_instructions() > max_ops:
        return None, None
    try:
        with time_limit(timeout):
            m = sx_to_sympy(expr, inputs)
            simp = m.applyfunc(lambda e: simplify(sympy.expand_trig(e)) if e != 0 else e)
    except (_Timeout, RecursionError, MemoryError, NotImplementedError):
        return None, None
    if all(e == 0 for e in simp):
        return True, simp
    return None, simp

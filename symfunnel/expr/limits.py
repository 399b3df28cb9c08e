"""The limits of the expression language against CAS hangs and overflow, shared by the parser and the backends."""

from __future__ import annotations

from ..core.errors import InputError

MAX_LENGTH = 10_000      # characters of expression text
MAX_NODES = 5_000        # nodes of the parsed tree (Expression.size())
MAX_DEPTH = 200          # nesting depth of the parsed tree, and of brackets in the text
MAX_LITERAL = 1e12       # largest magnitude of a number written in the text
MAX_EXPONENT = 64        # largest |exponent| of a power whose exponent is a constant
MAX_EXACT_DIGITS = 4_000  # bound on the digits of any exact sympy number (Python refuses str() past 4300)


def check_exponent(value: float | None) -> None:
    """Refuse a numeric exponent beyond MAX_EXPONENT that only became known at evaluation time."""
    if value is not None and abs(value) > MAX_EXPONENT:
        raise InputError(f"an exponent evaluates to {value:g}",
                         expected=f"exponents of magnitude at most {MAX_EXPONENT}")

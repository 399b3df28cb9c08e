"""The floating-point rounding mode of the process: codac computes outward only while it is upward, and sets it upward
when it is imported, which would change every other computation of the process (a parsed "3.7525" becomes
3.7525000000000004), so the mode is set upward around codac's evaluations only and restored everywhere else.

The mode is the C library's (`fegetround`/`fesetround` through ctypes); the constant for "upward" differs between
architectures, so it is found by probing which mode makes 1 + 2^-60 round above 1.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import math
from collections.abc import Iterator

from ..core.errors import SymfunnelError

_libm = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")
_libm.fegetround.restype = ctypes.c_int
_libm.fesetround.argtypes = [ctypes.c_int]
_libm.fesetround.restype = ctypes.c_int

#: FE_UPWARD of x86 (SSE/x87), of AArch64 and of PowerPC/RISC-V-like conventions, tried in this order
_UPWARD_CANDIDATES = (0x800, 0x400000, 0x2, 0x3)


def get_mode() -> int:
    """The current rounding mode (the C library's constant)."""
    return int(_libm.fegetround())


def set_mode(mode: int) -> None:
    """Set the rounding mode; refuses a mode the C library does not take."""
    if _libm.fesetround(int(mode)) != 0:
        raise SymfunnelError(f"the C library refuses rounding mode {mode:#x}")


def rounds_up() -> bool:
    """Whether additions round upward now (1 + 2^-60 > 1 only then; computed at run time, not folded)."""
    one, tiny = float(1), math.ldexp(1.0, -60)
    return one + tiny > one


def rounds_to_nearest() -> bool:
    """Whether the mode rounds to nearest: 1 + 2^-60 is 1 and -1 - 2^-60 is -1 (upward or downward break one)."""
    one, tiny = float(1), math.ldexp(1.0, -60)
    return one + tiny == one and -one - tiny == -one and one - tiny == one


def _find_upward() -> int:
    saved = get_mode()
    try:
        for mode in _UPWARD_CANDIDATES:
            if _libm.fesetround(mode) == 0 and rounds_up():
                return mode
    finally:
        set_mode(saved)
    raise SymfunnelError("cannot find the upward rounding mode of this C library")


UPWARD = _find_upward()


@contextlib.contextmanager
def upward() -> Iterator[None]:
    """The block runs with upward rounding (what codac's outward arithmetic needs); the caller's mode after it."""
    saved = get_mode()
    set_mode(UPWARD)
    try:
        yield
    finally:
        set_mode(saved)


@contextlib.contextmanager
def keeping_mode() -> Iterator[None]:
    """The caller's rounding mode after the block whatever the block does to it (importing codac sets it upward)."""
    saved = get_mode()
    try:
        yield
    finally:
        set_mode(saved)

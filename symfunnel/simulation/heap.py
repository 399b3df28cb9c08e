"""glibc's heap kept between a run's chunks: every chunk allocates a few MB of numpy arrays (its states, its samples
between output points, their signals) and frees them, and glibc's defaults hand that memory back to the kernel
(trimming the heap's top, or one mmap per large array) only to fault it in again at the next chunk -- a tenth of a
20 s paper run's CPU time went to those page faults, a sixth of arm7's 20 s run (whose chunk arrays and CVODES step
history are tens of MB each: hence thresholds in the hundreds of MB; its peak memory 602 -> 634 MB; figures in
docs/performance.md). `keep_heap` raises the thresholds once per process; $SYMFUNNEL_KEEP_HEAP=0, or any of glibc's own MALLOC_*_ settings, leaves them as they are."""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["MMAP_THRESHOLD", "TOP_PAD", "TRIM_THRESHOLD", "keep_heap"]

#: mallopt's parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
#: allocations up to this size come from the heap (glibc's default: 128 kB, adapting up to 32 MB)
MMAP_THRESHOLD = 256 << 20
#: free memory at the heap's top kept up to this size (default: 128 kB, adapting)
TRIM_THRESHOLD = 512 << 20
#: the heap grows by this much more than asked (default: 128 kB)
TOP_PAD = 16 << 20
_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")
_DONE: list[bool] = []


def keep_heap() -> bool:
    """Set glibc's heap thresholds for this process (once); whether they are set (False off glibc, or opted out)."""
    if _DONE:
        return _DONE[0]
    ok = False
    if sys.platform.startswith("linux") and os.environ.get("SYMFUNNEL_KEEP_HEAP", "1").strip() != "0" \
            and not any(k in os.environ for k in _ENV):
        try:
            libc = ctypes.CDLL(None)
            libc.gnu_get_libc_version           # glibc only: another libc's mallopt may mean something else
            mallopt = libc.mallopt
            mallopt.restype, mallopt.argtypes = ctypes.c_int, [ctypes.c_int, ctypes.c_int]
            ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
                      and mallopt(_M_TOP_PAD, TOP_PAD))
        except (OSError, AttributeError):
            ok = False
    _DONE.append(ok)
    return ok

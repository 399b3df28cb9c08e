"""BLAS threads: one thread around the small dense eigenvalue and SVD calls and in campaign workers, where a second
OpenBLAS thread only spins against the other core's work (an N = 200 reservoir's spectral radius: 1-2.5 CPU-s
with two threads, 0.04 s with one, the same result)."""

from __future__ import annotations

import sys
from contextlib import nullcontext

__all__ = ["one_blas_thread", "pin_blas_threads"]

_PINNED: list[object] = []
#: (number of imported modules, threadpoolctl controller) of this process: finding the loaded BLAS libraries scans
#: every shared object of the process (10 ms and more in a large one), so the scan is redone only after an import
_CONTROLLER: list[tuple[int, object]] = []


def _controller():
    """threadpoolctl's view of the loaded BLAS libraries, rescanned when a module has been imported since (a BLAS
    comes with the extension module that loads it: numpy's, scipy's)."""
    from threadpoolctl import ThreadpoolController
    n = len(sys.modules)
    if not _CONTROLLER or _CONTROLLER[0][0] != n:
        _CONTROLLER[:] = [(n, ThreadpoolController())]
    return _CONTROLLER[0][1]


def one_blas_thread():
    """A context in which BLAS and LAPACK run on one thread (threadpoolctl); a no-op without threadpoolctl."""
    try:
        controller = _controller()
    except ImportError:           # pragma: no cover - a declared dependency
        return nullcontext()
    return controller.limit(limits=1, user_api="blas")


def pin_blas_threads() -> None:
    """One BLAS thread for the rest of this process (a campaign worker: one process per core already)."""
    if _PINNED:
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:           # pragma: no cover - a declared dependency
        return
    _PINNED.append(threadpool_limits(limits=1, user_api="blas"))

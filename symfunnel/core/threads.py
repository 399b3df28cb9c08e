"""BLAS threads: one thread around the small dense eigenvalue and SVD calls and in campaign workers, where a second
OpenBLAS thread only spins against the other core's work (an N = 200 reservoir's spectral radius: 1-2.5 CPU-s
with two threads, 0.04 s with one, the same result)."""

from __future__ import annotations

from contextlib import nullcontext

__all__ = ["one_blas_thread", "pin_blas_threads"]

_PINNED: list[object] = []


def one_blas_thread():
    """A context in which BLAS and LAPACK run on one thread (threadpoolctl); a no-op without threadpoolctl."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:           # pragma: no cover - a declared dependency
        return nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def pin_blas_threads() -> None:
    """One BLAS thread for the rest of this process (a campaign worker: one process per core already)."""
    if _PINNED:
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:           # pragma: no cover - a declared dependency
        return
    _PINNED.append(threadpool_limits(limits=1, user_api="blas"))

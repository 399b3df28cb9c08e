"""BLAS threads are limited to one around the reservoir's dense eigenvalues and 2-norm (core/threads.py), with the
same weights as with any number of threads."""

from __future__ import annotations

import numpy as np
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")


def _blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_restored_after():
    from symfunnel.core.threads import one_blas_thread
    np.linalg.eigvals(np.eye(3))                          # BLAS loaded
    before = _blas_threads()
    assert before
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        outer = _blas_threads()
        with one_blas_thread():
            assert _blas_threads() == [1] * len(before)
        assert _blas_threads() == outer
    assert _blas_threads() == before


def test_the_reservoir_is_the_same_whatever_the_threads(monkeypatch):
    """The spectral radius and 2-norm the reservoir's scaling uses are computed inside one_blas_thread, so its W is
    the same bits under any outer thread setting."""
    from symfunnel.family import esn
    rng = np.random.default_rng(0)
    W = rng.normal(size=(120, 120))
    seen = []

    def spy(*a, **k):
        seen.append(_blas_threads())
        return real(*a, **k)
    real = np.linalg.eigvals
    monkeypatch.setattr(np.linalg, "eigvals", spy)
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        r2 = esn._spectral_radius(W)
    with threadpoolctl.threadpool_limits(limits=1, user_api="blas"):
        r1 = esn._spectral_radius(W)
    assert r1 == r2
    assert all(t == [1] * len(t) for t in seen)


def test_the_library_scan_is_reused_until_a_module_is_imported(monkeypatch):
    """one_blas_thread scans the process's shared objects once, and again after an import (which may bring a BLAS
    of its own), and the limit holds either way."""
    import sys
    import types

    from symfunnel.core import threads
    with threads.one_blas_thread():
        first = threads._CONTROLLER[0][1]
    with threads.one_blas_thread():
        assert threads._CONTROLLER[0][1] is first
    monkeypatch.setitem(sys.modules, "symfunnel_test_fake_module", types.ModuleType("symfunnel_test_fake_module"))
    with threads.one_blas_thread():
        assert threads._CONTROLLER[0][1] is not first
        assert _blas_threads() == [1] * len(_blas_threads())

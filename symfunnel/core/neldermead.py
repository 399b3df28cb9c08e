"""Nelder-Mead minimisation, step for step as scipy's `minimize(method="Nelder-Mead")` without bounds, so that the
audit's local refinement gives scipy's iterates without importing `scipy.optimize` (about 0.35 CPU-s per process:
it pulls in scipy.linalg and scipy.sparse). tests/test_neldermead.py compares both on several functions.

The simplex, the coefficients (reflection 1, expansion 2, contraction 0.5, shrink 0.5), the order of the
floating-point operations and the tie-breaking of the sorts are scipy's (scipy.optimize._optimize, BSD-3-Clause).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class Result:
    """The fields of scipy's OptimizeResult the callers read: best point, its value, iterations, evaluations."""

    x: np.ndarray
    fun: float
    nit: int
    nfev: int


def minimize(func: Callable[[np.ndarray], float], x0, *, xatol: float = 1e-4, fatol: float = 1e-4,
             maxiter: int) -> Result:
    """Minimise `func` from `x0` (scipy's Nelder-Mead with options xatol, fatol, maxiter; no bounds, no maxfev)."""
    rho, chi, psi, sigma = 1, 2, 0.5, 0.5
    nonzdelt, zdelt = 0.05, 0.00025
    x0 = np.atleast_1d(np.asarray(x0)).flatten()
    x0 = np.asarray(x0, dtype=x0.dtype if np.issubdtype(x0.dtype, np.inexact) else np.float64)
    N = len(x0)
    sim = np.empty((N + 1, N), dtype=x0.dtype)
    sim[0] = x0
    for k in range(N):
        y = np.array(x0, copy=True)
        y[k] = (1 + nonzdelt) * y[k] if y[k] != 0 else zdelt
        sim[k + 1] = y
    nfev = 0

    def f(x):
        nonlocal nfev
        nfev += 1
        fx = func(np.copy(x))
        if not np.isscalar(fx):
            fx = np.asarray(fx).item()
        return fx

    fsim = np.full((N + 1,), np.inf, dtype=float)
    for k in range(N + 1):
        fsim[k] = f(sim[k])
    ind = np.argsort(fsim)
    sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    ind = np.argsort(fsim)
    fsim, sim = np.take(fsim, ind, 0), np.take(sim, ind, 0)
    iterations = 1
    while iterations < maxiter:
        if np.max(np.ravel(np.abs(sim[1:] - sim[0]))) <= xatol and np.max(np.abs(fsim[0] - fsim[1:])) <= fatol:
            break
        xbar = np.add.reduce(sim[:-1], 0) / N
        xr = (1 + rho) * xbar - rho * sim[-1]
        fxr = f(xr)
        doshrink = 0
        if fxr < fsim[0]:
            xe = (1 + rho * chi) * xbar - rho * chi * sim[-1]
            fxe = f(xe)
            if fxe < fxr:
                sim[-1], fsim[-1] = xe, fxe
            else:
                sim[-1], fsim[-1] = xr, fxr
        elif fxr < fsim[-2]:
            sim[-1], fsim[-1] = xr, fxr
        else:
            if fxr < fsim[-1]:
                xc = (1 + psi * rho) * xbar - psi * rho * sim[-1]
                fxc = f(xc)
                if fxc <= fxr:
                    sim[-1], fsim[-1] = xc, fxc
                else:
                    doshrink = 1
            else:
                xcc = (1 - psi) * xbar + psi * sim[-1]
                fxcc = f(xcc)
                if fxcc < fsim[-1]:
                    sim[-1], fsim[-1] = xcc, fxcc
                else:
                    doshrink = 1
            if doshrink:
                for j in range(1, N + 1):
                    sim[j] = sim[0] + sigma * (sim[j] - sim[0])
                    fsim[j] = f(sim[j])
        iterations += 1
        ind = np.argsort(fsim)
        sim, fsim = np.take(sim, ind, 0), np.take(fsim, ind, 0)
    return Result(x=sim[0], fun=np.min(fsim), nit=iterations, nfev=nfev)

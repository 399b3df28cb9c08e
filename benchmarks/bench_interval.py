"""Boxes per second of the interval tape walk (codac, arb; natural and mean-value forms) against CasADi in double.

    python benchmarks/bench_interval.py [scenario] [signal]      # default: paper tau
"""

from __future__ import annotations

import sys
import time

import casadi as ca
import numpy as np

import symfunnel as sf
from symfunnel.sx.interval import IntervalFunction
from symfunnel.sx.tape import count_ops


def _rate(fn, min_seconds: float = 1.0) -> float:
    """Calls per second of fn() over at least `min_seconds`."""
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_seconds:
            return n / dt


def funnel_point(d, rng) -> dict:
    """A random point of the design's inputs with e1 and e2 inside their funnels (|e| < F / 2)."""
    n = d.n
    F1, F2, e2 = d.function("F1", ["t"]), d.function("F2", ["t"]), d.function("e2", ["t", "q", "dq", "qd", "dqd"])
    t = rng.uniform(0.0, 2.0)
    qd, dqd, ddqd = (rng.uniform(-0.5, 0.5, n) for _ in range(3))
    q = qd + rng.uniform(-0.5, 0.5, n) * np.asarray(F1(t)).ravel()
    e20 = np.asarray(e2(t, q, dqd, qd, dqd)).ravel()              # e2 is dq - dqd + (terms without dq)
    dq = dqd - e20 + rng.uniform(-0.5, 0.5, n) * np.asarray(F2(t)).ravel()
    p = {"t": t, "q": q, "dq": dq, "qd": qd, "dqd": dqd, "ddqd": ddqd}
    assert np.all(np.abs(np.asarray(e2(t, q, dq, qd, dqd)).ravel()) < np.asarray(F2(t)).ravel())
    for name, (r, c) in d.states:
        p[name] = rng.uniform(-0.5, 0.5, (r, c)) if c > 1 else rng.uniform(-0.5, 0.5, r)
    return p


def main() -> int:
    scenario = sys.argv[1] if len(sys.argv) > 1 else "paper"
    signal = sys.argv[2] if len(sys.argv) > 2 else "tau"
    d = sf.derive(sf.load_scenario(scenario))
    f = d.function(signal)
    rng = np.random.default_rng(0)
    F0 = IntervalFunction(f, "codac")
    x = F0.flatten_point(funnel_point(d, rng))
    lo, hi = x - 1e-6 * (1 + np.abs(x)), x + 1e-6 * (1 + np.abs(x))
    args = [np.asarray(v) for v in F0.unflatten_point(x).values()]
    print(f"{scenario} {signal}: {count_ops(f)['operations']} operations, {F0.n_in_nz} scalar inputs, "
          f"{F0.n_out_nz} outputs; box half-width 1e-6 (1 + |x|) around a point inside both funnels")
    float_call = _rate(lambda: f(*args))
    N = 10000
    fm = f.map(N)
    X = [ca.repmat(ca.DM(a), 1, N) for a in args]
    float_batch = _rate(lambda: fm(*X)) * N
    print(f"  casadi double, one call from Python   {float_call:10.0f} points/s")
    print(f"  casadi double, map({N})            {float_batch:10.0f} points/s")
    for backend in ("codac", "arb"):
        for form in ("natural", "mean_value"):
            t0 = time.perf_counter()
            F = IntervalFunction(f, backend, form=form)
            build = time.perf_counter() - t0
            r = _rate(lambda: F.eval_flat(lo, hi))
            L, H = F.eval_flat(lo, hi)
            print(f"  {backend:5s} {form:10s} {r:10.0f} boxes/s  ({float_call / r:6.1f}x a casadi call, "
                  f"{float_batch / r:7.0f}x a mapped point; compiled in {build:.2f} s; "
                  f"mean width {np.mean(H - L):.3g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

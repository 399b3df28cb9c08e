"""The 20 s paper simulation: symfunnel (CVODES on compiled, cached C) against scipy solve_ivp (BDF) on a numpy RHS
generated from the same graph, measured in one run.

    python benchmarks/bench_simulate.py [--json]     # same figures as `symfunnel bench --only simulate`
"""

from __future__ import annotations

import json
import sys

from symfunnel.bench.simulate import run


def main() -> int:
    results = run(lambda s: print(s, file=sys.stderr))
    by = {r["id"]: r for r in results}
    rtf = by["simulate.realtime_factor"]
    sp = by["simulate.speedup_vs_scipy"]
    print(f"paper scenario, {rtf['t_final']:g} s simulated, status {rtf['status']}, code {rtf['code']}")
    print(f"  first run (compile or cache load) {rtf['first_run_wall']:8.3f} s  (cache hit: {rtf['cache_hit_first_run']})")
    print(f"  symfunnel simulate                {sp['value']:8.3f} s  real-time factor {rtf['value']:.0f} (target >= 100)")
    print(f"  scipy solve_ivp BDF, numpy RHS    {sp['baseline_value']:8.3f} s  real-time factor {rtf['baseline_value']:.2f}")
    print(f"  speedup vs scipy                  {sp['ratio']:8.1f} x (target >= 20)")
    print(f"  max |q symfunnel - q scipy|       {sp['max_abs_q_diff_vs_scipy']}")
    if "--json" in sys.argv[1:]:
        print(json.dumps({"results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

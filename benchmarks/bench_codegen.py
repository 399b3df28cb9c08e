"""Time one controller call: compiled C (timed in C), CasADi's VM from Python, generated numpy-only Python.

    python benchmarks/bench_codegen.py          # same figures as `symfunnel bench --only codegen`
"""

from __future__ import annotations

import json
import sys

from symfunnel.bench.codegen import run


def main() -> int:
    results = run(lambda s: print(s, file=sys.stderr))
    by = {r["id"]: r for r in results}
    c = by["codegen.c_controller_ns"]
    py = by["codegen.python_controller_ns"]
    print(f"controller of scenario '{c['scenario']}' (N = {c['esn_units']} reservoir units), "
          f"{c['operations']} operations")
    print(f"  compiled C (timed in C)     {c['value']:12.0f} ns/call")
    print(f"  CasADi VM from Python       {c['baseline_value']:12.0f} ns/call   "
          f"({c['ratio']:.1f}x the C time; DM args)")
    print(f"  CasADi VM, numpy arguments  {c['casadi_vm_numpy_ns']:12.0f} ns/call")
    print(f"  generated Python (1 point)  {py['value']:12.0f} ns/call   ({py['value'] / c['value']:.0f}x the C time)")
    b = by["codegen.python_batch_ns"]
    print(f"  generated Python (batch)    {b['value']:12.0f} ns/point  (casadi map {b['baseline_value']:.0f} ns/point)")
    print(f"  target <= {c['target_ns']:.0f} ns: {'met' if c['meets_target'] else 'NOT met'}")
    if "--json" in sys.argv[1:]:
        print(json.dumps({"results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

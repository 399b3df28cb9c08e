"""URDF -> M, C, G, exact alpha2_dot and compiled C for serial arms of n = 2..7 joints, against sympy.physics.mechanics.

    python benchmarks/bench_models.py                 # same figures as `symfunnel bench --only models`
    python benchmarks/bench_models.py --n 2 3 4       # some n only
    python benchmarks/bench_models.py --limit 20      # a shorter hard limit for the sympy baseline
    python benchmarks/bench_models.py --no-sympy      # symfunnel only
    python benchmarks/bench_models.py --json          # the raw results too
"""

from __future__ import annotations

import argparse
import json
import sys

from symfunnel.bench.models import NS, SYMPY_LIMIT_S, run


def _f(x, fmt):
    return "-" if x is None else format(x, fmt)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=list(NS), help="numbers of joints (1..7)")
    ap.add_argument("--limit", type=float, default=SYMPY_LIMIT_S, help="hard limit of one sympy run, seconds")
    ap.add_argument("--no-sympy", action="store_true", help="skip the sympy baseline")
    ap.add_argument("--json", action="store_true", help="also print the results as JSON")
    args = ap.parse_args(argv)
    results = run(lambda s: print(s, file=sys.stderr), ns=args.n, sympy_limit=args.limit, sympy=not args.no_sympy)
    by = {r["id"]: r for r in results}
    print(f"{'n':>2} {'symfunnel s':>12} {'sympy s':>9} {'ratio':>8} {'ops M,C,G':>10} {'sympy ops':>10} "
          f"{'ops a2dot':>10} {'ops ctl':>8} {'URDF->C s':>10}  sympy")
    for n in args.n:
        b, o = by[f"models.build_s.n{n}"], by[f"models.ops.n{n}"]
        c = by[f"models.urdf_to_c_s.n{n}"]
        print(f"{n:>2} {b['value']:>12.4f} {_f(b['baseline_value'], '9.2f'):>9} "
              f"{_f(b['ratio'], '7.0f') + ('x' if b['ratio'] else ''):>8} {o['value']:>10.0f} "
              f"{_f(o['baseline_value'], '10.0f'):>10} {by[f'models.ops_alpha2_dot.n{n}']['value']:>10.0f} "
              f"{by[f'models.ops_controller.n{n}']['value']:>8.0f} {c['value']:>10.3f}  {b['sympy_status']}")
    if "models.derive_eval_s.n7" in by:
        e = by["models.derive_eval_s.n7"]
        print(f"symfunnel derive arm7 --eval: {e['value']:.3f} s (target {e['target_s']:g} s: "
              f"{'met' if e['meets_target'] else 'NOT met'}; tau finite: {e['finite_tau']})")
    if "models.urdf_to_c_s.n7" in by:
        c = by["models.urdf_to_c_s.n7"]
        print(f"arm7 URDF -> compiled C: {c['value']:.3f} s (target {c['target_s']:g} s: "
              f"{'met' if c['meets_target'] else 'NOT met'})")
    if args.json:
        print(json.dumps({"results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

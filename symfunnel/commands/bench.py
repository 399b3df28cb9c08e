"""`symfunnel bench [--json] [--only AREA]`: performance figures against baselines measured in the same run."""

from __future__ import annotations

import json


def _areas() -> tuple[str, ...]:
    from ..bench import AREAS
    return AREAS


def register(sub, common) -> None:
    """Add the `bench` subcommand."""
    sp = sub.add_parser("bench", help="performance figures, each beside a baseline measured in the same run")
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--only", action="append", metavar="AREA", help="one area (repeatable): " + ", ".join(_areas()))
    sp.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    sp.set_defaults(func=run)


def run(args) -> int:
    """Run the selected benchmarks and print them as a table or JSON."""
    from ..bench import AREAS
    from ..bench import run as run_bench
    from ._common import _progress
    from ..core.errors import InputError
    for a in args.only or []:
        if a not in AREAS:
            raise InputError(f"unknown area '{a}'", key="--only", expected="one of " + ", ".join(AREAS))
    results = run_bench(args.only, _progress(args.quiet or args.json))
    if args.json:
        print(json.dumps({"results": results}, indent=2))
        return 0
    print(f"{'id':<40} {'value':>14} {'unit':<10} {'baseline':<34} {'baseline value':>14} {'ratio':>8}")
    for r in results:
        bv = "" if r["baseline_value"] is None else f"{r['baseline_value']:.4g}"
        ra = "" if r["ratio"] is None else f"{r['ratio']:.1f}x"
        print(f"{r['id']:<40} {r['value']:>14.4g} {r['unit']:<10} {str(r['baseline'] or ''):<34} {bv:>14} {ra:>8}")
    return 0

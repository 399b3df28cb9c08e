"""`symfunnel audit [SCENARIO] [--json] [--strict]`: model properties, funnel feasibility and the printed claims
against the exact derivation."""

from __future__ import annotations

from ._common import _dump, _load, _progress


def register(sub, common) -> None:
    """Add the `audit` subcommand."""
    sp = sub.add_parser("audit", help="model properties and printed claims against the exact derivation")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--strict", action="store_true", help="exit 1 when any check fails")
    sp.set_defaults(func=cmd_audit)


def cmd_audit(args) -> int:
    """`symfunnel audit`: model properties and printed claims; --strict exits 1 on any failed check."""
    from ._common import loading
    with loading():
        from ..pipeline import Run
        sc = _load(args)
    say = _progress(args.quiet or args.json)
    results = Run(sc, progress=say).audit
    failed = [r for r in results if r.status == "fail"]
    if args.json:
        print(_dump({"scenario": sc.name, "checks": [r.to_json() for r in results]}))
    else:
        print(f"audit of scenario {sc.name} ({sc.file})")
        from .verify import print_checks
        print_checks(results)
        unexpected = [r for r in results if r.unexpected]
        print(f"{len(results) - len(failed)} passed, {len(failed)} failed "
              f"({len(failed) - sum(r.expected == 'pass' for r in failed)} expected by the scenario)"
              + (f"; unexpected: {', '.join(r.id for r in unexpected)}" if unexpected else ""))
    return 1 if (failed and args.strict) else 0
